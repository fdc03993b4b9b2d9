"""Evaluate a run's policy, on its own layout and dynamics or elsewhere (``d2spo eval``).

What an evaluation runs is an ``EvalConfig``. A specialist's policy runs on any layout and dynamics
whose observation has the same size (same task, same number of areas, same number of lidar rays);
a generalist's on any task and any layout its field bank can hold (``d2spo.zero_shot`` checks the
layouts; the generalist is built once and each layout swaps its bank in). The run's config, learner
and policies come from ``d2spo.run``; the rollouts are ``d2spo.rollout``'s. Nothing here prints:
the CLI shows the result with ``d2spo.console.print_evaluation``.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Annotated

import jax
import numpy as np
import tyro

from d2spo import zero_shot
from d2spo.algos import has_runtime_filter
from d2spo.config import TrainConfig
from d2spo.envs import dynamics as dyn
from d2spo.envs.env_config import EnvConfig
from d2spo.envs.layouts import RANDOM_KINDS, random_seed
from d2spo.envs.layouts import load as load_layout
from d2spo.errors import ConfigError, TaskWarning
from d2spo.evalfiles import layout_sha256, number_tag
from d2spo.fields import check_choice, check_fields, field_docstring
from d2spo.inputs import sha256_of
from d2spo.ltl.tasks import same_task
from d2spo.memory import check_eval_memory
from d2spo.rollout import make_rollout, rates, visit_optimum
from d2spo.run import (
    POLICY_CHOICES,
    barrier_margin,
    build,
    check_layout_unchanged,
    is_training_layout,
    load_policy,
    load_run_config,
    preflight_checks,
)

DynamicsOverrides = dataclasses.make_dataclass(
    "DynamicsOverrides",
    [(name, Annotated[float | None, tyro.conf.arg(help=field_docstring(EnvConfig, name))], dataclasses.field(default=None))
     for name in dyn.DYNAMICS_FIELDS],
    frozen=True,
)
DynamicsOverrides.__module__ = __name__
DynamicsOverrides.__doc__ = """Per-field dynamics of an evaluation: each given field replaces the trained value (or
the --dynamics preset's or file's). The fields are ``EnvConfig``'s ``DYNAMICS_FIELDS``."""


def given(overrides) -> dict[str, float]:
    """The fields of a ``DynamicsOverrides`` that are set."""
    return {f.name: getattr(overrides, f.name) for f in dataclasses.fields(overrides) if getattr(overrides, f.name) is not None}


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """What `d2spo eval` runs: episodes, where, under which dynamics, which policy."""

    episodes: int = 100
    """Evaluation episodes per layout (run in parallel)."""
    layout: str | None = None
    """Evaluate on another layout (a name as train's --layout takes, world:SEED and zones:SEED among them,
    or a JSON file); default: the training layout."""
    task: str | None = None
    """Zero-shot: run a generalist (`d2spo train --generalist`) on this task, a name or a formula over
    the layout's area labels (A1..A4, or a layout file's own: docs/layouts.md; needs --layout); other
    runs only take the task they learnt."""
    dynamics: str | None = None
    """Evaluate under other dynamics: a preset (ideal, default, turtlebot: its unmodelled effects, with the
    trained time step and speed limits) or a JSON file (every field it gives: docs/env.md)."""
    seed: int = 0
    """Seed of the evaluation episodes (their starts and noise). Training's final evaluation in
    summary.json ran the run's seed + 10000: ``--seed`` that number and ``--episodes`` its count give
    its episodes again."""
    layout_seeds: int = 1
    """With a drawn --layout (random, random5, zones or world[:SEED]): average over this many
    layouts of it (seeds SEED..SEED+n-1)."""
    runtime_filter: bool | None = None
    """D²SPO only: switch the runtime safety filter on or off for this evaluation; default: as trained on
    the training layout and dynamics, on elsewhere and for a generalist everywhere (π_Ω alone transfers
    poorly to unseen layouts)."""
    filter_iters: int | None = None
    """D²SPO only: linearise-and-project iterations of the runtime filter; default: as trained."""
    filter_alpha: float | None = None
    """D²SPO only: coefficient of α in the runtime filter's condition (smaller brakes earlier); default: as trained."""
    max_steps: int | None = None
    """The episode limit in steps; default: the run's own (a generalist: the longest its layouts need).
    A patrol's route-optimal count follows it: e.g. 1000 to score one as DeepLTL's ZoneEnv episodes do."""
    policy: str = "best"
    """best: the validated policy where the run has one (a generalist's, kept on its validation layouts,
    `--validation-layouts`; a patrol's on one layout, `--patrol-validation`), else the last; last: the
    newest checkpoint's."""
    forbidden_range: float | None = None
    """Generalist only: observe a forbidden area only within this many metres of its edge, beyond it as if
    none were forbidden, as `train --forbidden-range` does; inf: at any distance, as a generalist trained
    without it sees it in training; default: the range it was trained with, else the robot's lidar range
    (its sensing radius, 1.2 m for the default robot)."""
    overrides: Annotated[DynamicsOverrides, tyro.conf.arg(name="")] = dataclasses.field(default_factory=DynamicsOverrides)

    def __post_init__(self):
        check_fields(self, nullable=("filter_iters", "filter_alpha", "max_steps", "forbidden_range"),
                     count=("episodes", "layout_seeds", "max_steps", "filter_iters"),
                     seed=("seed",), positive=("filter_alpha",))
        if self.forbidden_range is not None and not self.forbidden_range > 0:  # inf: always observed
            raise ConfigError("forbidden_range", f"must be a number > 0 (inf: always seen), got {self.forbidden_range!r}")
        check_choice(self, "policy", POLICY_CHOICES)
        if self.layout_seeds != 1 and _family(self.layout) is None:
            raise ConfigError("layout_seeds", f"only applies with a drawn layout, --layout "
                              f"{'|'.join(RANDOM_KINDS)}[:SEED], got {self.layout_seeds} with layout "
                              f"{self.layout or 'as trained'!r}")

    def layouts(self) -> list[str | None]:
        """The layouts evaluated: ``layout`` (None: the training one), or with ``layout_seeds`` > 1 the
        drawn layouts KIND:SEED .. KIND:SEED + n - 1 (KIND: random, random5, zones or world)."""
        drawn = random_seed(self.layout) if self.layout is not None and self.layout_seeds > 1 else None
        if drawn is not None:  # else layouts.load names a bad seed
            kind, seed = drawn
            return [f"{kind}:{seed + i}" for i in range(self.layout_seeds)]
        return [self.layout]


