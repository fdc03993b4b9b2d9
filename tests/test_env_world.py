"""``world:SEED`` (envs/world.py): the generalist's training world of rectangular arenas, pillars and labels."""

import collections

import numpy as np
import pytest

from d2spo.envs import layout_bank, layouts, world
from d2spo.envs.generator import RANDOM_RADIUS
from d2spo.envs.workspace import check_robot_fits

SEEDS = range(40)


@pytest.fixture(scope="module")
def drawn():
    return [world.generate(s) for s in SEEDS]


def test_world_layouts_are_deterministic_and_loadable_by_name(drawn):
    assert world.generate(7) == drawn[7] == layouts.load("world:7")
    assert world.generate(8) != drawn[7]


def test_every_style_and_the_ranges_are_drawn(drawn):
    styles = collections.Counter(world.style_of(s) for s in SEEDS)
    assert set(styles) == set(world.STYLES)
    for lay, s in zip(drawn, SEEDS):
        w, h = lay.arena
        if world.style_of(s) == "zones":
            assert (w, h) == (6.6, 6.6) and len(lay.areas) == 8 and not lay.obstacles
            assert collections.Counter(a.label for a in lay.areas) == {label: 2 for label in world.LABELS}
            continue
        assert world.SIDE[0] <= min(w, h) and max(w, h) <= world.SIDE[1]
        assert min(w, h) >= world.MIN_ASPECT * max(w, h) - 1e-6
        assert len(world.LABELS) <= len(lay.areas) <= world.MAX_AREAS
    rect = [lay for lay in drawn if lay.arena[0] != lay.arena[1]]
    assert len(rect) > len(drawn) // 2  # most are not square
    assert any(lay.disks for lay in drawn) and max(len(lay.areas) for lay in drawn) >= 10
    assert max(max(lay.arena) for lay in drawn) > 15.0


def test_every_layout_carries_the_task_labels_fits_a_slot_and_is_reachable(drawn):
    for lay in drawn:
        labels = [a.label for a in lay.areas]
        assert set(world.LABELS) <= set(labels)
        assert set(labels) <= set(world.LABELS) | set(world.DISTRACTORS)
        assert [a.name for a in lay.areas] == [f"area-{k + 1}" for k in range(len(lay.areas))]
        layout_bank.check_fits(lay)
        check_robot_fits(lay, RANDOM_RADIUS)
    shared = sum(any(n > 1 for n in collections.Counter(a.label for a in lay.areas).values()) for lay in drawn)
    assert shared > len(drawn) // 2  # shared labels are common


def test_gap_layouts_put_a_task_label_beyond_the_wall(drawn):
    gaps = [lay for lay, s in zip(drawn, SEEDS) if world.style_of(s) == "gap"]
    assert gaps
    for lay in gaps:
        wall = max(lay.boxes, key=lambda o: max(o.half_extents))  # the wall's longest piece
        axis = int(np.argmin(wall.half_extents))  # the wall runs across this axis
        at = wall.center[axis]
        beyond = {a.label for a in lay.areas if (a.center[axis] > at) != (lay.start[axis] > at)}
        assert beyond & set(world.LABELS), lay.name
