"""TD3 (Fujimoto et al., 2018) on the vectorised env, fused into one jitted chunk.

Used directly by ``--algo td3`` (RL-phi: sparse task reward) and ``--algo tlgrl`` (TD3 with the
LTL progress reward of Eq. (8) and the annealed subtask radius of Sec. IV-C). D²SPO builds on the
same pieces (``TD3Agent``, ``explore``, ``td3_update``) in ``algos/d2spo.py``.

Per vectorised step: act (uniform random before ``learning_starts``, then pi(s) + N(0, sigma)),
step every env, store (s, a, r, c, s', terminated) in the device replay buffer (the opening every
off-policy learner shares, ``offpolicy.explore_and_store``), then
``updates_per_step`` TD3 updates (critics every update; actor and targets every
``policy_delay``-th).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from d2spo import replay
from d2spo.algos.base import ChunkLog, RunSchedule, episode_log, params_finite
from d2spo.algos.common.networks import DeterministicActor, TwinQ, first_critic, init_params
from d2spo.algos.common.td3_losses import soft_update, td3_actor_loss, td3_critic_loss
from d2spo.algos.offpolicy import explore_and_store
from d2spo.errors import ConfigError
from d2spo.fields import check_choice, check_fields
from d2spo.ltl.anneal import AnnealConfig
from d2spo.replay import ReplayBuffer, Transition

DEFAULT_WIDTHS = (128, 128)
"""TD3's hidden widths when ``TD3Config.hidden`` is None (and ``--fast`` does not choose)."""


NOISE_SPACES = ("action", "pre-tanh")
"""Values of ``TD3Config.exploration_noise_space``."""


