"""SAC-Lagrangian (LSAC of Tables II-III): SAC with a cost critic and a Lagrange multiplier.

SAC (Haarnoja et al., 2018, "SAC: algorithms and applications"): tanh-Gaussian actor, twin reward
critics with clipped double-Q soft targets, automatic entropy tuning towards H_target = -|A|.
The constrained problem max J_r s.t. J_c <= d is solved on the Lagrangian (OmniSafe's SACLag):

    critics:  y_r = r + gamma (1 - done) (min_i Q'_i(s', a') - alpha log pi(a'|s')),  a' ~ pi(s')
              y_c = c + gamma (1 - done) reduce_i Qc'_i(s', a')          (reduce = max: pessimistic)
    actor:    min  E[alpha log pi(a|s) - min_i Q_i(s, a) + lambda reduce_i Qc_i(s, a)],  a ~ pi(s)
    lambda:   lambda <- max(0, lambda + step(J_c - d))  once per vectorised step,
              J_c = mean cost of the last ``cost_window`` finished episodes.

The SAC pieces (``SACConfig``, ``SACAgent``, ``sac_critic_step``, ``sac_actor_step``) are also
RCRL's (``algos/rcrl.py``), which the authors built on SAC too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from d2spo.algos.common import lagrange
from d2spo.algos.common.lagrange import LagrangeConfig, LagrangeState
from d2spo.algos.common.networks import GaussianActor, TwinQ, init_params
from d2spo.algos.common.sac_losses import (
    alpha_loss,
    default_target_entropy,
    sac_actor_loss,
    sac_cost_critic_loss,
    sac_critic_loss,
    sample_action,
)
from d2spo.algos.common.td3_losses import PenaltyFn, reduce_critics, soft_update
from d2spo.algos.offpolicy import (
    OffPolicyLoop,
    check_cost_options,
    default_lagrange,
    delayed,
    update_multiplier,
)
from d2spo.fields import check_fields
from d2spo.ltl.anneal import AnnealConfig


@dataclass(frozen=True)
class SACConfig:
    """SAC hyper-parameters (Haarnoja et al., 2018, Table 1, except where noted)."""

    hidden: tuple[int, ...] = (128, 128)
    """Hidden layer widths of the actor and of every critic (paper: 256, 256; halved to fit 2 CPU cores)."""
    actor_lr: float = 3e-4
    """Adam learning rate of the actor."""
    critic_lr: float = 3e-4
    """Adam learning rate of every critic (reward, cost or safety)."""
    alpha_lr: float = 3e-4
    """Adam learning rate of log alpha (automatic entropy tuning)."""
    init_alpha: float = 0.05
    """Initial temperature alpha (auto-tuned from there). Ours, for this env's O(0.01) per-step rewards: from
    1.0 (SB3, Brax) the policy stays entropy-driven for over 1M env steps at 1 update per 16 env steps."""
    target_entropy: float | None = None
    """Entropy target of the temperature; None = -|A| (= -2 here)."""
    gamma: float = 0.99
    """Discount factor (reward and cost)."""
    tau: float = 0.005
    """Polyak averaging rate of the target critics (every critic update)."""
    policy_delay: int = 2
    """Actor and temperature update every this many critic updates (OmniSafe SACLag: 2)."""
    batch_size: int = 128
    """Minibatch size of each update (paper: 256; halved to fit 2 CPU cores)."""
    buffer_size: int = 300_000
    """Replay capacity (transitions), kept on the device."""
    learning_starts: int = 5_000
    """Transitions collected with uniform random actions before learning starts."""
    updates_per_step: int = 1
    """Gradient updates per vectorised env step (num_envs transitions)."""

    def __post_init__(self) -> None:
        check_fields(self, "sac", nullable=("target_entropy",), widths=("hidden",),
                     lr=("actor_lr", "critic_lr", "alpha_lr"), positive=("init_alpha",), finite=("target_entropy",),
                     discount=("gamma",), rate=("tau",),
                     count=("policy_delay", "batch_size", "buffer_size", "updates_per_step"),
                     natural=("learning_starts",))


@dataclass(frozen=True)
class SACLagConfig:
    """SAC-Lagrangian: the SAC core, a cost critic ensemble and the Lagrange multiplier."""

    sac: SACConfig = field(default_factory=SACConfig)
    """The SAC core."""
    cost_critics: int = 2
    """Cost critics in the ensemble (twin by default)."""
    cost_reduce: str = "max"
    """How the cost ensemble is combined in the target and the actor penalty: max (pessimistic), min, mean."""
    cost_window: int = 10
    """J_c for the multiplier = mean cost of this many last finished episodes (OmniSafe: window_lens 10)."""
    lagrange: LagrangeConfig = field(default_factory=default_lagrange)
    """Multiplier: cost limit d on the per-episode cost (collisions), its lr, initial value, optimizer."""

    def __post_init__(self) -> None:
        check_cost_options(self, "sac_lag")


# -- the SAC core (shared with RCRL) ----------------------------------------------------------


@struct.dataclass
class SACNets:
    actor: GaussianActor = struct.field(pytree_node=False)
    critic: TwinQ = struct.field(pytree_node=False)
    actor_tx: Any = struct.field(pytree_node=False)
    critic_tx: Any = struct.field(pytree_node=False)
    alpha_tx: Any = struct.field(pytree_node=False)
    target_entropy: float = struct.field(pytree_node=False)


@struct.dataclass
class SACAgent:
    """Actor, twin reward critics and target, log alpha, their optimiser states."""

    actor: Any
    critic: Any
    critic_target: Any
    log_alpha: jax.Array
    actor_opt: Any
    critic_opt: Any
    alpha_opt: Any
    updates: jax.Array


def make_sac_nets(action_size: int, cfg: SACConfig) -> SACNets:
    target = default_target_entropy(action_size) if cfg.target_entropy is None else cfg.target_entropy
    return SACNets(GaussianActor(action_size, cfg.hidden), TwinQ(cfg.hidden), optax.adam(cfg.actor_lr),
                   optax.adam(cfg.critic_lr), optax.adam(cfg.alpha_lr), target)


def init_sac_agent(key: jax.Array, nets: SACNets, obs_size: int, cfg: SACConfig) -> SACAgent:
    k1, k2 = jax.random.split(key)
    obs, act = jnp.zeros((1, obs_size)), jnp.zeros((1, nets.actor.action_dim))
    actor, critic = init_params(nets.actor, k1, obs), init_params(nets.critic, k2, obs, act)
    log_alpha = jnp.float32(math.log(cfg.init_alpha))
    return SACAgent(actor, critic, critic, log_alpha, nets.actor_tx.init(actor), nets.critic_tx.init(critic),
                    nets.alpha_tx.init(log_alpha), jnp.zeros((), jnp.int32))


def sac_behaviour(nets: SACNets, agent: SACAgent, obs: jax.Array, key: jax.Array) -> jax.Array:
    """Exploration: a ~ pi(.|s)."""
    return sample_action(key, agent.actor, obs, nets.actor.apply)[0]


def sac_act(nets: SACNets, actor_params: Any, obs: jax.Array) -> jax.Array:
    """Deterministic evaluation action tanh(mean)."""
    return jnp.tanh(nets.actor.apply(actor_params, obs)[0])


def sac_critic_step(nets: SACNets, agent: SACAgent, batch, key: jax.Array, cfg: SACConfig):
    """Soft clipped double-Q step on the reward critics and their Polyak-averaged target."""
    (_, m), g = jax.value_and_grad(sac_critic_loss, has_aux=True)(
        agent.critic, agent.critic_target, agent.actor, jnp.exp(agent.log_alpha), batch, key, cfg.gamma,
        nets.actor.apply, nets.critic.apply)
    upd, opt = nets.critic_tx.update(g, agent.critic_opt, agent.critic)
    critic = optax.apply_updates(agent.critic, upd)
    agent = agent.replace(critic=critic, critic_opt=opt, critic_target=soft_update(agent.critic_target, critic, cfg.tau))
    return agent, {"losses/qf": m["losses/qf"], "values/q": m["values/q"]}


def sac_actor_step(nets: SACNets, agent: SACAgent, obs: jax.Array, key: jax.Array, penalty_fn: PenaltyFn | None):
    """Actor on alpha log pi - min Q + penalty, then the temperature on the same sample's log pi."""
    alpha = jnp.exp(agent.log_alpha)
    (_, m), g = jax.value_and_grad(sac_actor_loss, has_aux=True)(
        agent.actor, agent.critic, alpha, obs, key, nets.actor.apply, nets.critic.apply, penalty_fn)
    upd, actor_opt = nets.actor_tx.update(g, agent.actor_opt, agent.actor)
    a_loss, a_grad = jax.value_and_grad(alpha_loss)(agent.log_alpha, m["values/log_prob"], nets.target_entropy)
    a_upd, alpha_opt = nets.alpha_tx.update(a_grad, agent.alpha_opt, agent.log_alpha)
    agent = agent.replace(actor=optax.apply_updates(agent.actor, upd), actor_opt=actor_opt,
                          log_alpha=optax.apply_updates(agent.log_alpha, a_upd), alpha_opt=alpha_opt)
    metrics = {"losses/actor": m["losses/actor"], "losses/alpha": a_loss, "charts/alpha": alpha,
               "charts/entropy": m["values/entropy"]}
    return agent, metrics


