"""What the Gymnasium and gymnax front ends share, with no dependency on either library: the
environment's id, ``EnvConfig`` built from keyword overrides (``gymnasium.make(ENV_ID, layout=...)``)
and the JAX key of an integer seed (Gymnasium's ``reset(seed=...)``)."""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any

import jax
import numpy as np

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


def seed_key(seed: int, *more: int) -> jax.Array:
    """The JAX key of a Gymnasium seed, any int >= 0: ``jax.random.key(seed)`` below 2**32 (as it always
    was), its higher 32-bit words folded in above (``key`` alone keeps the low 32 bits: 2**32 was seed 0);
    then every word of ``more`` (a vector env's list of seeds) folded in too."""
    low, *rest = _words(seed)
    key = jax.random.key(low)
    for word in rest + [w for x in more for w in _words(x)]:
        key = jax.random.fold_in(key, word)
    return key


def _words(seed: int) -> list[int]:
    """``seed`` (an int >= 0) as 32-bit words, lowest first, at least one."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected an int >= 0, got {seed!r}")
    seed, words = int(seed), []
    while True:
        words.append(seed & 0xFFFFFFFF)
        seed >>= 32
        if not seed:
            return words
