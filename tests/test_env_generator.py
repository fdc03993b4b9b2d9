"""The random layout generator (``random:SEED``): deterministic, valid, varied."""

import numpy as np

from d2spo.envs import generator, layouts, workspace


def test_generate_is_deterministic_and_is_what_random_seed_loads():
    assert generator.generate(3) == generator.generate(3) == layouts.load("random:3")
    assert layouts.load("random") == generator.generate(0)
    assert generator.generate(3) != generator.generate(4)
    assert layouts.load("random5:3") == generator.random_layout(3)  # the earlier 5 m generator, kept


def test_layouts_are_valid_and_varied():
    drawn = [generator.generate(s) for s in range(24)]
    styles = {generator.style_of(s) for s in range(24)}
    assert styles == set(generator.STYLES)
    sides = [lay.arena[0] for lay in drawn]
    assert min(sides) < 6.0 and max(sides) > 9.0 and all(5.0 <= s <= 10.0 for s in sides)
    for lay in drawn:
        assert lay.arena[0] == lay.arena[1]
        assert lay.area_names == ("A1", "A2", "A3", "A4")
        assert all(0.35 <= a.radius <= 0.5 for a in lay.areas)
        assert 1 <= len(lay.obstacles) <= generator.MAX_BOXES
        workspace.validate(lay)
        workspace.check_robot_fits(lay, generator.RANDOM_RADIUS)
        centres = np.array([a.center for a in lay.areas])
        radii = np.array([a.radius for a in lay.areas])
        apart = np.linalg.norm(centres[:, None] - centres[None], axis=-1) - radii[:, None] - radii[None]
        assert np.all(apart[~np.eye(4, dtype=bool)] >= generator.AREA_SPACING - 1e-9)  # areas do not overlap


def test_box_count_grows_with_the_area_and_the_gap_style_has_one_narrow_opening():
    boxes = [(generator.generate(s).arena[0], len(generator.generate(s).obstacles))
             for s in range(60) if generator.style_of(s) == "boxes"]
    assert min(side for side, _ in boxes) < 6.5 and max(side for side, _ in boxes) > 9.0
    for side, n in boxes:  # about BOX_DENSITY boxes per square metre: 3-6 at 5 m, 12-22 at 10 m
        lo, hi = (d * side * side for d in generator.BOX_DENSITY)
        assert max(3, round(lo)) <= n <= min(generator.MAX_BOXES, round(hi))
    seed = next(s for s in range(60) if generator.style_of(s) == "gap")
    lay = generator.generate(seed)
    wall = sorted((o for o in lay.obstacles if max(o.half_extents) * 2 > 0.2 * lay.arena[0]
                   and min(o.half_extents) <= 0.15), key=lambda o: o.center)
    assert len(wall) == 2  # the wall across the arena: two boxes with the opening between them
    axis = int(np.argmax(wall[0].half_extents))  # the wall runs along this axis
    opening = wall[1].lo[axis] - wall[0].hi[axis]
    assert generator.GAP_WIDTH[0] - 1e-3 <= opening <= generator.GAP_WIDTH[1] + 1e-3
