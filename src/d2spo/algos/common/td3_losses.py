"""TD3 losses (Fujimoto et al., 2018) as pure functions, plus Polyak averaging.

Apply-function contracts (close over the flax module, e.g. ``lambda p, s: actor.apply(p, s)``):

* ``actor_apply(params, obs) -> action`` in [-1, 1]^m, shape [B, m];
* ``critic_apply(params, obs, action) -> q`` of shape [K, B] (critic axis first, as ``TwinQ``).

``batch`` is any object with fields ``obs, action, reward, cost, next_obs, done`` (e.g.
``replay.Transition``); ``done`` is 1 only on termination. Each loss returns ``(loss, metrics)``
so it can be used with ``jax.value_and_grad(..., has_aux=True)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

ActorApply = Callable[[Any, jax.Array], jax.Array]
CriticApply = Callable[[Any, jax.Array, jax.Array], jax.Array]
PenaltyFn = Callable[[jax.Array, jax.Array], jax.Array]

REDUCTIONS = ("min", "max", "mean")


def reduce_critics(q: jax.Array, how: str) -> jax.Array:
    """Combine an ensemble [K, B] -> [B]: 'min' (clipped double-Q), 'max' (pessimistic cost), 'mean'."""
    if how == "min":
        return jnp.min(q, axis=0)
    if how == "max":
        return jnp.max(q, axis=0)
    if how == "mean":
        return jnp.mean(q, axis=0)
    raise ValueError(f"reduce_critics: `how` must be one of {REDUCTIONS}, got {how!r}")


def target_policy_action(
    key: jax.Array,
    target_actor_params: Any,
    next_obs: jax.Array,
    actor_apply: ActorApply,
    policy_noise: float,
    noise_clip: float,
    low: float | jax.Array = -1.0,
) -> jax.Array:
    """Target policy smoothing: clip(pi'(s') + clip(eps, -c, c), low, 1), eps ~ N(0, sigma^2); ``low``:
    the actor's smallest action (per coordinate, or one number)."""
    action = actor_apply(target_actor_params, next_obs)
    noise = jnp.clip(policy_noise * jax.random.normal(key, action.shape, action.dtype), -noise_clip, noise_clip)
    return jnp.clip(action + noise, low, 1.0)


def td_target(signal: jax.Array, done: jax.Array, next_q: jax.Array, gamma: float) -> jax.Array:
    """y = signal + gamma (1 - done) next_q, with gradients stopped."""
    y = signal + gamma * (1.0 - done.astype(jnp.float32)) * next_q
    return jax.lax.stop_gradient(y)


def ensemble_mse(q: jax.Array, y: jax.Array) -> jax.Array:
    """Sum over the critics of each critic's MSE to the target: q [K, B], y [B] -> []."""
    return jnp.sum(jnp.mean((q - y[None]) ** 2, axis=1))


