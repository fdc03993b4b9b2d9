"""Random layouts: ``random:SEED``, of varied size and kind (docs/layouts.md, "random"), and ``random5:SEED``.

``generate(seed)`` is a deterministic function of ``seed`` (``numpy.random.default_rng(seed)``).
The seed picks a style and a square arena of side uniform in ``SIDE``; then obstacles, four
areas ``A1 .. A4`` and a start are drawn until the layout passes ``workspace.validate`` and
``workspace.check_robot_fits(layout, RANDOM_RADIUS)`` (at most ``MAX_TRIES`` draws, all from
the same generator, so the result depends on the seed only). The styles:

* ``boxes``: scattered boxes of varied sizes and aspect ratios, their count growing with the area
  (about 4 in a 5 m arena, 17 in a 10 m one);
* ``corridors``: 2 to 4 long thin walls across the arena (all horizontal or all vertical), each
  with one or two openings of ``OPENING`` m, and a few small boxes;
* ``gap``: one wall across the arena with a single opening of ``GAP_WIDTH`` m, at least one area
  beyond it from the start, and a few small boxes away from the opening.

Every layout has at most ``MAX_BOXES`` obstacles, so a bank of layouts pads to one shape
(``envs.layout_bank``). ``random_layout(seed)`` draws the 5 m layouts ``random5:SEED``. A layout
is accepted when ``feasible``: valid, and a robot of ``RANDOM_RADIUS`` fits and reaches every area.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from d2spo.envs.workspace import Area, Layout, Obstacle, check_robot_fits, validate
from d2spo.errors import ConfigError

RANDOM_RADIUS = 0.25
"""Robot radius (m, unscaled) for which every random layout is checked to be feasible. It covers
the default robot (0.15 m) and the TurtleBot (0.105 m on a layout scaled by 0.5, i.e. 0.21 m)."""
STYLES = ("boxes", "corridors", "gap")
"""The kinds of layout, drawn with equal probability."""
SIDE = (5.0, 10.0)
"""Range of the arena's side (m), uniform; the arena is square."""
N_AREAS = 4
"""Areas per layout, named ``A1 .. A4``."""
AREA_RADIUS = (0.35, 0.5)
"""Range of an area's radius (m), uniform per area."""
AREA_MARGIN = 0.3
"""Least distance (m) from an area's disk to an obstacle or wall."""
AREA_SPACING = 0.5
"""Least distance (m) between two areas' disks, and from an area's disk to the start."""
START_CLEARANCE = 0.4
"""Least distance (m) from the start to an obstacle or wall."""
BOX_HALF = (0.1, 0.6)
"""Range of a scattered box's half extent (m), uniform per axis."""
BOX_DENSITY = (0.12, 0.22)
"""Scattered boxes per square metre in the ``boxes`` style (range, uniform per layout)."""
WALL_HALF_THICKNESS = (0.05, 0.1)
"""Range of a wall's half thickness (m)."""
OPENING = (0.8, 1.4)
"""Range of the width (m) of a corridor wall's openings."""
GAP_WIDTH = (0.6, 0.8)
"""Range of the width (m) of the ``gap`` style's single opening. Not narrower than 0.6 m: every
layout must admit a robot of ``RANDOM_RADIUS`` = 0.25 m (on the reachability grid that needs
more than 0.55 m), and D²SPO's learned barrier has no safe point in a gap narrower than twice its
0.3 m safety distance (docs/layouts.md, ``paper``)."""
MAX_BOXES = 24
"""Most obstacles in one layout."""
MAX_TRIES = 200
"""Draws of obstacles, areas and start before ``generate`` gives up (none has needed half of them)."""


def style_of(seed: int) -> str:
    """The style ``generate(seed)`` draws (its first draw)."""
    return STYLES[int(np.random.default_rng(seed).integers(len(STYLES)))]


def generate(seed: int) -> Layout:
    """The random layout ``random:SEED``: a deterministic function of ``seed`` (module docstring)."""
    rng = np.random.default_rng(seed)
    style = STYLES[int(rng.integers(len(STYLES)))]
    side = round(float(rng.uniform(*SIDE)), 2)
    for _ in range(MAX_TRIES):
        obstacles, far_side = _OBSTACLES[style](rng, side)
        layout = _with_start_and_areas(rng, Layout(f"random:{seed}", (side, side), (0.0, 0.0, 0.0), obstacles, ()),
                                       far_side)
        if layout is not None and feasible(layout):
            return layout
    raise RuntimeError(f"no feasible random layout found for seed {seed} in {MAX_TRIES} draws")  # pragma: no cover


