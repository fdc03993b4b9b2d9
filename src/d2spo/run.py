"""A run directory, for everyone who reads or writes one: the learner its config names, its config,
its policies (the last checkpoint's, a validated best, the snapshots), the preparation
of a new or resumed directory, and the directory of a group of seeds trained together.

``d2spo.train`` writes runs; ``d2spo.evaluate``, ``d2spo.certify``, ``d2spo.plots``,
``d2spo.reproduce`` and the demo read them through this module. The files themselves (config.json,
checkpoints, the lock) are described in docs/runs.md.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import warnings
import weakref
from pathlib import Path
from typing import Any

import jax
from flax import serialization

from d2spo import memo
from d2spo.algos import has_runtime_filter, make_learner
from d2spo.algos.generalist import build_generalist
from d2spo.checkpoint import DamagedState, has_checkpoint, load_checkpoint, restore_bytes, run_fingerprint
from d2spo.config import TrainConfig, config_from_dict, config_to_dict
from d2spo.config_diff import config_differences
from d2spo.envs import layouts, make_env
from d2spo.envs.preflight import preflight
from d2spo.errors import ConfigError, RunDirError, RunDirWarning, UserError
from d2spo.inputs import sha256_of
from d2spo.ltl.parser import parse
from d2spo.runio import atomic_write_bytes, atomic_write_json, read_json, remove_file, remove_tmp_files, temporary_of


def build(cfg: TrainConfig):
    """(env, env_params, learner) for a config. Raises ConfigError on bad input.

    Built once per process for a config (seed aside: no learner reads it) and its layout file's
    content (``d2spo.memo``): the learner returned again brings the programs JAX traced and
    compiled for it, so a second run of the config starts at once."""
    key = _build_key(cfg)
    return _build(cfg) if key is None else memo.built(key, lambda: _build(cfg))


def _build_key(cfg: TrainConfig) -> str | None:
    """What a build depends on: the config with its seed set aside, and the layout file's bytes;
    None for a layout file that cannot be read (the build says why, as without the memo)."""
    file = None if cfg.generalist else layouts.layout_file(cfg.layout)
    try:
        digest = None if file is None else sha256_of(file, _layout_error)
    except ConfigError:
        return None
    return json.dumps([config_to_dict(dataclasses.replace(cfg, seed=0)), digest], sort_keys=True)


def _build(cfg: TrainConfig):
    if cfg.generalist:
        return _build_generalist(cfg)
    env, params = make_env(cfg.env_config(), task=cfg.task)
    learner = make_learner(cfg, env, params)
    return env, params, learner



def _build_generalist(cfg: TrainConfig):
    """(env, params, learner) of ``--generalist``: the layouts WORLD:0 .. WORLD:N-1 (WORLD: its
    ``generalist_world``), each in ``generalist_pairings`` consecutive slots, slot k paired with task
    k modulo the mixture's size (``algos.generalist.build_generalist``)."""
    drawn = [layouts.load(f"{cfg.generalist_world}:{s}") for s in range(cfg.generalist_layouts)
             for _ in range(cfg.generalist_pairings)]
    return build_generalist(cfg, drawn, cfg.env.max_steps)  # None: each layout's slot_max_steps



def check_new_run_dir(out: Path) -> None:
    """RunDirError when ``out`` is a directory that holds files but no d2spo run (no config.json a run
    wrote): a new run there would delete its hidden ``.*.tmp`` files and ``policy-*.msgpack`` and write
    its own config.json over one of the same name. Empty, missing, or a run's (one stopped before its
    first checkpoint is started again): fine. Checked before the run's lock file is made in it."""
    out = Path(out)
    if not out.is_dir():
        return
    names = sorted(p.name for p in out.iterdir() if p.name != ".lock" and temporary_of(p.name) is None)
    if not names:
        return
    try:
        config_from_dict(read_json(out / "config.json", "the run's config"))
        return
    except (UserError, ValueError, TypeError, KeyError):
        pass
    shown = ", ".join(names[:3]) + (", …" if len(names) > 3 else "")
    raise RunDirError(f"{out}: not empty and holds no d2spo run ({shown}); choose another --out, or an empty "
                      "or new directory")