def _family(layout: str | None) -> str | None:
    """The family of a drawn layout name (``random:3`` -> ``random``, ``world`` -> ``world``), else None."""
    kind = (layout or "").partition(":")[0]
    return kind if kind in RANDOM_KINDS else None


EFFECT_FIELDS = ("actuator_tau", "v_gain", "omega_gain", "slip", "noise_xy", "noise_theta")
"""What ``d2spo eval --dynamics PRESET`` changes."""


def eval_env_config(cfg: TrainConfig, layout: str | None, dynamics: str | None = None,
                    overrides: dict[str, float] | None = None):
    """The env config of an evaluation: the training one on ``layout``, under ``dynamics`` (a preset:
    its unmodelled effects only, the robot's time step and speed limits stay those the policy was
    trained with; or a JSON file: every field it gives), then the per-field ``overrides``."""
    env_cfg = cfg.env
    if layout is not None:
        env_cfg = dataclasses.replace(env_cfg, layout=layout)
    if dynamics in dyn.PRESETS:
        p = dyn.get_preset(dynamics)
        env_cfg = dataclasses.replace(env_cfg, **{k: getattr(p, k) for k in EFFECT_FIELDS})
    elif dynamics is not None:
        if not (dynamics.endswith(".json") or Path(dynamics).exists()):
            raise ConfigError("dynamics", f"unknown dynamics {dynamics!r}; use a preset {sorted(dyn.PRESETS)} "
                              "or a .json file (docs/env.md)")
        env_cfg = dataclasses.replace(env_cfg, **dyn.load_dynamics(dynamics))
    for name, value in (overrides or {}).items():
        if name not in dyn.DYNAMICS_FIELDS:
            raise ConfigError(name, f"not a dynamics field; choose from {list(dyn.DYNAMICS_FIELDS)}")
        env_cfg = dataclasses.replace(env_cfg, **{name: dyn.check_value(name, value)})
    return env_cfg


