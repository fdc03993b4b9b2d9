"""bench/route_bound.py: the continuous shortest patrol routes that bound what a policy can score
(bench/RESULTS.md, "2026-11-30"): exact where the answer is known, and below the grid search's
routes by at most its 8-neighbour excess where passages are wide."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from pathlib import Path

import pytest

from d2spo.envs import layouts, routes
from d2spo.envs.workspace import Area, Obstacle
from d2spo.ltl.buchi_task import task_automaton
from d2spo.ltl.tasks import TASKS

_spec = importlib.util.spec_from_file_location("route_bound", Path(__file__).parent.parent / "bench" / "route_bound.py")
route_bound = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(route_bound)


def _open_field(**kw):
    base = layouts.load("paper")
    areas = (Area(name="A1", center=(1.0, 1.0), radius=0.35, label="A1"),
             Area(name="A3", center=(4.0, 1.0), radius=0.35, label="A3"),
             Area(name="A4", center=(2.5, 4.0), radius=0.35, label="A4"))
    return dataclasses.replace(base, start=(0.6, 1.0, 0.0), obstacles=(), areas=areas, **kw)


def test_in_the_open_the_routes_are_straight_lines():
    first, lap = route_bound.bound(_open_field(), ("A1", "A3"), ["A4"], 0.3, rim=72)
    # start -> through A1 -> A3's rim along y = 1; each lap twice the gap between the rims
    assert first == pytest.approx(4.0 - 0.35 - 0.6, abs=2e-3)
    assert lap == pytest.approx(2 * (3.0 - 0.7), abs=2e-3)
    # a forbidden disk on the line is gone round, further with a margin kept from it
    lay = _open_field()
    lay = dataclasses.replace(lay, areas=lay.areas[:2] + (dataclasses.replace(lay.areas[2], center=(2.5, 1.0)),))
    _, round_it = route_bound.bound(lay, ("A1", "A3"), ["A4"], 0.3, rim=72)
    _, wider = route_bound.bound(lay, ("A1", "A3"), ["A4"], 0.3, rim=72, forbid_margin=0.1)
    assert lap < round_it < wider


def test_a_box_between_the_areas_is_gone_round_at_the_margin():
    lay = _open_field()
    lay = dataclasses.replace(lay, obstacles=(Obstacle(center=(2.5, 1.0), half_extents=(0.25, 0.25)),))
    c = 0.3
    _, lap = route_bound.bound(lay, ("A1", "A3"), ["A4"], c, rim=72)
    # the exact detour, symmetric about x = 2.5: from A1's rim along the line from its centre that
    # is tangent to the grown box's rounded corner (radius c round (2.25, 1.25)), round that arc to
    # the box's top, 0.5 m along it, and down the mirror image to A3's rim
    centre, corner = (1.0, 1.0), (2.25, 1.25)
    d = math.dist(centre, corner)
    tangent = math.sqrt(d * d - c * c) - 0.35
    heading = math.atan2(corner[1] - centre[1], corner[0] - centre[0]) + math.asin(c / d)
    exact = 2 * (tangent + c * heading) + 0.5
    assert lap / 2 == pytest.approx(exact, rel=1e-3)
    assert lap / 2 > 3.0 - 0.7  # longer than the straight gap


def test_paper_at_the_robots_radius_lies_under_the_grid_routes_by_at_most_their_excess():
    lay = layouts.load("paper")
    c = 0.15
    first, lap = route_bound.bound(lay, ("A1", "A3"), ["A4"], c, per_corner=8, rim=90)
    grid = routes.visit_lengths(task_automaton(TASKS["patrol2"]), lay, "event", c, math.inf, 2)
    assert first <= grid[0] <= first * routes.OCTILE_EXCESS
    assert lap <= grid[1] - grid[0] <= lap * routes.OCTILE_EXCESS


def test_visits_that_fit_with_and_without_turning_round():
    """1 m to the first visit, 2 m laps, 0.1 m a step, 100 steps: visits at steps 10, 30, 50, 70, 90;
    turning round in 5 steps at each area (once before the first visit, twice a lap): at 15, 45, 75."""
    assert route_bound.visits_fit(1.0, 2.0, 0.1, 100) == 5
    assert route_bound.visits_fit(1.0, 2.0, 0.1, 100, turn_steps=5.0) == 3
    assert route_bound.visits_fit(11.0, 2.0, 0.1, 100) == 0


def test_a_margin_no_route_keeps_gives_no_lap_and_one_line(capsys, monkeypatch):
    """Boxes closing the arena from wall to wall between A1 and A3: no route at all, so (inf, inf),
    not nan; the command prints one line for that margin instead of failing on it."""
    lay = _open_field()
    wall = Obstacle(center=(2.5, lay.arena[1] / 2), half_extents=(0.1, lay.arena[1] / 2))
    lay = dataclasses.replace(lay, obstacles=(wall,))
    assert route_bound.bound(lay, ("A1", "A3"), ["A4"], 0.3, rim=36) == (math.inf, math.inf)
    monkeypatch.setattr(route_bound.layouts, "load", lambda name: lay)
    monkeypatch.setattr("sys.argv", ["route_bound.py", "--margins", "0.3", "--forward-only"])
    route_bound.main()
    assert "margin 0.30 m: no route keeps it" in capsys.readouterr().out
