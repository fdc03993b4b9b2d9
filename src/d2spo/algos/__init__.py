"""Learners, and the one table that says what each ``--algo`` is (``LEARNERS``).

Per learner: the class that builds it, the learner-specific TrainConfig sections it reads (the
others cannot change its run), its reward (Eq. (8)'s progress reward or the sparse task reward),
whether it trains with the annealed subtask radius of Sec. IV-C (``TrainConfig.anneal``), and
whether it executes D²SPO's π_Ω, whose runtime filter ``--runtime-filter`` switches.
``make_learner(cfg, env, params)`` builds the one ``cfg.algo`` names.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from d2spo.algos.cpo import CPOLearner
from d2spo.algos.d2spo import D2SPOLearner
from d2spo.algos.ppo_lag import PPOLagLearner
from d2spo.algos.rcrl import RCRLLearner
from d2spo.algos.sac_lag import SACLagLearner
from d2spo.algos.td3 import TD3Learner
from d2spo.algos.td3_lag import TD3LagLearner


def runs_a_recurrence(env) -> bool:
    """Whether the one-layout env's task is a recurrence (a patrol): ``TD3Config.for_task``, and the
    progress line (no completion to show)."""
    task = getattr(env, "task", None)
    return bool(task is not None and task.recurrence)


def _td3(cfg, env, params, anneal):
    return TD3Learner(env, params, cfg.td3.for_task(runs_a_recurrence(env)), anneal, cfg.num_envs, cfg.chunk_steps,
                      cfg.episodes)


def _d2spo(cfg, env, params, anneal):
    return D2SPOLearner(env, params, cfg.td3.for_task(runs_a_recurrence(env)), cfg.cbf, anneal, cfg.num_envs,
                        cfg.chunk_steps, cfg.episodes, cfg.d2spo)


def _td3_lag(cfg, env, params, anneal):
    lag = dataclasses.replace(cfg.td3_lag, td3=cfg.td3_lag.td3.for_task(runs_a_recurrence(env)))  # as _td3's
    return TD3LagLearner(env, params, lag, anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes)


def _sac_lag(cfg, env, params, anneal):
    return SACLagLearner(env, params, cfg.sac_lag, anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes)


def _rcrl(cfg, env, params, anneal):
    return RCRLLearner(env, params, cfg.rcrl, anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes)


def _ppo_lag(cfg, env, params, anneal):
    return PPOLagLearner(env, params, cfg.ppo_lag, anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes)


def _cpo(cfg, env, params, anneal):
    return CPOLearner(env, params, cfg.cpo, anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes)


@dataclass(frozen=True)
class LearnerSpec:
    """What one ``--algo`` is."""

    build: Callable[[Any, Any, Any, Any], Any]
    """``build(cfg, env, params, anneal)`` -> the learner; ``anneal`` is the AnnealConfig it trains with."""
    sections: tuple[str, ...]
    """The learner-specific TrainConfig sections it reads (``anneal`` is added when ``anneal`` is true)."""
    reward: Literal["progress", "sparse"]
    """Eq. (8)'s progress reward (with its shaping), or the sparse task reward."""
    anneal: bool
    """Trains with the annealed subtask radius (``TrainConfig.anneal``; it only applies to the progress reward)."""
    runtime_filter: bool = False
    """Executes D²SPO's π_Ω, whose runtime filter ``--runtime-filter`` switches."""


LEARNERS: dict[str, LearnerSpec] = {
    "d2spo": LearnerSpec(_d2spo, ("td3", "cbf", "d2spo"), "progress", anneal=True, runtime_filter=True),
    "td3": LearnerSpec(_td3, ("td3",), "sparse", anneal=False),  # RL-phi of Tables II-III
    "tlgrl": LearnerSpec(_td3, ("td3",), "progress", anneal=True),
    "sl": LearnerSpec(_d2spo, ("td3", "cbf", "d2spo"), "sparse", anneal=False, runtime_filter=True),
    # the safe baselines, on the same footing (reward, annealed radius) as tlgrl
    "td3-lag": LearnerSpec(_td3_lag, ("td3_lag",), "progress", anneal=True),
    "sac-lag": LearnerSpec(_sac_lag, ("sac_lag",), "progress", anneal=True),
    "rcrl": LearnerSpec(_rcrl, ("rcrl",), "progress", anneal=True),
    "ppo-lag": LearnerSpec(_ppo_lag, ("ppo_lag",), "progress", anneal=True),
    "cpo": LearnerSpec(_cpo, ("cpo",), "progress", anneal=True),
}


def known_algos() -> tuple[str, ...]:
    return tuple(LEARNERS)


def config_sections(algo: str) -> tuple[str, ...]:
    """The learner-specific TrainConfig sections ``algo`` reads (``td3``, ``anneal``, ``cbf``, ``ppo_lag``, ...)."""
    spec = LEARNERS[algo]
    return spec.sections + (("anneal",) if spec.anneal else ())


def all_config_sections() -> set[str]:
    return {s for algo in LEARNERS for s in config_sections(algo)}


def reward_mode(algo: str) -> str:
    """The reward ``algo`` trains on: ``progress`` (Eq. (8)) or ``sparse``."""
    return LEARNERS[algo].reward


def learner_anneals(algo: str) -> bool:
    """Whether ``algo`` anneals the labelling radius (Sec. IV-C) when ``--anneal.enabled`` is on."""
    return LEARNERS[algo].anneal


def has_runtime_filter(algo: str) -> bool:
    """Whether ``algo`` executes D²SPO's π_Ω, whose runtime filter ``--runtime-filter`` switches."""
    return LEARNERS[algo].runtime_filter


def make_learner(cfg, env, params):
    """The learner for ``cfg.algo`` on (env, params)."""
    spec = LEARNERS[cfg.algo]
    anneal = dataclasses.replace(cfg.anneal, enabled=cfg.anneal.enabled and spec.anneal)
    return spec.build(cfg, env, params, anneal)