@dataclass(frozen=True)
class TD3Config:
    """TD3 hyper-parameters (Fujimoto et al., 2018; where our defaults differ: docs/config.md)."""

    hidden: tuple[int, ...] | None = None
    """Hidden widths; None: 128 128, 256 256 with --generalist, or 64 64 with --fast."""
    actor_lr: float = 3e-4
    """Adam learning rate of the actor."""
    critic_lr: float = 3e-4
    """Adam learning rate of the critics."""
    gamma: float = 0.99
    """Discount factor."""
    tau: float = 0.005
    """Polyak averaging rate of the target networks."""
    policy_noise: float = 0.2
    """Target-policy smoothing noise std (action units)."""
    noise_clip: float = 0.5
    """Clip of the target-policy smoothing noise."""
    policy_delay: int = 2
    """Actor and targets update every this many critic updates."""
    exploration_noise: float = 0.2
    """Gaussian exploration noise std (action units)."""
    exploration_noise_final: float | None = None
    """When set, the exploration noise falls linearly from exploration_noise to this over the run's
    episodes, so the last episodes act near the greedy policy; None: constant (a patrol on one
    layout: recurrence_noise_final)."""
    recurrence_noise_final: float | None = 0.05
    """The exploration_noise_final of a recurrence (a patrol) trained on one layout when that is
    None: its training episodes are scored by their visits, and the noise costs them whole laps
    (docs/ltl.md); None: constant noise for every task."""
    batch_size: int = 128
    """Minibatch size of each update."""
    buffer_size: int = 300_000
    """Replay capacity (transitions), kept on the device."""
    learning_starts: int = 5_000
    """Random-action transitions before learning starts."""
    updates_per_step: int = 1
    """Gradient updates per vectorised env step."""
    critic_layer_norm: bool = False
    """LayerNorm in the critics' hidden layers."""
    forward_only: bool | None = None
    """The actor proposes action[0] (the linear speed) in [0, 1] only, never reverse; None: on for
    the generalist. What is executed (π_Ω, the filter) may still reverse."""
    smoothness: float = 0.0
    """Weight of a temporal smoothness term in the actor's loss, ``smoothness * ||pi(s') - pi(s)||²``
    over the replay batch's consecutive observations (CAPS' temporal term, squared;
    ``td3_actor_loss``): proposals that change less from step to step; 0: none (the default)."""
    smoothness_dims: tuple[int, ...] | None = None
    """The action dimensions the smoothness term covers (0: the linear speed, 1: the turn rate); None:
    both. ``1`` smooths the steering and leaves a patrol free to flip from forwards to astern."""
    saturation: float = 0.0
    """Weight of a term in the actor's loss, ``saturation * ||max(|z| - saturation_bound, 0)||²`` with z
    the actor's output before its tanh (``td3_actor_loss``): an actor held where the tanh still has
    a slope can still be moved to the other side of an action's range; 0: none (the default)."""
    saturation_bound: float = 2.5
    """|z| beyond which the saturation term counts (tanh(2.5) = 0.987 of the bound)."""
    speed_search: float = 0.0
    """Weight of a term in the actor's loss that pulls a near-stalled proposal's linear speed towards
    the best of a few speeds over its range where the critic values that one more
    (``td3_losses.td3_actor_loss``): an actor stalled at a local maximum of Q, or deep in its tanh,
    reaches the faster speed the critic prefers; 0: none (the default)."""
    exploration_noise_space: str = "action"
    """Where the exploration noise is added: "action" (TD3's: clip(pi(s) + N(0, noise^2)), which
    slows an actor at full speed on average, by 0.4 noise) or "pre-tanh" (to the actor's output
    before its tanh, scaled so that it equals "action" at the box's centre: an action at a bound
    stays there; not in TD3; docs/config.md)."""

    def actor_low(self, action_size: int) -> tuple[float, ...] | None:
        """The actor's smallest action per coordinate (``DeterministicActor.low``): (0, -1, ..) when
        ``forward_only``, else None (-1 everywhere)."""
        return (0.0,) + (-1.0,) * (action_size - 1) if self.forward_only else None

    def noise_at(self, episodes: jax.Array, per_episode) -> jax.Array | float:
        """The exploration noise std after ``episodes`` finished episodes of a run each of whose
        episodes is ``per_episode`` of it (``RunSchedule.per_episode``, 1 / episodes in float32):
        ``exploration_noise``, or with ``exploration_noise_final`` the straight line between the two."""
        if self.exploration_noise_final is None:
            return self.exploration_noise
        done = jnp.minimum(1.0, episodes.astype(jnp.float32) * per_episode)
        return self.exploration_noise + (self.exploration_noise_final - self.exploration_noise) * done

    def for_task(self, recurrence: bool) -> TD3Config:
        """This config as a run on one layout uses it: with ``recurrence`` (the task is a patrol) and
        ``exploration_noise_final`` None, the noise falls to ``recurrence_noise_final``."""
        if recurrence and self.exploration_noise_final is None and self.recurrence_noise_final is not None:
            return replace(self, exploration_noise_final=self.recurrence_noise_final)
        return self

    @property
    def widths(self) -> tuple[int, ...]:
        """The hidden widths in use: ``hidden``, or ``DEFAULT_WIDTHS`` when it is None."""
        return DEFAULT_WIDTHS if self.hidden is None else self.hidden

    def __post_init__(self) -> None:
        check_fields(self, "td3", nullable=("hidden", "forward_only", "exploration_noise_final", "smoothness_dims",
                                            "recurrence_noise_final"),
                     widths=("hidden",), lr=("actor_lr", "critic_lr"), discount=("gamma",),
                     rate=("tau",), positive=("saturation_bound",),
                     non_negative=("policy_noise", "noise_clip", "exploration_noise", "exploration_noise_final",
                                   "recurrence_noise_final", "smoothness", "saturation", "speed_search"),
                     count=("policy_delay", "batch_size", "buffer_size", "updates_per_step"),
                     natural=("learning_starts",), flag=("critic_layer_norm", "forward_only"))
        dims = self.smoothness_dims
        if dims is not None and (not dims or len(set(dims)) != len(dims) or any(d not in (0, 1) for d in dims)):
            raise ConfigError("td3.smoothness_dims", f"distinct action dimensions among 0 (linear speed) and 1 "
                              f"(turn rate), got {dims!r}")
        check_choice(self, "exploration_noise_space", NOISE_SPACES, "td3")


@struct.dataclass
class TD3Agent:
    """Actor, twin critics, their targets and optimiser states."""

    actor: Any
    actor_target: Any
    critic: Any
    critic_target: Any
    actor_opt: Any
    critic_opt: Any
    updates: jax.Array


@struct.dataclass
class TD3Nets:
    actor: DeterministicActor = struct.field(pytree_node=False)
    critic: TwinQ = struct.field(pytree_node=False)
    actor_tx: Any = struct.field(pytree_node=False)
    critic_tx: Any = struct.field(pytree_node=False)


def make_nets(action_size: int, cfg: TD3Config) -> TD3Nets:
    return TD3Nets(
        actor=DeterministicActor(action_size, cfg.widths, low=cfg.actor_low(action_size)),
        critic=TwinQ(cfg.widths, layer_norm=cfg.critic_layer_norm),
        actor_tx=optax.adam(cfg.actor_lr),
        critic_tx=optax.adam(cfg.critic_lr),
    )


def init_agent(key: jax.Array, nets: TD3Nets, obs_size: int, action_size: int) -> TD3Agent:
    k1, k2 = jax.random.split(key)
    obs = jnp.zeros((1, obs_size))
    act = jnp.zeros((1, action_size))
    actor = init_params(nets.actor, k1, obs)
    critic = init_params(nets.critic, k2, obs, act)
    return TD3Agent(actor, actor, critic, critic, nets.actor_tx.init(actor), nets.critic_tx.init(critic),
                    jnp.zeros((), jnp.int32))


