"""Running mean / variance of observations as a pytree (optional observation normalisation).

Batched updates merge the batch's moments into the running ones exactly (the parallel form of
Welford's algorithm), so the result equals the mean and population variance of all data seen.

    rms = RunningMeanStd.create(obs_shape)
    rms = update(rms, obs_batch)          # leaves [..., *obs_shape]; any number of leading axes
    x = normalize(rms, obs)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class RunningMeanStd:
    """Running moments over the trailing ``shape`` axes."""

    mean: jax.Array
    var: jax.Array
    """Population variance (divides by count)."""
    count: jax.Array
    """float32 []: number of samples merged so far."""

    @classmethod
    def create(cls, shape: Sequence[int]) -> RunningMeanStd:
        """No data yet: mean 0, var 1, count 0 (``normalize`` is then the identity, up to clipping)."""
        shape = tuple(shape)
        return cls(mean=jnp.zeros(shape, jnp.float32), var=jnp.ones(shape, jnp.float32), count=jnp.float32(0.0))


def update(rms: RunningMeanStd, x: jax.Array) -> RunningMeanStd:
    """Merge a batch whose trailing axes match ``rms.mean.shape``."""
    x = jnp.asarray(x, jnp.float32)
    n_batch_axes = x.ndim - rms.mean.ndim
    if n_batch_axes < 0 or x.shape[n_batch_axes:] != rms.mean.shape:
        raise ValueError(f"normalize.update: batch shape {x.shape} does not end with {rms.mean.shape}")
    axes = tuple(range(n_batch_axes))
    n_int = math.prod(x.shape[:n_batch_axes])
    if n_int == 0:
        return rms
    n = jnp.float32(n_int)
    batch_mean = jnp.mean(x, axis=axes)
    batch_var = jnp.var(x, axis=axes)
    total = rms.count + n
    delta = batch_mean - rms.mean
    mean = rms.mean + delta * (n / total)
    m2 = rms.var * rms.count + batch_var * n + delta**2 * (rms.count * n / total)
    return RunningMeanStd(mean=mean, var=m2 / total, count=total)


def normalize(rms: RunningMeanStd, x: jax.Array, clip: float | None = 10.0, eps: float = 1e-8) -> jax.Array:
    """(x - mean) / sqrt(var + eps), clipped to [-clip, clip] when ``clip`` is not None."""
    z = (jnp.asarray(x, jnp.float32) - rms.mean) / jnp.sqrt(rms.var + eps)
    return z if clip is None else jnp.clip(z, -clip, clip)
