"""Limited sensing (Example 1): the sensor model b(z, O_s) of Sec. IV-A, the CBF's input.

``cbf_input(pose, sensed, ...)`` is x = b(z, O_s), what the learned CBF h and the executed policy
π_Ω read: the K lidar ranges (``lidar``) and the distance to the nearest sensed obstacle or wall
(``nearest_obstacle``, the paper's scalar b), all in metres and clipped to [0, H].
``cbf_input_from_obs`` is the same x read off an observation (the lidar part of it, all obstacles
within H sensed). The networks rescale x by 1/H (``safety.cbf.network_input``).

The robot sees only what lies within its sensing radius H: obstacle boxes and disks (restricted
to the set O_s given as a mask) and the arena walls. Each of the K rays starts at the robot
centre; ray k points at heading theta + 2*pi*k/K (ray 0 looks straight ahead, the rays go
counter-clockwise).
A reading is the distance in metres to the first surface hit, clipped to [0, H]; a ray that hits
nothing within H reads H, and a ray cast from inside an obstacle reads 0.

The ray casts are analytic (slab method for boxes and for the arena, the quadratic for disks), so
the scan is an exact, pure function of the pose, differentiable almost everywhere.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization, struct

from d2spo.envs import geometry
from d2spo.envs.geometry import UNROLL_MAX, Geometry

_EPS = 1e-9
"""Ray direction components smaller than this are treated as +-_EPS (avoids 1/0)."""


def ray_offsets(n_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin [K] of the ray angles relative to the heading (numpy constants)."""
    phi = 2.0 * math.pi * np.arange(n_rays) / n_rays
    return np.cos(phi).astype(np.float32), np.sin(phi).astype(np.float32)


def _safe_inverse(d: jnp.ndarray) -> jnp.ndarray:
    return 1.0 / jnp.where(jnp.abs(d) < _EPS, jnp.where(d < 0.0, -_EPS, _EPS), d)


def lidar(
    pose: jnp.ndarray, geom: Geometry, sensed_mask: jnp.ndarray, n_rays: int, H: jnp.ndarray | float,
    unroll: bool | None = None, for_grad: bool = False,
) -> jnp.ndarray:
    """The sensor model b(z, O_s): K ranges in metres, each in [0, H].

    pose: [3] = (x, y, theta); geom: the workspace; sensed_mask: bool [M + D], the obstacle set O_s
    (boxes, then disks; obstacles outside the mask are invisible); n_rays: K (static); H: sensing radius.
    Walls are always visible within H. ``unroll`` (static) picks how the minimum over obstacles is
    computed: an unrolled chain (fastest forward pass under vmap on CPU) or one reduction (compiles
    its gradient ~3x faster); None unrolls up to ``UNROLL_MAX`` obstacles. Both give identical values.
    ``for_grad`` (static) is for callers that differentiate the ranges: ``unroll`` is then ignored,
    and each ray's first obstacle is found on values held constant, so that only that obstacle's
    range is differentiated (``_first_hit``).
    """
    return lidar_cs(pose[:2], jnp.cos(pose[2]), jnp.sin(pose[2]), geom, sensed_mask, n_rays, H, unroll, for_grad)


