"""The hand-made layouts of tests/data/layouts/handmade (issue 33; docs/layouts.md, "Hand-made layouts").

Layouts drawn by hand, not by any generator of ours: corridors, cluttered rooms, narrow gaps,
L-shaped rooms, a lab and a warehouse, 5 m to 20 m, with disks and shared labels. Each loads,
validates, fits the default robot, and its task (``TASKS``) is feasible, also while keeping the
barrier's 0.3 m margin. No training: compiling the tasks takes a few seconds.
"""

from __future__ import annotations

import functools
import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from d2spo.envs import EnvConfig, layouts, make_env, preflight, routes, workspace
from d2spo.errors import TaskWarning

HANDMADE = Path(__file__).parent / "data" / "layouts" / "handmade"
PHI1 = "(!A3 U A2) & (!A2 U A1) & F A1 & F A3"
TASKS = {
    "corridor-5.json": PHI1,
    "corridor-12.json": PHI1,
    "cluttered-6.json": PHI1,
    "cluttered-10.json": PHI1,
    "narrow-gap-5.json": PHI1,
    "narrow-gap-15.json": PHI1,
    "l-room-8.json": PHI1,
    "l-room-20.json": PHI1,
    "lab-12x6.json": "F (desk & F kitchen)",
    "warehouse-16.json": "F (dock & F A1)",
}
"""Each layout's representative task (also listed in docs/layouts.md)."""
FOUR_AREAS = list(TASKS)[:8]
"""The layouts with areas A1..A4 (phi1 and the other A1..A4 tasks run there)."""
ROBOT_RADIUS = 0.15
BARRIER_MARGIN = 0.3
"""D²SPO's barrier distance d: every route should keep it (``preflight.check_margin``)."""


@functools.lru_cache(maxsize=None)
def load(file: str) -> workspace.Layout:
    return layouts.load(str(HANDMADE / file))


def test_the_set_is_complete():
    files = sorted(p.name for p in HANDMADE.glob("*.json"))
    assert files == sorted(TASKS), "every hand-made layout needs a task in TASKS (and a line in docs/layouts.md)"
    assert len(files) >= 8
    longest = [max(load(f).arena) for f in files]
    assert min(longest) == 5.0 and max(longest) == 20.0  # 5 m to 20 m
    assert sum(bool(load(f).disks) for f in files) >= 5
    shared = [f for f in files if len(load(f).labels) < len(load(f).areas)]
    assert len(shared) >= 3


@pytest.mark.parametrize("file", list(TASKS))
def test_loads_validates_and_fits(file):
    raw = json.loads((HANDMADE / file).read_text())
    assert raw["name"] == file.removesuffix(".json")
    assert isinstance(raw["description"], str) and raw["description"] and "\n" not in raw["description"]
    lay = load(file)
    workspace.validate(lay)
    workspace.check_robot_fits(lay, ROBOT_RADIUS)
    assert len(lay.obstacles) >= 2 and lay.areas
    for a in lay.areas:
        assert 0.3 <= a.radius <= 0.5, a.name
    assert lay.clearance(np.array(lay.start[:2])) >= 0.4  # the start is clear of obstacles and walls


@pytest.mark.parametrize("file", FOUR_AREAS)
def test_first_eight_have_a1_to_a4(file):
    assert {"A1", "A2", "A3", "A4"} <= set(load(file).area_names)


@pytest.mark.parametrize("file, task", list(TASKS.items()) + [(f, "F A4 & F A1") for f in FOUR_AREAS])
def test_task_is_feasible_with_the_barrier_margin(file, task):
    env, params = make_env(EnvConfig(layout=str(HANDMADE / file)), task)  # raises ConfigError if infeasible
    assert np.isfinite(env.task.route_length)
    with warnings.catch_warnings():
        warnings.simplefilter("error", TaskWarning)
        preflight.check_margin(env.task, BARRIER_MARGIN, task)  # a route keeps 0.3 m from obstacles and walls
        preflight.check_time(env.task, int(params.max_steps), env.config.dt, env.config.v_max * env.config.v_gain, task)


def test_a_patrol_whose_every_cycle_passes_closer_than_the_margin_is_warned_of():
    """``patrol2`` (GF A1 & GF A3 & G !A4) on corridor-5: the robot (0.15 m) gets from A1 to A3 only
    between A4 and a box, where no route keeps the barrier's 0.3 m from the box; D²SPO trained 3334
    episodes without an accepting visit (2026-12-01). The margin check warns of a recurrence as of a
    co-safe task; before, ``routes.visit_lengths`` with no length limit returned [inf] for "no visit", not
    the empty list, and preflight took that for a route."""
    from d2spo.ltl import task_formula

    formula = task_formula("patrol2")
    env, _ = make_env(EnvConfig(layout=str(HANDMADE / "corridor-5.json")), formula)
    task = env.task
    assert task.recurrence and np.isfinite(task.route_length)  # the robot itself gets round
    assert routes.visit_lengths(task.automaton, task.layout, task.label_mode, BARRIER_MARGIN, np.inf, 3) == []
    with pytest.warns(TaskWarning, match="while keeping 0.3 m from every obstacle and wall"):
        preflight.check_margin(task, BARRIER_MARGIN, "patrol2")
    paper, _ = make_env(EnvConfig(layout="paper"), formula)  # where a cycle keeps the margin: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", TaskWarning)
        preflight.check_margin(paper.task, BARRIER_MARGIN, "patrol2")