def _twin_td_loss(
    critic_params: Any,
    target_critic_params: Any,
    target_actor_params: Any,
    batch: Any,
    signal: jax.Array,
    key: jax.Array,
    gamma: float,
    policy_noise: float,
    noise_clip: float,
    actor_apply: ActorApply,
    critic_apply: CriticApply,
    reduce: str,
    low: float | jax.Array = -1.0,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    next_action = target_policy_action(key, target_actor_params, batch.next_obs, actor_apply, policy_noise, noise_clip,
                                       low)
    next_q = reduce_critics(critic_apply(target_critic_params, batch.next_obs, next_action), reduce)
    y = td_target(signal, batch.done, next_q, gamma)
    q = critic_apply(critic_params, batch.obs, batch.action)  # [K, B]
    return ensemble_mse(q, y), q, y


def td3_critic_loss(
    critic_params: Any,
    target_critic_params: Any,
    target_actor_params: Any,
    batch: Any,
    key: jax.Array,
    gamma: float,
    policy_noise: float,
    noise_clip: float,
    actor_apply: ActorApply,
    critic_apply: CriticApply,
    low: float | jax.Array = -1.0,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Clipped double-Q: y = r + gamma (1 - done) min_i Q'_i(s', a~'), loss = sum_i MSE(Q_i(s, a), y);
    ``low``: the actor's smallest action (``target_policy_action``)."""
    loss, q, y = _twin_td_loss(
        critic_params, target_critic_params, target_actor_params, batch, batch.reward, key,
        gamma, policy_noise, noise_clip, actor_apply, critic_apply, "min", low,
    )  # fmt: skip
    return loss, {"losses/qf": loss, "values/q": jnp.mean(q), "values/q_target": jnp.mean(y)}


def cost_critic_loss(
    cost_critic_params: Any,
    target_cost_critic_params: Any,
    target_actor_params: Any,
    batch: Any,
    key: jax.Array,
    gamma: float,
    policy_noise: float,
    noise_clip: float,
    actor_apply: ActorApply,
    cost_critic_apply: CriticApply,
    reduce: str = "max",
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Cost critic, same TD form with the cost: y = c + gamma (1 - done) reduce_i Qc'_i(s', a~').

    ``reduce='max'`` over the ensemble over-estimates the cost (pessimistic for safety); 'min'
    reproduces the reward critic's rule; with a single critic (K = 1) all choices coincide.
    """
    loss, q, y = _twin_td_loss(
        cost_critic_params, target_cost_critic_params, target_actor_params, batch, batch.cost, key,
        gamma, policy_noise, noise_clip, actor_apply, cost_critic_apply, reduce,
    )  # fmt: skip
    return loss, {"losses/qc": loss, "values/qc": jnp.mean(q), "values/qc_target": jnp.mean(y)}


def td3_actor_loss(
    actor_params: Any,
    critic_params: Any,
    obs: jax.Array,
    actor_apply: ActorApply,
    critic_apply: CriticApply,
    penalty_fn: PenaltyFn | None = None,
    execute_fn: Callable[[jax.Array, jax.Array], jax.Array] | None = None,
    proposal_weight: float = 0.0,
    next_obs: jax.Array | None = None,
    smoothness: float = 0.0,
    smoothness_dims: tuple[int, ...] | None = None,
    saturation: float = 0.0,
    saturation_bound: float = 2.5,
    speed_search: float = 0.0,
    speed_low: float = -1.0,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Deterministic policy gradient: mean(-Q1(s, a) + penalty_fn(s, a)), a = pi(s).

    ``penalty_fn(obs, action) -> [B]`` adds a differentiable per-sample term, e.g. for TD3-Lag
    ``lambda s, a: lam * qc_apply(qc_params, s, a)[0]`` with lam held constant.

    ``execute_fn(obs, proposal) -> action``: the policy's output is a proposal that a safety layer
    turns into the executed action (D²SPO's π_Ω). Q1 is then evaluated at the executed action
    a = execute_fn(s, pi(s)) (what the critic was trained on), the gradient flows through the layer,
    and ``proposal_weight * ||pi(s) - a||²`` asks for proposals the layer lets through.

    ``smoothness * ||pi(s') - pi(s)||²`` over the batch's consecutive observations (``next_obs``)
    asks for proposals that change little from one step to the next: the temporal term of CAPS
    (Mysore et al., ICRA 2021), squared; ``smoothness_dims`` limits it to those action
    dimensions (None: all). Off (0) by default.

    ``saturation * ||max(|z| - saturation_bound, 0)||²``, z the actor's output before its tanh
    (``actor_apply(params, obs, pre_tanh=True)``), keeps z where the tanh still has a slope
    (tanh(2.5) = 0.987): an actor pinned at an action's bound gets no gradient towards the other
    side of the box. Off (0) by default.

    ``speed_search``: the proposal with its linear speed (action[0]) replaced by each of
    ``SPEED_SEARCH_POINTS`` speeds spread over [``speed_low``, 1] is scored by Q1 (through the safety
    layer); where the proposal is slower than a quarter of the speed range either way (a near stall:
    0.25 for a forward-only actor) and the best of them beats it by more than
    ``SPEED_SEARCH_MARGIN``, the
    actor's speed output before its tanh is pulled towards that speed's,
    ``speed_search * (z_0 - atanh(·))²``. The policy gradient climbs Q1 only locally, and where the
    actor's output sits deep in its tanh (a stall at speed 0) it gets almost no gradient at all;
    this term reaches the better speed the critic already knows. Off (0) by default.
    """
    proposal = actor_apply(actor_params, obs)
    action = proposal if execute_fn is None else execute_fn(obs, proposal)
    q1 = critic_apply(critic_params, obs, action)[0]
    per_sample = -q1
    metrics = {"values/actor_q": jnp.mean(q1)}
    if execute_fn is not None and proposal_weight > 0:
        override = jnp.sum((proposal - action) ** 2, axis=-1)
        per_sample = per_sample + proposal_weight * override
        metrics["values/actor_override"] = jnp.mean(override)
    if smoothness > 0:
        change = actor_apply(actor_params, next_obs) - proposal
        if smoothness_dims is not None:
            change = change[..., list(smoothness_dims)]
        jerk = jnp.sum(change**2, axis=-1)
        per_sample = per_sample + smoothness * jerk
        metrics["values/actor_jerk"] = jnp.mean(jerk)
    # the actor's output before its tanh, for the terms that read it (one forward pass for both)
    z = actor_apply(actor_params, obs, pre_tanh=True) if saturation > 0 or speed_search > 0 else None
    if saturation > 0:
        excess = jnp.maximum(jnp.abs(z) - saturation_bound, 0.0)
        beyond = jnp.sum(excess**2, axis=-1)
        per_sample = per_sample + saturation * beyond
        metrics["values/actor_saturation"] = jnp.mean(beyond)
    if speed_search > 0:
        search = _speed_search(z[..., 0], proposal, critic_params, obs, critic_apply, execute_fn, q1, speed_low)
        per_sample = per_sample + speed_search * search
        metrics["values/actor_speed_search"] = jnp.mean(search > 0)
    if penalty_fn is not None:
        penalty = penalty_fn(obs, action)
        per_sample = per_sample + penalty
        metrics["values/actor_penalty"] = jnp.mean(penalty)
    loss = jnp.mean(per_sample)
    metrics["losses/actor"] = loss
    return loss, metrics


SPEED_SEARCH_POINTS = 5
"""Candidate linear speeds of ``td3_actor_loss``'s speed search, evenly over the actor's range."""
SPEED_SEARCH_MARGIN = 0.05
"""How much more Q1 a candidate speed must promise than the proposal before the actor is pulled."""


def _speed_search(z0, proposal, critic_params, obs, critic_apply, execute_fn, q1, speed_low):
    """Per sample, ``(z0 - atanh(t))²`` towards the best candidate speed where it beats the proposal
    by ``SPEED_SEARCH_MARGIN`` in Q1, else 0 (``td3_actor_loss``'s ``speed_search``; z0 the speed's
    output before the tanh)."""
    proposal = jax.lax.stop_gradient(proposal)
    speeds = jnp.linspace(speed_low, 1.0, SPEED_SEARCH_POINTS)

    def q_at(v):
        candidate = proposal.at[..., 0].set(v)
        executed = candidate if execute_fn is None else execute_fn(obs, candidate)
        return critic_apply(critic_params, obs, executed)[0]

    q = jax.lax.stop_gradient(jax.vmap(q_at)(speeds))  # [K, B]
    # only a proposal slower than a quarter of the speed range, either way: a stall, not a choice
    stalled = jnp.abs(proposal[..., 0]) < (1.0 - speed_low) / 4.0
    better = (jnp.max(q, axis=0) > jax.lax.stop_gradient(q1) + SPEED_SEARCH_MARGIN) & stalled
    # the best speed in the tanh's coordinate, kept inside (-0.95, 0.95) where the tanh has a slope
    c0, c1 = (1.0 + speed_low) / 2.0, (1.0 - speed_low) / 2.0
    target = jnp.arctanh(jnp.clip((speeds[jnp.argmax(q, axis=0)] - c0) / c1, -0.95, 0.95))
    return jnp.where(better, (z0 - target) ** 2, 0.0)


def soft_update(target: Any, online: Any, tau: float) -> Any:
    """Polyak averaging: target <- (1 - tau) target + tau online, leaf by leaf."""
    return jax.tree_util.tree_map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)