def random_layout(seed: int, n_obstacles: int = 6, n_areas: int = 4) -> Layout:
    """A procedural 5 m x 5 m layout, a deterministic function of ``seed``: ``random5:SEED``.

    Obstacles are rectangles with half-extents in [0.2, 0.5] m, areas have radius 0.35 m and are
    named A1 .. An. Candidates are drawn until one is feasible: the start has 0.4 m clearance, the
    areas keep 0.3 m from obstacles and walls and 1 m from each other and from the start, and every
    area is reachable by a robot of radius ``RANDOM_RADIUS``.
    """
    rng = np.random.default_rng(seed)
    size, radius = 5.0, 0.35
    for _ in range(10_000):
        obstacles = tuple(
            Obstacle(_rounded(rng.uniform(0.6, size - 0.6, 2)), _rounded(rng.uniform(0.2, 0.5, 2)))
            for _ in range(n_obstacles)
        )
        start = (*_rounded(rng.uniform(0.5, size - 0.5, 2)), *_rounded(rng.uniform(-math.pi, math.pi, 1)))
        layout = Layout(f"random5:{seed}", (size, size), start, obstacles, ())
        if layout.clearance(np.array(start[:2])) < 0.4:
            continue
        areas: list[Area] = []
        for _ in range(200):
            c = np.array(_rounded(rng.uniform(radius + 0.3, size - radius - 0.3, 2)))
            if layout.clearance(c) < radius + 0.3 or np.linalg.norm(c - np.asarray(start[:2])) < 1.0:
                continue
            if any(np.linalg.norm(c - np.asarray(a.center)) < 2 * radius + 1.0 for a in areas):
                continue
            areas.append(Area(f"A{len(areas) + 1}", _rounded(c), radius))
            if len(areas) == n_areas:
                break
        if len(areas) < n_areas:
            continue
        layout = replace(layout, areas=tuple(areas))
        if feasible(layout):
            return layout
    raise RuntimeError(f"no feasible random layout found for seed {seed}")  # pragma: no cover


def feasible(layout: Layout, robot_radius: float = RANDOM_RADIUS) -> bool:
    """Whether ``validate`` and ``check_robot_fits`` pass (the random generators' acceptance test)."""
    try:
        validate(layout)
        check_robot_fits(layout, robot_radius)
    except ConfigError:
        return False
    return True


# ------------------------------------------------------------------------------------- obstacles


