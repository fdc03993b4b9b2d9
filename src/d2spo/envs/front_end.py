"""What the Gymnasium and gymnax front ends share, with no dependency on either library: the
environment's id and ``EnvConfig`` built from keyword overrides (``gymnasium.make(ENV_ID, layout=...)``)."""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any

from d2spo.envs.env_config import EnvConfig
from d2spo.errors import ConfigError

ENV_ID = "d2spo/Nav-v0"
"""The id registered with Gymnasium (``d2spo.envs.gym_env``) and the name of the gymnax env."""


def env_config(config: EnvConfig | None, overrides: dict[str, Any]) -> EnvConfig:
    """``config`` (or the default) with keyword overrides, e.g. ``layout="relaxed"``."""
    if config is not None and not isinstance(config, EnvConfig):  # e.g. a dict: its fields are keywords
        raise ConfigError("config", f"expected a d2spo.envs.EnvConfig, got {type(config).__name__}; pass its "
                          "fields as keyword arguments instead (layout=..., max_steps=...)")
    config = config or EnvConfig()
    known = {f.name for f in fields(EnvConfig)}
    for name in overrides:
        if name not in known:
            raise ConfigError(name, f"not an EnvConfig field; known fields: {sorted(known)}")
    return replace(config, **overrides)
