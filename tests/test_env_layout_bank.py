"""The bank of per-(target, forbidden subset) distance fields: values, both solvers, lookups under jit/vmap."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.envs import generator, geodesic
from d2spo.envs import layout_bank as lb
from d2spo.envs.workspace import Area, Layout

GRID = 32
# an empty 5 m arena: A1 left, A2 in the middle on the straight line from A1 to the right side
HAND = Layout("hand", (5.0, 5.0), (4.5, 4.5, 0.0), (), (
    Area("A1", (1.0, 2.5), 0.4), Area("A2", (2.5, 2.5), 0.6), Area("A3", (4.3, 4.3), 0.35),
    Area("A4", (4.3, 0.7), 0.35)))


@pytest.fixture(scope="module")
def bank():
    """The hand layout and two generated ones, fields by the JAX solver (one compile)."""
    return lb.bank_of([HAND, generator.generate(1), generator.generate(2)], grid=GRID)


def node(xy):
    return tuple(int(round(v / (5.0 / (GRID - 1)))) for v in xy[::-1])  # (row, column) of the node nearest xy


def test_open_field_is_the_straight_distance_to_the_disk(bank):
    field = np.asarray(bank.fields[0, 0, 0])  # target A1, nothing forbidden
    spacing = 5.0 / (GRID - 1)
    ys, xs = np.mgrid[0:GRID, 0:GRID] * spacing
    straight = np.maximum(np.hypot(xs - 1.0, ys - 2.5) - 0.4, 0.0)
    away = (np.minimum.reduce([xs, ys, 5 - xs, 5 - ys]) >= lb.CLEARANCE)  # off the walls' costly band
    assert np.all(field[away] >= straight[away] - 1e-4)
    # an 8-neighbour path is at most 8.2% longer than the segment, plus under a step at the disk
    assert np.all(field[away] <= straight[away] * math.sqrt(4 - 2 * math.sqrt(2)) + spacing)
    assert field[node((1.0, 2.5))] == 0.0


def test_a_forbidden_area_is_gone_round(bank):
    far = node((4.4, 2.5))  # behind A2 seen from A1
    free = float(bank.fields[0, 0, 0][far])
    f_a2 = int(lb.subsets(jnp.array([False, True, False, False]))[0])
    assert f_a2 == 1  # for target A1, bit 0 is A2
    round_a2 = float(bank.fields[0, 0, f_a2][far])
    penalty = geodesic.BLOCKED_COST * math.hypot(5.0, 5.0)
    straight = far[1] * 5.0 / (GRID - 1) - 1.4  # along y = 2.5 to A1's disk
    # round A2 (r 0.6 + 0.3 m keep-out) it is longer, but far less than entering it
    assert straight <= free < straight + 0.1 and free + 0.3 < round_a2 < free + 2.0 < penalty
    # forbidding A3 and A4, far from the way, changes nothing there
    f_34 = int(lb.subsets(jnp.array([False, False, True, True]))[0])
    assert float(bank.fields[0, 0, f_34][far]) == pytest.approx(free, abs=1e-5)


def test_jax_fields_match_the_numpy_reference(bank):
    args = (bank.arena, bank.box_lo, bank.box_hi, bank.box_mask, bank.area_center, bank.area_radius)
    for b in (0, 2):
        ref = lb.fields_numpy(*(a[b] for a in args), grid=GRID)
        np.testing.assert_allclose(np.asarray(bank.fields[b]), ref, rtol=1e-4, atol=1e-4)
    assert np.all(np.isfinite(np.asarray(bank.fields)))


def test_field_at_and_nearest_under_jit_and_vmap(bank):
    xy = jnp.array([4.0, 2.5])
    target = jnp.array([True, False, False, False])
    forbidden = jnp.array([False, True, False, False])
    nearest, field_at = jax.jit(lb.nearest), jax.jit(lb.field_at)
    d, direction = nearest(bank, 0, target, forbidden, xy)
    assert d.shape == () and direction.shape == (2,)
    assert float(d) == pytest.approx(float(field_at(bank, 0, 0, 1, xy)), rel=1e-6)
    assert float(jnp.linalg.norm(direction)) == pytest.approx(1.0, abs=1e-5)
    d_open, dir_open = nearest(bank, 0, target, jnp.zeros(4, bool), xy)  # nothing forbidden: straight left
    assert float(d_open) < float(d) and float(dir_open[0]) < -0.95
    # the nearest of two targets; none: 0 and no direction
    d_two, _ = nearest(bank, 0, jnp.array([True, False, False, True]), forbidden, xy)
    assert float(d_two) == pytest.approx(min(float(field_at(bank, 0, 3, 0, xy)), float(d)), rel=1e-6)
    d_none, dir_none = nearest(bank, 0, jnp.zeros(4, bool), forbidden, xy)
    assert float(d_none) == 0.0 and not jnp.any(dir_none)
    # vmapped over layouts and points, as a batch of environments would read it
    bs, pts = jnp.array([0, 1, 2]), jnp.array([[4.0, 2.5], [1.0, 1.0], [2.0, 3.0]])
    ds, dirs = jax.jit(jax.vmap(lb.nearest, in_axes=(None, 0, None, None, 0)))(bank, bs, target, forbidden, pts)
    assert ds.shape == (3,) and dirs.shape == (3, 2) and bool(jnp.all(jnp.isfinite(ds)))
    assert float(ds[0]) == pytest.approx(float(d), rel=1e-6)


def test_pack_refuses_what_a_bank_cannot_hold():
    from d2spo.errors import ConfigError

    with pytest.raises(ConfigError, match="square"):
        lb.pack([Layout("r", (5.0, 4.0), (1.0, 1.0, 0.0), (), HAND.areas)])
    with pytest.raises(ConfigError, match="4 areas"):
        lb.pack([Layout("r", (5.0, 5.0), (4.5, 4.5, 0.0), (), HAND.areas[:3])])
