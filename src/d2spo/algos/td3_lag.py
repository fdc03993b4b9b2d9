"""TD3-Lagrangian (LTD3 of Tables II-III): TD3 with a cost critic and a Lagrange multiplier.

TD3 (Fujimoto et al., 2018) exactly as ``algos/td3.py`` (same ``TD3Config`` fields, the same
pieces: ``make_nets``, ``init_agent``, ``explore``) inside the Lagrangian shell of
``algos/common/cost_critic.py`` (OmniSafe's TD3Lag):

    cost critics: y_c = c + gamma (1 - done) reduce_i Qc'_i(s', a~'),  a~' the smoothed target action
                  (reduce = max over the twin cost critics: pessimistic)
    actor:        min E[-Q_1(s, pi(s)) + lambda reduce_i Qc_i(s, pi(s))]   (every policy_delay-th update)
    lambda:       lambda <- max(0, lambda + step(J_c - d))  once per vectorised step,
                  J_c = mean cost of the last ``cost_window`` finished episodes (OmniSafe: window 10).

The cost is the env's collision indicator, so J_c is the expected number of collisions per episode
(0 or 1 when collisions end the episode) and d = 0.05 asks for 95% collision-free episodes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from d2spo.algos.common.cost_critic import LagrangianShell, check_cost_options, default_lagrange
from d2spo.algos.common.lagrange import LagrangeConfig, LagrangeState
from d2spo.algos.common.networks import first_critic
from d2spo.algos.common.td3_losses import cost_critic_loss, soft_update, td3_actor_loss, td3_critic_loss
from d2spo.algos.offpolicy import OffPolicyLoop, delayed
from d2spo.algos.td3 import TD3Agent, TD3Config, explore, init_agent, make_nets
from d2spo.errors import ConfigError
from d2spo.ltl.anneal import AnnealConfig


@dataclass(frozen=True)
class TD3LagConfig:
    """TD3-Lagrangian: the TD3 core, a cost critic ensemble and the Lagrange multiplier."""

    td3: TD3Config = field(default_factory=lambda: TD3Config(hidden=(128, 128), batch_size=128))
    """The TD3 core (TD3Config's defaults: a constant exploration noise, which falls over a patrol's run
    as D²SPO's does, ``recurrence_noise_final``)."""
    cost_critics: int = 2
    """Cost critics in the ensemble (twin by default)."""
    cost_reduce: str = "max"
    """Cost ensemble reduction: max (pessimistic), min, mean."""
    cost_window: int = 10
    """J_c = mean cost of this many last finished episodes."""
    lagrange: LagrangeConfig = field(default_factory=default_lagrange)
    """Lagrange multiplier on the per-episode cost (collisions)."""

    def __post_init__(self) -> None:
        check_cost_options(self, "td3_lag")
        for term in ("smoothness", "saturation", "speed_search"):
            if getattr(self.td3, term):
                raise ConfigError(f"td3_lag.td3.{term}", f"is for td3, tlgrl, d2spo and sl; td3-lag's actor loss "
                                  f"has no {term.replace('_', ' ')} term")


@struct.dataclass
class TD3LagAgent:
    td3: TD3Agent
    cost_critic: Any
    cost_critic_target: Any
    cost_opt: Any
    lag: LagrangeState


class TD3LagLearner:
    """``--algo td3-lag``: see the module docstring."""

    def __init__(self, env, params, cfg: TD3LagConfig, anneal: AnnealConfig, num_envs: int, chunk_steps: int,
                 total_episodes: int):
        self.env, self.cfg, t = env, cfg, cfg.td3
        self.nets = make_nets(env.action_size, t)
        self.shell = LagrangianShell(t.widths, t.critic_lr, cfg)
        self.loop = OffPolicyLoop(env, params, anneal, num_envs, chunk_steps, total_episodes,
                                  buffer_size=t.buffer_size, batch_size=t.batch_size,
                                  learning_starts=t.learning_starts, updates_per_step=t.updates_per_step,
                                  cost_window=cfg.cost_window)

    def init(self, key: jax.Array):
        k_td3, k_cost, k_loop = jax.random.split(key, 3)
        obs_size, act_size = self.env.observation_size, self.env.action_size
        td3 = init_agent(k_td3, self.nets, obs_size, act_size)
        agent = TD3LagAgent(td3, *self.shell.init(k_cost, obs_size, act_size))
        return self.loop.init(k_loop, agent)

    def chunk(self, carry):
        return self.loop.chunk(carry, self)

    # -- hooks of the loop --------------------------------------------------------------
    def behaviour(self, agent: TD3LagAgent, obs, key, episodes):
        t = self.cfg.td3
        return explore(self.nets, agent.td3, obs, key, jnp.bool_(False),
                       t.noise_at(episodes, self.loop.schedule.per_episode), t.exploration_noise_space)

    def on_step(self, agent: TD3LagAgent, mean_cost):
        return self.shell.on_step(agent, mean_cost)

    def update(self, agent: TD3LagAgent, batch, key):
        t, a = self.cfg.td3, agent.td3
        actor_apply, critic_apply = self.nets.actor.apply, self.nets.critic.apply
        k_q, k_c = jax.random.split(key)
        (_, m), g = jax.value_and_grad(td3_critic_loss, has_aux=True)(
            a.critic, a.critic_target, a.actor_target, batch, k_q, t.gamma, t.policy_noise, t.noise_clip,
            actor_apply, critic_apply)
        upd, critic_opt = self.nets.critic_tx.update(g, a.critic_opt, a.critic)
        critic = optax.apply_updates(a.critic, upd)
        qc, cost_opt, mc = self.shell.critic_step(agent, cost_critic_loss, a.actor_target, batch, k_c, t.gamma,
                                                  t.policy_noise, t.noise_clip, actor_apply)
        penalty = self.shell.penalty(agent.lag, qc)  # lambda Qc(s, pi(s))

        def actor_step(old):  # actor, then every target network (TD3's delayed updates)
            actor, actor_opt, actor_t, critic_t, cost_t = old
            (_, am), g = jax.value_and_grad(td3_actor_loss, has_aux=True)(
                actor, critic, batch.obs, actor_apply, first_critic(self.nets.critic), penalty)
            upd, actor_opt = self.nets.actor_tx.update(g, actor_opt, actor)
            actor = optax.apply_updates(actor, upd)
            new = (actor, actor_opt, soft_update(actor_t, actor, t.tau), soft_update(critic_t, critic, t.tau),
                   soft_update(cost_t, qc, t.tau))
            return new, {"losses/actor": am["losses/actor"], "values/actor_penalty": am["values/actor_penalty"]}

        old = (a.actor, a.actor_opt, a.actor_target, a.critic_target, agent.cost_critic_target)
        (actor, actor_opt, actor_t, critic_t, cost_t), am = delayed(a.updates % t.policy_delay == 0, actor_step, old)
        td3 = TD3Agent(actor, actor_t, critic, critic_t, actor_opt, critic_opt, a.updates + 1)
        metrics = {"losses/qf": m["losses/qf"], "values/q": m["values/q"], **mc, **am}
        return TD3LagAgent(td3, qc, cost_t, cost_opt, agent.lag), metrics

    # -- evaluation ---------------------------------------------------------------------
    def policy(self, carry):
        return carry.agent.td3.actor

    def act(self, policy, obs, env_state, key):
        return self.nets.actor.apply(policy, obs)
