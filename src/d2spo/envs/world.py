"""The generalist's world: ``world:SEED``, random layouts of every kind a generalist reads.

``generate(seed)`` is a deterministic function of ``seed`` (``numpy.random.default_rng(seed)``).
The seed picks a style; then the arena, obstacles, areas and a start are drawn until the layout
passes ``workspace.validate``, fits a bank slot (``layout_bank.check_fits``) and admits a robot of
``generator.RANDOM_RADIUS`` that reaches every area (``generator.feasible``). The styles:

* ``scatter``: boxes and round pillars (disks) scattered over a rectangular arena;
* ``corridors``: 1 to 4 long thin walls across a rectangular arena, each with one or two openings
  (``generator.OPENING``), and a few boxes and pillars;
* ``gap``: one wall across a rectangular arena with a single opening of ``generator.GAP_WIDTH``
  m, some area of a task label beyond it from the start, and a few obstacles away
  from the opening;
* ``zones``: ZoneEnv's layout (``envs.zones``): a 6.6 m square, 8 zones of 0.4 m, two per label.

The arenas of the first three styles are rectangles with sides in ``SIDE`` (m) and an aspect ratio
of at least ``MIN_ASPECT``. Every layout has the labels ``LABELS`` (the propositions the
generalist's training tasks name), at least one area each, and up to ``MAX_AREAS`` areas in all:
the others either share one of those labels or carry a distractor label of ``DISTRACTORS``, which
no training task names (the robot may cross them). Area names are ``area-1``, ``area-2``, ...:
nothing the generalist reads depends on names or on how many areas there are.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from d2spo.envs import generator, layout_bank, zones
from d2spo.envs.workspace import Area, DiskObstacle, Layout, Obstacle
from d2spo.errors import ConfigError

STYLES = ("scatter", "corridors", "gap", "zones")
"""The kinds of layout, drawn with equal probability."""
SIDE = (5.0, 20.0)
"""Range of the arena's longer side (m), uniform."""
MIN_ASPECT = 0.5
"""The shorter side is at least this fraction of the longer one (and at least ``SIDE[0]`` m)."""
LABELS = ("A1", "A2", "A3", "A4")
"""Labels every world layout carries (the propositions of the generalist's training tasks)."""
DISTRACTORS = ("B1", "B2", "B3", "B4")
"""Labels of areas no training task names."""
MAX_AREAS = 12
"""Most areas in a world layout (a bank slot holds ``layout_bank.N_AREAS``)."""
AREA_DENSITY = 1 / 3.0
"""At most this many areas per square metre of arena."""
SHARED = 0.5
"""Probability that an area beyond the first four shares one of ``LABELS`` (else a distractor's)."""
OBSTACLE_DENSITY = (0.08, 0.16)
"""Scattered obstacles per square metre in the ``scatter`` style (range, uniform per layout)."""
DISK_SHARE = 0.35
"""Fraction of scattered obstacles that are round pillars."""
DISK_RADIUS = (0.15, 0.45)
"""Range of a pillar's radius (m)."""
MAX_TRIES = 200
"""Draws before ``generate`` gives up."""


def style_of(seed: int) -> str:
    """The style ``generate(seed)`` draws (its first draw)."""
    return STYLES[int(np.random.default_rng(seed).integers(len(STYLES)))]


def generate(seed: int) -> Layout:
    """The layout ``world:SEED`` (module docstring)."""
    rng = np.random.default_rng(seed)
    style = STYLES[int(rng.integers(len(STYLES)))]
    if style == "zones":
        return _zones(seed, int(rng.integers(2**31)))
    for _ in range(MAX_TRIES):
        long_side = float(rng.uniform(*SIDE))
        short = max(SIDE[0], long_side * float(rng.uniform(MIN_ASPECT, 1.0)))
        w, h = (long_side, short) if rng.integers(2) else (short, long_side)
        w, h = round(w, 2), round(h, 2)
        obstacles, far_side = _OBSTACLES[style](rng, w, h)
        layout = _with_start_and_areas(rng, Layout(f"world:{seed}", (w, h), (0.0, 0.0, 0.0), obstacles, ()),
                                       far_side)
        if layout is None:
            continue
        try:
            layout_bank.check_fits(layout)
        except ConfigError:
            continue
        if generator.feasible(layout):
            return layout
    raise RuntimeError(f"no feasible world layout found for seed {seed} in {MAX_TRIES} draws")  # pragma: no cover


def _zones(seed: int, zone_seed: int) -> Layout:
    """ZoneEnv's layout ``zones:zone_seed``, its four colours relabelled ``LABELS``."""
    lay = zones.zones_layout(zone_seed)
    relabel = dict(zip(zones.COLOURS, LABELS))
    areas = tuple(replace(a, name=f"area-{k + 1}", label=relabel[a.label]) for k, a in enumerate(lay.areas))
    return replace(lay, name=f"world:{seed}", areas=areas)


# ------------------------------------------------------------------------------------- obstacles