def dynamics_label(dynamics: str | None, overrides: dict[str, float] | None, trained: str) -> str:
    """How an evaluation's dynamics are named in its output and file name: the preset, or the file's
    stem and the first 12 hex digits of its content's SHA-256 (as a layout file's, ``layout_tag``: two
    files of one name in two folders never share an evaluation file), or the trained preset, then
    each override, e.g. ``default-slip0.2``, ``robot-3f9a0c2b71de``."""
    if dynamics is None:
        base = trained
    elif dynamics in dyn.PRESETS:
        base = dynamics
    else:
        digest = sha256_of(Path(dynamics), lambda message: ConfigError("dynamics", message))
        base = f"{Path(dynamics).stem}-{digest[:12]}"
    return base + "".join(f"-{k}{number_tag(v)}" for k, v in sorted((overrides or {}).items()))


def trained_dynamics(cfg: TrainConfig) -> str:
    """The name of the dynamics a run trained under: its preset's, or ``trained`` when a dynamics
    file or per-field flags (``--dynamics robot.json``, ``--v-gain 0.85``) gave other values."""
    preset = dyn.get_preset(cfg.env.preset)
    own = cfg.env.resolved()
    return cfg.env.preset if all(getattr(own, k) == getattr(preset, k) for k in dyn.DYNAMICS_FIELDS) else "trained"


def learner_on(cfg: TrainConfig, layout: str | None, dynamics: str | None, overrides: dict[str, float] | None = None):
    """A learner of the same kind on another layout/dynamics (for acting only); ``dynamics`` is a
    preset name or a dynamics JSON file (``eval_env_config``)."""
    return build(dataclasses.replace(cfg, env=eval_env_config(cfg, layout, dynamics, overrides)))


def filter_choice(cfg: TrainConfig, layout: str | None, dynamics: str | None, asked: bool | None,
                  overrides: dict[str, float] | None = None, training_layout: bool | None = None) -> bool | None:
    """The runtime filter's setting for an evaluation: what was asked; else on for a D²SPO policy on
    another layout or other dynamics than it was trained on (deployment where the learned h never
    saw data), and for a generalist on any layout (it trained on a bank of drawn layouts, never on a
    named one: its config's ``env.layout`` is an unused default); else None, as trained.
    ``training_layout``: whether ``layout`` names the training layout (``run.is_training_layout``: a
    file by its content); None: when it is the run's layout by name."""
    if asked is not None or not has_runtime_filter(cfg.algo):
        return asked
    trained, now = cfg.env.resolved(), eval_env_config(cfg, layout, dynamics, overrides).resolved()
    if training_layout is None:
        training_layout = layout == cfg.layout
    elsewhere = (cfg.generalist or (layout is not None and not training_layout)
                 or any(getattr(trained, k) != getattr(now, k) for k in dyn.DYNAMICS_FIELDS))
    return True if elsewhere else None