# -- SAC-Lagrangian ---------------------------------------------------------------------------


@struct.dataclass
class SACLagAgent:
    sac: SACAgent
    cost_critic: Any
    cost_critic_target: Any
    cost_opt: Any
    lag: LagrangeState


class SACLagLearner:
    """``--algo sac-lag``: see the module docstring."""

    def __init__(self, env, params, cfg: SACLagConfig, anneal: AnnealConfig, num_envs: int, chunk_steps: int,
                 total_episodes: int):
        self.env, self.cfg, s = env, cfg, cfg.sac
        self.nets = make_sac_nets(env.action_size, s)
        self.cost_net = TwinQ(s.hidden, n_critics=cfg.cost_critics)
        self.cost_tx = optax.adam(s.critic_lr)
        self.loop = OffPolicyLoop(env, params, anneal, num_envs, chunk_steps, total_episodes,
                                  buffer_size=s.buffer_size, batch_size=s.batch_size,
                                  learning_starts=s.learning_starts, updates_per_step=s.updates_per_step,
                                  cost_window=cfg.cost_window)

    def init(self, key: jax.Array):
        k_sac, k_cost, k_loop = jax.random.split(key, 3)
        obs_size = self.env.observation_size
        sac = init_sac_agent(k_sac, self.nets, obs_size, self.cfg.sac)
        qc = init_params(self.cost_net, k_cost, jnp.zeros((1, obs_size)), jnp.zeros((1, self.env.action_size)))
        agent = SACLagAgent(sac, qc, qc, self.cost_tx.init(qc), lagrange.create(self.cfg.lagrange))
        return self.loop.init(k_loop, agent)

    def chunk(self, carry):
        return self.loop.chunk(carry, self)

    # -- hooks of the loop --------------------------------------------------------------
    def behaviour(self, agent: SACLagAgent, obs, key):
        return sac_behaviour(self.nets, agent.sac, obs, key)

    def on_step(self, agent: SACLagAgent, mean_cost):
        lag = update_multiplier(agent.lag, mean_cost)
        return agent.replace(lag=lag), {"charts/lambda": lag.multiplier}

    def update(self, agent: SACLagAgent, batch, key):
        s = self.cfg.sac
        k_q, k_c, k_pi = jax.random.split(key, 3)
        sac, metrics = sac_critic_step(self.nets, agent.sac, batch, k_q, s)
        (_, m), g = jax.value_and_grad(sac_cost_critic_loss, has_aux=True)(
            agent.cost_critic, agent.cost_critic_target, sac.actor, batch, k_c, s.gamma, self.nets.actor.apply,
            self.cost_net.apply, self.cfg.cost_reduce)
        upd, cost_opt = self.cost_tx.update(g, agent.cost_opt, agent.cost_critic)
        qc = optax.apply_updates(agent.cost_critic, upd)
        lam = lagrange.value(agent.lag)

        def penalty(obs, action):  # lambda Qc(s, a), the constraint term of the Lagrangian
            return lam * reduce_critics(self.cost_net.apply(qc, obs, action), self.cfg.cost_reduce)

        sac, a_metrics = delayed(sac.updates % s.policy_delay == 0,
                                 lambda sac: sac_actor_step(self.nets, sac, batch.obs, k_pi, penalty), sac)
        agent = SACLagAgent(sac.replace(updates=sac.updates + 1), qc, soft_update(agent.cost_critic_target, qc, s.tau),
                            cost_opt, agent.lag)
        return agent, {**metrics, **a_metrics, "losses/qc": m["losses/qc"], "values/qc": m["values/qc"]}

    # -- evaluation ---------------------------------------------------------------------
    def policy(self, carry):
        return carry.agent.sac.actor

    def act(self, policy, obs, env_state, key):
        return sac_act(self.nets, policy, obs)