def explore(nets: TD3Nets, agent: TD3Agent, obs: jax.Array, key: jax.Array, random_phase: jax.Array,
            noise: float, space: str = "action") -> jax.Array:
    """Behaviour action: uniform during warm-up, else the greedy pi(s) with Gaussian noise of std
    ``noise``, within the actor's box [low, 1] (``DeterministicActor.low``; -1 by default).

    ``space`` (``TD3Config.exploration_noise_space``): "action" adds it to the action and clips,
    TD3's rule; "pre-tanh" adds noise / c1 to the tanh's argument, atanh((pi(s) - c0) / c1), where
    a = c0 + c1 tanh(.) spans the box: the same spread at the box's centre, none at its bounds."""
    k1, k2 = jax.random.split(key)
    low = nets.actor.action_low()
    uniform = jax.random.uniform(k1, (obs.shape[0], nets.actor.action_dim), minval=low, maxval=1.0)
    greedy = nets.actor.apply(agent.actor, obs)
    eps = jax.random.normal(k2, greedy.shape)
    if space == "pre-tanh":
        c0, c1 = (1.0 + low) / 2.0, (1.0 - low) / 2.0
        z = jnp.arctanh(jnp.clip((greedy - c0) / c1, -1.0 + 1e-6, 1.0 - 1e-6))
        noisy = jnp.clip(c0 + c1 * jnp.tanh(z + noise / c1 * eps), low, 1.0)
    else:
        noisy = jnp.clip(greedy + noise * eps, low, 1.0)
    return jnp.where(random_phase, uniform, noisy)


def td3_update(nets: TD3Nets, agent: TD3Agent, batch: Transition, key: jax.Array, cfg: TD3Config,
               execute_fn=None, proposal_weight: float = 0.0):
    """One TD3 update: critics always; actor and targets when ``updates % policy_delay == 0``.

    ``execute_fn``/``proposal_weight``: the actor's output goes through a safety layer before it is
    executed (D²SPO); see ``td3_actor_loss``.
    """
    actor_apply = nets.actor.apply
    critic_apply = nets.critic.apply
    (_, c_metrics), c_grads = jax.value_and_grad(td3_critic_loss, has_aux=True)(
        agent.critic, agent.critic_target, agent.actor_target, batch, key, cfg.gamma, cfg.policy_noise,
        cfg.noise_clip, actor_apply, critic_apply, nets.actor.action_low())
    c_upd, critic_opt = nets.critic_tx.update(c_grads, agent.critic_opt, agent.critic)
    critic = optax.apply_updates(agent.critic, c_upd)

    def actor_step(_):
        (_, a_metrics), a_grads = jax.value_and_grad(td3_actor_loss, has_aux=True)(
            agent.actor, critic, batch.obs, actor_apply, first_critic(nets.critic), None, execute_fn, proposal_weight,
            batch.next_obs, cfg.smoothness, cfg.smoothness_dims, cfg.saturation, cfg.saturation_bound,
            cfg.speed_search, nets.actor.speed_low())
        a_upd, actor_opt = nets.actor_tx.update(a_grads, agent.actor_opt, agent.actor)
        actor = optax.apply_updates(agent.actor, a_upd)
        return (actor, actor_opt, soft_update(agent.actor_target, actor, cfg.tau),
                soft_update(agent.critic_target, critic, cfg.tau), a_metrics["losses/actor"])

    def skip(_):
        return agent.actor, agent.actor_opt, agent.actor_target, agent.critic_target, jnp.float32(jnp.nan)

    actor, actor_opt, actor_target, critic_target, actor_loss = jax.lax.cond(
        agent.updates % cfg.policy_delay == 0, actor_step, skip, None)
    agent = TD3Agent(actor, actor_target, critic, critic_target, actor_opt, critic_opt, agent.updates + 1)
    return agent, {"losses/qf": c_metrics["losses/qf"], "values/q": c_metrics["values/q"], "losses/actor": actor_loss}


@struct.dataclass
class TD3Carry:
    key: jax.Array
    env_state: Any
    obs: jax.Array
    agent: TD3Agent
    buffer: ReplayBuffer
    steps: jax.Array
    """Vectorised env steps taken (each is num_envs transitions)."""
    episodes: jax.Array
    """Episodes finished so far (I_ep of the annealed radius)."""


TD3_METRICS = ("losses/qf", "values/q", "losses/actor")
"""The metrics of ``td3_update`` (NaN for a step without updates)."""