def evaluate_run(run_dir: Path, ecfg: EvalConfig = EvalConfig(), keep_paths: int = 0, on_layout=None) -> dict:
    """Safety and completion of a run's policy as ``ecfg`` says, deterministic, on its own layout and
    dynamics or others. The runtime filter, unless ``ecfg.runtime_filter`` forces it: as trained on
    the training layout and dynamics, and on for a D²SPO policy evaluated on another layout or
    dynamics (π_Ω alone is far less safe on layouts it never saw: docs/cbf.md). ``keep_paths`` > 0
    adds ``"paths"``: per layout, (Layout, poses [k, T + 1, 3], collided [k], completed [k]) of its
    first ``keep_paths`` episodes, for ``plots.evaluation_figure`` (arrays: drop the key before
    writing JSON). ``on_layout(k, n, name)``, if given, is called before the rollouts of the k-th of the
    n layouts (the first also compiles) and once more with k = n when they are done (a progress display)."""
    cfg = load_run_config(run_dir, ecfg.layout)
    overrides = given(ecfg.overrides)
    if ecfg.task is not None and not cfg.generalist and not same_task(ecfg.task, cfg.task):
        raise ConfigError("task", f"only a generalist (d2spo train --generalist) runs another task than it "
                          f"learnt; this run learnt {cfg.task!r}")
    if cfg.generalist and ecfg.layout is None:
        raise ConfigError("layout", "a generalist run has no layout of its own: give --layout NAME|FILE|random:SEED")
    has_filter = has_runtime_filter(cfg.algo)
    for name in ("runtime_filter", "filter_iters", "filter_alpha"):
        if getattr(ecfg, name) is not None and not has_filter:
            raise ConfigError(name, f"only D²SPO has a runtime filter; this run is {cfg.algo!r}")
    runtime_filter = filter_choice(cfg, ecfg.layout, ecfg.dynamics, ecfg.runtime_filter, overrides,
                                   ecfg.layout is not None and is_training_layout(run_dir, cfg, ecfg.layout))
    if runtime_filter is not None:
        cfg = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, runtime_filter=runtime_filter))
    cbf_changes = {k: v for k, v in (("filter_iters", ecfg.filter_iters), ("filter_alpha_coef", ecfg.filter_alpha))
                   if v is not None}
    if cbf_changes:
        cfg = dataclasses.replace(cfg, cbf=dataclasses.replace(cfg.cbf, **cbf_changes))
    if ecfg.layout is None:  # the training layout: as it was when the run started
        check_layout_unchanged(run_dir, cfg, f"to evaluate on it as it is now, pass --layout {cfg.layout}")
    if ecfg.forbidden_range is not None and not cfg.generalist:
        raise ConfigError("forbidden_range", "is what a generalist observes of a forbidden area; this run "
                          "is a specialist, which reads every area in its own slot")
    if ecfg.max_steps is not None and not cfg.generalist:  # a generalist's limit: _generalist_rollouts
        cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, max_steps=ecfg.max_steps))
    layouts = ecfg.layouts()
    env_cfg = eval_env_config(cfg, ecfg.layout, ecfg.dynamics, overrides)
    if cfg.generalist:  # asked for, else as trained with one, else the lidar's range
        env_cfg = zero_shot.seen_forbidden_range(env_cfg, ecfg.forbidden_range)
    check_eval_memory(env_cfg, ecfg.episodes)  # before anything is built
    try:
        if cfg.generalist:
            results, limit, which = _generalist_rollouts(run_dir, cfg, ecfg, env_cfg, layouts, keep_paths, on_layout)
        else:
            _, learner, policy, meta = load_policy(run_dir, ecfg.policy, layout=ecfg.layout)
            results = _specialist_rollouts(cfg, learner, policy, ecfg, overrides, keep_paths, on_layout)
            # the episode limit run: the one asked for, else the longest of the layouts' own limits
            limit, which = max(r["max_steps"] for r in results), meta["policy"]
    except ConfigError as e:  # the run's own task on a layout the user typed: the layout is what to change
        if e.field != "task" or ecfg.task is not None or ecfg.layout is None:
            raise
        raise ConfigError("layout", f"the run's task {cfg.task!r} does not fit this layout: "
                          f"{str(e).removeprefix('task: ')}") from None
    if on_layout is not None:
        on_layout(len(layouts), len(layouts), None)
    paths = [r.pop("paths") for r in results] if keep_paths else None
    out = {
        "run": str(run_dir), "policy": which, "generalist": cfg.generalist, "episodes": ecfg.episodes * len(layouts),
        "layout": ecfg.layout or cfg.layout, "layouts": [lay or cfg.layout for lay in layouts],
        "layout_sha256": layout_sha256(ecfg.layout or cfg.layout),
        "dynamics": dynamics_label(ecfg.dynamics, overrides, trained_dynamics(cfg)),
        "dynamics_values": {k: getattr(env_cfg.resolved(), k) for k in dyn.DYNAMICS_FIELDS}, "seed": ecfg.seed,
        "task": ecfg.task or cfg.task, "task_given": ecfg.task is not None and ecfg.task != cfg.task,
        "max_steps": limit, "max_steps_given": ecfg.max_steps is not None,
        "runtime_filter": bool(cfg.d2spo.runtime_filter) if has_filter else None,
        "forbidden_range": env_cfg.forbidden_range if cfg.generalist else None,
        "forbidden_range_given": ecfg.forbidden_range is not None,
        "filter_iters": cfg.cbf.filter_iters if has_filter else None,
        "filter_alpha": cfg.cbf.filter_alpha if has_filter else None,
        "per_layout": [{"layout": lay or cfg.layout, **r} for lay, r in zip(layouts, results)],
        **{k: float(np.mean([r[k] for r in results]))
           for k in ("safety_rate", "completion_rate", "mean_return", "mean_distance")},
    }
    if results and all("rejection_rate" in r for r in results):
        out["rejection_rate"] = float(np.mean([r["rejection_rate"] for r in results]))
    if results and all("accepting_visits_per_episode" in r for r in results):  # a Büchi task (``ltl.buchi_task``)
        out["accepting_visits_per_episode"] = float(np.mean([r["accepting_visits_per_episode"] for r in results]))
        if all(r.get("visit_fraction") is not None for r in results):  # a recurrence, against its optimum
            out["visit_fraction"] = float(np.mean([r["visit_fraction"] for r in results]))
    if paths is not None:
        out["paths"] = paths
    return out


