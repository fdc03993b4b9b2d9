"""Learners. ``make_learner(cfg, env, params)`` builds the one ``--algo`` names."""

from __future__ import annotations

from collections.abc import Callable

_REGISTRY: dict[str, Callable] = {}


def _td3(cfg, env, params, anneal: bool):
    import dataclasses

    from d2spo.algos.td3 import TD3Learner

    return TD3Learner(env, params, cfg.td3, dataclasses.replace(cfg.anneal, enabled=cfg.anneal.enabled and anneal),
                      cfg.num_envs, cfg.chunk_steps, cfg.episodes)


def _d2spo(cfg, env, params, progress: bool):
    import dataclasses

    from d2spo.algos.d2spo import D2SPOLearner

    anneal = dataclasses.replace(cfg.anneal, enabled=cfg.anneal.enabled and progress)
    return D2SPOLearner(env, params, cfg.td3, cfg.cbf, anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes,
                        cfg.d2spo)


_REGISTRY.update({
    "d2spo": lambda cfg, env, params: _d2spo(cfg, env, params, progress=True),
    "sl": lambda cfg, env, params: _d2spo(cfg, env, params, progress=False),
    "tlgrl": lambda cfg, env, params: _td3(cfg, env, params, anneal=True),
    "td3": lambda cfg, env, params: _td3(cfg, env, params, anneal=False),
})


def _safe_offpolicy(module: str, learner: str, field: str) -> Callable:
    """td3-lag, sac-lag, rcrl: same env, Eq. (8) reward and annealed radius as tlgrl; config ``cfg.<field>``."""

    def build(cfg, env, params):
        import importlib

        cls = getattr(importlib.import_module(f"d2spo.algos.{module}"), learner)
        return cls(env, params, getattr(cfg, field), cfg.anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes)

    return build


_REGISTRY.update({
    "td3-lag": _safe_offpolicy("td3_lag", "TD3LagLearner", "td3_lag"),
    "sac-lag": _safe_offpolicy("sac_lag", "SACLagLearner", "sac_lag"),
    "rcrl": _safe_offpolicy("rcrl", "RCRLLearner", "rcrl"),
})

_REGISTRY.update({  # on-policy baselines, on the same footing (reward, annealed radius) as tlgrl
    "ppo-lag": _safe_offpolicy("ppo_lag", "PPOLagLearner", "ppo_lag"),
    "cpo": _safe_offpolicy("cpo", "CPOLearner", "cpo"),
})


def known_algos() -> tuple[str, ...]:
    return tuple(_REGISTRY)


def make_learner(cfg, env, params):
    """The learner for ``cfg.algo`` on (env, params)."""
    return _REGISTRY[cfg.algo](cfg, env, params)
