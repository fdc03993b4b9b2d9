"""The fused off-policy loop shared by the safe baselines ``td3-lag``, ``sac-lag`` and ``rcrl``, and
the opening of every off-policy learner's vectorised step (``explore_and_store``), which TD3 and D²SPO
call too. Per vectorised step, inside the chunk's ``lax.scan``:

1. act: uniform in [-1, 1]^m until ``learning_starts`` transitions are stored, then the
   algorithm's ``behaviour`` (exploration) policy;
2. step every env with the annealed labelling radius of Sec. IV-C (``d2spo.ltl.anneal``);
3. store (s, a, r, c, s', terminated) in the device replay buffer; with a ``cost_window`` (the
   ``*-lag`` methods), write the cost of every episode that just ended into a ring of the last
   ``cost_window`` episode costs (J_c's estimate);
4. once ``learning_starts`` transitions are stored: with a cost window, the algorithm's ``on_step``
   hook (the Lagrange multiplier step), then ``updates_per_step`` gradient ``update`` s on uniform
   minibatches.

Metrics are scalars per step; NaN means "no value this step" (warm-up, or a delayed actor).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
from flax import struct

from d2spo import replay
from d2spo.algos.base import ChunkLog, RunSchedule, episode_log, params_finite
from d2spo.ltl.anneal import AnnealConfig
from d2spo.replay import ReplayBuffer, Transition

Metrics = dict[str, jax.Array]


class Stepped(NamedTuple):
    """What the opening of a vectorised step (``explore_and_store``) hands the learner that goes on."""

    carry: Any
    """The carry with its key, env states, observations, buffer and counters advanced; agent unchanged."""
    keys: dict[str, jax.Array]
    """This step's keys, by the names the learner split its key into."""
    params: Any
    """The env params of this step (its annealed labelling radius)."""
    proposal: jax.Array
    """[N, m]: the learner's proposed action."""
    action: jax.Array
    """[N, m]: the executed (and stored) action: D²SPO's π_Ω of the proposal, else the proposal."""
    done: jax.Array
    info: dict[str, jax.Array]


def explore_and_store(c, keys: tuple[str, ...], act: Callable, env, params, schedule: RunSchedule, num_envs: int,
                      learning_starts: int) -> Stepped:
    """The opening of every off-policy learner's vectorised step, written once. ``c`` has ``key``,
    ``env_state``, ``obs``, ``buffer``, ``steps`` and ``episodes`` (``TD3Carry``, ``OffPolicyCarry``).

    1. split ``c.key`` into the next key and one key per name in ``keys`` (each learner its own split;
       one of them is ``"env"``);
    2. act: ``act(keys, random_phase) -> (proposal, action)``; ``random_phase`` is true until
       ``learning_starts`` transitions are stored;
    3. step every env with the annealed labelling radius of Sec. IV-C;
    4. store (s, a, r, c, s', terminated) in the replay buffer.
    """
    key, *split = jax.random.split(c.key, 1 + len(keys))
    named = dict(zip(keys, split))
    random_phase = c.steps * num_envs < learning_starts
    proposal, action = act(named, random_phase)
    params = schedule.env_params(params, c.episodes)
    env_state, obs, reward, cost, done, info = env.step_batch(named["env"], c.env_state, action, params)
    buffer = replay.add_batch(c.buffer, Transition(c.obs, action, reward, cost, info["next_obs"],
                                                   info["terminated"].astype(jnp.float32)))
    carry = c.replace(key=key, env_state=env_state, obs=obs, buffer=buffer, steps=c.steps + 1,
                      episodes=c.episodes + jnp.sum(done).astype(jnp.int32))
    return Stepped(carry, named, params, proposal, action, done, info)


@struct.dataclass
class CostWindow:
    """The costs of the last W finished episodes, as a ring (the multiplier's estimate of J_c)."""

    costs: jax.Array
    """float32 [W]."""
    count: jax.Array
    """int32 []: episodes recorded so far (the ring is full once count >= W)."""


def empty_window(size: int) -> CostWindow:
    return CostWindow(jnp.zeros((size,), jnp.float32), jnp.zeros((), jnp.int32))


def record_episodes(window: CostWindow, done: jax.Array, ep_cost: jax.Array) -> CostWindow:
    """Append the costs of the episodes that ended (``done`` [N]) in env order; keeps the last W."""
    costs, total = replay.write_rows(window.costs, window.count, ep_cost, done)
    return CostWindow(costs, window.count + total)


def mean_episode_cost(window: CostWindow) -> jax.Array:
    """Mean cost of the recorded episodes (at most W); NaN before the first one ends."""
    size = window.costs.shape[0]
    filled = jnp.minimum(window.count, size)
    total = jnp.sum(jnp.where(jnp.arange(size) < filled, window.costs, 0.0))
    return jnp.where(filled > 0, total / jnp.maximum(filled, 1), jnp.nan).astype(jnp.float32)


