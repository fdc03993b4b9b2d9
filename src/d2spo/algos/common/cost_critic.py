"""The Lagrangian shell of td3-lag and sac-lag: a cost-critic ensemble Qc and the multiplier lambda.

The constrained problem max J_r s.t. J_c <= d is solved on its Lagrangian (OmniSafe's TD3Lag,
SACLag), around an unconstrained core (TD3 or SAC) that brings its own reward critics and actor:

    cost critics: y_c = c + gamma (1 - done) reduce_i Qc'_i(s', a'),   a' the core's next action
                  (reduce = max over the ensemble: pessimistic)
    actor:        the core's loss + lambda reduce_i Qc_i(s, a)         (``penalty``)
    lambda:       lambda <- max(0, lambda + step(J_c - d))  once per vectorised step,
                  J_c = mean cost of the last ``cost_window`` finished episodes (``on_step``).

The learner's agent carries the fields ``cost_critic``, ``cost_critic_target``, ``cost_opt`` and
``lag``; the cost TD loss is the core's (``td3_losses.cost_critic_loss``,
``sac_losses.sac_cost_critic_loss``), passed in.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax

from d2spo.algos.common import lagrange
from d2spo.algos.common.lagrange import LagrangeConfig, LagrangeState
from d2spo.algos.common.networks import TwinQ, init_params
from d2spo.algos.common.td3_losses import REDUCTIONS, PenaltyFn, reduce_critics
from d2spo.fields import check_choice, check_fields

Metrics = dict[str, jax.Array]


def default_lagrange() -> LagrangeConfig:
    """The *-lag multiplier: OmniSafe's off-policy TD3Lag/SACLag (Adam, lr 1e-3, init 1e-3), with
    d = 0.05 collisions per episode (a 95% collision-free target; OmniSafe's 25 is Safety Gym's)."""
    return LagrangeConfig(cost_limit=0.05, lr=1e-3, init=1e-3)


def check_cost_options(cfg, section: str) -> None:
    """ConfigError on a bad cost-critic ensemble, reduction or cost window (td3-lag, sac-lag)."""
    check_fields(cfg, section, count=("cost_critics", "cost_window"))
    check_choice(cfg, "cost_reduce", REDUCTIONS, section)


def update_multiplier(lag: LagrangeState, mean_cost: jax.Array) -> LagrangeState:
    """One projected ascent step on lambda (J_c - d); no step while J_c is unknown (NaN)."""
    known = jnp.isfinite(mean_cost)
    stepped = lagrange.update(lag, jnp.where(known, mean_cost, 0.0))
    return jax.tree_util.tree_map(lambda new, old: jnp.where(known, new, old), stepped, lag)


class LagrangianShell:
    """Qc (``n_critics`` networks of ``hidden`` widths), its Adam optimiser, and the multiplier.

    ``cfg`` is the learner's section (``TD3LagConfig``, ``SACLagConfig``): ``cost_critics``,
    ``cost_reduce``, ``lagrange``.
    """

    def __init__(self, hidden: tuple[int, ...], critic_lr: float, cfg):
        self.net = TwinQ(hidden, n_critics=cfg.cost_critics)
        self.tx = optax.adam(critic_lr)
        self.reduce = cfg.cost_reduce
        self.lagrange = cfg.lagrange

    def init(self, key: jax.Array, obs_size: int, action_size: int) -> tuple[Any, Any, Any, LagrangeState]:
        """(cost_critic, cost_critic_target, cost_opt, lag): the agent's Lagrangian fields, fresh."""
        qc = init_params(self.net, key, jnp.zeros((1, obs_size)), jnp.zeros((1, action_size)))
        return qc, qc, self.tx.init(qc), lagrange.create(self.lagrange)

    def on_step(self, agent: Any, mean_cost: jax.Array) -> tuple[Any, Metrics]:
        """The multiplier's step of the off-policy loop (once per vectorised step after warm-up)."""
        lag = update_multiplier(agent.lag, mean_cost)
        return agent.replace(lag=lag), {"charts/lambda": lag.multiplier}

    def critic_step(self, agent: Any, loss_fn: Callable, *loss_args) -> tuple[Any, Any, Metrics]:
        """One Adam step of Qc on ``loss_fn(qc, qc_target, *loss_args, qc_apply, reduce)``: (qc, cost_opt, metrics)."""
        (_, m), g = jax.value_and_grad(loss_fn, has_aux=True)(
            agent.cost_critic, agent.cost_critic_target, *loss_args, self.net.apply, self.reduce)
        upd, cost_opt = self.tx.update(g, agent.cost_opt, agent.cost_critic)
        qc = optax.apply_updates(agent.cost_critic, upd)
        return qc, cost_opt, {"losses/qc": m["losses/qc"], "values/qc": m["values/qc"]}

    def penalty(self, lag: LagrangeState, qc: Any) -> PenaltyFn:
        """lambda reduce_i Qc_i(s, a), the constraint term of the Lagrangian (lambda held constant)."""
        lam = lagrange.value(lag)

        def penalty(obs, action):
            return lam * reduce_critics(self.net.apply(qc, obs, action), self.reduce)

        return penalty
