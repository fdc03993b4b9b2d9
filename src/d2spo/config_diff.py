"""Which settings of two run configs differ in a way that can change the run.

``effective_config`` drops what a run cannot read (another learner's section, the shaping under the
sparse reward, the generalist's settings on one layout, the patrols' settings for a task that is no
recurrence); ``config_differences`` lists what is left that differs. A resume (``run.prepare_dir``),
``reproduce``'s staleness check and flags given beside ``--resume`` (``cli``) use it.
"""

from __future__ import annotations

from typing import Any

from d2spo.algos import all_config_sections, config_sections
from d2spo.config import TrainConfig, config_to_dict

_SHAPING_FIELDS = ("shaping", "shaping_metric", "shaping_clearance", "shaping_clearance_cost", "shaping_collide_cost",
                   "shaping_neighbours", "shaping_gamma")


_GENERALIST_FIELDS = ("generalist_layouts", "generalist_redraw", "generalist_pairings", "generalist_world",
                      "generalist_tasks", "generalist_patrols", "validation_layouts", "validation_episodes")
"""Settings only a generalist reads (``env.distance_obs`` too)."""


def _runs_a_recurrence(cfg: TrainConfig) -> bool:
    """Whether the run can meet a recurrence (a patrol): a generalist (its mixture may hold patrols),
    or a task whose automaton is one; True too when the task does not translate (nothing is assumed)."""
    if cfg.generalist:
        return True
    from d2spo.ltl.buchi_task import is_recurrence, task_automaton
    from d2spo.ltl.tasks import task_formula
    try:
        return is_recurrence(task_automaton(task_formula(cfg.task)))
    except Exception:  # noqa: BLE001 - a task that does not translate is refused where it is built
        return True


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
    if not _runs_a_recurrence(cfg):
        d.pop("patrol_validation", None)
        d["env"].pop("recurrence_max_steps", None)
        _drop_key(d, "recurrence_noise_final")
    return d


def config_differences(old: TrainConfig, new: TrainConfig) -> list[str]:
    """``'path: old -> new'`` for each effective setting that differs between two configs."""
    out: list[str] = []

    def walk(a: Any, b: Any, where: str) -> None:
        if isinstance(a, dict) and isinstance(b, dict):
            for k in sorted(set(a) | set(b)):
                walk(a.get(k), b.get(k), f"{where}.{k}" if where else k)
        elif a != b:
            out.append(f"{where}: {a!r} -> {b!r}")

    walk(effective_config(old), effective_config(new), "")
    return out
