"""Load a trained policy from a run directory and evaluate it, possibly elsewhere (``d2spo eval``).

The policy is restored with the training config (the checkpoint's shapes depend on it) and then
run on any layout and dynamics whose observation has the same size (same task, same number of
areas, same number of lidar rays). The rollouts are ``d2spo.rollout``'s; the run's config and
learner come from ``d2spo.train`` (``load_run_config``, ``build``). Nothing here prints: the CLI
shows the result with ``d2spo.console.print_evaluation``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np

from d2spo.checkpoint import load_checkpoint, run_fingerprint
from d2spo.config import TrainConfig
from d2spo.errors import ConfigError, NaNError, RunDirError
from d2spo.fields import check_fields
from d2spo.rollout import make_rollout, rates
from d2spo.runio import atomic_write_json
from d2spo.train import best_policy_path, build, load_best_policy, load_run_config

POLICY_CHOICES = ("best", "last")
"""Which policy of a run ``load_policy`` returns (``d2spo eval --policy``)."""


def load_policy(run_dir: Path, which: str = "best"):
    """(cfg, learner, policy, meta) of a finished or checkpointed run. ``which``: "best" is a
    validated generalist's kept policy (``TrainConfig.validation_layouts``) where there is one, else
    the last; "last" is the newest checkpoint's. ``meta["policy"]`` says which was taken."""
    if which not in POLICY_CHOICES:
        raise ConfigError("policy", f"expected one of {', '.join(POLICY_CHOICES)}, got {which!r}")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunDirError(f"{run_dir}: no such run directory")
    cfg = load_run_config(run_dir)
    # a generalist's checkpoint holds no layout: a one-layout bank gives the same shapes, fast
    _, _, learner = build(dataclasses.replace(cfg, generalist_layouts=1, generalist_tasks=0) if cfg.generalist else cfg)
    template = jax.eval_shape(learner.init, jax.random.PRNGKey(0))  # shapes only: no pre-training
    carry, meta = load_checkpoint(run_dir, template, run_fingerprint(run_dir))
    meta = dict(meta)
    best = meta.get("best")
    if which == "best" and best is not None and best_policy_path(run_dir).is_file():
        meta["policy"] = f"best on validation (after {best['episodes']} episodes)"
        return cfg, learner, load_best_policy(run_dir, learner), meta
    meta["policy"] = f"last (after {meta.get('episodes')} episodes)"
    return cfg, learner, learner.policy(carry), meta


EFFECT_FIELDS = ("actuator_tau", "v_gain", "omega_gain", "slip", "noise_xy", "noise_theta")
"""What ``d2spo eval --dynamics PRESET`` changes."""


