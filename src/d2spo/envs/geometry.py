"""Workspace geometry as arrays: axis-aligned box and disk obstacles inside a rectangular arena.

Everything here is pure JAX and works on one position; ``vmap`` it for batches. Distances are
measured from the robot *centre*; the robot radius enters only in :func:`collides`.

Sign convention: a signed distance is positive outside an obstacle (in free space) and negative
inside it. For the arena it is positive inside the arena and negative outside.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
from flax import struct

UNROLL_MAX = 32
"""Reductions over at most this many obstacles are unrolled into elementwise minima: under vmap
XLA:CPU vectorises those across the batch, while a reduction over a short minor axis runs scalar."""


def min_over_obstacles(values: jnp.ndarray, initial: jnp.ndarray) -> jnp.ndarray:
    """min(initial, values[..., 0], ..., values[..., M-1]) over the last (obstacle) axis."""
    m = values.shape[-1]
    if m > UNROLL_MAX:
        return jnp.minimum(jnp.min(values, axis=-1), initial)
    return functools.reduce(jnp.minimum, (values[..., i] for i in range(m)), initial)


@struct.dataclass
class Geometry:
    """The static obstacles of a workspace (what the sensor can see)."""

    box_lo: jnp.ndarray
    """float32 [M, 2]: lower-left corner (x_min, y_min) of each obstacle."""
    box_hi: jnp.ndarray
    """float32 [M, 2]: upper-right corner (x_max, y_max) of each obstacle."""
    arena_lo: jnp.ndarray
    """float32 [2]: lower-left corner of the arena."""
    arena_hi: jnp.ndarray
    """float32 [2]: upper-right corner of the arena."""
    disk_center: jnp.ndarray | None = None
    """float32 [D, 2]: centre of each disk obstacle; None: no disks (the arrays of a layout without
    them are exactly those of boxes only). Obstacle i < M is box i, obstacle M + j disk j."""
    disk_radius: jnp.ndarray | None = None
    """float32 [D]: radius of each disk obstacle; None with ``disk_center``."""

    @property
    def n_obstacles(self) -> int:
        """M + D: the boxes, then the disks (a sensed mask has this length)."""
        return self.box_lo.shape[-2] + self.n_disks

    @property
    def n_disks(self) -> int:
        return 0 if self.disk_center is None else self.disk_center.shape[-2]


def box_signed_distance(pos: jnp.ndarray, geom: Geometry) -> jnp.ndarray:
    """Signed distance [M] from a point ``pos`` [2] to every obstacle box (negative inside).

    Exact Euclidean distance outside a box; minus the distance to the nearest face inside. The
    gradient is finite everywhere (the square root is guarded at zero).
    """
    centre = 0.5 * (geom.box_lo + geom.box_hi)
    half = 0.5 * (geom.box_hi - geom.box_lo)
    dx = jnp.abs(pos[0] - centre[:, 0]) - half[:, 0]  # [M], > 0 beyond the box's x-range
    dy = jnp.abs(pos[1] - centre[:, 1]) - half[:, 1]
    ox, oy = jnp.maximum(dx, 0.0), jnp.maximum(dy, 0.0)
    sq = ox * ox + oy * oy
    positive = sq > 0.0
    outside = jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)
    inside = jnp.minimum(jnp.maximum(dx, dy), 0.0)
    return outside + inside


def disk_signed_distance(pos: jnp.ndarray, geom: Geometry) -> jnp.ndarray:
    """Signed distance [D] from a point ``pos`` [2] to every disk obstacle (negative inside); the
    square root is guarded at the centre, so the gradient is finite everywhere."""
    dx = pos[0] - geom.disk_center[:, 0]
    dy = pos[1] - geom.disk_center[:, 1]
    sq = dx * dx + dy * dy
    positive = sq > 0.0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0) - geom.disk_radius


def obstacle_signed_distance(pos: jnp.ndarray, geom: Geometry) -> jnp.ndarray:
    """Signed distance [M + D] from ``pos`` to every obstacle: the boxes, then the disks."""
    boxes = box_signed_distance(pos, geom)
    return boxes if geom.disk_center is None else jnp.concatenate([boxes, disk_signed_distance(pos, geom)])


def arena_signed_distance(pos: jnp.ndarray, geom: Geometry) -> jnp.ndarray:
    """Distance [] from ``pos`` to the nearest arena wall; negative when outside the arena."""
    lo = pos - geom.arena_lo
    hi = geom.arena_hi - pos
    return jnp.minimum(jnp.minimum(lo[0], lo[1]), jnp.minimum(hi[0], hi[1]))


def clearance(pos: jnp.ndarray, geom: Geometry) -> jnp.ndarray:
    """Signed distance [] from the robot centre to the nearest obstacle or wall."""
    d = min_over_obstacles(box_signed_distance(pos, geom), arena_signed_distance(pos, geom))
    return d if geom.disk_center is None else min_over_obstacles(disk_signed_distance(pos, geom), d)


def collides(pos: jnp.ndarray, geom: Geometry, robot_radius: jnp.ndarray) -> jnp.ndarray:
    """bool []: the robot disk touches an obstacle or leaves the arena (clearance - radius <= 0), or
    its position is not a number (a NaN action's): a pose nobody knows is not a safe one."""
    return ~(clearance(pos, geom) - robot_radius > 0.0)


def sensed_mask(pos: jnp.ndarray, geom: Geometry, sensing_radius: jnp.ndarray) -> jnp.ndarray:
    """bool [M + D]: obstacles whose boundary is within the sensing radius H of ``pos`` (the set O_s)."""
    return obstacle_signed_distance(pos, geom) <= sensing_radius