def lidar_cs(
    xy: jnp.ndarray, cos_theta: jnp.ndarray, sin_theta: jnp.ndarray, geom: Geometry, sensed_mask: jnp.ndarray,
    n_rays: int, H: jnp.ndarray | float, unroll: bool | None = None, for_grad: bool = False,
) -> jnp.ndarray:
    """:func:`lidar` with the heading given by its cosine and sine (shared with the observation)."""
    cos_phi, sin_phi = ray_offsets(n_rays)
    dx = cos_theta * cos_phi - sin_theta * sin_phi  # [K], cos(theta + phi_k)
    dy = sin_theta * cos_phi + cos_theta * sin_phi
    inv_x, inv_y = _safe_inverse(dx), _safe_inverse(dy)

    # Arena: the ray leaves the rectangle at the nearest of its far slab boundaries.
    alo = geom.arena_lo - xy
    ahi = geom.arena_hi - xy
    t_wall = jnp.minimum(jnp.maximum(alo[0] * inv_x, ahi[0] * inv_x), jnp.maximum(alo[1] * inv_y, ahi[1] * inv_y))

    # Boxes, slab method: the ray is inside the x-slab for t in [tx1, tx2] (in some order), likewise
    # y; it meets the box iff the two intervals overlap at some t >= 0.
    m = geom.box_lo.shape[0]
    box_mask = sensed_mask if geom.disk_center is None else sensed_mask[:m]
    if for_grad:
        t = jnp.minimum(t_wall, H)
        if m:
            t = jnp.minimum(t, _first_hit(lambda lo_, hi_, vis: _box_range(lo_ - xy, hi_ - xy, inv_x, inv_y, vis, H),
                                          geom.box_lo, geom.box_hi, box_mask))
        if geom.disk_center is not None and geom.n_disks:
            t = jnp.minimum(t, _first_hit(
                lambda c, r, vis: _disk_range(c[..., 0] - xy[0], c[..., 1] - xy[1], r, dx, dy, vis, H),
                geom.disk_center, geom.disk_radius, sensed_mask[m:]))
        return jnp.clip(t, 0.0, H)
    lo = geom.box_lo - xy  # [M, 2], corners relative to the robot
    hi = geom.box_hi - xy
    if m == 0 or (m <= UNROLL_MAX if unroll is None else unroll):  # one [K]-chain per obstacle (vectorises under vmap)
        t = jnp.minimum(t_wall, H)
        for i in range(m):
            t = jnp.minimum(t, _box_range(lo[i], hi[i], inv_x, inv_y, box_mask[i], H))
    else:
        t_box = _box_range(lo[:, None, :], hi[:, None, :], inv_x, inv_y, box_mask[:, None], H)  # [M, K]
        t = jnp.minimum(jnp.min(t_box, axis=0), jnp.minimum(t_wall, H))
    if geom.disk_center is not None:  # disks: the ray-circle quadratic
        rel, r, disk_mask = geom.disk_center - xy, geom.disk_radius, sensed_mask[m:]  # centres relative to the robot
        if geom.n_disks == 0 or (geom.n_disks <= UNROLL_MAX if unroll is None else unroll):
            for j in range(geom.n_disks):
                t = jnp.minimum(t, _disk_range(rel[j, 0], rel[j, 1], r[j], dx, dy, disk_mask[j], H))
        else:
            t_disk = _disk_range(rel[:, 0, None], rel[:, 1, None], r[:, None], dx, dy, disk_mask[:, None], H)
            t = jnp.minimum(t, jnp.min(t_disk, axis=0))
    return jnp.clip(t, 0.0, H)


def _first_hit(ranges, *obstacles: jnp.ndarray) -> jnp.ndarray:
    """The range [K] along each ray to the first of N obstacles it meets, differentiable through that
    obstacle alone.

    ``obstacles`` are the obstacles' arrays, each [N, ...]; ``ranges(*arrays)`` gives the ranges to
    the obstacles it is passed, [N, K] for all of them (each array [N, 1, ...]) or [K] for one per
    ray (each [K, ...]). All N ranges are computed without gradient and the nearest per ray kept
    (the first on a tie), then that obstacle's range is computed again, differentiably. The values
    are the minimum's (bit for bit at XLA's default optimisation level; to rounding at others), and
    so is the gradient, except on a tie between two obstacles, where the minimum's would split
    itself between them. The minimum's own gradient runs backwards through all N × K ranges:
    through this one it took Eq. (9)'s lidar from 0.25 to 0.14 ms per batch of 256 poses
    (bench/RESULTS.md, "2026-12-04, afternoon")."""
    t_all = jax.lax.stop_gradient(ranges(*(a[:, None] for a in obstacles)))  # [N, K]
    # argmin, not a comparison with the minimum: XLA may compute t_all twice in two kernels, an ulp
    # apart (at the test suite's optimisation level it did, and no range equalled the minimum)
    first = jnp.argmin(t_all, axis=0)
    return ranges(*(a[first] for a in obstacles))


def _disk_range(cx, cy, radius, dx, dy, visible, H):
    """Distance along each ray (unit direction dx, dy [K]) to a disk whose centre is (cx, cy) from the
    robot, or H when missed or invisible; 0 from inside. The ray p(t) = t d meets the circle where
    t^2 - 2 b t + c = 0, b = (cx, cy) . d, c = cx^2 + cy^2 - r^2: outside (c > 0) both roots have b's
    sign, so it hits at t = b - sqrt(b^2 - c) when that is real and b >= 0."""
    b = cx * dx + cy * dy
    c = cx * cx + cy * cy - radius * radius
    disc = b * b - c
    real = disc > 0.0  # (a tangent ray, disc = 0, grazes the disk at t = b: counted as a miss)
    t = b - jnp.where(real, jnp.sqrt(jnp.where(real, disc, 1.0)), 0.0)  # the root guarded for the gradient
    t = jnp.where(c <= 0.0, 0.0, jnp.where(real & (b >= 0.0), t, H))
    return jnp.where(visible, t, H)


def _box_range(lo, hi, inv_x, inv_y, visible, H):
    """Distance along each ray to one box (or H when missed or invisible); lo/hi relative to the robot."""
    tx1, tx2 = lo[..., 0] * inv_x, hi[..., 0] * inv_x
    ty1, ty2 = lo[..., 1] * inv_y, hi[..., 1] * inv_y
    t_near = jnp.maximum(jnp.minimum(tx1, tx2), jnp.minimum(ty1, ty2))
    t_far = jnp.minimum(jnp.maximum(tx1, tx2), jnp.maximum(ty1, ty2))
    t_enter = jnp.maximum(t_near, 0.0)  # 0 when the robot centre is inside the box
    return jnp.where((t_far >= t_enter) & visible, t_enter, H)


