"""Learners. ``make_learner(cfg, env, params)`` builds the one ``--algo`` names."""

from __future__ import annotations

from collections.abc import Callable

_REGISTRY: dict[str, Callable] = {}
_SECTIONS: dict[str, tuple[str, ...]] = {}
"""The learner-specific TrainConfig sections each learner reads (the others cannot change its run)."""


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
# the annealed radius only applies with the progress reward, so td3 and sl ignore it
_SECTIONS.update({"d2spo": ("td3", "anneal", "cbf", "d2spo"), "sl": ("td3", "cbf", "d2spo"),
                  "tlgrl": ("td3", "anneal"), "td3": ("td3",)})


def _safe_offpolicy(module: str, learner: str, field: str) -> Callable:
    """td3-lag, sac-lag, rcrl: same env, Eq. (8) reward and annealed radius as tlgrl; config ``cfg.<field>``."""

    def build(cfg, env, params):
        import importlib

        cls = getattr(importlib.import_module(f"d2spo.algos.{module}"), learner)
        return cls(env, params, getattr(cfg, field), cfg.anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes)

    return build


# off-policy (td3-lag, sac-lag, rcrl) and on-policy (ppo-lag, cpo) baselines, on the same footing
# (reward, annealed radius) as tlgrl
for _name, _module, _learner in (("td3-lag", "td3_lag", "TD3LagLearner"), ("sac-lag", "sac_lag", "SACLagLearner"),
                                 ("rcrl", "rcrl", "RCRLLearner"), ("ppo-lag", "ppo_lag", "PPOLagLearner"),
                                 ("cpo", "cpo", "CPOLearner")):
    _REGISTRY[_name] = _safe_offpolicy(_module, _learner, _module)
    _SECTIONS[_name] = (_module, "anneal")
del _name, _module, _learner


def known_algos() -> tuple[str, ...]:
    return tuple(_REGISTRY)


def config_sections(algo: str) -> tuple[str, ...]:
    """The learner-specific TrainConfig sections ``algo`` reads (``td3``, ``cbf``, ``ppo_lag``, ...)."""
    return _SECTIONS[algo]


def all_config_sections() -> set[str]:
    return {s for v in _SECTIONS.values() for s in v}


def has_runtime_filter(algo: str) -> bool:
    """Whether ``algo`` executes D²SPO's π_Ω, whose runtime filter ``--runtime-filter`` switches."""
    return "d2spo" in config_sections(algo)


def make_learner(cfg, env, params):
    """The learner for ``cfg.algo`` on (env, params)."""
    return _REGISTRY[cfg.algo](cfg, env, params)
