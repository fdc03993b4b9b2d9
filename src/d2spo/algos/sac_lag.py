"""SAC-Lagrangian (LSAC of Tables II-III): SAC with a cost critic and a Lagrange multiplier.

The SAC core of ``algos/sac.py`` inside the Lagrangian shell of ``algos/common/cost_critic.py``
(OmniSafe's SACLag):

    critics:  y_r = r + gamma (1 - done) (min_i Q'_i(s', a') - alpha log pi(a'|s')),  a' ~ pi(s')
              y_c = c + gamma (1 - done) reduce_i Qc'_i(s', a')          (reduce = max: pessimistic)
    actor:    min  E[alpha log pi(a|s) - min_i Q_i(s, a) + lambda reduce_i Qc_i(s, a)],  a ~ pi(s)
    lambda:   lambda <- max(0, lambda + step(J_c - d))  once per vectorised step,
              J_c = mean cost of the last ``cost_window`` finished episodes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import jax
from flax import struct

from d2spo.algos.common.cost_critic import LagrangianShell, check_cost_options, default_lagrange
from d2spo.algos.common.lagrange import LagrangeConfig, LagrangeState
from d2spo.algos.common.sac_losses import sac_cost_critic_loss
from d2spo.algos.common.td3_losses import soft_update
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
from d2spo.ltl.anneal import AnnealConfig


@dataclass(frozen=True)
class SACLagConfig:
    """SAC-Lagrangian: the SAC core, a cost critic ensemble and the Lagrange multiplier."""

    sac: SACConfig = field(default_factory=SACConfig)
    """The SAC core."""
    cost_critics: int = 2
    """Cost critics in the ensemble (twin by default)."""
    cost_reduce: str = "max"
    """Cost ensemble reduction: max (pessimistic), min, mean."""
    cost_window: int = 10
    """J_c = mean cost of this many last finished episodes."""
    lagrange: LagrangeConfig = field(default_factory=default_lagrange)
    """Lagrange multiplier on the per-episode cost (collisions)."""

    def __post_init__(self) -> None:
        check_cost_options(self, "sac_lag")


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
        self.shell = LagrangianShell(s.hidden, s.critic_lr, cfg)
        self.loop = OffPolicyLoop(env, params, anneal, num_envs, chunk_steps, total_episodes,
                                  buffer_size=s.buffer_size, batch_size=s.batch_size,
                                  learning_starts=s.learning_starts, updates_per_step=s.updates_per_step,
                                  cost_window=cfg.cost_window)

    def init(self, key: jax.Array):
        k_sac, k_cost, k_loop = jax.random.split(key, 3)
        obs_size = self.env.observation_size
        sac = init_sac_agent(k_sac, self.nets, obs_size, self.cfg.sac)
        agent = SACLagAgent(sac, *self.shell.init(k_cost, obs_size, self.env.action_size))
        return self.loop.init(k_loop, agent)

    def chunk(self, carry):
        return self.loop.chunk(carry, self)

    # -- hooks of the loop --------------------------------------------------------------
    def behaviour(self, agent: SACLagAgent, obs, key, episodes):  # SAC's own entropy: no schedule
        return sac_behaviour(self.nets, agent.sac, obs, key)

    def on_step(self, agent: SACLagAgent, mean_cost):
        return self.shell.on_step(agent, mean_cost)

    def update(self, agent: SACLagAgent, batch, key):
        s = self.cfg.sac
        k_q, k_c, k_pi = jax.random.split(key, 3)
        sac, metrics = sac_critic_step(self.nets, agent.sac, batch, k_q, s)
        qc, cost_opt, mc = self.shell.critic_step(agent, sac_cost_critic_loss, sac.actor, batch, k_c, s.gamma,
                                                  self.nets.actor.apply)
        penalty = self.shell.penalty(agent.lag, qc)  # lambda Qc(s, a), a ~ pi(s)
        sac, a_metrics = delayed(sac.updates % s.policy_delay == 0,
                                 lambda sac: sac_actor_step(self.nets, sac, batch.obs, k_pi, penalty), sac)
        agent = SACLagAgent(sac.replace(updates=sac.updates + 1), qc, soft_update(agent.cost_critic_target, qc, s.tau),
                            cost_opt, agent.lag)
        return agent, {**metrics, **a_metrics, **mc}

    # -- evaluation ---------------------------------------------------------------------
    def policy(self, carry):
        return carry.agent.sac.actor

    def act(self, policy, obs, env_state, key):
        return sac_act(self.nets, policy, obs)
