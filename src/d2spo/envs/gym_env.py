"""Gymnasium front ends of the navigation environment, registered as ``d2spo/Nav-v0``.

* ``NavEnv``: a single ``gymnasium.Env`` (``gymnasium.make``);
* ``NavVectorEnv``: a natively batched ``gymnasium.vector.VectorEnv`` (``gymnasium.make_vec``: one
  jit-compiled call steps every sub-environment);
* ``CostTuple`` / ``VectorCostTuple``: wrappers returning Safety-Gymnasium's six values.

gymnasium is an optional dependency (``pip install 'd2spo[gym]'``, gymnasium >= 1.1, < 2): importing
this module without it, or beside an older one, raises an ImportError saying so.

``step`` returns Gymnasium's five values ``(obs, reward, terminated, truncated, info)`` with the
cost in ``info["cost"]`` (what Safety-Gymnasium's ``SafetyGymnasium2Gymnasium`` produces, and what
the safe-RL libraries read). The environment's own episode statistics are in
``info["episode_stats"]`` on the step that ends an episode, so that ``info["episode"]`` stays free
for Gymnasium's ``RecordEpisodeStatistics`` (the ``r``/``l``/``t`` keys of SB3 and CleanRL).

The vector env resets a finished sub-environment on the next call to ``step`` by default
(``AutoresetMode.NEXT_STEP``, Gymnasium's own default, which every vector wrapper accepts); pass
``autoreset_mode=AutoresetMode.SAME_STEP`` to reset in the same step, as the functional API does.

>>> import gymnasium as gym, d2spo.envs
>>> envs = gym.make_vec("d2spo/Nav-v0", num_envs=8, layout="paper", task="phi1")
>>> obs, info = envs.reset(seed=0)
>>> obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
>>> info["cost"]  # float32 [8]
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from functools import lru_cache, partial
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

try:
    import gymnasium
    from gymnasium.vector import AutoresetMode, VectorEnv, VectorWrapper
except ImportError as missing:  # gymnasium is an optional dependency (d2spo[gym])
    try:
        found = f"gymnasium {version('gymnasium')} is installed"
    except PackageNotFoundError:
        found = "gymnasium is not installed"
    raise ImportError(f"d2spo's Gymnasium front end needs gymnasium>=1.1 ('d2spo[gym]') and {found}; "
                      "the functional env (d2spo.envs.make_env) and the gymnax-style env "
                      "(d2spo.envs.gymnax_env) need no gymnasium", name="gymnasium") from missing

from d2spo.envs.env_config import EnvConfig
from d2spo.envs.front_end import ENV_ID, env_config, seed_key
from d2spo.envs.nav import Env, make_env
from d2spo.envs.params import EnvParams
from d2spo.envs.spaces import observation_bounds
from d2spo.errors import ConfigError

if TYPE_CHECKING:
    from d2spo.envs.render import FrameRenderer

EPISODE_STATS = "episode_stats"
"""The info key of the environment's own episode statistics (``info["episode"]`` is Gymnasium's)."""

_INFO_KEYS = ("collided", "completed", "completed_relaxed", "q", "q_next")
_EPISODE_KEYS = ("ep_return", "ep_cost", "ep_length", "ep_collided", "ep_completed", "ep_completed_relaxed")


def _finite(action, what: str) -> np.ndarray:
    """``action`` as an array, or ValueError where an entry is NaN or infinite: out-of-range actions
    are clipped (docs/env.md), but a policy that outputs NaN has a bug the episode should not hide."""
    a = np.asarray(action, np.float32)
    if not np.isfinite(a).all():
        raise ValueError(f"{what} {np.array2string(a, precision=3)} is not finite (NaN or infinite); a policy's "
                         "bug, not an action: the env clips out-of-range actions but cannot step on these")
    return a


def _checked(action, what: str, space, shape: tuple[int, ...]) -> jax.Array:
    """``action`` finite (``_finite``) and of ``shape``'s size, as float32 of that shape; ValueError
    naming ``space`` otherwise."""
    a = _finite(action, what)
    if a.size != int(np.prod(shape)):
        raise ValueError(f"{what}: expected {space} (shape {shape}), got shape {a.shape}")
    return jnp.asarray(a.reshape(shape))


def _step_masked(env: Env, key, state, actions, params, autoreset):
    """``env.step_batch``, except that the sub-environments in ``autoreset`` (whose state is
    already a fresh episode's, from the previous step) keep that state and report nothing."""
    stepped, first_obs, reward, cost, done, info = env.step_batch(key, state, actions, params)
    go = ~autoreset

    def keep(old, new):
        return jnp.where(autoreset.reshape(autoreset.shape + (1,) * (new.ndim - 1)), old, new)

    out = {k: jnp.where(go, info[k], False) for k in ("terminated", "truncated", "collided", "completed",
                                                        "completed_relaxed")}
    out |= {"q": keep(state.q, info["q"]), "q_next": keep(state.q, info["q_next"]),
            "next_pose": keep(state.pose, info["next_pose"]), "next_obs": info["next_obs"]}
    out |= {k: info[k] for k in _EPISODE_KEYS}
    if "accepting_visit" in info:  # a Büchi task
        out["accepting_visit"] = jnp.where(go, info["accepting_visit"], False)
    return (jax.tree.map(keep, state, stepped), first_obs, jnp.where(go, reward, 0.0), jnp.where(go, cost, 0.0),
            done & go, out)


class _Compiled(NamedTuple):
    """An environment, its params and its jitted functions, shared by every front end made alike."""

    env: Env
    params: EnvParams
    reset: Any
    step: Any
    reset_batch: Any
    step_masked: Any


def _build(config: EnvConfig, task: Any) -> _Compiled:
    env, params = make_env(config, task)
    return _Compiled(env, params, jax.jit(env.reset), jax.jit(env.step), jax.jit(env.reset_batch, static_argnums=2),
                     jax.jit(partial(_step_masked, env)))


_build_cached = lru_cache(maxsize=16)(_build)


def compiled(config: EnvConfig, task: Any) -> _Compiled:
    """``make_env(config, task)`` and its jitted functions, cached: gymnasium's env checker and
    ``make`` loops build many envs alike, and each would otherwise trace and compile again."""
    try:
        return _build_cached(config, task)
    except TypeError:  # an unhashable task object
        return _build(config, task)


def _spaces(env: Env) -> tuple[gymnasium.spaces.Box, gymnasium.spaces.Box]:
    low, high = observation_bounds(env)
    return (gymnasium.spaces.Box(low, high, dtype=np.float32),
            gymnasium.spaces.Box(-1.0, 1.0, (env.action_size,), np.float32))


def _has_display() -> bool:
    """A window can open: always on macOS and Windows, with X11 or Wayland on Linux."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _check_render_mode(render_mode: str | None, allowed: list[str]) -> None:
    if render_mode == "human" and not _has_display():
        raise ConfigError("render_mode", "'human' needs a display (DISPLAY is not set); use 'rgb_array'")
    if render_mode is not None and render_mode not in allowed:
        raise ConfigError("render_mode", f"unknown render mode {render_mode!r}; choose one of {allowed}")


def _frame_renderer(env: Env) -> FrameRenderer:
    from d2spo.envs.render import FrameRenderer  # matplotlib: imported when a frame is first drawn

    return FrameRenderer(env.layout, env.config.robot_radius, env.config.sensing_radius)


def _refuse_forked_workers() -> None:
    """ConfigError when the env is being made by a ``gymnasium.vector.AsyncVectorEnv``
    (``make_vec(..., vectorization_mode="async")``) that will start its workers with ``fork``: a
    forked copy of a process in which JAX runs waits forever on JAX's threads, which fork does not
    copy. ``spawn`` and ``forkserver`` workers start a fresh interpreter, and work."""
    frame = sys._getframe(1)
    while frame is not None:  # AsyncVectorEnv makes a first env itself, before it starts its workers
        owner = frame.f_locals.get("self")
        if isinstance(owner, gymnasium.vector.AsyncVectorEnv):
            if multiprocessing.get_context(getattr(owner, "context", None)).get_start_method() == "fork":
                raise ConfigError("vectorization_mode", "'async' starts its workers with fork here, and a forked "
                                  "copy of a process running JAX hangs; pass vector_kwargs={'context': 'spawn'} "
                                  "(in a script guarded by if __name__ == '__main__'), or leave vectorization_mode "
                                  "out for one batched env, which is faster")
            return
        frame = frame.f_back


class NavEnv(gymnasium.Env):
    """One navigation environment with Gymnasium's single-env contract: after ``terminated`` or
    ``truncated``, ``step`` has returned the episode's last observation and the caller resets."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array", "human"], "render_fps": 10}
    """The class lists "human" with or without a display, so that `gym.make(..., render_mode="human")`
    reaches the constructor, which says in a ConfigError that it needs one (left out, `gym.make`
    wrapped the env in its pygame ``HumanRendering`` instead); an instance lists what it can do here."""

    def __init__(self, task: Any = "phi1", config: EnvConfig | None = None, render_mode: str | None = None,
                 max_episode_steps: int | None = None, **overrides):
        _refuse_forked_workers()
        _check_render_mode(render_mode, ["rgb_array", "human"])
        if max_episode_steps is not None:  # as NavVectorEnv's; gym.make gives its own to TimeLimit
            overrides["max_steps"] = max_episode_steps
        self._fns = compiled(env_config(config, overrides), task)
        self.env, self.params = self._fns.env, self._fns.params
        self.observation_space, self.action_space = _spaces(self.env)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.env.config.dt),
                         "render_modes": ["rgb_array", "human"] if _has_display() else ["rgb_array"]}
        self._key = None  # the first reset's seed, or one drawn from entropy (Gymnasium's rule)
        self._state = None
        self._pose = np.asarray(self.env.layout.start, np.float32)
        self._renderer: FrameRenderer | None = None
        self._window = None

    def _next_key(self) -> jax.Array:
        self._key, key = jax.random.split(self._key)
        return key

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """A new episode (``options`` is not used); ``seed`` makes it and every later step repeatable."""
        super().reset(seed=seed)
        if seed is not None:
            self._key = seed_key(seed)
        elif self._key is None:  # never seeded: a seed from entropy, through Gymnasium's np_random
            self._key = seed_key(int(self.np_random.integers(2**63)))
        self._state, obs = self._fns.reset(self._next_key(), self.params)
        self._pose = np.asarray(self._state.pose)
        if self.render_mode == "human":
            self.render()
        return np.asarray(obs), {}

    def step(self, action):
        """Returns (obs, reward, terminated, truncated, info) with the cost in ``info["cost"]``."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = _checked(action, "action", self.action_space, (self.env.action_size,))
        self._state, _, reward, cost, done, info = self._fns.step(self._next_key(), self._state, action, self.params)
        reward, cost, done, info = jax.device_get((reward, cost, done, info))
        self._pose = info["next_pose"]
        out: dict[str, Any] = {"cost": float(cost), **{k: info[k].item() for k in _INFO_KEYS}}
        if "accepting_visit" in info:  # a Büchi task: whether this step took an accepting transition
            out["accepting_visit"] = info["accepting_visit"].item()
        if done:
            out[EPISODE_STATS] = {k: info[k].item() for k in _EPISODE_KEYS}
        if self.render_mode == "human":
            self.render()
        return info["next_obs"], float(reward), bool(info["terminated"]), bool(info["truncated"]), out

    def render(self):
        """An RGB array (``rgb_array``), or the frame shown in a window (``human``); None otherwise."""
        if self.render_mode is None:
            return None
        self._renderer = self._renderer or _frame_renderer(self.env)
        frame = self._renderer(self._pose, f"{self.env.layout.name}: t = {int(getattr(self._state, 't', 0))}")
        if self.render_mode == "rgb_array":
            return frame
        import matplotlib.pyplot as plt  # only for a window on a display

        if self._window is None:
            plt.ion()
            self._window = plt.figure("d2spo/Nav-v0").add_subplot().imshow(frame)
            self._window.axes.set_axis_off()
        self._window.set_data(frame)
        plt.pause(1.0 / self.metadata["render_fps"])
        return None

    def close(self):
        if self._window is not None:
            import matplotlib.pyplot as plt  # only for a window on a display

            plt.close(self._window.figure)
            self._window = None


class NavVectorEnv(VectorEnv):
    """``num_envs`` navigation environments stepped together by one jit-compiled call.

    ``autoreset_mode``: ``NEXT_STEP`` (default: the step after the one that ends an episode resets
    that sub-environment, returns its first observation, reward 0 and no termination, and ignores
    its action) or ``SAME_STEP`` (``obs`` is already the next episode's first observation; the last
    one is in ``info["final_obs"]``, mask ``info["_final_obs"]``). ``max_episode_steps`` (what
    ``make_vec(..., max_episode_steps=N)`` passes) sets ``EnvConfig.max_steps``.
    """

    metadata: ClassVar[dict[str, Any]] = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, num_envs: int = 1, task: Any = "phi1", config: EnvConfig | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, render_mode: str | None = None,
                 max_episode_steps: int | None = None, **overrides):
        _check_render_mode(render_mode, self.metadata["render_modes"])
        try:
            mode = AutoresetMode(autoreset_mode)
        except ValueError:
            raise ConfigError("autoreset_mode", f"expected 'NextStep' or 'SameStep', got {autoreset_mode!r}") from None
        if mode not in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
            raise ConfigError("autoreset_mode", f"{mode} is not supported; use NEXT_STEP or SAME_STEP")
        if max_episode_steps is not None:
            overrides["max_steps"] = max_episode_steps
        self._fns = compiled(env_config(config, overrides), task)
        self.env, self.params = self._fns.env, self._fns.params
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ConfigError("num_envs", f"must be a whole number >= 1, got {num_envs!r}")
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "autoreset_mode": mode, "render_fps": round(1.0 / self.env.config.dt)}
        self.single_observation_space, self.single_action_space = _spaces(self.env)
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, num_envs)
        self._key = None  # the first reset's seed, or one drawn from entropy
        self._state = None
        self._autoreset = np.zeros(num_envs, bool)
        self._first_obs = None  # where _autoreset: the first observation of the next episode
        self._pose = None
        self._renderer: FrameRenderer | None = None

    def _next_key(self) -> jax.Array:
        self._key, key = jax.random.split(self._key)
        return key

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset every sub-environment (``options`` is not used). ``seed``: one int for the batch, or a
        list of one per sub-environment (``num_envs`` ints, as Gymnasium allows), which seeds the batch
        as a whole: the same list gives the same episodes (sub-environment i is not the single env of
        seed ``seed[i]``: the batch splits one key)."""
        if isinstance(seed, (list, tuple, np.ndarray)):
            seeds = [int(x) for x in seed]
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed: a list of {self.num_envs} seeds (one per sub-environment), got {len(seeds)}")
            self._key = seed_key(*seeds)
        elif seed is not None:
            self._key = seed_key(seed)
        elif self._key is None:  # never seeded: a seed from entropy
            self._key = seed_key(int(np.random.default_rng().integers(2**63)))
        self._state, obs = self._fns.reset_batch(self._next_key(), self.params, self.num_envs)
        self._autoreset = np.zeros(self.num_envs, bool)
        self._pose = np.asarray(self._state.pose)
        return np.asarray(obs), {}

    def step(self, actions):
        """Step all sub-environments; returns (obs, reward, terminated, truncated, info), cost in info."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        actions = _checked(actions, "actions", self.action_space, (self.num_envs, self.env.action_size))
        next_step = self.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
        autoreset = jnp.asarray(self._autoreset if next_step else np.zeros(self.num_envs, bool))
        self._state, *out = self._fns.step_masked(self._next_key(), self._state, actions, self.params, autoreset)
        first_obs, reward, cost, done, info = jax.device_get(out)
        self._pose = info["next_pose"]
        extra: dict[str, Any] = {"cost": cost, **{k: info[k] for k in (*_INFO_KEYS, "accepting_visit") if k in info}}
        extra[EPISODE_STATS] = {k: info[k] for k in _EPISODE_KEYS}
        extra["_" + EPISODE_STATS] = done
        if next_step:
            obs = np.where(self._autoreset[:, None], self._first_obs, info["next_obs"]) if self._autoreset.any() \
                else info["next_obs"]
            self._first_obs, self._autoreset = first_obs, done
        else:
            obs = first_obs
            extra["final_obs"], extra["_final_obs"] = info["next_obs"], done
        return obs, reward, info["terminated"], info["truncated"], extra

    def render(self):
        """``rgb_array``: a tuple of one frame per sub-environment; None without a render mode."""
        if self.render_mode is None or self._pose is None:
            return None
        self._renderer = self._renderer or _frame_renderer(self.env)
        return tuple(self._renderer(pose, f"{self.env.layout.name}: env {i}") for i, pose in enumerate(self._pose))


class CostTuple(gymnasium.Wrapper):
    """Safety-Gymnasium's six values from ``NavEnv``: (obs, reward, cost, terminated, truncated, info)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, info["cost"], terminated, truncated, info


class VectorCostTuple(VectorWrapper):
    """Safety-Gymnasium's six values from a vector env: (obs, reward, cost, terminated, truncated, info)."""

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.env.step(actions)
        return obs, reward, info["cost"], terminated, truncated, info


def register() -> None:
    """Register ``d2spo/Nav-v0`` with gymnasium (done on ``import d2spo.envs``; idempotent).

    The spec's ``max_episode_steps`` is the default config's step limit (``EnvConfig.base_max_steps``,
    what the default task on the default layout gets), so ``gym.make`` adds ``TimeLimit`` with it; the
    env also truncates itself at its own ``max_steps``, which a long route raises (docs/env.md). The
    kwarg ``max_episode_steps=None`` keeps ``make_vec`` from passing the spec's limit on as ``max_steps``:
    a vector env keeps its own limit unless the caller gives one."""
    if ENV_ID in gymnasium.registry:
        return
    gymnasium.register(
        id=ENV_ID,
        entry_point="d2spo.envs.gym_env:NavEnv",
        vector_entry_point="d2spo.envs.gym_env:NavVectorEnv",
        max_episode_steps=EnvConfig().base_max_steps,
        kwargs={"max_episode_steps": None},
    )
