"""The datasets T, P_exp, X_s and X_L of Sec. IV-A/IV-B, as device-resident ring buffers
(``d2spo.replay.ReplayBuffer``, the one ring buffer of the code).

Everything is generic in the sensor: `features_fn(pose, context) -> x [K]` maps one pose
(x, y, θ) and one sensed-obstacle context O_s (any pytree) to the feature vector b(z, O_s); it
must be differentiable in the pose. For a vector x, "b(z, O_s) ≥ d" is read as min(x) ≥ d: the
nearest sensed obstacle is at least d from the robot's centre.

- T: every real transition (z, z', O_s) with the observation, executed action and RL proposal.
- P_exp: the transitions of T with min b(z, O_s) past `p_exp_threshold(cfg)` (d in the paper,
  unsafe_max by default). X_s is the x of those with min x ≥ d, so it is not stored twice.
- X_L: unsafe feature vectors from the ring {unsafe_max − σ ≤ min x ≤ unsafe_max} below the safe
  region, synthesised from recorded poses without ever driving the robot there (`synthesize_unsafe`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from d2spo import replay
from d2spo.replay import ReplayBuffer
from d2spo.safety.cbf import CBFConfig, TeBatch, p_exp_threshold


def weighted_sample(buf: ReplayBuffer, key: jax.Array, n: int):
    """n items drawn uniformly with replacement, and a weight [n] that is 0 when the buffer is empty."""
    return replay.sample(buf, key, n), jnp.full((n,), buf.size > 0, jnp.float32)


@struct.dataclass
class Transition:
    """One real transition of T. Batched when stored or sampled (leading axis)."""

    pose: jnp.ndarray       # z = s(t), [3]
    next_pose: jnp.ndarray  # z' = s(t + Δt), [3] (before any auto-reset)
    context: Any            # O_s: the obstacles sensed at s(t), e.g. a bool mask [M]
    obs: jnp.ndarray        # the RL observation at s(t), so π_rl(z) can be recomputed
    action: jnp.ndarray     # the executed action π_Ω, [m]
    u_rl: jnp.ndarray       # π_rl's proposal at collection time, [m]


def te_batch(tr: Transition, weight: jnp.ndarray, u_rl: jnp.ndarray | None = None) -> TeBatch:
    """A T_e/T_g batch from sampled P_exp transitions; pass `u_rl` to use the current π_rl(obs)."""
    return TeBatch(tr.pose, tr.next_pose, tr.context, tr.u_rl if u_rl is None else u_rl, weight, tr.action)


@struct.dataclass
class SafetyData:
    """The three buffers of Algorithm 1: T (all transitions), P_exp, and X_L (features)."""

    transitions: ReplayBuffer
    p_exp: ReplayBuffer
    unsafe: ReplayBuffer


def init_safety_data(cfg: CBFConfig, example: Transition, n_features: int) -> SafetyData:
    """Empty buffers sized by `cfg`; `example` is one unbatched transition (only shapes matter)."""
    return SafetyData(
        transitions=ReplayBuffer.create(cfg.transitions_capacity, example),
        p_exp=ReplayBuffer.create(cfg.p_exp_capacity, example),
        unsafe=ReplayBuffer.create(cfg.unsafe_capacity, jnp.zeros((n_features,), jnp.float32)),
    )


def in_p_exp(x: jnp.ndarray, d: float) -> jnp.ndarray:
    """P_exp membership of features x [..., K]: min(x) ≥ d."""
    return jnp.min(x, axis=-1) >= d


def synthesize_unsafe(key: jax.Array, pose: jnp.ndarray, context, features_fn: Callable,
                      lo: float, hi: float, n_iter: int = 8):
    """Move a recorded pose into the ring lo ≤ min b(z, O_s) ≤ hi; return (x, pose, valid).

    A target range c ~ U[lo, hi] and a new heading ~ U[-π, π) are drawn; then Newton steps on the
    position solve min b((p, θ), O_s) = c, p ← p − (m(p) − c) ∇m / |∇m|². A ray range is linear in
    the position along its ray, so this converges in a step or two, and a step is never longer than
    m(p) − c. `valid` is false when no obstacle is sensed (∇m = 0) or the ring was not reached.
    The robot never goes there: this only evaluates the sensor model at a hypothetical pose.
    """
    k_c, k_th = jax.random.split(key)
    target = jax.random.uniform(k_c, (), minval=lo, maxval=hi)
    theta = jax.random.uniform(k_th, (), minval=-jnp.pi, maxval=jnp.pi)

    def min_range(p):
        return jnp.min(features_fn(jnp.concatenate([p, theta[None]]), context))

    def newton(_, p):
        m, g = jax.value_and_grad(min_range)(p)
        g2 = jnp.sum(g**2)
        return p - jnp.where(g2 > 1e-12, (m - target) / jnp.maximum(g2, 1e-12), 0.0) * g

    p = jax.lax.fori_loop(0, n_iter, newton, pose[:2])
    new_pose = jnp.concatenate([p, theta[None]])
    x = features_fn(new_pose, context)
    m = jnp.min(x)
    valid = (m >= lo) & (m <= hi) & jnp.all(jnp.isfinite(x))
    return x, new_pose, valid


def _ring_samples(key: jax.Array, pose: jnp.ndarray, context, features_fn: Callable, cfg: CBFConfig):
    """One X_L candidate per pose of a batch: (features [n, K], valid [n])."""
    lo, hi = cfg.unsafe_max - cfg.sigma, cfg.unsafe_max
    x, _, ok = jax.vmap(lambda k, p, c: synthesize_unsafe(k, p, c, features_fn, lo, hi, cfg.ring_newton_iters))(
        jax.random.split(key, pose.shape[0]), pose, context)
    return x, ok


def update_datasets(data: SafetyData, key: jax.Array, tr: Transition, *, features_fn: Callable,
                    cfg: CBFConfig, mask: jnp.ndarray | None = None):
    """UPDATE(D) of Algorithm 1 for a batch of transitions [n]: add to T, P_exp and X_L.

    `mask` [n] drops rows (e.g. padding). One unsafe sample is synthesised per transition; those
    that reach the ring are kept. Returns (data, stats) with `stats` counts of added rows.
    """
    n = tr.pose.shape[0]
    mask = jnp.ones((n,), bool) if mask is None else mask.astype(bool)
    x = jax.vmap(features_fn)(tr.pose, tr.context)
    exp = mask & in_p_exp(x, p_exp_threshold(cfg))
    x_u, ok = _ring_samples(key, tr.pose, tr.context, features_fn, cfg)
    ok = ok & mask
    data = SafetyData(
        transitions=replay.add_batch(data.transitions, tr, mask),
        p_exp=replay.add_batch(data.p_exp, tr, exp),
        unsafe=replay.add_batch(data.unsafe, x_u, ok),
    )
    return data, {"safety/added_p_exp": jnp.sum(exp), "safety/added_unsafe": jnp.sum(ok)}


@struct.dataclass
class PretrainData:
    """Synthetic samples for the cautious start: poses with their context and features, whether
    each is safe (min x ≥ d), and an unsafe ring sample synthesised from each pose."""

    pose: jnp.ndarray
    context: Any
    x: jnp.ndarray
    safe: jnp.ndarray
    x_unsafe: jnp.ndarray
    unsafe_valid: jnp.ndarray


def synthetic_pretrain_data(key: jax.Array, features_fn: Callable, sample_fn: Callable, n: int, *,
                            cfg: CBFConfig) -> PretrainData:
    """Safe and unsafe samples before the first environment step.

    `sample_fn(key) -> (pose, context)` draws one hypothetical pose among obstacles (e.g. random
    boxes of the layout's kind), not necessarily collision-free. Safe samples are those with
    min x ≥ d; unsafe ones come from `synthesize_unsafe` applied to every pose.
    """
    k_s, k_u = jax.random.split(key)
    pose, context = jax.vmap(sample_fn)(jax.random.split(k_s, n))
    x = jax.vmap(features_fn)(pose, context)
    x_u, ok = _ring_samples(k_u, pose, context, features_fn, cfg)
    return PretrainData(pose=pose, context=context, x=x, safe=in_p_exp(x, cfg.d), x_unsafe=x_u, unsafe_valid=ok)


def seed_unsafe(data: SafetyData, pre: PretrainData) -> SafetyData:
    """Put the cautious start's valid ring samples into X_L, so T_u has data from the first update."""
    return data.replace(unsafe=replay.add_batch(data.unsafe, pre.x_unsafe, pre.unsafe_valid))