def eval_env_config(cfg: TrainConfig, layout: str | None, dynamics: str | None = None,
                    overrides: dict[str, float] | None = None):
    """The env config of an evaluation: the training one on ``layout``, under ``dynamics`` (a preset:
    its unmodelled effects only, the robot's time step and speed limits stay those the policy was
    trained with; or a JSON file: every field it gives), then the per-field ``overrides``."""
    from d2spo.envs import dynamics as dyn

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
    stem, or the trained preset, then each override, e.g. ``default-slip0.2``."""
    base = trained if dynamics is None else (dynamics if "/" not in dynamics and not dynamics.endswith(".json")
                                             else Path(dynamics).stem)
    return base + "".join(f"-{k}{v:g}" for k, v in sorted((overrides or {}).items()))


def learner_on(cfg: TrainConfig, layout: str | None, preset: str | None, overrides: dict[str, float] | None = None):
    """A learner of the same kind on another layout/dynamics (for acting only); ``preset`` is a preset
    name or a dynamics JSON file (``eval_env_config``)."""
    return build(dataclasses.replace(cfg, env=eval_env_config(cfg, layout, preset, overrides)))


def filter_choice(cfg: TrainConfig, layout: str | None, preset: str | None, asked: bool | None,
                  overrides: dict[str, float] | None = None) -> bool | None:
    """The runtime filter's setting for an evaluation: what was asked; else on for a D²SPO policy on
    another layout or other dynamics than it was trained on (deployment where the learned h never
    saw data); else None, as trained."""
    from d2spo.algos import has_runtime_filter
    from d2spo.envs.dynamics import DYNAMICS_FIELDS

    if asked is not None or not has_runtime_filter(cfg.algo):
        return asked
    trained, now = cfg.env.resolved(), eval_env_config(cfg, layout, preset, overrides).resolved()
    elsewhere = ((layout is not None and layout != cfg.layout)
                 or any(getattr(trained, k) != getattr(now, k) for k in DYNAMICS_FIELDS))
    return True if elsewhere else None


def evaluate_run(run_dir: Path, episodes: int = 100, layout: str | None = None, preset: str | None = None,
                 seed: int = 0, layout_seeds: int = 1, runtime_filter: bool | None = None,
                 filter_iters: int | None = None, filter_alpha: float | None = None,
                 dynamics: dict[str, float] | None = None, task: str | None = None, policy: str = "best",
                 keep_paths: int = 0) -> dict:
    """Safety and completion of the run's final policy, deterministic, on its own layout and dynamics
    or others. ``runtime_filter=None``: as trained on the training layout and dynamics, and on for a
    D²SPO policy evaluated on another layout or dynamics (π_Ω alone is far less safe on layouts it
    never saw: docs/cbf.md); True/False force it. ``preset``: a dynamics preset or JSON file;
    ``dynamics``: per-field values on top of it (``eval_env_config``). ``task``: another task (a
    name or a formula) for a generalist run, zero-shot (``d2spo.zero_shot``); a generalist needs
    ``layout``. ``policy``: "best" or "last" (``load_policy``). ``keep_paths`` > 0 adds ``"paths"``:
    per layout, (Layout, poses [k, T + 1, 3], collided [k], completed [k]) of its first ``keep_paths``
    episodes, for ``plots.evaluation_figure`` (arrays: drop the key before writing JSON)."""
    from d2spo.algos import has_runtime_filter
    from d2spo.envs.dynamics import DYNAMICS_FIELDS

    asked = SimpleNamespace(episodes=episodes, layout_seeds=layout_seeds, seed=seed, filter_iters=filter_iters,
                            filter_alpha=filter_alpha)
    check_fields(asked, nullable=("filter_iters", "filter_alpha"), count=("episodes", "layout_seeds"),
                 seed=("seed",), natural=("filter_iters",), positive=("filter_alpha",))
    if layout_seeds != 1 and not (layout or "").startswith("random"):
        raise ConfigError("layout_seeds", f"only applies with --layout random[:SEED] or random5[:SEED], got {layout_seeds} "
                          f"with layout {layout or 'as trained'!r}")
    cfg, learner, policy_params, meta = load_policy(run_dir, policy)
    policy, which = policy_params, meta["policy"]
    if task is not None and not cfg.generalist and task != cfg.task:
        raise ConfigError("task", f"only a generalist (d2spo train --generalist) runs another task than it "
                          f"learnt; this run learnt {cfg.task!r}")
    if cfg.generalist and layout is None:
        raise ConfigError("layout", "a generalist run has no layout of its own: give --layout NAME|FILE|random:SEED")
    has_filter = has_runtime_filter(cfg.algo)
    asked = {"runtime_filter": runtime_filter, "filter_iters": filter_iters, "filter_alpha": filter_alpha}
    for name, value in asked.items():
        if value is not None and not has_filter:
            raise ConfigError(name, f"only D²SPO has a runtime filter; this run is {cfg.algo!r}")
    runtime_filter = filter_choice(cfg, layout, preset, runtime_filter, dynamics)
    if runtime_filter is not None:
        cfg = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, runtime_filter=runtime_filter))
    cbf_changes = {k: v for k, v in (("filter_iters", filter_iters), ("filter_alpha_coef", filter_alpha)) if v is not None}
    if cbf_changes:
        cfg = dataclasses.replace(cfg, cbf=dataclasses.replace(cfg.cbf, **cbf_changes))
    layouts = [layout]
    if layout is not None and layout.startswith("random") and layout_seeds > 1:
        kind, _, base = layout.partition(":")  # random:SEED or random5:SEED
        if base.isdigit() or not base:  # else load() names the bad seed
            layouts = [f"{kind}:{int(base or 0) + i}" for i in range(layout_seeds)]
    env_cfg = eval_env_config(cfg, layout, preset, dynamics)
    if cfg.generalist:
        from d2spo.zero_shot import rollouts

        results, limit = rollouts(cfg, policy, task or cfg.task, layouts, episodes, seed, env_cfg, keep_paths)
    else:
        results, limit = _specialist_rollouts(cfg, learner, policy, layouts, episodes, seed, preset, dynamics,
                                              keep_paths), None
    paths = [r.pop("paths") for r in results] if keep_paths else None
    out = {
        "run": str(run_dir), "policy": which, "episodes": episodes * len(layouts), "layout": layout or cfg.layout,
        "layouts": [lay or cfg.layout for lay in layouts], "dynamics": dynamics_label(preset, dynamics, cfg.env.preset),
        "dynamics_values": {k: getattr(env_cfg.resolved(), k) for k in DYNAMICS_FIELDS}, "seed": seed,
        "task": task or cfg.task, "task_given": task is not None and task != cfg.task,
        "max_steps": limit,
        "runtime_filter": bool(cfg.d2spo.runtime_filter) if has_filter else None,
        "filter_iters": cfg.cbf.filter_iters if has_filter else None,
        "filter_alpha": cfg.cbf.filter_alpha if has_filter else None,
        "per_layout": [{"layout": lay or cfg.layout, **r} for lay, r in zip(layouts, results)],
        **{k: float(np.mean([r[k] for r in results]))
           for k in ("safety_rate", "completion_rate", "mean_return", "mean_distance")},
    }
    if paths is not None:
        out["paths"] = paths
    return out


def _specialist_rollouts(cfg: TrainConfig, learner, policy, layouts: list[str | None], episodes: int, seed: int,
                         preset: str | None, dynamics: dict[str, float] | None, keep_paths: int = 0) -> list[dict]:
    """Rates per layout of a policy that reads its layout's coordinates (every learner but the
    generalist): the observation must keep its size (number of areas, automaton states). With
    ``keep_paths`` each also holds ``"paths"`` (``evaluate_run``)."""
    results = []
    compiled: dict = {}  # one compiled rollout per shape of the env params (random5 layouts share one)
    for lay in layouts:
        env, params, other = learner_on(cfg, lay, preset, dynamics)
        if env.observation_size != learner_obs_size(learner):
            raise ConfigError("layout", f"the policy was trained with observations of size {learner_obs_size(learner)}, "
                              f"layout {lay!r} gives {env.observation_size} (different number of areas or "
                              "automaton states)")
        leaves, tree = jax.tree_util.tree_flatten(params)  # the structure holds the static fields (n_rays, ...)
        shape = (tree, tuple((x.shape, x.dtype) for x in leaves))
        if shape not in compiled:
            compiled[shape] = make_rollout(other, env, episodes, int(params.max_steps))
        res = compiled[shape](params, policy, jax.random.PRNGKey(seed))
        results.append(rates(*res))
        if keep_paths:
            poses, collided, completed = (np.asarray(a[:keep_paths]) for a in (res[4], res[0], res[1]))
            results[-1]["paths"] = (env.layout, poses, collided, completed)
    return results


def learner_obs_size(learner) -> int:
    return learner.env.observation_size


def evaluation_path(run_dir: Path, res: dict) -> Path:
    """Where ``write_evaluation`` puts ``res``: RUN_DIR/eval-LAYOUT[xN]-DYNAMICS[-filter-aA-iN].json."""
    n = len(res["per_layout"])  # random:0 over 3 layouts is another evaluation than random:0 alone
    tag = f"{Path(res['layout']).stem.replace(':', '')}{f'x{n}' if n > 1 else ''}-{res['dynamics']}"
    if res.get("task_given"):
        from d2spo.zero_shot import task_tag

        tag += f"-{task_tag(res['task'])}"
    if str(res.get("policy", "")).startswith("best"):  # a validated generalist's kept policy
        tag += "-best"
    if res["runtime_filter"]:
        tag += f"-filter-a{res['filter_alpha']:g}-i{res['filter_iters']}"
    return Path(run_dir) / f"eval-{tag}.json"


def write_evaluation(run_dir: Path, res: dict) -> Path:
    """Write ``evaluate_run``'s result into the run directory (``evaluation_path``); returns the path.
    Raises NaNError, leaving any earlier file as it was, when a mean rate is not finite."""
    path = evaluation_path(run_dir, res)
    means = [res[k] for k in ("safety_rate", "completion_rate", "mean_return", "mean_distance")]
    if not all(np.isfinite(means)):  # never replace an earlier result with a broken one
        raise NaNError(f"{run_dir}: the evaluation gave non-finite rates {means}; {path.name} left as it was")
    atomic_write_json(path, res)
    return path