def _scattered(rng: np.random.Generator, w: float, h: float, n: int, half: tuple[float, float],
               keep_clear: tuple[float, float, float] | None = None) -> list:
    """``n`` obstacles, ``DISK_SHARE`` of them pillars, the others boxes with half extents in ``half``;
    ``keep_clear`` = (x, y, d): none comes within d of that point. At most the bank's slots of each."""
    boxes, disks = [], []
    for _ in range(n):
        c = np.array([rng.uniform(0.3, w - 0.3), rng.uniform(0.3, h - 0.3)])
        if rng.uniform() < DISK_SHARE:
            r = float(rng.uniform(*DISK_RADIUS))
            if keep_clear is not None and np.linalg.norm(c - np.asarray(keep_clear[:2])) - r < keep_clear[2]:
                continue
            if len(disks) < layout_bank.D_MAX:
                disks.append(DiskObstacle(generator._rounded(c), round(r, 3)))
            continue
        hh = rng.uniform(*half, 2)
        if keep_clear is not None:
            q = np.abs(c - np.asarray(keep_clear[:2])) - hh
            if np.linalg.norm(np.maximum(q, 0.0)) + min(q.max(), 0.0) < keep_clear[2]:
                continue
        boxes.append(Obstacle(generator._rounded(c), generator._rounded(hh)))
    return boxes + disks


def _scatter(rng: np.random.Generator, w: float, h: float):
    n = int(np.clip(round(rng.uniform(*OBSTACLE_DENSITY) * w * h), 3, layout_bank.M_MAX))
    return tuple(_scattered(rng, w, h, n, generator.BOX_HALF)), None


def _walls(rng: np.random.Generator, w: float, h: float, k: int, widths_of) -> tuple[list, bool, list[float]]:
    """k walls across the arena (all along x or all along y), each with the openings ``widths_of()``
    gives, at random places; returns (boxes, vertical, where the walls are)."""
    vertical = bool(rng.integers(2))
    length, across = (h, w) if vertical else (w, h)
    pitch = across / (k + 1)
    out, where = [], []
    for j in range(k):
        at = pitch * (j + 1) + rng.uniform(-0.2, 0.2) * pitch
        widths = widths_of()
        free = length - sum(widths) - 1.0 - 0.2 * len(widths)
        starts = np.sort(rng.uniform(0.5, 0.5 + max(free, 0.0), len(widths)))
        openings = [s + 0.2 * i + sum(widths[:i]) + widths[i] / 2 for i, s in enumerate(starts)]
        out += generator._wall(length, at, rng.uniform(*generator.WALL_HALF_THICKNESS), openings, widths, vertical)
        where.append((at, openings))
    return out, vertical, where


def _corridors(rng: np.random.Generator, w: float, h: float):
    across = min(w, h) if rng.integers(2) else max(w, h)
    k = int(rng.integers(1, max(1, min(4, int(across / 2.5))) + 1))
    out, _, _ = _walls(rng, w, h, k, lambda: list(rng.uniform(*generator.OPENING, int(rng.integers(1, 3)))))
    n = int(rng.integers(0, max(1, round(0.03 * w * h)) + 1))
    out += _scattered(rng, w, h, min(n, layout_bank.M_MAX - len(out)), (0.1, 0.3))
    return tuple(out), None


def _gap(rng: np.random.Generator, w: float, h: float):
    out, vertical, [(at, [centre])] = _walls(rng, w, h, 1, lambda: [float(rng.uniform(*generator.GAP_WIDTH))])
    hole = (at, centre) if vertical else (centre, at)
    n = int(rng.integers(0, max(1, round(0.04 * w * h)) + 1))
    out += _scattered(rng, w, h, min(n, layout_bank.M_MAX - len(out)), (0.1, 0.4), keep_clear=(*hole, 1.0))
    return tuple(out), (0 if vertical else 1, at)


_OBSTACLES = {"scatter": _scatter, "corridors": _corridors, "gap": _gap}


# ------------------------------------------------------------------------------- start and areas


def _with_start_and_areas(rng: np.random.Generator, layout: Layout, far_side) -> Layout | None:
    """``layout`` with a start and its areas (module docstring), or None when the draws do not fit.
    With ``far_side`` = (axis, at), an area of a label of ``LABELS`` lies beyond ``at`` from the start."""
    w, h = layout.arena
    start = None
    for _ in range(100):
        xy = np.array([rng.uniform(0.5, w - 0.5), rng.uniform(0.5, h - 0.5)])
        if layout.clearance(xy) >= generator.START_CLEARANCE:
            start = (*generator._rounded(xy), round(float(rng.uniform(-math.pi, math.pi)), 3))
            break
    if start is None:
        return None
    n_areas = int(rng.integers(len(LABELS), max(len(LABELS), min(MAX_AREAS, int(w * h * AREA_DENSITY))) + 1))
    labels = list(LABELS) + [str(rng.choice(LABELS)) if rng.uniform() < SHARED else str(rng.choice(DISTRACTORS))
                             for _ in range(n_areas - len(LABELS))]
    areas: list[Area] = []
    for _ in range(60 * n_areas):
        r = round(float(rng.uniform(*generator.AREA_RADIUS)), 3)
        lo = r + generator.AREA_MARGIN
        c = np.array(generator._rounded([rng.uniform(lo, w - lo), rng.uniform(lo, h - lo)]))
        if layout.clearance(c) < lo or np.linalg.norm(c - start[:2]) < r + generator.AREA_SPACING:
            continue
        if any(np.linalg.norm(c - np.asarray(a.center)) < r + a.radius + generator.AREA_SPACING for a in areas):
            continue
        areas.append(Area(f"area-{len(areas) + 1}", tuple(c.tolist()), r, labels[len(areas)]))
        if len(areas) == n_areas:
            break
    if len(areas) < n_areas:
        return None
    if far_side is not None:
        axis, at = far_side
        beyond = {a.label for a in areas if (a.center[axis] > at) != (start[axis] > at)}
        if not beyond & set(LABELS):
            return None
    return replace(layout, start=start, areas=tuple(areas))

