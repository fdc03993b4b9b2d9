"""The navigation environment of Example 1: a unicycle among box and disk obstacles with an LTL task.

A pure-JAX functional environment (Gymnasium ``FuncEnv`` / Brax style):

>>> env, params = make_env(EnvConfig(layout="paper"), task="phi1")
>>> state, obs = env.reset(key, params)
>>> state, obs, reward, cost, done, info = env.step(key, state, action, params)

``step`` resets finished episodes itself (same-step autoreset): when ``done``, the returned state
and ``obs`` belong to a fresh episode and ``info["next_obs"]`` / ``info["next_pose"]`` hold the
last observation and pose of the finished one. Everything is jit- and vmap-able; ``reset_batch``
and ``step_batch`` vmap over environments.

Per step: the action is clipped to [-1, 1]^2 and applied to the true dynamics (``dynamics.py``);
cost is 1 when the robot disk touches an obstacle or leaves the arena; the automaton reads the
letter of the new position twice, once with the relaxed labelling radius (state ``q``, which
drives the reward and termination) and once with the true area radius (``q_true``, which drives
``completed``). The reward is ``ltl.reward.step_reward`` (Eq. (8) plus shaping); the env only
measures the shaping's distances on the layout.

``make_env`` compiles the task onto the layout once (``envs.compiled_task``; the env keeps it as
``env.task``), checks it (``envs.preflight``) and fills the params from it (``envs.params``).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from d2spo.envs import dynamics, geodesic, geometry, layouts, preflight, sensors, workspace
from d2spo.envs.compiled_task import CompiledTask, compile_task
from d2spo.envs.eager import compiled_when_eager
from d2spo.envs.env_config import EnvConfig
from d2spo.envs.params import EnvParams, env_params
from d2spo.envs.workspace import Layout
from d2spo.errors import ConfigError, in_file
from d2spo.ltl import NoDeterministicBuchi, task_automaton, task_formula
from d2spo.ltl.automaton import Automaton
from d2spo.ltl.labelling import accepting_visit, next_state
from d2spo.ltl.reward import PER_STATE, distance_to_progress, step_reward


@struct.dataclass
class EnvState:
    """State of one environment (add a leading axis for a batch)."""

    pose: jnp.ndarray
    """float32 [3]: (x, y, theta)."""
    vel: jnp.ndarray
    """float32 [2]: realised (v, omega) of the last step (the actuator state, hidden from the agent)."""
    q: jnp.ndarray
    """int32 []: automaton state under relaxed labelling."""
    q_true: jnp.ndarray
    """int32 []: automaton state under true labelling."""
    letter: jnp.ndarray
    """int32 []: last letter under relaxed labelling (for event labelling)."""
    letter_true: jnp.ndarray
    """int32 []: last letter under true labelling."""
    t: jnp.ndarray
    """int32 []: steps taken in this episode."""
    ep_return: jnp.ndarray
    """float32 []: reward so far in this episode."""
    ep_cost: jnp.ndarray
    """float32 []: cost so far in this episode."""
    ep_collided: jnp.ndarray
    """bool []: a collision happened in this episode."""


_LOW = float(np.nextafter(np.float32(-1.0), np.float32(0.0)))
_SQRT2 = math.sqrt(2.0)


def _compute_once(x: jnp.ndarray) -> jnp.ndarray:
    """x, computed once and stored: an exact identity that XLA cannot fuse into x's consumers.

    XLA:CPU fuses cheap elementwise producers into every consumer and recomputes them there once
    per element the consumer reads: the pose update (with its sine and cosine) would be redone for
    each of the K rays of a ray cast and in each of the state's fields. A reduction cannot be fused
    into its consumers, so taking the maximum of x and -inf makes XLA materialise x.
    (``lax.optimization_barrier`` is removed before fusion on CPU.)
    """
    if x.dtype == jnp.bool_:
        return jnp.any(jnp.stack([x, jnp.zeros_like(x)]), axis=0)
    return jnp.max(jnp.stack([x, jnp.full_like(x, -jnp.inf)]), axis=0)


def _uniform(key: jax.Array, n: int) -> jnp.ndarray:
    """n floats uniform in (-1, 1): one PRNG call serves all randomness of a step."""
    return jax.random.uniform(key, (n,), jnp.float32, minval=_LOW, maxval=1.0)


class Env:
    """Pure functional navigation environment; all methods take ``params`` explicitly.

    Observation (float32 [observation_size]), in this order:

    * ``lidar`` [K]: ``sensors.lidar`` ranges divided by H (1 = nothing within H);
    * ``pose`` [4]: x, y scaled to [-1, 1] over the arena, cos(theta), sin(theta);
    * ``areas`` [2N]: each area centre in the robot frame (forward, left), divided by the arena's
      longer side, area by area;
    * ``automaton`` [Q]: one-hot of the relaxed automaton state q;
    * ``path`` [2], with ``EnvConfig.observe_path`` only: the direction of steepest descent of state
      q's shaping field at the robot (``geodesic.descent``) in the robot frame (forward, left).

    An environment over other layouts or with another observation (``envs.generalist``) overrides
    the public hooks: ``observation_parts`` and ``observe`` (the observation), ``reset_state`` (a
    fresh episode) and ``shaping_distance`` (what the reward's shaping measures).
    """

    action_size = 2

    def __init__(self, config: EnvConfig, automaton: Any, n_states: int, n_obstacles: int, n_areas: int,
                 task: CompiledTask | None = None):
        self.config = config
        """The resolved configuration."""
        self.task = task
        """The task compiled on the layout (``envs.compiled_task``); None over a bank of layouts."""
        self.layout: Layout | None = None if task is None else task.layout
        """The (scaled) layout; None over a bank of layouts."""
        self.automaton: Automaton | None = automaton if isinstance(automaton, Automaton) else None
        """The task's automaton (None for an object with ``aps`` and ``arrays()`` only)."""
        self.aps: tuple[str, ...] = tuple(automaton.aps)
        """Automaton propositions; bit i of a letter is aps[i]."""
        self.n_states = n_states
        self.n_obstacles = n_obstacles
        self.n_areas = n_areas
        self.n_rays = config.n_rays
        self.observation_slices: dict[str, slice] = {}
        """Where each part of the observation lies (``observation_parts``)."""
        self.observation_size = 0
        for part, size in self.observation_parts():
            self.observation_slices[part] = slice(self.observation_size, self.observation_size + size)
            self.observation_size += size

    def observation_parts(self) -> list[tuple[str, int]]:
        """The observation's parts, in order, with their sizes (the class docstring)."""
        parts = [("lidar", self.n_rays), ("pose", 4), ("areas", 2 * self.n_areas), ("automaton", self.n_states)]
        return parts + [("path", 2)] if self.config.observe_path else parts

    # ------------------------------------------------------------------------- observation

    @staticmethod
    def _center_distance(xy: jnp.ndarray, params: EnvParams) -> jnp.ndarray:
        """[N]: distance from xy to each area's centre, by the reward's shaping metric."""
        if params.reward.shaping_metric == "geodesic":
            return geodesic.lookup(params.geodesic, xy)
        rel = params.area_center - xy
        return jnp.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1])

    def shaping_distance(self, xy: jnp.ndarray, q: jnp.ndarray, params: EnvParams) -> jnp.ndarray:
        """The reward shaping's distance from xy to what makes progress from automaton state q, by
        its metric: the field of state q, or the nearest progress area (along free space or straight)."""
        if params.reward.shaping_metric == PER_STATE:
            return geodesic.lookup(params.state_field, xy, index=q)
        return distance_to_progress(params.advance, q, self._center_distance(xy, params), params.label_radius)

    def observe(self, state: EnvState, params: EnvParams) -> jnp.ndarray:
        """The observation of ``state`` (see the class docstring for the layout)."""
        geom = params.geom
        pose = state.pose
        frame = _compute_once(jnp.stack([pose[0], pose[1], jnp.cos(pose[2]), jnp.sin(pose[2])]))
        xy, c, s = frame[:2], frame[2], frame[3]
        all_obstacles = jnp.ones((self.n_obstacles,), bool)  # rays are clipped at H: same as O_s
        scan = sensors.lidar_cs(xy, c, s, geom, all_obstacles, params.n_rays, params.sensing_radius)
        scan = scan / params.sensing_radius
        extent = geom.arena_hi - geom.arena_lo
        xy_scaled = 2.0 * (xy - geom.arena_lo) / extent - 1.0
        rel = params.area_center - xy  # [N, 2]
        forward = (c * rel[:, 0] + s * rel[:, 1]) / jnp.max(extent)
        left = (c * rel[:, 1] - s * rel[:, 0]) / jnp.max(extent)
        areas = jnp.stack([forward, left], axis=-1).reshape(-1)
        onehot = (jnp.arange(self.n_states) == state.q).astype(jnp.float32)
        parts = [scan, xy_scaled, jnp.stack([c, s]), areas, onehot]
        if self.config.observe_path:
            d = geodesic.descent(params.state_field, xy, state.q)
            parts.append(jnp.stack([c * d[0] + s * d[1], c * d[1] - s * d[0]]))
        return jnp.concatenate(parts).astype(jnp.float32)

    # ------------------------------------------------------------------------------ labelling

    @staticmethod
    def _letters(xy: jnp.ndarray, q: jnp.ndarray, params: EnvParams) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Letters at position xy under relaxed labelling (in automaton state q) and true labelling: bit
        i is set iff xy is inside an area labelled aps[i]."""
        dx = params.area_center[:, 0] - xy[0]
        dy = params.area_center[:, 1] - xy[1]
        d2 = dx * dx + dy * dy  # [N]; written out, a reduction over the axis of size 2 is slow on CPU
        radius = jnp.where(params.relax_mask[q], params.label_radius, params.area_radius)
        bits = params.area_bits.astype(jnp.int32)  # areas of one label set one bit: OR them, not add
        relaxed = jax.lax.reduce(jnp.where(d2 <= radius**2, bits, 0), np.int32(0), jax.lax.bitwise_or, (0,))
        true = jax.lax.reduce(jnp.where(d2 <= params.area_radius**2, bits, 0), np.int32(0), jax.lax.bitwise_or, (0,))
        return relaxed, true

    # ---------------------------------------------------------------------------------- reset

    def reset_state(self, u: jnp.ndarray, params: EnvParams) -> EnvState:
        """A fresh episode's state from three uniforms in [-1, 1] (the start jitter)."""
        pose = params.start + params.start_jitter * u
        pose = jnp.stack([pose[0], pose[1], dynamics.wrap_angle(pose[2])])
        zero = jnp.zeros((), jnp.int32)
        q0 = params.aut.initial.astype(jnp.int32)
        letter, letter_true = self._letters(pose[:2], q0, params)
        state = EnvState(
            pose=pose,
            vel=jnp.zeros((2,), jnp.float32),
            q=next_state(params.aut, q0, letter, zero, params.event),
            q_true=next_state(params.aut, q0, letter_true, zero, params.event),
            letter=letter,
            letter_true=letter_true,
            t=zero,
            ep_return=jnp.zeros((), jnp.float32),
            ep_cost=jnp.zeros((), jnp.float32),
            ep_collided=jnp.zeros((), bool),
        )
        return state

    @compiled_when_eager()
    def reset(self, key: jax.Array, params: EnvParams) -> tuple[EnvState, jnp.ndarray]:
        """A new episode: the layout's start pose plus uniform jitter; the automaton reads L(z_0)."""
        state = self.reset_state(_uniform(key, 3), params)
        return state, self.observe(state, params)

    # ----------------------------------------------------------------------------------- step

    @compiled_when_eager()
    def step(
        self, key: jax.Array, state: EnvState, action: jnp.ndarray, params: EnvParams
    ) -> tuple[EnvState, jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray, dict[str, Any]]:
        """One control period; returns (state, obs, reward, cost, done, info), resetting if done.
        ``action`` has shape (``action_size``,) (checked when traced: JAX would clamp a missing entry's
        index and step on a wrong command)."""
        if jnp.shape(action) != (self.action_size,):
            raise ValueError(f"action: expected shape ({self.action_size},), got {jnp.shape(action)} "
                             f"(a batch of actions goes to step_batch, shape (n, {self.action_size}))")
        aut = params.aut
        u = _uniform(key, 8)
        normal = _compute_once(_SQRT2 * jax.scipy.special.erfinv(u))  # vectorised over all 8
        noise = normal[0:3]  # standard normal
        slip_u = 0.5 * (u[3:5] + 1.0)  # uniform in [0, 1]

        sensed = geometry.sensed_mask(state.pose[:2], params.geom, params.sensing_radius)
        proposed, vel = dynamics.unicycle_step(state.pose, state.vel, action, noise, slip_u, params.dyn)
        proposed = _compute_once(proposed)
        collided = geometry.collides(proposed[:2], params.geom, params.robot_radius)
        if params.collision_terminates:
            pose, vel_next = proposed, vel
        else:  # blocked: the position stays, the heading turns, the wheels stop
            pose = jnp.where(collided, proposed.at[:2].set(state.pose[:2]), proposed)
            vel_next = jnp.where(collided, 0.0, vel)
        cost = collided.astype(jnp.float32)

        letter, letter_true = self._letters(pose[:2], state.q, params)
        q_next = next_state(aut, state.q, letter, state.letter, params.event)
        q_true_next = next_state(aut, state.q_true, letter_true, state.letter_true, params.event)
        def shaping_distances():  # what the reward's shaping measures, read only when it is on
            diag = jnp.linalg.norm(params.geom.arena_hi - params.geom.arena_lo)
            return (self.shaping_distance(state.pose[:2], state.q, params),
                    self.shaping_distance(pose[:2], q_next, params), diag)

        visit = accepting_visit(aut, state.q, letter, state.letter, params.event)  # None for a monitor
        reward = step_reward(aut, state.q, q_next, collided, params.reward, shaping_distances, visit)

        completed = aut.accepting[q_true_next]
        completed_relaxed = aut.accepting[q_next]
        terminated = completed_relaxed | aut.rejecting[q_next]
        if params.collision_terminates:
            terminated = terminated | collided
        t = state.t + 1
        truncated = (t >= params.max_steps) & ~terminated
        done = _compute_once(terminated | truncated)

        stepped = state.replace(  # replace, not EnvState(...): a subclass's extra fields (e.g. its layout) stay
            pose=pose,
            vel=vel_next,
            q=q_next,
            q_true=q_true_next,
            letter=letter,
            letter_true=letter_true,
            t=t,
            ep_return=state.ep_return + reward,
            ep_cost=state.ep_cost + cost,
            ep_collided=state.ep_collided | collided,
        )
        next_obs = self.observe(stepped, params)
        fresh = self.reset_state(u[5:8], params)
        new_state = jax.tree.map(lambda a, b: jnp.where(done, a, b), fresh, stepped)
        obs = self.observe(new_state, params)  # one ray cast, not a select between two
        info = {
            "terminated": terminated,
            "truncated": truncated,
            "collided": collided,
            "completed": completed,
            "completed_relaxed": completed_relaxed,
            "next_obs": next_obs,
            "pose": state.pose,
            "next_pose": pose,
            "sensed": sensed,
            "q": state.q,
            "q_next": q_next,
            "q_true": state.q_true,
            "q_true_next": q_true_next,
            "ep_return": stepped.ep_return,
            "ep_cost": stepped.ep_cost,
            "ep_length": t,
            "ep_collided": stepped.ep_collided,
            "ep_completed": completed,
            "ep_completed_relaxed": completed_relaxed,
        }
        if aut.visit is not None:  # a Büchi task: its accepting visits under the true labelling
            info["accepting_visit"] = accepting_visit(aut, state.q_true, letter_true, state.letter_true, params.event)
        return new_state, obs, reward, cost, done, info

    # ---------------------------------------------------------------------------------- batch

    @compiled_when_eager(static_argnums=(2,))
    def reset_batch(self, key: jax.Array, params: EnvParams, n: int) -> tuple[EnvState, jnp.ndarray]:
        """``n`` environments: ``reset(k_i, params)`` with ``k_i = jax.random.split(key, n)[i]``."""
        return jax.vmap(self.reset, in_axes=(0, None))(jax.random.split(key, n), params)

    @compiled_when_eager()
    def step_batch(self, key: jax.Array, state: EnvState, action: jnp.ndarray, params: EnvParams):
        """Step a batch (leading axis n): ``step(k_i, state[i], action[i], params)`` with
        ``k_i = jax.random.split(key, n)[i]``."""
        if jnp.ndim(action) != 2:
            raise ValueError(f"actions: expected shape (n, {self.action_size}), got {jnp.shape(action)}")
        n = action.shape[0]
        return jax.vmap(self.step, in_axes=(0, 0, 0, None))(jax.random.split(key, n), state, action, params)