def _box(lo: tuple[float, float], hi: tuple[float, float]) -> Obstacle:
    return Obstacle(_rounded(((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2)), _rounded(((hi[0] - lo[0]) / 2,
                                                                                      (hi[1] - lo[1]) / 2)))


def _scattered(rng: np.random.Generator, side: float, n: int, half: tuple[float, float],
               keep_clear: tuple[float, float, float] | None = None) -> list[Obstacle]:
    """``n`` boxes with half extents uniform in ``half`` (per axis), centres anywhere in the arena;
    ``keep_clear`` = (x, y, d): no box comes within d of that point."""
    out = []
    for _ in range(n):
        c = rng.uniform(0.3, side - 0.3, 2)
        h = rng.uniform(*half, 2)
        if keep_clear is not None:
            q = np.abs(c - np.asarray(keep_clear[:2])) - h
            if np.linalg.norm(np.maximum(q, 0.0)) + min(q.max(), 0.0) < keep_clear[2]:
                continue
        out.append(Obstacle(_rounded(c), _rounded(h)))
    return out


def _boxes(rng: np.random.Generator, side: float):
    n = int(np.clip(round(rng.uniform(*BOX_DENSITY) * side * side), 3, MAX_BOXES))
    return tuple(_scattered(rng, side, n, BOX_HALF)), None


def _wall(side: float, at: float, half_t: float, openings: list[float],
          widths: list[float], vertical: bool) -> list[Obstacle]:
    """The boxes of a wall across the arena at ``at`` with openings centred at ``openings``."""
    cuts = sorted((c - w / 2, c + w / 2) for c, w in zip(openings, widths))
    edges = [0.0] + [x for cut in cuts for x in cut] + [side]
    out = []
    for a, b in zip(edges[::2], edges[1::2]):
        if b - a < 0.2:  # no stub: the opening takes it
            continue
        lo, hi = (a, at - half_t), (b, at + half_t)
        if vertical:
            lo, hi = (lo[1], lo[0]), (hi[1], hi[0])
        out.append(_box(lo, hi))
    return out


def _corridors(rng: np.random.Generator, side: float):
    vertical = bool(rng.integers(2))
    k = int(rng.integers(2, max(2, int(side / 2.2)) + 1))
    pitch = side / (k + 1)
    out: list[Obstacle] = []
    for j in range(k):
        at = pitch * (j + 1) + rng.uniform(-0.2, 0.2) * pitch
        widths = list(rng.uniform(*OPENING, int(rng.integers(1, 3))))
        # openings side by side along the wall, in random order, not overlapping
        free = side - sum(widths) - 0.2 * len(widths)
        starts = np.sort(rng.uniform(0.0, free, len(widths)))
        openings = [s + 0.2 * i + sum(widths[:i]) + widths[i] / 2 for i, s in enumerate(starts)]
        out += _wall(side, at, rng.uniform(*WALL_HALF_THICKNESS), openings, widths, vertical)
    n = int(rng.integers(0, max(1, round(0.04 * side * side)) + 1))
    out += _scattered(rng, side, min(n, MAX_BOXES - len(out)), (0.1, 0.3))
    return tuple(out), None


def _gap(rng: np.random.Generator, side: float):
    vertical = bool(rng.integers(2))
    at = rng.uniform(0.35, 0.65) * side
    width = rng.uniform(*GAP_WIDTH)
    centre = rng.uniform(width / 2 + 0.5, side - width / 2 - 0.5)
    out = _wall(side, at, rng.uniform(0.05, 0.15), [centre], [width], vertical)
    hole = (at, centre) if vertical else (centre, at)
    n = int(rng.integers(0, max(1, round(0.05 * side * side)) + 1))
    out += _scattered(rng, side, n, (0.1, 0.4), keep_clear=(*hole, 1.0))
    axis = 0 if vertical else 1
    return tuple(out), (axis, at)


_OBSTACLES = {"boxes": _boxes, "corridors": _corridors, "gap": _gap}


# ------------------------------------------------------------------------------- start and areas


def _with_start_and_areas(rng: np.random.Generator, layout: Layout, far_side) -> Layout | None:
    """``layout`` with a start and ``N_AREAS`` areas, or None when the draws do not fit. With
    ``far_side`` = (axis, at), at least one area lies on the other side of ``at`` from the start."""
    side = layout.arena[0]
    start = None
    for _ in range(100):
        xy = rng.uniform(0.5, side - 0.5, 2)
        if layout.clearance(xy) >= START_CLEARANCE:
            start = (*_rounded(xy), round(float(rng.uniform(-math.pi, math.pi)), 3))
            break
    if start is None:
        return None
    areas: list[Area] = []
    for _ in range(300):
        r = round(float(rng.uniform(*AREA_RADIUS)), 3)
        c = np.array(_rounded(rng.uniform(r + AREA_MARGIN, side - r - AREA_MARGIN, 2)))
        if layout.clearance(c) < r + AREA_MARGIN or np.linalg.norm(c - start[:2]) < r + AREA_SPACING:
            continue
        if any(np.linalg.norm(c - np.asarray(a.center)) < r + a.radius + AREA_SPACING for a in areas):
            continue
        areas.append(Area(f"A{len(areas) + 1}", tuple(c.tolist()), r))
        if len(areas) == N_AREAS:
            break
    if len(areas) < N_AREAS:
        return None
    if far_side is not None:
        axis, at = far_side
        if not any((a.center[axis] > at) != (start[axis] > at) for a in areas):
            return None
    return replace(layout, start=start, areas=tuple(areas))


def _rounded(values) -> tuple[float, ...]:
    return tuple(round(float(v), 3) for v in values)