def prepare_dir(out: Path, cfg: TrainConfig, resume: bool) -> None:
    """With the directory's lock held: temporary files a kill left are removed; a resume checks
    ``cfg`` against config.json; a new run writes config.json (over a run killed before its first
    checkpoint, whose policy snapshots and TensorBoard files go too)."""
    remove_tmp_files(out)
    cfg_path = out / "config.json"
    if resume:
        theirs = load_run_config(out)
        if theirs != cfg:
            diffs = config_differences(theirs, cfg) or ["settings this learner does not read"]
            raise RunDirError(f"{out}: resuming takes the run's own config.json, and this config differs "
                              f"({'; '.join(diffs)})")
        check_layout_unchanged(out, cfg, RESUME_REMEDY)
        return
    if (out / "summary.json").exists() or has_checkpoint(out):
        raise RunDirError(f"{out}: already holds a run; use --resume {out} or another --out")
    for p in out.glob("policy-*.msgpack"):
        remove_file(p)
    if (out / "tb").is_dir():  # the stopped start's scalars would mix with this run's in TensorBoard
        shutil.rmtree(out / "tb")
    atomic_write_json(cfg_path, config_to_dict(cfg))
    record_inputs(out, cfg)


INPUTS = "inputs.json"
"""The SHA-256 of the layout file a run trains on, recorded as it starts (``record_inputs``):
config.json holds the file's path only. (A ``--dynamics`` file needs none: config.json holds its values.)"""
RESUME_REMEDY = "resuming would train on another layout: restore the file, or start a new run with another --out"


def _layout_error(message: str) -> ConfigError:
    return ConfigError("layout", message)


def record_inputs(out: Path, cfg: TrainConfig) -> None:
    """Write ``INPUTS`` for a new run of ``cfg`` on a layout file; none for a built-in or random layout."""
    path = Path(out) / INPUTS
    file = None if cfg.generalist else layouts.layout_file(cfg.layout)
    if file is None:
        remove_file(path)  # left by an earlier start of this directory on a layout file
        return
    atomic_write_json(path, {"layout": {"file": cfg.layout, "sha256": sha256_of(file, _layout_error),
                                        "path": str(file.resolve())}})  # for commands run from elsewhere


def _recorded_layout(run_dir: Path) -> dict:
    """``INPUTS``' entry for the run's layout file (``file``, ``path``, ``sha256``); {} without one."""
    if not (Path(run_dir) / INPUTS).is_file():
        return {}
    data = read_json(Path(run_dir) / INPUTS, "the hash of the run's layout file")
    return data.get("layout") if isinstance(data, dict) and isinstance(data.get("layout"), dict) else {}


def _found_layout(run_dir: Path, cfg: TrainConfig, given: str | None) -> TrainConfig:
    """``cfg`` with its layout file found from here: a path relative to where the run was trained is
    looked up at the absolute path ``INPUTS`` recorded, then at ``given`` (a command's --layout), each
    taken only if it holds what the run started with (the recorded SHA-256). RunDirError when none is
    found. A built-in or random layout, or a file readable from here, is left as it is."""
    file = None if cfg.generalist else layouts.layout_file(cfg.layout)
    if file is None or file.exists():
        return cfg
    entry = _recorded_layout(run_dir)
    for candidate in (entry.get("path"), given):
        if isinstance(candidate, str) and layouts.layout_file(candidate) is not None and Path(candidate).is_file() \
                and sha256_of(Path(candidate), _layout_error) == entry.get("sha256"):
            return dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, layout=candidate))
    where = f" (at {entry['path']} when it started)" if isinstance(entry.get("path"), str) else ""
    raise RunDirError(f"{run_dir}: its layout file {cfg.layout}{where} is not found from {Path.cwd()}; run the "
                      "command from the directory it was trained in, or pass --layout PATH to that file where "
                      "the command takes one")


