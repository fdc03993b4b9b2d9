"""Replay buffer that lives on the device as a pytree (a ring buffer over arbitrary transitions).

    buf = ReplayBuffer.create(capacity, example_transition)   # one transition, no batch axis
    buf = add_batch(buf, transitions)                         # leaves [N, ...]: one row per env
    batch = sample(buf, key, batch_size)                      # leaves [batch_size, ...]

Every function is pure and jit-able (``batch_size`` must be static). Sampling is uniform with
replacement over the filled rows only.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct


class Transition(NamedTuple):
    """One step of experience. Every off-policy loss in ``algos.common`` reads these fields.

    ``done`` is 1 only where the episode *terminated* (no bootstrap from ``next_obs``): store the
    env's ``info['terminated']``, not its ``done``. A time-limit truncation stores done = 0 with the
    true final observation (``info['next_obs']``) in ``next_obs``.
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    cost: jax.Array
    next_obs: jax.Array
    done: jax.Array
    extras: Any = None
    """Any further pytree an algorithm wants to store (e.g. the automaton state)."""


def _shape_dtype(leaf: Any) -> tuple[tuple[int, ...], Any]:
    if isinstance(leaf, jax.ShapeDtypeStruct):
        return tuple(leaf.shape), leaf.dtype
    arr = jnp.asarray(leaf)
    return tuple(arr.shape), arr.dtype


@struct.dataclass
class ReplayBuffer:
    """Ring buffer. ``data`` mirrors the transition pytree with a leading [capacity] axis."""

    data: Any
    ptr: jax.Array
    """int32 []: row written by the next add."""
    size: jax.Array
    """int32 []: number of filled rows (saturates at capacity)."""
    capacity: int = struct.field(pytree_node=False)

    @classmethod
    def create(cls, capacity: int, example_transition: Any) -> ReplayBuffer:
        """Empty buffer for transitions shaped like ``example_transition`` (arrays, scalars or
        ``jax.ShapeDtypeStruct`` leaves, without a batch axis)."""
        if not isinstance(capacity, int) or capacity <= 0:
            raise ValueError(f"ReplayBuffer capacity must be a positive int, got {capacity!r}")

        def zeros(leaf: Any) -> jax.Array:
            shape, dtype = _shape_dtype(leaf)
            return jnp.zeros((capacity, *shape), dtype)

        data = jax.tree_util.tree_map(zeros, example_transition)
        return cls(data=data, ptr=jnp.int32(0), size=jnp.int32(0), capacity=capacity)

    @property
    def full(self) -> jax.Array:
        """bool []: every row holds a transition."""
        return self.size >= self.capacity


def add_batch(buffer: ReplayBuffer, transitions: Any) -> ReplayBuffer:
    """Write N transitions (leaves [N, ...]) at ``ptr``, wrapping around; oldest rows are overwritten."""
    leaves = jax.tree_util.tree_leaves(transitions)
    if not leaves:
        raise ValueError("add_batch: transitions pytree has no leaves")
    n = leaves[0].shape[0]
    if n > buffer.capacity:
        raise ValueError(f"add_batch: batch of {n} transitions exceeds capacity {buffer.capacity}")
    idx = (buffer.ptr + jnp.arange(n, dtype=jnp.int32)) % buffer.capacity

    def write(stored: jax.Array, new: jax.Array) -> jax.Array:
        new = jnp.asarray(new)
        if new.shape != (n, *stored.shape[1:]):
            raise ValueError(f"add_batch: leaf shape {new.shape} does not match buffer rows {(n, *stored.shape[1:])}")
        return stored.at[idx].set(new.astype(stored.dtype))

    data = jax.tree_util.tree_map(write, buffer.data, transitions)
    return buffer.replace(
        data=data,
        ptr=(buffer.ptr + n) % buffer.capacity,
        size=jnp.minimum(buffer.size + n, buffer.capacity).astype(jnp.int32),
    )


def add(buffer: ReplayBuffer, transition: Any) -> ReplayBuffer:
    """Write one transition (no batch axis)."""
    return add_batch(buffer, jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], transition))


def sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int) -> Any:
    """``batch_size`` transitions drawn uniformly (with replacement) from the filled rows.

    On an empty buffer this returns copies of row 0 (zeros); callers start updates after a warm-up.
    """
    idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    return jax.tree_util.tree_map(lambda x: x[idx], buffer.data)