# ------------------------------------------------------------------ the CBF's input x = b(z, O_s)


@struct.dataclass
class Sensed:
    """O_s: obstacle boxes and disks and which of them the robot senses (leading batch axes allowed)."""

    box_lo: jax.Array
    """float32 [..., M, 2]: lower corners."""
    box_hi: jax.Array
    """float32 [..., M, 2]: upper corners."""
    mask: jax.Array
    """bool [..., M + D]: sensed (the boxes, then the disks)."""
    disk_center: jax.Array | None = None
    """float32 [..., D, 2]: disk centres; None: no disks."""
    disk_radius: jax.Array | None = None
    """float32 [..., D]: disk radii; None: no disks."""


def _sensed_state(s: Sensed) -> dict:
    """A checkpoint's record of O_s: without disks, the three fields it always had (so runs on
    layouts without disks write byte-identical checkpoints)."""
    keys = ("box_lo", "box_hi", "mask") + (() if s.disk_center is None else ("disk_center", "disk_radius"))
    return {k: serialization.to_state_dict(getattr(s, k)) for k in keys}


def _sensed_from_state(s: Sensed, state: dict) -> Sensed:
    return s.replace(**{k: serialization.from_state_dict(getattr(s, k), v, name=k) for k, v in state.items()})


serialization.register_serialization_state(Sensed, _sensed_state, _sensed_from_state, override=True)


def sensed_obstacles(geom: Geometry, mask: jax.Array) -> Sensed:
    """O_s among the layout's obstacles: ``mask`` [..., M + D], the obstacles broadcast to its leading axes."""
    lead = mask.shape[:-1]
    b = lambda a: None if a is None else jnp.broadcast_to(a, lead + a.shape)  # noqa: E731
    return Sensed(b(geom.box_lo), b(geom.box_hi), mask, b(geom.disk_center), b(geom.disk_radius))


def nearest_obstacle(xy: jax.Array, geom: Geometry, mask: jax.Array, H: jax.Array | float) -> jax.Array:
    """The paper's b: distance from xy to the nearest obstacle of the mask or wall, clipped to [0, H]."""
    boxes = jnp.where(mask, geometry.obstacle_signed_distance(xy, geom), H)
    walls = geometry.arena_signed_distance(xy, geom)
    return jnp.clip(jnp.min(jnp.concatenate([boxes, walls[None]])), 0.0, H)


def cbf_input(pose: jax.Array, sensed: Sensed, arena_lo: jax.Array, arena_hi: jax.Array, n_rays: int,
              H: jax.Array | float, unroll: bool | None = None, for_grad: bool = False) -> jax.Array:
    """x = b(z, O_s) [K + 1]: the K lidar ranges and the distance to the nearest sensed obstacle or wall.

    The last entry is the paper's b; the ranges tell h and π_Ω where the obstacles are. min(x) is
    that distance: a ray never hits closer than the nearest obstacle, while the nearest point of a
    box corner can lie between two rays (16 rays overestimate it by up to 27%). Pure and
    differentiable in ``pose`` almost everywhere (Eq. (9)'s T_e differentiates through it).
    ``unroll``: as :func:`lidar`'s (the same values either way, up to float rounding where XLA
    fuses the two differently); ``for_grad``: as :func:`lidar`'s.
    """
    geom = Geometry(sensed.box_lo, sensed.box_hi, arena_lo, arena_hi, sensed.disk_center, sensed.disk_radius)
    scan = lidar(pose, geom, sensed.mask, n_rays, H, unroll, for_grad)
    return jnp.concatenate([scan, nearest_obstacle(pose[:2], geom, sensed.mask, H)[None]])


def cbf_input_from_obs(obs: jax.Array, geom: Geometry, lidar_part: slice, pose_part: slice,
                       H: jax.Array | float) -> jax.Array:
    """x = b(z, O_s) [..., K + 1] from observations [..., D] (``nav.Env.observation_slices``): their
    lidar part times H (ranges beyond H read H either way) and the nearest-obstacle distance at the
    position they report, every obstacle sensed (obstacles beyond H count as H, as unsensed ones do)."""
    scan = obs[..., lidar_part] * H
    p = obs[..., pose_part]
    xy = (p[..., :2] + 1.0) * 0.5 * (geom.arena_hi - geom.arena_lo) + geom.arena_lo
    everything = jnp.ones((geom.n_obstacles,), bool)
    near = jnp.vectorize(lambda q: nearest_obstacle(q, geom, everything, H), signature="(2)->()")(xy)
    return jnp.concatenate([scan, near[..., None]], axis=-1)