def is_training_layout(run_dir: Path, cfg: TrainConfig, layout: str) -> bool:
    """Whether ``layout`` (a command's --layout) names the layout the run trained on: the same name
    for a built-in or drawn layout; for a file, the bytes the run started with (``INPUTS``' SHA-256),
    however its path is spelled (``in/lab.json``, ``./in/lab.json``, an absolute path), or, for a run
    without ``INPUTS``, the same file. An edited file is another layout. Never for a generalist."""
    if cfg.generalist:
        return False
    given, trained = layouts.layout_file(layout), layouts.layout_file(cfg.layout)
    if given is None or trained is None:
        return layout == cfg.layout
    entry = _recorded_layout(run_dir)
    if not isinstance(entry.get("sha256"), str):
        return given.resolve() == trained.resolve()
    return given.is_file() and sha256_of(given, _layout_error) == entry["sha256"]


def check_layout_unchanged(run_dir: Path, cfg: TrainConfig, remedy: str) -> None:
    """RunDirError, ending in ``remedy``, when the layout file ``cfg`` names no longer holds what
    the run ``run_dir`` started with (``INPUTS``). A run without ``INPUTS`` (a built-in or random
    layout, or written before d2spo recorded it) is not checked."""
    path = Path(run_dir) / INPUTS
    file = None if cfg.generalist else layouts.layout_file(cfg.layout)
    if file is None or not path.exists():
        return
    data = read_json(path, "the hash of the run's layout file")
    entry = data.get("layout") if isinstance(data, dict) else None
    if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
        raise RunDirError(f"{path}: damaged (no layout.sha256); restore it, or delete it to skip this check")
    if entry.get("file") != cfg.layout:  # config.json was edited: its checkpoint fingerprint says so
        return
    now = sha256_of(file, _layout_error)
    if now != entry["sha256"]:
        raise RunDirError(f"{run_dir}: its layout file {cfg.layout} changed since the run started (SHA-256 "
                          f"{now[:12]}…, recorded {entry['sha256'][:12]}… in {INPUTS}); {remedy}")


def preflight_checks(cfg: TrainConfig, env, params) -> None:
    """The checks before a run of ``cfg`` on (env, params), training or evaluation
    (``envs.preflight.preflight``): the task can be done, within an episode, and, for a learner that
    executes π_Ω (D²SPO, SL), keeping the barrier's margin ``cfg.cbf.d``."""
    preflight(env, params, repr(cfg.task), margin=barrier_margin(cfg) or 0.0)


def barrier_margin(cfg: TrainConfig) -> float | None:
    """The margin d a run's learned barrier keeps from obstacles (D²SPO and SL: ``cbf.d``, with the
    runtime filter on or off), else None: what the run-start barrier-margin check and a patrol's
    ``route_optimal_visits_margin`` (``d2spo eval``) hold routes to."""
    return cfg.cbf.d if has_runtime_filter(cfg.algo) else None


def default_out(cfg: TrainConfig) -> Path:
    """Where `d2spo train` writes a run without --out: runs/ALGO-TASK-LAYOUT-sSEED; a formula's TASK
    is ``custom-`` and 8 hex digits of its parse tree's hash, so that two formulas get two
    directories and one formula, however spelt, the same."""
    task = cfg.task if cfg.task.replace("-", "").isalnum() else f"custom-{formula_tag(cfg.task)}"
    layout = Path(cfg.layout).stem if cfg.layout.endswith(".json") else cfg.layout.replace(":", "")
    if cfg.generalist:
        layout = f"generalist{cfg.generalist_layouts}"
    return Path("runs") / f"{cfg.algo}-{task}-{layout}-s{cfg.seed}"


