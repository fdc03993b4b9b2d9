"""Reachability Constrained RL (RCRL; Yu, Ma, Li and Chen, ICML 2022), on SAC as the authors' RAC.

The constraint is state-wise: h(s) <= 0 at every step. Its safety value Q_h(s, a) (the worst h
the trajectory will meet, discounted as in Fisac et al., 2019) satisfies the reachability
self-consistency condition, whose backup is (the paper's safety Bellman operator)

    Q_h(s, a) = (1 - gamma) h(s) + gamma max{h(s), V_h(s')},   V_h(s') = Q_h(s', a'), a' ~ pi(s')

and the feasible set is {s : V_h(s) <= 0}. The policy solves the state-wise Lagrangian

    min_pi max_{lambda(.) >= 0}  E_s[ alpha log pi(a|s) - min_i Q_i(s, a) + lambda(s) Q_h(s, a) ],  a ~ pi(s)

with a multiplier network lambda(s) = softplus(MLP(s)) trained by gradient *ascent* on
lambda(s) Q_h(s, a) every ``multiplier_delay``-th update (slower timescale than the policy).

h from this env (documented in docs/baselines.md): a signed distance read off the lidar part of the
observation, h(s) = r + margin - H min_k lidar_k(s) in metres (> 0: the rays see an obstacle or
wall within ``margin`` of the robot disk). A collision the rays miss still counts as unsafe: on a
transition with cost > 0, h(s') >= margin. A terminated s' is absorbing: V_h(s') = h(s').
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from d2spo.algos.common.networks import MLP, TwinQ, init_params
from d2spo.algos.common.sac_losses import sample_action
from d2spo.algos.common.td3_losses import ensemble_mse, reduce_critics, soft_update
from d2spo.algos.offpolicy import OffPolicyLoop, delayed
from d2spo.algos.sac import (
    SACAgent,
    SACConfig,
    init_sac_agent,
    make_sac_nets,
    sac_act,
    sac_actor_step,
    sac_behaviour,
    sac_critic_step,
)
from d2spo.fields import check_fields
from d2spo.ltl.anneal import AnnealConfig


@dataclass(frozen=True)
class RCRLConfig:
    """RCRL: the SAC core, the safety critic Q_h and the state-dependent multiplier lambda(s).
    Sources of the defaults: docs/baselines.md."""

    sac: SACConfig = field(default_factory=SACConfig)
    """The SAC core (sac-lag's defaults)."""
    margin: float = 0.05
    """Safety margin (m) in h(s) = r + margin - lidar range."""
    safety_critics: int = 1
    """Q_h networks; with more, their max is used."""
    multiplier_hidden: tuple[int, ...] = (64, 64)
    """Hidden widths of the multiplier network lambda(s)."""
    multiplier_lr: float = 5e-5
    """Adam learning rate of lambda(s)."""
    multiplier_delay: int = 12
    """lambda(s) takes one ascent step every this many updates."""
    multiplier_bias: float = 0.0
    """lambda(s) starts at softplus(bias)."""

    def __post_init__(self) -> None:
        check_fields(self, "rcrl", positive=("margin",), count=("safety_critics", "multiplier_delay"),
                     widths=("multiplier_hidden",), lr=("multiplier_lr",), finite=("multiplier_bias",))


# -- the maths ------------------------------------------------------------------------------


def constraint_value(lidar: jax.Array, robot_radius: jax.Array, sensing_radius: jax.Array,
                     margin: float) -> jax.Array:
    """h(s) = r + margin - H min_k lidar_k (metres; lidar normalised by H as in the observation)."""
    return robot_radius + margin - sensing_radius * jnp.min(lidar, axis=-1)


def rcrl_target(h: jax.Array, next_v: jax.Array, gamma: float) -> jax.Array:
    """Reachability backup: Q_h(s, a) <- (1 - gamma) h(s) + gamma max{h(s), V_h(s')}."""
    return jax.lax.stop_gradient((1.0 - gamma) * h + gamma * jnp.maximum(h, next_v))


def safety_target(h: jax.Array, h_next: jax.Array, cost: jax.Array, done: jax.Array, next_qh: jax.Array,
                  gamma: float, margin: float) -> jax.Array:
    """The Q_h target of a stored transition (s, a, c, s', done), next_qh = Q_h'(s', a'), a' ~ pi(s').

    A collision (c > 0) is unsafe even where the rays miss it: h(s') >= margin. A terminated s' is
    absorbing, V_h(s') = h(s'); otherwise V_h(s') = next_qh (time-limit ends bootstrap).
    """
    h_next = jnp.where(cost > 0, jnp.maximum(h_next, margin), h_next)
    return rcrl_target(h, jnp.where(done > 0, h_next, next_qh), gamma)


def multiplier_loss(mult_params: Any, obs: jax.Array, qh: jax.Array, mult_apply) -> jax.Array:
    """-mean(lambda(s) Q_h(s, pi(s))): descending it is ascent on the Lagrangian in lambda."""
    return -jnp.mean(mult_apply(mult_params, obs) * jax.lax.stop_gradient(qh))


class StateMultiplier(nn.Module):
    """lambda(s) = softplus(MLP(s) + bias) >= 0; the last layer starts at zero, so lambda = softplus(bias)."""

    hidden: Sequence[int] = (64, 64)
    bias: float = 0.0

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        x = MLP(self.hidden, 1, final_kernel_init=nn.initializers.zeros)(obs)[..., 0]
        return jax.nn.softplus(x + self.bias)


# -- the learner ----------------------------------------------------------------------------


@struct.dataclass
class RCRLAgent:
    sac: SACAgent
    safety: Any
    safety_target: Any
    safety_opt: Any
    multiplier: Any
    multiplier_opt: Any


class RCRLLearner:
    """``--algo rcrl``: see the module docstring."""

    def __init__(self, env, params, cfg: RCRLConfig, anneal: AnnealConfig, num_envs: int, chunk_steps: int,
                 total_episodes: int):
        self.env, self.params, self.cfg, s = env, params, cfg, cfg.sac
        self.nets = make_sac_nets(env.action_size, s)
        self.safety_net = TwinQ(s.hidden, n_critics=cfg.safety_critics)
        self.safety_tx = optax.adam(s.critic_lr)
        self.mult_net = StateMultiplier(cfg.multiplier_hidden, cfg.multiplier_bias)
        self.mult_tx = optax.adam(cfg.multiplier_lr)
        self.lidar = env.observation_slices["lidar"]
        self.loop = OffPolicyLoop(env, params, anneal, num_envs, chunk_steps, total_episodes,
                                  buffer_size=s.buffer_size, batch_size=s.batch_size,
                                  learning_starts=s.learning_starts, updates_per_step=s.updates_per_step)

    def h(self, obs: jax.Array) -> jax.Array:
        """The constraint function h(s) of this env (> 0: unsafe), from the observation's lidar."""
        return constraint_value(obs[..., self.lidar], self.params.robot_radius, self.params.sensing_radius,
                                self.cfg.margin)

    def init(self, key: jax.Array):
        k_sac, k_h, k_m, k_loop = jax.random.split(key, 4)
        obs, act = jnp.zeros((1, self.env.observation_size)), jnp.zeros((1, self.env.action_size))
        sac = init_sac_agent(k_sac, self.nets, self.env.observation_size, self.cfg.sac)
        qh = init_params(self.safety_net, k_h, obs, act)
        mult = init_params(self.mult_net, k_m, obs)
        agent = RCRLAgent(sac, qh, qh, self.safety_tx.init(qh), mult, self.mult_tx.init(mult))
        return self.loop.init(k_loop, agent)

    def chunk(self, carry):
        return self.loop.chunk(carry, self)

    def _qh(self, params, obs, action):
        return reduce_critics(self.safety_net.apply(params, obs, action), "max")

    def safety_loss(self, qh_params, qh_target, actor, batch, key):
        """Sum over the Q_h networks of their MSE to the reachability target."""
        h = self.h(batch.obs)
        next_action, _ = sample_action(key, actor, batch.next_obs, self.nets.actor.apply)
        next_qh = self._qh(qh_target, batch.next_obs, next_action)
        y = safety_target(h, self.h(batch.next_obs), batch.cost, batch.done, next_qh, self.cfg.sac.gamma,
                          self.cfg.margin)
        q = self.safety_net.apply(qh_params, batch.obs, batch.action)
        loss = ensemble_mse(q, y)
        return loss, {"losses/qh": loss, "values/qh": jnp.mean(q), "values/h": jnp.mean(h)}

    # -- hooks of the loop --------------------------------------------------------------
    def behaviour(self, agent: RCRLAgent, obs, key, episodes):  # SAC's own entropy: no schedule
        return sac_behaviour(self.nets, agent.sac, obs, key)

    def update(self, agent: RCRLAgent, batch, key):
        s, cfg = self.cfg.sac, self.cfg
        k_q, k_h, k_pi, k_m = jax.random.split(key, 4)
        sac, metrics = sac_critic_step(self.nets, agent.sac, batch, k_q, s)
        (_, mh), g = jax.value_and_grad(self.safety_loss, has_aux=True)(
            agent.safety, agent.safety_target, sac.actor, batch, k_h)
        upd, safety_opt = self.safety_tx.update(g, agent.safety_opt, agent.safety)
        qh = optax.apply_updates(agent.safety, upd)
        lam = jax.lax.stop_gradient(self.mult_net.apply(agent.multiplier, batch.obs))

        def penalty(obs, action):  # lambda(s) Q_h(s, a), the state-wise constraint term
            return lam * self._qh(qh, obs, action)

        sac, am = delayed(sac.updates % s.policy_delay == 0,
                          lambda sac: sac_actor_step(self.nets, sac, batch.obs, k_pi, penalty), sac)

        def ascend(mult):  # one step on lambda(s) Q_h(s, pi(s)), a ~ pi(s) from the updated actor
            action, _ = sample_action(k_m, sac.actor, batch.obs, self.nets.actor.apply)
            v = self._qh(qh, batch.obs, action)
            loss, g = jax.value_and_grad(multiplier_loss)(mult[0], batch.obs, v, self.mult_net.apply)
            upd, opt = self.mult_tx.update(g, mult[1], mult[0])
            return (optax.apply_updates(mult[0], upd), opt), {"losses/multiplier": loss,
                                                              "charts/feasible_frac": jnp.mean(v <= 0.0)}

        (mult, mult_opt), mm = delayed(sac.updates % cfg.multiplier_delay == 0, ascend,
                                       (agent.multiplier, agent.multiplier_opt))
        agent = RCRLAgent(sac.replace(updates=sac.updates + 1), qh, soft_update(agent.safety_target, qh, s.tau),
                          safety_opt, mult, mult_opt)
        metrics = {**metrics, **am, **mh, **mm, "charts/lambda_mean": jnp.mean(lam), "charts/lambda_max": jnp.max(lam)}
        return agent, metrics

    # -- evaluation ---------------------------------------------------------------------
    def policy(self, carry):
        return carry.agent.sac.actor

    def act(self, policy, obs, env_state, key):
        return sac_act(self.nets, policy, obs)
