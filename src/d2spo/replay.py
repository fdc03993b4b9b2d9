"""The ring buffer every learner stores on the device: a pytree of rows with a write pointer.

    buf = ReplayBuffer.create(capacity, example_item)   # one item, no batch axis
    buf = add_batch(buf, items, mask=None)             # leaves [N, ...]: the rows where mask is true
    batch = sample(buf, key, batch_size)               # leaves [batch_size, ...]

Every function is pure and jit-able (``batch_size`` must be static). Sampling is uniform with
replacement over the filled rows only. TD3's replay buffer, D²SPO's datasets T, P_exp and X_L
(``safety.datasets``) and the ``*-lag`` cost window (``algos.offpolicy``) all write rows with
``write_rows``.
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
    """Ring buffer. ``data`` mirrors the item pytree (e.g. a ``Transition``) with a leading [capacity] axis."""

    data: Any
    ptr: jax.Array
    """int32 []: row written by the next add."""
    size: jax.Array
    """int32 []: number of filled rows (saturates at capacity)."""
    capacity: int = struct.field(pytree_node=False)

    @classmethod
    def create(cls, capacity: int, example_item: Any) -> ReplayBuffer:
        """Empty buffer for items shaped like ``example_item`` (arrays, scalars or
        ``jax.ShapeDtypeStruct`` leaves, without a batch axis)."""
        if not isinstance(capacity, int) or capacity <= 0:
            raise ValueError(f"ReplayBuffer capacity must be a positive int, got {capacity!r}")

        def zeros(leaf: Any) -> jax.Array:
            shape, dtype = _shape_dtype(leaf)
            return jnp.zeros((capacity, *shape), dtype)

        data = jax.tree_util.tree_map(zeros, example_item)
        return cls(data=data, ptr=jnp.int32(0), size=jnp.int32(0), capacity=capacity)

    @property
    def full(self) -> jax.Array:
        """bool []: every row holds an item."""
        return self.size >= self.capacity


def write_rows(data: Any, start: jax.Array, items: Any, mask: jax.Array | None = None) -> tuple[Any, jax.Array]:
    """Write the rows of ``items`` where ``mask`` is true into the ring ``data`` from row ``start`` on, in order.

    ``data`` and ``items`` are pytrees of the same structure, leaves [capacity, ...] and [N, ...].
    Returns (data, n_add), n_add = number of rows written (int32 []). Masked-out rows are scattered
    out of range and dropped, so this is jit-able; of more than ``capacity`` rows only the last
    ``capacity`` are kept.
    """
    n = jax.tree_util.tree_leaves(items)[0].shape[0]
    capacity = jax.tree_util.tree_leaves(data)[0].shape[0]
    mask = jnp.ones((n,), bool) if mask is None else mask.astype(bool)
    rank = jnp.cumsum(mask) - 1  # position among the rows written
    n_add = jnp.sum(mask, dtype=jnp.int32)
    keep = mask & (rank >= n_add - capacity)
    idx = jnp.where(keep, (start + rank) % capacity, capacity)  # `capacity` is out of range: dropped
    data = jax.tree_util.tree_map(lambda d, x: d.at[idx].set(jnp.asarray(x).astype(d.dtype), mode="drop"), data, items)
    return data, n_add


def add_batch(buffer: ReplayBuffer, items: Any, mask: jax.Array | None = None) -> ReplayBuffer:
    """Append the rows of ``items`` (leaves [N, ...]) where ``mask`` [N] is true (all when None),
    overwriting the oldest rows; of more than ``capacity`` rows only the last ``capacity`` are kept."""
    leaves = jax.tree_util.tree_leaves(items)
    if not leaves:
        raise ValueError("add_batch: the items pytree has no leaves")
    n = jnp.shape(leaves[0])[0] if jnp.ndim(leaves[0]) else 0

    def check(stored: jax.Array, new: Any) -> None:
        if jnp.shape(new) != (n, *stored.shape[1:]):
            raise ValueError(f"add_batch: leaf shape {jnp.shape(new)} does not match buffer rows "
                             f"{(n, *stored.shape[1:])}")

    jax.tree_util.tree_map(check, buffer.data, items)
    data, n_add = write_rows(buffer.data, buffer.ptr, items, mask)
    return buffer.replace(
        data=data,
        ptr=(buffer.ptr + n_add) % buffer.capacity,
        size=jnp.minimum(buffer.size + n_add, buffer.capacity),
    )


def add(buffer: ReplayBuffer, item: Any) -> ReplayBuffer:
    """Write one item (no batch axis)."""
    return add_batch(buffer, jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], item))


def sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int) -> Any:
    """``batch_size`` items drawn uniformly (with replacement) from the filled rows.

    On an empty buffer this returns copies of row 0 (zeros); callers start updates after a warm-up.
    """
    idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    return jax.tree_util.tree_map(lambda x: x[idx], buffer.data)