def formula_tag(formula: str) -> str:
    """8 hex digits naming a formula by its parse tree (``str(parse(formula))``), not its spelling."""
    try:
        text = str(parse(formula))
    except UserError:  # refused later, with its column; a name is still needed now
        text = formula
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def load_run_config(run_dir: Path, layout: str | None = None) -> TrainConfig:
    """The config a run was trained with (its config.json), its layout file found from here
    (``_found_layout``; ``layout``: a command's --layout, tried too)."""
    if not Path(run_dir).is_dir():
        raise RunDirError(f"{run_dir}: is a file, not a run directory" if Path(run_dir).exists()
                          else f"{run_dir}: no such run directory")
    path = Path(run_dir) / "config.json"
    try:
        cfg = config_from_dict(read_json(path, "the run's config"))
    except ConfigError as e:  # a value of the file's, not a flag of the command's: say where
        raise RunDirError(f"{path}: {e}") from None
    return _found_layout(run_dir, cfg, layout)



GROUP_PREFIX = ".group-"


def group_dir(outs: list[Path]) -> Path:
    """Where ``train_seeds`` checkpoints the group of runs ``outs``: ``OUT[0]/../.group-<names>``."""
    return Path(outs[0]).parent / (GROUP_PREFIX + "+".join(Path(o).name for o in outs))



BEST_POLICY = "policy-best.msgpack"
"""A validated generalist's best policy (``_Run.validate``), in the run directory."""


def best_policy_path(run_dir: Path) -> Path:
    return Path(run_dir) / BEST_POLICY


def load_best_policy(run_dir: Path, learner, key: jax.Array | None = None):
    """The policy ``_Run.validate`` kept; shapes come from the learner (nothing is trained; ``key``
    is kept for callers of old: shapes do not depend on it)."""
    path = best_policy_path(run_dir)
    if not path.is_file():
        raise RunDirError(f"{run_dir}: no validated policy ({path.name})")
    return _policy_from_file(path, learner, "; `--policy last` evaluates the newest checkpoint's policy instead")


_TEMPLATES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def carry_template(learner):
    """The shapes and dtypes of ``learner.init``'s carry (``jax.eval_shape``: nothing runs), traced
    once per learner: tracing D²SPO's init takes seconds, and a figure loads several snapshots."""
    try:
        return _TEMPLATES[learner]
    except (KeyError, TypeError):  # TypeError: a learner that cannot be weakly referenced
        pass
    init = getattr(learner, "init_template", learner.init)  # the same shapes, traced faster (D²SPO)
    template = jax.eval_shape(init, jax.random.PRNGKey(0))
    try:
        _TEMPLATES[learner] = template
    except TypeError:
        pass
    return template


def policy_template(learner):
    """The shapes of ``learner.policy(carry)`` (``carry_template``)."""
    return jax.eval_shape(learner.policy, carry_template(learner))


def snapshot_path(run_dir: Path, episodes: int) -> Path:
    return Path(run_dir) / f"policy-{episodes}.msgpack"


def save_snapshot(run_dir: Path, episodes: int, policy) -> None:
    """The policy's parameters after ``episodes`` training episodes (``TrainConfig.snapshots``)."""
    atomic_write_bytes(snapshot_path(run_dir, episodes), serialization.to_bytes(jax.device_get(policy)))


def load_snapshot(run_dir: Path, episodes: int, learner, key: jax.Array | None = None):
    """The policy saved by ``save_snapshot``; shapes come from the learner (nothing is trained; the
    ``key`` does not change them)."""
    path = snapshot_path(run_dir, episodes)
    if not path.is_file():
        raise RunDirError(f"{run_dir}: no policy snapshot after {episodes} episodes ({path.name})")
    return _policy_from_file(path, learner)


def _policy_from_file(path: Path, learner, hint: str = ""):
    """A policy file (``save_snapshot``, the validated policy) restored onto the learner's policy
    shapes; one ``RunDirError`` line when it is damaged or another config's."""
    try:
        return restore_bytes(policy_template(learner), path.read_bytes(), path.name)
    except DamagedState as e:
        raise RunDirError(f"{path.parent}: {e}{hint}") from None