def check_same_slots(trained, env, layout: str | None) -> None:
    """A specialist's observation holds each area's position in the slot of its place in the layout
    file, and one slot per automaton state: ConfigError for another count of either (one line naming
    both), a TaskWarning when the areas' labels come in another order than in training."""
    old = [a.label for a in trained.layout.areas]
    new = [a.label for a in env.layout.areas]
    if env.observation_size != trained.observation_size:
        raise ConfigError("layout", f"the policy was trained on {len(old)} areas and {trained.n_states} automaton "
                          f"states; layout {layout!r} has {len(new)} areas and the task {env.n_states} states here. "
                          "A specialist reads each area in its own slot: evaluate it on layouts with as many "
                          "areas, or train a generalist (--generalist) for other layouts")
    if old != new:
        warnings.warn(f"layout {layout!r} lists its areas' labels as {new}, the training layout as {old}: the "
                      "policy reads each area's position in the slot of its place in the file, where it learnt "
                      "another label's; list the areas in the training layout's order", TaskWarning, stacklevel=2)


def _specialist_rollouts(cfg: TrainConfig, learner, policy, ecfg: EvalConfig, overrides: dict[str, float],
                         keep_paths: int = 0, on_layout=None) -> list[dict]:
    """Rates per layout of a policy that reads its layout's coordinates (every learner but the
    generalist): the observation must keep its size (number of areas, automaton states). With
    ``keep_paths`` each also holds ``"paths"`` (``evaluate_run``)."""
    results = []
    compiled: dict = {}  # one compiled rollout per shape of the env params (random5 layouts share one)
    names = ecfg.layouts()
    for lay in names:  # every layout named loads, before the first progress line and rollout
        if lay is not None:
            load_layout(lay)
    for k, lay in enumerate(names):
        env, params, other = learner_on(cfg, lay, ecfg.dynamics, overrides)
        if lay is not None or ecfg.dynamics is not None or overrides or ecfg.max_steps is not None:
            # training checked its own layout at its own limit
            preflight_checks(cfg, env, params)  # as training: the time and barrier-margin warnings here
        check_same_slots(learner.env, env, lay)
        if on_layout is not None:  # after the checks: a refused layout is the one line the user sees
            on_layout(k, len(names), lay or cfg.layout)
        leaves, tree = jax.tree_util.tree_flatten(params)  # the structure holds the static fields (n_rays, ...)
        shape = (tree, tuple((x.shape, x.dtype) for x in leaves))
        if shape not in compiled:
            compiled[shape] = make_rollout(other, env, ecfg.episodes, int(params.max_steps))
        res = compiled[shape](params, policy, jax.random.PRNGKey(ecfg.seed))
        results.append({**rates(*res, max_steps=int(params.max_steps)), "max_steps": int(params.max_steps)})
        results[-1].update(visit_optimum(env.task, params.max_steps, env.config,
                                          results[-1].get("accepting_visits_per_episode"), barrier_margin(cfg)))
        if keep_paths:
            poses, collided, completed = (np.asarray(a[:keep_paths]) for a in (res[4], res[0], res[1]))
            results[-1]["paths"] = (env.layout, poses, collided, completed)
    return results


def _generalist_rollouts(run_dir: Path, cfg: TrainConfig, ecfg: EvalConfig, env_cfg: EnvConfig,
                         layouts: list[str], keep_paths: int = 0, on_layout=None) -> tuple[list[dict], int, str]:
    """(rates per layout, episode limit, which policy) of a generalist run on ``ecfg.task`` (default:
    its own) over ``layouts``, zero-shot: every layout is checked first, then the generalist is built
    once and its policy loaded into it (``d2spo.zero_shot``)."""
    task = ecfg.task or cfg.task
    checked = [zero_shot.generalist_layout(env_cfg, name, task, cfg.cbf.d, ecfg.max_steps) for name in layouts]
    env, params, learner, limit = zero_shot.generalist_on(cfg, env_cfg, task, checked, ecfg.max_steps)
    _, _, policy, meta = load_policy(run_dir, ecfg.policy, learner)
    results = zero_shot.rollouts(env, params, learner, policy, checked, ecfg.episodes, ecfg.seed, limit, keep_paths,
                                 barrier_margin(cfg), on_layout)
    return results, limit, meta["policy"]