class OffPolicyAlgo(Protocol):
    """What an algorithm gives the loop (all pure, traced inside the chunk)."""

    def behaviour(self, agent: Any, obs: jax.Array, key: jax.Array, episodes: jax.Array) -> jax.Array:
        """Exploration action [N, m] in [-1, 1] once warm-up is over, ``episodes`` episodes into the run
        (an annealed exploration noise reads it)."""

    def on_step(self, agent: Any, mean_cost: jax.Array) -> tuple[Any, Metrics]:
        """Once per vectorised step after warm-up, before the updates; ``mean_cost`` may be NaN.
        Called only when the loop keeps a cost window."""

    def update(self, agent: Any, batch: Transition, key: jax.Array) -> tuple[Any, Metrics]:
        """One gradient update on a minibatch."""


@struct.dataclass
class OffPolicyCarry:
    key: jax.Array
    env_state: Any
    obs: jax.Array
    agent: Any
    buffer: ReplayBuffer
    steps: jax.Array
    """Vectorised env steps taken (each is num_envs transitions)."""
    episodes: jax.Array
    """Episodes finished so far (I_ep of the annealed radius)."""
    costs: CostWindow | None
    """The last episode costs (None without a cost window)."""


class OffPolicyLoop:
    """Acting, env stepping, storage, warm-up and update scheduling, written once."""

    def __init__(self, env, params, anneal: AnnealConfig, num_envs: int, chunk_steps: int, total_episodes: int, *,
                 buffer_size: int, batch_size: int, learning_starts: int, updates_per_step: int,
                 cost_window: int | None = None):
        self.env, self.params = env, params
        self.schedule = RunSchedule.for_run(anneal, total_episodes)
        self.num_envs, self.chunk_steps = num_envs, chunk_steps
        self.buffer_size, self.batch_size = buffer_size, batch_size
        self.learning_starts, self.updates_per_step = learning_starts, updates_per_step
        self.cost_window = cost_window

    def init(self, key: jax.Array, agent: Any) -> OffPolicyCarry:
        k_env, key = jax.random.split(key)
        env_state, obs = self.env.reset_batch(k_env, self.schedule.env_params(self.params, jnp.int32(0)), self.num_envs)
        o = jax.ShapeDtypeStruct((self.env.observation_size,), jnp.float32)
        example = Transition(obs=o, action=jax.ShapeDtypeStruct((self.env.action_size,), jnp.float32),
                             reward=jnp.float32(0), cost=jnp.float32(0), next_obs=o, done=jnp.float32(0))
        zero = jnp.zeros((), jnp.int32)
        costs = None if self.cost_window is None else empty_window(self.cost_window)
        return OffPolicyCarry(key, env_state, obs, agent, ReplayBuffer.create(self.buffer_size, example), zero, zero,
                              costs)

    def chunk(self, carry: OffPolicyCarry, algo: OffPolicyAlgo) -> tuple[OffPolicyCarry, ChunkLog]:
        carry, log = jax.lax.scan(lambda c, _: self._iteration(c, algo), carry, None, length=self.chunk_steps)
        return carry, log._replace(nonfinite=jnp.any(log.nonfinite) | ~params_finite(carry.agent))

    def _iteration(self, c: OffPolicyCarry, algo: OffPolicyAlgo):
        def act(k, warm_up):
            uniform = jax.random.uniform(k["uniform"], (self.num_envs, self.env.action_size), minval=-1.0, maxval=1.0)
            action = jnp.where(warm_up, uniform, algo.behaviour(c.agent, c.obs, k["act"], c.episodes))
            return action, action

        s = explore_and_store(c, ("act", "uniform", "env", "update"), act, self.env, self.params, self.schedule,
                              self.num_envs, self.learning_starts)
        costs = None if c.costs is None else record_episodes(c.costs, s.done, s.info["ep_cost"])
        mean_cost = None if costs is None else mean_episode_cost(costs)
        ready = s.carry.steps * self.num_envs >= self.learning_starts
        agent, metrics = self._learn(algo, c.agent, s.carry.buffer, s.keys["update"], mean_cost, ready)
        metrics["charts/label_radius"] = jnp.mean(s.params.label_radius)
        if mean_cost is not None:
            metrics["charts/recent_ep_cost"] = mean_cost
        return s.carry.replace(agent=agent, costs=costs), episode_log(s.done, s.info, metrics)

    def _learn(self, algo: OffPolicyAlgo, agent, buffer, key, mean_cost, ready):
        def one(agent, k):
            k1, k2 = jax.random.split(k)
            return algo.update(agent, replay.sample(buffer, k1, self.batch_size), k2)

        def learn(agent):
            step_metrics = {}
            if mean_cost is not None:
                agent, step_metrics = algo.on_step(agent, mean_cost)
            agent, m = jax.lax.scan(one, agent, jax.random.split(key, self.updates_per_step))
            return agent, {**step_metrics, **{k: jnp.nanmean(v) for k, v in m.items()}}

        def wait(agent):
            shapes = jax.eval_shape(learn, agent)[1]
            return agent, {k: jnp.full(s.shape, jnp.nan, s.dtype) for k, s in shapes.items()}

        return jax.lax.cond(ready, learn, wait, agent)


def delayed(do: jax.Array, step, agent):
    """``step(agent) -> (agent, metrics)`` if ``do``, else the agent unchanged and NaN metrics."""

    def skip(agent):
        shapes = jax.eval_shape(step, agent)[1]
        return agent, {k: jnp.full(s.shape, jnp.nan, s.dtype) for k, s in shapes.items()}

    return jax.lax.cond(do, step, skip, agent)