def _shared_best(run_dir: Path) -> dict | None:
    """The meta of a finished run's validated policy (a generalist's, a patrol's) read from
    summary.json, for a run directory that holds config.json, summary.json and the policy but no
    checkpoint (none was written, or it was left behind to share the run); None if any of them is
    missing."""
    summary = Path(run_dir) / "summary.json"
    if not (summary.is_file() and best_policy_path(run_dir).is_file()):
        return None
    try:
        record = read_json(summary, "the run's summary")
        best, trained = record["validation"]["best"], int(record["episodes"])
        kept = int(best["episodes"])
    except (RunDirError, ValueError, KeyError, TypeError):
        return None
    return {"policy": f"best on validation (after {kept} episodes)", "best": best, "episodes": trained}


POLICY_CHOICES = ("best", "last")
"""Which policy of a run ``load_policy`` returns (``d2spo eval --policy``)."""


def load_policy(run_dir: Path, which: str = "best", learner=None, layout: str | None = None):
    """(cfg, learner, policy, meta) of a finished or checkpointed run. ``which``: "best" is a
    validated run's kept policy (a generalist's, ``TrainConfig.validation_layouts``; a patrol's on one
    layout, ``TrainConfig.patrol_validation``) where there is one, else the last; "last" is the
    newest checkpoint's. ``meta["policy"]`` says which was taken.
    ``learner``: one already built with this run's array shapes (an evaluation's, elsewhere); by
    default one is built from config.json, and a layout file changed since the run started is refused
    (``check_layout_unchanged``, as `d2spo eval` and `export` do). ``layout``: as ``load_run_config``'s."""
    if which not in POLICY_CHOICES:
        raise ConfigError("policy", f"expected one of {', '.join(POLICY_CHOICES)}, got {which!r}")
    cfg = load_run_config(run_dir, layout)
    if learner is None and layout is None:  # built from config.json's layout file: as it was, or refused
        check_layout_unchanged(run_dir, cfg, "restore it, or train a new run on it as it is now")
    if learner is None:
        # a generalist's checkpoint holds no layout: a one-layout bank gives the same shapes, fast
        _, _, learner = build(dataclasses.replace(cfg, generalist_layouts=1, generalist_tasks=0, generalist_patrols=0,
                                                  generalist_pairings=1)
                              if cfg.generalist else cfg)
    shared = _shared_best(run_dir) if which == "best" else None
    if shared is not None and not has_checkpoint(run_dir):  # a finished generalist copied without them
        return cfg, learner, load_best_policy(run_dir, learner), shared
    try:
        carry, meta = load_checkpoint(run_dir, carry_template(learner), run_fingerprint(run_dir))
    except RunDirError as e:  # e.g. copied without the state files (the replay: hundreds of MB)
        if shared is None:
            raise
        warnings.warn(f"{e}; the validated policy and summary.json are used", RunDirWarning, stacklevel=2)
        return cfg, learner, load_best_policy(run_dir, learner), shared
    policy, meta = checkpoint_policy(run_dir, which, learner, carry, meta)
    return cfg, learner, policy, meta


def checkpoint_policy(run_dir: Path, which: str, learner, carry, meta: dict) -> tuple[Any, dict]:
    """(policy, meta) of a run whose newest checkpoint (``carry``, ``meta``) is loaded: the validated
    policy for "best" where the run kept one, else the checkpoint's; ``meta["policy"]`` says which."""
    meta = dict(meta)
    best = meta.get("best")
    if which == "best" and best is not None and best_policy_path(run_dir).is_file():
        meta["policy"] = f"best on validation (after {best['episodes']} episodes)"
        return load_best_policy(run_dir, learner), meta
    meta["policy"] = f"last (after {meta.get('episodes')} episodes)"
    return learner.policy(carry), meta
