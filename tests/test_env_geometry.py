"""Collision checks and the lidar sensor model against independent numpy implementations."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from d2spo.envs import geometry, layouts, sensors
from d2spo.envs.geometry import Geometry

LAYOUT = layouts.load("paper")
GEOM = Geometry(
    box_lo=jnp.asarray([o.lo for o in LAYOUT.obstacles], jnp.float32),
    box_hi=jnp.asarray([o.hi for o in LAYOUT.obstacles], jnp.float32),
    arena_lo=jnp.zeros(2, jnp.float32),
    arena_hi=jnp.asarray(LAYOUT.arena, jnp.float32),
)
RADIUS = 0.15
H = 1.2
K = 16


# ------------------------------------------------------------------------ independent references


def np_box_distance(p, lo, hi) -> float:
    """Signed distance point -> box via the closest point (clamping); minus depth inside."""
    closest = np.clip(p, lo, hi)
    if np.all(closest == p):
        return -float(min(np.min(p - lo), np.min(hi - p)))
    return float(np.linalg.norm(p - closest))


def np_clearance(p) -> float:
    walls = min(p[0], p[1], LAYOUT.arena[0] - p[0], LAYOUT.arena[1] - p[1])
    return min([walls] + [np_box_distance(p, o.lo, o.hi) for o in LAYOUT.obstacles])


def _segments(lo, hi):
    (x0, y0), (x1, y1) = lo, hi
    return [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]


def _ray_segment(p, d, a, b) -> float:
    """Distance along the ray p + t d (t >= 0) to segment ab, or inf (Cramer's rule)."""
    e = np.subtract(b, a)
    m = np.array([[d[0], -e[0]], [d[1], -e[1]]])
    det = np.linalg.det(m)
    if abs(det) < 1e-12:
        return math.inf
    t, s = np.linalg.solve(m, np.subtract(a, p))
    return t if t >= 0 and -1e-12 <= s <= 1 + 1e-12 else math.inf


def np_lidar(pose, mask) -> np.ndarray:
    """Ray casting by intersecting each ray with every edge of the visible boxes and the arena."""
    p = np.asarray(pose[:2], np.float64)
    out = []
    for k in range(K):
        ang = pose[2] + 2 * math.pi * k / K
        d = np.array([math.cos(ang), math.sin(ang)])
        best = H
        for o, visible in zip(LAYOUT.obstacles, mask):
            if not visible:
                continue
            if np.all(o.lo <= p) and np.all(p <= o.hi):
                best = 0.0
            for a, b in _segments(o.lo, o.hi):
                best = min(best, _ray_segment(p, d, a, b))
        for a, b in _segments((0.0, 0.0), LAYOUT.arena):
            best = min(best, _ray_segment(p, d, a, b))
        out.append(min(max(best, 0.0), H))
    return np.array(out)


# ------------------------------------------------------------------------------------- tests

_collides = jax.jit(lambda xy: geometry.collides(xy, GEOM, RADIUS))
_clearance = jax.jit(lambda xy: geometry.clearance(xy, GEOM))
_lidar = jax.jit(lambda pose, mask: sensors.lidar(pose, GEOM, mask, K, H))

coord = st.floats(-0.3, 5.3, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(coord, coord)
def test_collision_exactly_when_signed_distance_nonpositive(x, y):
    p = np.array([x, y], np.float32)
    d = np_clearance(p.astype(np.float64)) - RADIUS
    assert float(_clearance(p)) == pytest.approx(d + RADIUS, abs=1e-5)
    if abs(d) > 1e-5:  # away from float32 rounding at the boundary
        assert bool(_collides(p)) == (d <= 0)


def test_collision_on_the_boundary_counts():
    o = LAYOUT.obstacles[0]  # left face at x = 2.25; radius 0.25 keeps every number exact in float32
    collides = jax.jit(lambda xy: geometry.collides(xy, GEOM, 0.25))
    touching = np.array([o.lo[0] - 0.25, o.center[1]], np.float32)  # disk touches the left face
    assert bool(collides(touching))
    assert not bool(collides(touching - np.array([1e-3, 0], np.float32)))
    assert bool(collides(np.array([0.25, 2.5], np.float32)))  # touches the arena wall
    assert bool(collides(np.array([-1.0, 2.5], np.float32)))  # outside the arena


@settings(max_examples=60, deadline=None)
@given(st.floats(0.05, 4.95), st.floats(0.05, 4.95), st.floats(-math.pi, math.pi),
       st.lists(st.booleans(), min_size=8, max_size=8))
def test_lidar_matches_independent_ray_cast(x, y, theta, mask):
    pose = np.array([x, y, theta], np.float32)
    # Degenerate: a centre on the line of a box's face (e.g. (3.0, 2.0) with the face y = 2.0) sends an
    # axis-aligned ray along that face, grazing its corner 1e-16 m away in float64 and missing it in
    # float32; hit or miss is then a rounding convention, not a property of the sensor.
    faces = np.array([[o.lo, o.hi] for o in LAYOUT.obstacles], np.float64)  # [M, 2, 2]
    assume(np.all(np.abs(faces[:, :, 0] - pose[0]) > 1e-4) and np.all(np.abs(faces[:, :, 1] - pose[1]) > 1e-4))
    got = np.asarray(_lidar(pose, jnp.asarray(mask)))
    want = np_lidar(pose.astype(np.float64), mask)
    assert got.shape == (K,)
    assert np.all(got >= 0) and np.all(got <= H)
    np.testing.assert_allclose(got, want, atol=2e-4)


def test_lidar_sensed_mask_hides_obstacles_and_walls_always_visible():
    o = LAYOUT.obstacles[0]
    pose = np.array([o.lo[0] - 0.5, o.center[1], 0.0], np.float32)  # 0.5 m left of box 0, facing it
    seen = np.asarray(_lidar(pose, jnp.ones(8, bool)))
    hidden = np.asarray(_lidar(pose, jnp.zeros(8, bool)))
    assert seen[0] == pytest.approx(0.5, abs=1e-5)
    assert hidden[0] == pytest.approx(H)
    wall = np.asarray(_lidar(np.array([0.3, 2.5, math.pi], np.float32), jnp.zeros(8, bool)))
    assert wall[0] == pytest.approx(0.3, abs=1e-5)  # facing the left wall


def test_lidar_inside_an_obstacle_reads_zero_and_sensed_mask_matches_distance():
    o = LAYOUT.obstacles[2]
    inside = np.array([*o.center, 0.3], np.float32)
    assert np.all(np.asarray(_lidar(inside, jnp.ones(8, bool))) == 0.0)
    p = np.array([2.0, 2.0], np.float32)
    sensed = np.asarray(jax.jit(geometry.sensed_mask)(p, GEOM, H))
    want = [np_box_distance(p.astype(np.float64), ob.lo, ob.hi) <= H for ob in LAYOUT.obstacles]
    assert sensed.tolist() == want


def test_lidar_is_differentiable_in_pose():
    jac = jax.jit(jax.jacrev(lambda z: sensors.lidar(z, GEOM, jnp.ones(8, bool), K, H)))
    grad = np.asarray(jac(jnp.array([1.7, 2.4, 0.3])))
    assert grad.shape == (K, 3)
    assert np.all(np.isfinite(grad))
    # a ray that hits a face perpendicular to it shortens 1:1 as the robot moves towards the face
    o = LAYOUT.obstacles[0]
    facing = jnp.array([o.lo[0] - 0.5, o.center[1], 0.0])
    np.testing.assert_allclose(np.asarray(jac(facing))[0], [-1.0, 0.0, 0.0], atol=1e-4)


CASTS = {"unrolled": {"unroll": True}, "reduced": {"unroll": False}, "first hit": {"for_grad": True}}
"""The three ways ``sensors.lidar`` takes the minimum over obstacles: one chain per obstacle, one
reduction, or the first obstacle found without gradient and differentiated alone (``for_grad``: D²SPO's
features_for_grad, which T_e, the cautious start, UPDATE(D) and the runtime filter differentiate)."""


def test_every_way_of_casting_gives_the_same_ranges_and_gradients():
    poses = jax.random.uniform(jax.random.key(0), (200, 3), minval=-0.2, maxval=5.2)
    mask = jnp.arange(8) % 3 != 0

    def scan(how):
        return jax.jit(jax.vmap(lambda z: sensors.lidar(z, GEOM, mask, K, H, **CASTS[how])))(poses)

    for how in ("reduced", "first hit"):
        np.testing.assert_array_equal(np.asarray(scan("unrolled")), np.asarray(scan(how)))

    def jacobians(how):
        return np.asarray(jax.jit(jax.vmap(jax.jacrev(lambda z: sensors.lidar(z, GEOM, mask, K, H, **CASTS[how]))))(poses))

    unrolled = jacobians("unrolled")
    assert np.abs(unrolled).max() > 0.5  # the poses see obstacles
    for how in ("reduced", "first hit"):
        np.testing.assert_allclose(unrolled, jacobians(how), rtol=1e-6, atol=1e-6)
    # boxes and disks, as a generalist's world has (28 and 12 there: the unrolled gradient of that
    # many compiles for about 25 s, the reason the filter does not unroll)
    k_lo, k_disk, k_pose = jax.random.split(jax.random.key(1), 3)
    lo = jax.random.uniform(k_lo, (6, 2), minval=0.0, maxval=4.0)
    world = Geometry(lo, lo + 0.4, jnp.zeros(2), jnp.full(2, 5.0),
                     jax.random.uniform(k_disk, (4, 2), minval=0.0, maxval=5.0), jnp.full((4,), 0.3))
    poses = jax.random.uniform(k_pose, (300, 3), minval=0.2, maxval=4.8)
    visible = jnp.arange(10) % 4 != 1  # a box and a disk unsensed among them

    def both(how):
        cast = lambda z: sensors.lidar(z, world, visible, K, H, **CASTS[how])  # noqa: E731
        return jax.jit(jax.vmap(lambda z: (cast(z), jax.jacrev(cast)(z))))(poses)

    x_u, j_u = both("unrolled")
    assert np.abs(np.asarray(j_u)).max() > 0.5
    for how in ("reduced", "first hit"):
        x, j = both(how)
        # compiled beside their gradient, XLA may fuse the two differently: equal up to rounding (1 ulp).
        # Near a disk's tangent the gradient divides by sqrt(b² - c), which magnifies an ulp of it: the
        # first-hit cast, compiled in another shape, differs there by up to 2e-5 (relative)
        np.testing.assert_allclose(np.asarray(x_u), np.asarray(x), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(np.asarray(j_u), np.asarray(j), rtol=1e-6 if how == "reduced" else 5e-5, atol=1e-6)


def test_the_first_hit_cast_differentiates_the_nearest_obstacle_only():
    """Two boxes in a row ahead: the ray ahead reads the near one, and moving the far one changes
    neither the range nor its gradient in the pose; the gradient in the near box's corners is the
    ray's, that in the far box's is zero."""
    pose = jnp.array([0.5, 2.0, 0.0])

    def ahead(lo, hi):
        world = Geometry(lo, hi, jnp.zeros(2), jnp.full(2, 5.0))
        return sensors.lidar(pose, world, jnp.ones(2, bool), K, H, for_grad=True)[0]

    lo = jnp.array([[1.2, 1.5], [1.6, 1.5]])
    hi = lo + 1.0
    assert float(ahead(lo, hi)) == pytest.approx(0.7, abs=1e-6)
    g_lo, g_hi = jax.grad(ahead, argnums=(0, 1))(lo, hi)
    np.testing.assert_allclose(np.asarray(g_lo), [[1.0, 0.0], [0.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(np.asarray(g_hi), np.zeros((2, 2)), atol=1e-6)


def test_a_layout_of_round_pillars_only_casts_without_unrolling():
    """No boxes at all (a lab of round pillars): the reduced cast, which D²SPO's features took, used to
    take the minimum of an empty array ("zero-size array to reduction"); every cast equals the unrolled one."""
    pillars = Geometry(jnp.zeros((0, 2)), jnp.zeros((0, 2)), jnp.zeros(2), jnp.full(2, 5.0),
                       jnp.array([[2.0, 2.5], [3.5, 1.0]]), jnp.array([0.3, 0.2]))
    pose = jnp.array([1.0, 2.5, 0.0])
    unrolled = sensors.lidar(pose, pillars, jnp.ones(2, bool), K, H, unroll=True)
    for how in ("reduced", "first hit"):
        cast = sensors.lidar(pose, pillars, jnp.ones(2, bool), K, H, **CASTS[how])
        np.testing.assert_array_equal(np.asarray(cast), np.asarray(unrolled))
    assert float(unrolled[0]) == pytest.approx(0.7, abs=1e-5)  # the ray ahead meets the pillar at x = 1.7


def test_cbf_input_is_the_scan_and_the_nearest_sensed_obstacle():
    """x = b(z, O_s): the lidar ranges, then the clearance to the sensed boxes and the walls,
    clipped at H (numpy reference); no ray reads less than it; the observation gives the same x."""
    rng = np.random.default_rng(0)
    n, m = 32, len(LAYOUT.obstacles)
    mask = np.arange(m) % 2 == 0  # every other box sensed
    poses = np.column_stack([rng.uniform(0.2, 4.8, (n, 2)), rng.uniform(-math.pi, math.pi, n)]).astype(np.float32)
    xy = 2.0 * poses[:, :2] / np.asarray(LAYOUT.arena, np.float32) - 1.0

    @jax.jit
    def both(poses, masks, xy):
        x = jax.vmap(lambda p, s: sensors.cbf_input(p, s, GEOM.arena_lo, GEOM.arena_hi, K, H))(
            poses, sensors.sensed_obstacles(GEOM, masks))
        obs = jnp.concatenate([x[:, :K] / H, xy, jnp.zeros((n, 3))], axis=1)  # lidar / H, x, y in [-1, 1], ...
        return x, jax.vmap(lambda p: sensors.lidar(p, GEOM, masks[0], K, H))(poses), obs

    x, scan, _ = both(jnp.asarray(poses), jnp.asarray(np.broadcast_to(mask, (n, m))), jnp.asarray(xy))
    x, scan = np.asarray(x), np.asarray(scan)
    np.testing.assert_array_equal(x[:, :K], scan)
    for p, row in zip(poses, x, strict=True):
        walls = min(p[0], p[1], LAYOUT.arena[0] - p[0], LAYOUT.arena[1] - p[1])
        near = min([walls] + [np_box_distance(p[:2], o.lo, o.hi) for o, s in zip(LAYOUT.obstacles, mask) if s])
        assert row[K] == pytest.approx(min(max(near, 0.0), H), abs=1e-5)
    assert np.all(x[:, :K].min(axis=1) >= x[:, K] - 1e-5)
    # from an observation, every obstacle sensed
    x_all, _, obs = both(jnp.asarray(poses), jnp.ones((n, m), bool), jnp.asarray(xy))
    from_obs = sensors.cbf_input_from_obs(obs, GEOM, slice(0, K), slice(K, K + 4), H)
    np.testing.assert_allclose(np.asarray(from_obs), np.asarray(x_all), atol=1e-5)
