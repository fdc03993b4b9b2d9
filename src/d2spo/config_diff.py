"""Which settings of two run configs differ in a way that can change the run.

``effective_config`` drops what a run cannot read (another learner's section, the shaping under the
sparse reward, the generalist's settings on one layout, the patrols' settings for a task that is no
recurrence); ``config_differences`` lists what is left that differs. A resume (``run.prepare_dir``),
``reproduce``'s staleness check and flags given beside ``--resume`` (``cli``) use it.
"""

from __future__ import annotations

from typing import Any

from d2spo.algos import LEARNERS, all_config_sections, config_sections
from d2spo.config import TrainConfig, config_to_dict

_SHAPING_FIELDS = ("shaping", "shaping_metric", "shaping_clearance", "shaping_clearance_cost", "shaping_collide_cost",
                   "shaping_neighbours", "shaping_gamma")


_GENERALIST_FIELDS = ("generalist_layouts", "generalist_redraw", "generalist_pairings", "generalist_world",
                      "generalist_tasks", "generalist_patrols", "validation_layouts", "validation_episodes")
"""Settings only a generalist reads (``env.distance_obs`` and ``env.forbidden_range`` too)."""


def _runs_a_recurrence(cfg: TrainConfig) -> bool:
    """Whether the run can meet a recurrence (a patrol): a generalist (its mixture may hold patrols),
    or a task whose automaton is one; True too when the task does not translate (nothing is assumed)."""
    from d2spo.ltl.buchi_task import task_is_recurrence
    return cfg.generalist or task_is_recurrence(cfg.task) is not False


def _drop_key(node: Any, key: str) -> None:
    if isinstance(node, dict):
        node.pop(key, None)
        for value in node.values():
            _drop_key(value, key)


def effective_config(cfg: TrainConfig) -> dict:
    """``config_to_dict(cfg)`` without what cannot change this learner's run: the sections of other
    learners; under the sparse reward (td3, sl), the shaping fields; on one layout, the generalist's
    settings; for a task that is no recurrence, the patrols' (``patrol_validation``,
    ``env.recurrence_max_steps``, ``recurrence_noise_final``). Two runs with equal effective configs
    train identically."""
    d = config_to_dict(cfg)
    for name in all_config_sections() - set(config_sections(cfg.algo)):
        d.pop(name, None)
    if cfg.env_config().reward.mode == "sparse":
        for name in _SHAPING_FIELDS:
            d["env"]["reward"].pop(name, None)
    if not cfg.generalist:
        for name in _GENERALIST_FIELDS:
            d.pop(name, None)
        d["env"].pop("distance_obs", None)
        d["env"].pop("forbidden_range", None)
    if not _runs_a_recurrence(cfg):
        d.pop("patrol_validation", None)
        d["env"].pop("recurrence_max_steps", None)
        _drop_key(d, "recurrence_noise_final")
    return d


def _differences(a: Any, b: Any, where: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted path, a's value, b's value) for each leaf of two nested dicts that differs."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b)) for d in _differences(a.get(k), b.get(k), f"{where}.{k}" if where else k)]
    return [] if a == b else [(where, a, b)]


def config_differences(old: TrainConfig, new: TrainConfig) -> list[str]:
    """``'path: old -> new'`` for each effective setting that differs between two configs."""
    return [f"{where}: {a!r} -> {b!r}" for where, a, b in _differences(effective_config(old), effective_config(new))]


def flags_given(cfg: TrainConfig) -> list[str]:
    """The training flags a command line set (``--generalist-tasks``, ``--td3.batch-size``, ...): the
    fields of ``cfg`` that differ from a fresh config of the same learner, ``--algo``, ``--generalist``
    and ``--fast`` named first (the defaults the other fields take follow these three, so a field
    they fill is not a flag the user gave). Every field counts, read by this learner or not."""
    keys = {"algo": cfg.algo, "generalist": cfg.generalist, "fast": cfg.fast}
    named = [f"--{k}" for k, v in keys.items() if v != getattr(TrainConfig, k)]
    flags = ["--" + (where.rsplit(".", 1)[-1] if where.startswith("env.") else where).replace("_", "-")  # env's: flat
             for where, _, _ in _differences(config_to_dict(TrainConfig(**keys)), config_to_dict(cfg))]
    return named + [f for f in flags if f not in named]


def other_learners_flag(args: list[str], algo: str) -> tuple[str, list[str]] | None:
    """(flag, the learners that read its section) for the first flag of ``args`` whose section
    (``--cpo.``, ``--cbf.``) the learner ``algo`` does not read; None when there is none."""
    if algo not in LEARNERS:  # an unknown --algo: its own error says so
        return None
    for arg in args:
        section = arg[2:].split(".", 1)[0].replace("-", "_") if arg.startswith("--") and "." in arg else None
        if section is not None and section not in config_sections(algo):
            algos = [a for a in LEARNERS if section in config_sections(a)]
            if algos:
                return arg.split("=", 1)[0], algos
    return None