def no_updates() -> dict:
    """The metrics of a vectorised step that made no TD3 update: NaN each."""
    return {k: jnp.float32(jnp.nan) for k in TD3_METRICS}


def ready_to_learn(steps, num_envs: int, cfg: TD3Config):
    """Whether a vectorised step's updates run: once ``learning_starts`` transitions are stored by
    ``steps`` vectorised steps of ``num_envs`` envs."""
    return steps * num_envs >= cfg.learning_starts


def updates_on(nets, agent, batches, keys, cfg: TD3Config, execute_fn=None, proposal_weight: float = 0.0):
    """TD3 updates on the minibatches ``batches`` [U, ...], one key of ``keys`` [U] each: (agent, each
    metric's NaN-mean over the U)."""
    def one(agent, bk):
        return td3_update(nets, agent, bk[0], bk[1], cfg, execute_fn, proposal_weight)

    agent, m = jax.lax.scan(one, agent, (batches, keys))
    return agent, {k: jnp.nanmean(v) for k, v in m.items()}


def learn_from_buffer(nets, agent, buffer, key, steps, num_envs, cfg: TD3Config, execute_fn=None,
                      proposal_weight: float = 0.0):
    """``updates_per_step`` TD3 updates once ``learning_starts`` transitions are stored."""

    def one(agent, k):
        k1, k2 = jax.random.split(k)
        batch = replay.sample(buffer, k1, cfg.batch_size)
        return td3_update(nets, agent, batch, k2, cfg, execute_fn, proposal_weight)

    def learn(agent):
        agent, m = jax.lax.scan(one, agent, jax.random.split(key, cfg.updates_per_step))
        return agent, {k: jnp.nanmean(v) for k, v in m.items()}

    return jax.lax.cond(ready_to_learn(steps, num_envs, cfg), learn, lambda agent: (agent, no_updates()), agent)


class TD3Learner:
    """``--algo td3`` / ``--algo tlgrl``: see the module docstring."""

    def __init__(self, env, params, cfg: TD3Config, anneal: AnnealConfig, num_envs: int, chunk_steps: int,
                 total_episodes: int):
        self.env, self.params, self.cfg = env, params, cfg
        self.schedule = RunSchedule.for_run(anneal, total_episodes)
        self.num_envs, self.chunk_steps = num_envs, chunk_steps
        self.nets = make_nets(env.action_size, cfg)

    # -- shared with D2SPO --------------------------------------------------------------
    def empty_buffer(self) -> ReplayBuffer:
        o = jax.ShapeDtypeStruct((self.env.observation_size,), jnp.float32)
        example = Transition(obs=o, action=jax.ShapeDtypeStruct((self.env.action_size,), jnp.float32),
                             reward=jnp.float32(0), cost=jnp.float32(0), next_obs=o, done=jnp.float32(0))
        return ReplayBuffer.create(self.cfg.buffer_size, example)

    def init(self, key: jax.Array) -> TD3Carry:
        k_env, k_agent, key = jax.random.split(key, 3)
        env_state, obs = self.env.reset_batch(k_env, self.schedule.env_params(self.params, jnp.int32(0)), self.num_envs)
        agent = init_agent(k_agent, self.nets, self.env.observation_size, self.env.action_size)
        zero = jnp.zeros((), jnp.int32)
        return TD3Carry(key, env_state, obs, agent, self.empty_buffer(), zero, zero)

    def chunk(self, carry: TD3Carry) -> tuple[TD3Carry, ChunkLog]:
        carry, log = jax.lax.scan(lambda c, _: self._iteration(c), carry, None, length=self.chunk_steps)
        log = log._replace(nonfinite=jnp.any(log.nonfinite) | ~params_finite(carry.agent))
        return carry, log

    def _iteration(self, c: TD3Carry):
        def act(k, random_phase):
            action = explore(self.nets, c.agent, c.obs, k["act"], random_phase,
                             self.cfg.noise_at(c.episodes, self.schedule.per_episode), self.cfg.exploration_noise_space)
            return action, action

        s = explore_and_store(c, ("act", "env", "update"), act, self.env, self.params, self.schedule, self.num_envs,
                              self.cfg.learning_starts)
        agent, metrics = learn_from_buffer(self.nets, c.agent, s.carry.buffer, s.keys["update"], s.carry.steps,
                                           self.num_envs, self.cfg)
        metrics["charts/label_radius"] = jnp.mean(s.params.label_radius)
        return s.carry.replace(agent=agent), episode_log(s.done, s.info, metrics)

    # -- evaluation ---------------------------------------------------------------------
    def policy(self, carry: TD3Carry):
        return carry.agent.actor

    def act(self, policy, obs, env_state, key):
        return self.nets.actor.apply(policy, obs)
