"""A gymnax-compatible functional front end (gymnax / PureJaxRL conventions).

gymnax (1.x) code expects ``reset(key, params) -> (obs, state)`` and
``step(key, state, action, params) -> (obs, state, reward, terminated, truncated, info)`` with the
episode reset in the same step and ``info["final_observation"]`` holding the finished episode's
last observation, ``default_params``, and ``observation_space(params)`` / ``action_space(params)``.
``GymnaxNav`` offers exactly that over ``nav.Env`` (whose own order is ``(state, obs)`` and which
returns the cost separately); the cost goes to ``info["cost"]``. gymnax is not a dependency: when
it is installed the spaces are gymnax's own ``spaces.Box`` (its wrappers check for that class),
otherwise an equivalent small ``Box``. gymnax's wrappers (``LogWrapper``,
``FlattenObservationWrapper``, ...) wrap ``GymnaxNav`` as they wrap gymnax's own environments:

>>> env, params = GymnaxNav.make(task="F A1", layout="open")
>>> obs, state = env.reset(key, params)
>>> obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)
>>> jax.vmap(env.step, in_axes=(0, 0, 0, None))(keys, states, actions, params)   # info["cost"]
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.envs.env_config import EnvConfig
from d2spo.envs.front_end import ENV_ID, env_config
from d2spo.envs.nav import Env, EnvState, make_env
from d2spo.envs.params import EnvParams
from d2spo.envs.spaces import observation_bounds


@dataclass(frozen=True)
class _Box:
    """A box of float32 vectors with gymnax's ``spaces.Box`` interface (``sample(key)``, ``contains``)."""

    low: np.ndarray
    high: np.ndarray
    shape: tuple[int, ...]
    dtype: Any = jnp.float32

    def sample(self, key: jax.Array) -> jnp.ndarray:
        """Uniform in the box."""
        return jax.random.uniform(key, self.shape, self.dtype, jnp.asarray(self.low), jnp.asarray(self.high))

    def contains(self, x: jnp.ndarray) -> jnp.ndarray:
        """bool []: x lies in the box."""
        return jnp.all((x >= self.low) & (x <= self.high))


try:
    from gymnax.environments.spaces import Box
except ImportError:  # gymnax is optional
    Box = _Box


class GymnaxNav:
    """The navigation environment with gymnax's ``Environment`` interface (see the module docstring)."""

    def __init__(self, env: Env, params: EnvParams):
        self.env = env
        """The functional environment underneath."""
        self._params = params

    @classmethod
    def make(cls, task: Any = "phi1", config: EnvConfig | None = None, **overrides) -> tuple[GymnaxNav, EnvParams]:
        """``(env, env_params)`` as ``gymnax.make`` returns them; keywords are ``EnvConfig`` fields."""
        env, params = make_env(env_config(config, overrides), task)
        return cls(env, params), params

    @property
    def default_params(self) -> EnvParams:
        return self._params

    @property
    def name(self) -> str:
        return ENV_ID

    @property
    def num_actions(self) -> int:
        return self.env.action_size

    def reset(self, key: jax.Array, params: EnvParams | None = None) -> tuple[jnp.ndarray, EnvState]:
        """(obs, state) of a new episode; jitted, as gymnax's own ``reset`` is."""
        return self._reset(key, self._params if params is None else params)

    def step(self, key: jax.Array, state: EnvState, action: jnp.ndarray, params: EnvParams | None = None):
        """(obs, state, reward, terminated, truncated, info); a finished episode is reset in the
        same step: ``obs`` is then the next episode's first observation and
        ``info["final_observation"]`` the finished one's last. Jitted, as gymnax's own ``step`` is:
        a Python loop over it runs one compiled program per step (inside ``jax.jit``, ``vmap`` or
        ``lax.scan`` it is inlined as any jitted function is).

        ``info`` holds the functional env's info (``collided``, ``completed``, ``sensed``, ...; see
        docs/env.md) plus ``cost``, ``final_observation`` and ``discount`` (0 where terminated).
        """
        return self._step(key, state, action, self._params if params is None else params)

    @partial(jax.jit, static_argnums=0)
    def _reset(self, key: jax.Array, params: EnvParams) -> tuple[jnp.ndarray, EnvState]:
        state, obs = self.env.reset(key, params)
        return obs, state

    @partial(jax.jit, static_argnums=0)
    def _step(self, key: jax.Array, state: EnvState, action: jnp.ndarray, params: EnvParams):
        state, obs, reward, cost, _, info = self.env.step(key, state, action, params)
        terminated, truncated = info["terminated"], info["truncated"]
        info = {**info, "cost": cost, "final_observation": info["next_obs"],
                "discount": 1.0 - terminated.astype(jnp.float32)}
        return obs, state, reward, terminated, truncated, info

    def observation_space(self, params: EnvParams | None = None) -> Box:
        """The real bounds of the observation (``spaces.observation_bounds``)."""
        low, high = observation_bounds(self.env)
        return Box(low, high, low.shape)

    def action_space(self, params: EnvParams | None = None) -> Box:
        """[-1, 1]^2: (linear, angular) speed command as a fraction of the largest."""
        n = self.env.action_size
        return Box(-np.ones(n, np.float32), np.ones(n, np.float32), (n,))
