"""SAC losses (Haarnoja et al., 2018, "SAC: algorithms and applications") as pure functions.

Apply-function contracts:

* ``actor_apply(params, obs) -> (mean, log_std)`` of the pre-tanh Gaussian (``GaussianActor``);
  actions are tanh(u) in [-1, 1]^m;
* ``critic_apply(params, obs, action) -> q`` of shape [K, B] (``TwinQ``).

``batch`` has fields ``obs, action, reward, cost, next_obs, done`` (``done`` = termination only).
Every loss returns ``(loss, metrics)``. The temperature alpha enters the critic and actor losses
as a constant; it is learned through ``alpha_loss`` on log alpha (automatic entropy tuning).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from d2spo.algos.common.networks import tanh_gaussian_sample
from d2spo.algos.common.td3_losses import (
    CriticApply,
    PenaltyFn,
    ensemble_mse,
    reduce_critics,
    td_target,
)

GaussianApply = Callable[[Any, jax.Array], tuple[jax.Array, jax.Array]]


def default_target_entropy(action_dim: int) -> float:
    """The usual target entropy for automatic tuning: -dim(A)."""
    return -float(action_dim)


def sample_action(
    key: jax.Array, actor_params: Any, obs: jax.Array, actor_apply: GaussianApply
) -> tuple[jax.Array, jax.Array]:
    """(action [B, m] in [-1, 1], log_prob [B]) from the tanh-squashed policy, reparameterised."""
    mean, log_std = actor_apply(actor_params, obs)
    return tanh_gaussian_sample(key, mean, log_std)


def _soft_td_loss(
    critic_params: Any,
    target_critic_params: Any,
    actor_params: Any,
    entropy_coef: jax.Array | float,
    batch: Any,
    signal: jax.Array,
    key: jax.Array,
    gamma: float,
    actor_apply: GaussianApply,
    critic_apply: CriticApply,
    reduce: str,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    next_action, next_log_prob = sample_action(key, actor_params, batch.next_obs, actor_apply)
    next_q = reduce_critics(critic_apply(target_critic_params, batch.next_obs, next_action), reduce)
    soft_next = next_q - jax.lax.stop_gradient(entropy_coef) * next_log_prob
    y = td_target(signal, batch.done, soft_next, gamma)
    q = critic_apply(critic_params, batch.obs, batch.action)
    return ensemble_mse(q, y), q, y


def sac_critic_loss(
    critic_params: Any,
    target_critic_params: Any,
    actor_params: Any,
    alpha: jax.Array | float,
    batch: Any,
    key: jax.Array,
    gamma: float,
    actor_apply: GaussianApply,
    critic_apply: CriticApply,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Soft Bellman residual: y = r + gamma (1 - done) (min_i Q'_i(s', a') - alpha log pi(a'|s')),
    a' ~ pi(.|s'); loss = sum_i MSE(Q_i(s, a), y)."""
    loss, q, y = _soft_td_loss(
        critic_params, target_critic_params, actor_params, alpha, batch, batch.reward, key,
        gamma, actor_apply, critic_apply, "min",
    )  # fmt: skip
    return loss, {"losses/qf": loss, "values/q": jnp.mean(q), "values/q_target": jnp.mean(y)}


def sac_cost_critic_loss(
    cost_critic_params: Any,
    target_cost_critic_params: Any,
    actor_params: Any,
    batch: Any,
    key: jax.Array,
    gamma: float,
    actor_apply: GaussianApply,
    cost_critic_apply: CriticApply,
    reduce: str = "max",
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Cost critic for SAC-Lag, no entropy bonus: y = c + gamma (1 - done) reduce_i Qc'_i(s', a')."""
    loss, q, y = _soft_td_loss(
        cost_critic_params, target_cost_critic_params, actor_params, 0.0, batch, batch.cost, key,
        gamma, actor_apply, cost_critic_apply, reduce,
    )  # fmt: skip
    return loss, {"losses/qc": loss, "values/qc": jnp.mean(q), "values/qc_target": jnp.mean(y)}


def sac_actor_loss(
    actor_params: Any,
    critic_params: Any,
    alpha: jax.Array | float,
    obs: jax.Array,
    key: jax.Array,
    actor_apply: GaussianApply,
    critic_apply: CriticApply,
    penalty_fn: PenaltyFn | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """mean(alpha log pi(a|s) - min_i Q_i(s, a) + penalty_fn(s, a)), a ~ pi(.|s) reparameterised.

    ``metrics['values/log_prob']`` (mean log pi) is what ``alpha_loss`` needs.
    """
    action, log_prob = sample_action(key, actor_params, obs, actor_apply)
    q = reduce_critics(critic_apply(critic_params, obs, action), "min")
    per_sample = jax.lax.stop_gradient(alpha) * log_prob - q
    metrics = {
        "values/actor_q": jnp.mean(q),
        "values/log_prob": jnp.mean(log_prob),
        "values/entropy": -jnp.mean(log_prob),
    }
    if penalty_fn is not None:
        penalty = penalty_fn(obs, action)
        per_sample = per_sample + penalty
        metrics["values/actor_penalty"] = jnp.mean(penalty)
    loss = jnp.mean(per_sample)
    metrics["losses/actor"] = loss
    return loss, metrics


def alpha_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
    """Temperature loss -alpha * mean(log pi + target_entropy), alpha = exp(log_alpha).

    Its gradient in log_alpha is alpha * (H - target_entropy) with H = -mean(log pi): gradient
    descent lowers alpha while the policy's entropy is above the target, raises it below.
    """
    gap = jax.lax.stop_gradient(jnp.mean(log_prob) + target_entropy)
    return -jnp.exp(log_alpha) * gap
