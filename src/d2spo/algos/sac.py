"""The SAC core (Haarnoja et al., 2018, "SAC: algorithms and applications"), shared by sac-lag and rcrl.

Tanh-Gaussian actor, twin reward critics with clipped double-Q soft targets, automatic entropy
tuning towards H_target = -|A| (losses in ``algos/common/sac_losses.py``):

    critics:  y_r = r + gamma (1 - done) (min_i Q'_i(s', a') - alpha log pi(a'|s')),  a' ~ pi(s')
    actor:    min  E[alpha log pi(a|s) - min_i Q_i(s, a) + penalty(s, a)],  a ~ pi(s)
    alpha:    min  -alpha (mean log pi + H_target)

``penalty`` is the learner's constraint term: lambda Qc(s, a) for sac-lag, lambda(s) Q_h(s, a) for rcrl.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from d2spo.algos.common.networks import GaussianActor, TwinQ, init_params
from d2spo.algos.common.sac_losses import (
    alpha_loss,
    default_target_entropy,
    sac_actor_loss,
    sac_critic_loss,
    sample_action,
)
from d2spo.algos.common.td3_losses import PenaltyFn, soft_update
from d2spo.fields import check_fields


@dataclass(frozen=True)
class SACConfig:
    """SAC hyper-parameters (Haarnoja et al., 2018, Table 1; ours and their sources: docs/baselines.md)."""

    hidden: tuple[int, ...] = (128, 128)
    """Hidden widths of the actor and every critic."""
    actor_lr: float = 3e-4
    """Adam learning rate of the actor."""
    critic_lr: float = 3e-4
    """Adam learning rate of every critic."""
    alpha_lr: float = 3e-4
    """Adam learning rate of log alpha."""
    init_alpha: float = 0.05
    """Initial temperature alpha (auto-tuned from there)."""
    target_entropy: float | None = None
    """Entropy target; None = -|A| (= -2 here)."""
    gamma: float = 0.99
    """Discount factor (reward and cost)."""
    tau: float = 0.005
    """Polyak averaging rate of the target critics."""
    policy_delay: int = 2
    """Actor and alpha update every this many critic updates."""
    batch_size: int = 128
    """Minibatch size of each update."""
    buffer_size: int = 300_000
    """Replay capacity (transitions), kept on the device."""
    learning_starts: int = 5_000
    """Random-action transitions before learning starts."""
    updates_per_step: int = 1
    """Gradient updates per vectorised env step."""

    def __post_init__(self) -> None:
        check_fields(self, "sac", nullable=("target_entropy",), widths=("hidden",),
                     lr=("actor_lr", "critic_lr", "alpha_lr"), positive=("init_alpha",), finite=("target_entropy",),
                     discount=("gamma",), rate=("tau",),
                     count=("policy_delay", "batch_size", "buffer_size", "updates_per_step"),
                     natural=("learning_starts",))


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