# ------------------------------------------------------------------------------------ make_env


def checked_layout(cfg: EnvConfig) -> tuple[EnvConfig, Layout]:
    """The resolved config and its layout, scaled and checked for this robot (no task needed):
    what ``make_env`` checks before it reads the task. Raises ConfigError."""
    cfg = cfg.resolved()
    layout = layouts.load(cfg.layout).scaled(cfg.layout_scale)
    try:
        workspace.validate(layout)
        workspace.check_robot_fits(layout, cfg.robot_radius, cfg.start_jitter_xy)
    except ConfigError as e:  # a file's fault: which file, as its schema errors say (layouts.load)
        if layouts.layout_file(str(cfg.layout)) is None or "(in " in str(e):
            raise
        raise in_file(e, cfg.layout) from None
    return cfg, layout


def make_env(cfg: EnvConfig, task: Any = "phi1") -> tuple[Env, EnvParams]:
    """The environment and its parameters for a config and a task.

    ``task`` is a task name (``phi1``, ``phi2``, ``relaxed``, ...), an LTL formula string, or an
    automaton object with ``aps`` and ``arrays(feasible_letters)`` (as ``d2spo.ltl.translate``
    returns). The task is compiled onto the layout once (``compiled_task.compile_task``; the env
    keeps it as ``env.task``): the automaton's distances use only the letters this layout can
    produce. Raises ConfigError on a bad config or layout, or a task the layout's letters cannot
    complete; with the per-state shaping also a task the robot cannot complete
    (``preflight.check_feasible``). An unset ``max_steps`` follows the task
    (``preflight.default_max_steps``).
    """
    cfg, layout = checked_layout(cfg)
    try:
        automaton = task_automaton(task_formula(task)) if isinstance(task, str) else task
    except NoDeterministicBuchi as e:  # named as the task's other refusals are (`--task: ...`)
        raise ConfigError("task", str(e)) from None
    name = task if isinstance(task, str) else "the task"
    per_state = cfg.reward.shaping_metric == PER_STATE
    compiled = compile_task(automaton, layout, cfg.label_mode, cfg.robot_radius,
                            cfg.reward.field_costs(cfg.robot_radius) if per_state else None)
    preflight.check_letters(compiled, name)
    max_steps = cfg.max_steps
    if max_steps is None:
        max_steps = cfg.base_max_steps if compiled.distance is None else preflight.default_max_steps(
            compiled, cfg.dt, cfg.v_max * cfg.v_gain, cfg.base_max_steps,
            cfg.recurrence_max_steps)  # an automaton given by arrays(): no routes
        if max_steps > preflight.MAX_DERIVED_STEPS:  # a tiny --dt or --v-max: an episode would never end
            raise ConfigError("episode limit", f"{name}'s shortest route needs over {preflight.MAX_DERIVED_STEPS:,} "
                              f"steps of {cfg.dt:g} s at {cfg.v_max * cfg.v_gain:g} m/s (v_max · v_gain); "
                              "check --dt and --v-max, or give --max-steps")
    if per_state:
        preflight.check_feasible(compiled, repr(name))
    env = Env(cfg, automaton, compiled.n_states, len(layout.obstacles), len(layout.areas), compiled)
    return env, env_params(cfg, compiled, max_steps)
