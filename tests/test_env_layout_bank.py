"""The bank of per-state distance fields: values, both solvers, shared labels, disks, rectangular
arenas, lookups under jit/vmap, and what a bank refuses."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.envs import bank_fields, generator, geodesic
from d2spo.envs import layout_bank as lb
from d2spo.envs.workspace import Area, DiskObstacle, Layout
from d2spo.errors import ConfigError

GRID = 32
N = lb.N_AREAS
# an empty 5 m arena: A1 left, A2 in the middle on the straight line from A1 to the right side
HAND = Layout("hand", (5.0, 5.0), (4.5, 4.5, 0.0), (), (
    Area("A1", (1.0, 2.5), 0.4), Area("A2", (2.5, 2.5), 0.6), Area("A3", (4.3, 4.3), 0.35),
    Area("A4", (4.3, 0.7), 0.35)))
# a 8 m x 4 m room, a round pillar between two docks that share a label, a third area elsewhere
RECT = Layout("rect", (8.0, 4.0), (4.0, 0.6, 0.0), (DiskObstacle((4.0, 2.0), 0.5),), (
    Area("dock-1", (1.0, 2.0), 0.4, "dock"), Area("dock-2", (7.0, 2.0), 0.4, "dock"), Area("desk", (4.0, 3.5), 0.3)))


def roles(states: list[tuple[list[int], list[int]]]) -> tuple[np.ndarray, np.ndarray]:
    """(target [S, N], forbidden [S, N]) from (target areas, forbidden areas) per state."""
    target, forbidden = np.zeros((len(states), N), bool), np.zeros((len(states), N), bool)
    for s, (t, f) in enumerate(states):
        target[s, t], forbidden[s, f] = True, True
    return target, forbidden


STATES = [([0], []), ([0], [1]), ([0], [2, 3]), ([0, 3], [1]), ([], [1])]
"""Per state of the test bank: target A1; A1 round A2; A1 with A3, A4 forbidden; A1 or A4 round A2; none."""


@pytest.fixture(scope="module")
def bank():
    """The hand layout and a generated one with the states above, fields by the JAX solver."""
    lays = [HAND, generator.generate(2)]
    target, forbidden = roles(STATES)
    packed = lb.pack(lays)
    paired = lb.pair(packed, np.zeros((2, N), np.int32), np.stack([target] * 2), np.stack([forbidden] * 2))
    return lb.with_fields(paired, "jax", grid=GRID)


def node(xy, side=5.0):
    return tuple(int(round(v / (side / (GRID - 1)))) for v in xy[::-1])  # (row, column) of the node nearest xy


def test_open_field_is_the_straight_distance_to_the_disk(bank):
    field = np.asarray(bank.fields[0, 0])  # target A1, nothing forbidden
    spacing = 5.0 / (GRID - 1)
    ys, xs = np.mgrid[0:GRID, 0:GRID] * spacing
    straight = np.maximum(np.hypot(xs - 1.0, ys - 2.5) - 0.4, 0.0)
    away = (np.minimum.reduce([xs, ys, 5 - xs, 5 - ys]) >= bank_fields.CLEARANCE)  # off the walls' costly band
    assert np.all(field[away] >= straight[away] - 1e-4)
    # an 8-neighbour path is at most 8.2% longer than the segment, plus under a step at the disk
    assert np.all(field[away] <= straight[away] * math.sqrt(4 - 2 * math.sqrt(2)) + spacing)
    assert field[node((1.0, 2.5))] == 0.0


def test_a_forbidden_area_is_gone_round(bank):
    far = node((4.4, 2.5))  # behind A2 seen from A1
    free = float(bank.fields[0, 0][far])
    round_a2 = float(bank.fields[0, 1][far])
    penalty = geodesic.BLOCKED_COST * math.hypot(5.0, 5.0)
    straight = far[1] * 5.0 / (GRID - 1) - 1.4  # along y = 2.5 to A1's disk
    # round A2 (r 0.6 + 0.3 m keep-out) it is longer, but far less than entering it
    assert straight <= free < straight + 0.1 and free + 0.3 < round_a2 < free + 2.0 < penalty
    # forbidding A3 and A4, far from the way, changes nothing there
    assert float(bank.fields[0, 2][far]) == pytest.approx(free, abs=1e-5)


def test_two_targets_give_the_nearer(bank):
    """A state whose targets are A1 and A4 (two areas of one label, say) reads the nearer of them."""
    only_a1 = np.asarray(bank.fields[0, 1])
    target, forbidden = roles([([3], [1])])
    one = lb.pair(lb.pack([HAND]), np.zeros((1, N), np.int32), target[None], forbidden[None])
    only_a4 = np.asarray(lb.with_fields(one, "numpy", grid=GRID).fields[0, 0])
    np.testing.assert_allclose(np.asarray(bank.fields[0, 3]), np.minimum(only_a1, only_a4), rtol=1e-4, atol=1e-4)


def test_a_state_with_no_target_has_a_zero_field(bank):
    assert not np.any(np.asarray(bank.fields[:, 4]))


def test_jax_fields_match_the_numpy_reference(bank):
    ref = lb.with_fields(bank, "numpy", grid=GRID)
    np.testing.assert_allclose(np.asarray(bank.fields), np.asarray(ref.fields), rtol=1e-4, atol=1e-4)
    assert np.all(np.isfinite(np.asarray(bank.fields)))


def test_rectangle_disk_and_shared_label():
    """An 8 x 4 m arena: the grid spans the longer side, the pillar is gone round, and the field to
    'dock' (both docks) is the nearer dock's; JAX and numpy agree."""
    target, forbidden = roles([([0, 1], []), ([2], [])])
    paired = lb.pair(lb.pack([RECT]), np.zeros((1, N), np.int32), target[None], forbidden[None])
    fields = np.asarray(lb.with_fields(paired, "jax", grid=GRID).fields[0])
    np.testing.assert_allclose(fields, np.asarray(lb.with_fields(paired, "numpy", grid=GRID).fields[0]),
                               rtol=1e-4, atol=1e-4)
    spacing = 8.0 / (GRID - 1)
    at = lambda xy: fields[0][int(round(xy[1] / spacing)), int(round(xy[0] / spacing))]  # noqa: E731
    assert at((1.0, 2.0)) == 0.0 and at((7.0, 2.0)) == 0.0  # inside either dock
    assert at((2.5, 2.0)) == pytest.approx(1.1, abs=0.2)  # 1.5 m from dock-1's centre
    # from the start (4, 0.6), below the pillar: about 3 m to a dock, round the pillar's foot
    assert 2.3 < at((4.0, 0.6)) < 4.0
    # beyond the arena's 4 m height the nodes are walls: costlier than any route inside
    assert fields[0][-1, GRID // 2] > 50.0


def test_field_at_and_nearest_under_jit_and_vmap(bank):
    xy = jnp.array([4.0, 2.5])
    nearest, field_at = jax.jit(lb.nearest), jax.jit(lb.field_at)
    d, direction, found = nearest(bank, 0, 1, xy)  # A1 round A2
    assert d.shape == () and direction.shape == (2,) and bool(found)
    assert float(d) == pytest.approx(float(field_at(bank, 0, 1, xy)), rel=1e-6)
    assert float(jnp.linalg.norm(direction)) == pytest.approx(1.0, abs=1e-5)
    d_open, dir_open, _ = nearest(bank, 0, 0, xy)  # nothing forbidden: straight left
    assert float(d_open) < float(d) and float(dir_open[0]) < -0.95
    d_none, dir_none, found_none = nearest(bank, 0, 4, xy)
    assert float(d_none) == 0.0 and not jnp.any(dir_none) and not bool(found_none)
    # vmapped over slots and points, as a batch of environments would read it
    bs, pts = jnp.array([0, 1, 0]), jnp.array([[4.0, 2.5], [1.0, 1.0], [2.0, 3.0]])
    ds, dirs, _ = jax.jit(jax.vmap(lb.nearest, in_axes=(None, 0, None, 0)))(bank, bs, 1, pts)
    assert ds.shape == (3,) and dirs.shape == (3, 2) and bool(jnp.all(jnp.isfinite(ds)))
    assert float(ds[0]) == pytest.approx(float(d), rel=1e-6)


def test_pack_refuses_what_a_bank_cannot_hold():
    with pytest.raises(ConfigError, match="at most 20 m"):
        lb.pack([Layout("r", (21.0, 4.0), (1.0, 1.0, 0.0), (), HAND.areas)])
    many = tuple(Area(f"a{i}", (0.5 + 0.9 * (i % 10), 0.5 + 0.9 * (i // 10)), 0.3) for i in range(lb.N_AREAS + 1))
    with pytest.raises(ConfigError, match=f"{lb.N_AREAS + 1} areas, more than the {lb.N_AREAS}"):
        lb.pack([Layout("r", (10.0, 10.0), (9.5, 9.5, 0.0), (), many)])
    pillars = tuple(DiskObstacle((0.5 + 0.7 * i, 9.0), 0.1) for i in range(lb.D_MAX + 1))
    with pytest.raises(ConfigError, match="disk obstacles, more than"):
        lb.pack([Layout("r", (10.0, 10.0), (5.0, 5.0, 0.0), pillars, HAND.areas)])
    overlap = (Area("A1", (1.0, 1.0), 0.5), Area("A2", (1.6, 1.0), 0.5))
    with pytest.raises(ConfigError, match="A1 and A2 overlap"):
        lb.pack([Layout("r", (5.0, 5.0), (4.0, 4.0, 0.0), (), overlap)])
    with pytest.raises(ConfigError, match="no task states"):
        lb.with_fields(lb.pack([HAND]))
    # a Layout built in Python gets a file's checks too (it once reached the fields unchecked)
    for area, message in ((Area("a", (2.0, 2.0), -0.5), r"areas\[0\]\.radius: layout 'r': must be positive"),
                          (Area("a", (math.nan, 2.0), 0.5), r"areas\[0\]: layout 'r': holds a number that is not finite"),
                          (Area("a", (2.0, 2.0), 0.5), "area a overlaps obstacle 0")):
        with pytest.raises(ConfigError, match=message):
            lb.pack([Layout("r", (5.0, 5.0), (0.6, 0.6, 0.0), (DiskObstacle((2.2, 2.0), 0.3),), (area,))])


def test_a_slots_field_is_the_same_bit_for_bit_alone_and_among_others():
    """A bank is solved in calls of the next power of two slots up to 16 (``with_fields``): a slot's
    field must not depend on the call it shares, alone (1 slot), among 3 (a call of 4) or in a call
    of 16 (a 16-slot bank)."""
    target, forbidden = roles(STATES)
    lays = [HAND, generator.generate(2), generator.generate(5)]

    def fields(ls):
        k = len(ls)
        paired = lb.pair(lb.pack(ls), np.zeros((k, N), np.int32), np.stack([target] * k), np.stack([forbidden] * k))
        return np.asarray(lb.with_fields(paired, "jax", grid=GRID).fields)

    three, many = fields(lays), fields(lays * 5 + lays[:1])
    np.testing.assert_array_equal(fields(lays[1:2])[0], three[1])
    for i in range(3):
        np.testing.assert_array_equal(many[i], three[i])
        np.testing.assert_array_equal(many[i + 3], three[i])
