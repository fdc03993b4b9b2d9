"""Workspaces: a rectangular arena, axis-aligned box obstacles, circular areas of interest, a start.

``load(name_or_path)`` returns a validated :class:`Layout`: a built-in name (``paper``,
``relaxed``, ``open``, ``physical-1`` .. ``physical-4``), ``random`` / ``random:SEED`` for a
procedural layout (``envs.generator``; ``random5:SEED`` for the earlier 5 m one), or the path of a JSON file (schema in docs/layouts.md). Every mistake raises
``ConfigError`` naming the offending field (``layout``, ``layout.areas[2].radius``, ...).

Layouts are plain Python (numpy at most); the environment turns them into arrays once.
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np
from scipy import ndimage

from d2spo.errors import ConfigError

BUILTIN = ("paper", "relaxed", "open", "physical-1", "physical-2", "physical-3", "physical-4")
"""Names of the layouts shipped as JSON files in ``d2spo/envs/layouts/``."""

RANDOM_KINDS = ("random", "random5")
"""Procedural layouts by seed: ``random:SEED`` (``envs.generator.generate``: 5-10 m arenas of three
styles) and ``random5:SEED`` (``random_layout``: the 5 m generator of earlier sessions)."""

RANDOM_RADIUS = 0.25
"""Robot radius (m, unscaled) for which every random layout is checked to be feasible. It covers
the default robot (0.15 m) and the TurtleBot (0.105 m on a layout scaled by 0.5, i.e. 0.21 m)."""


@dataclass(frozen=True)
class Obstacle:
    """An axis-aligned box."""

    center: tuple[float, float]
    """Centre (x, y) in metres."""
    half_extents: tuple[float, float]
    """Half width and half height in metres."""

    @property
    def lo(self) -> np.ndarray:
        return np.asarray(self.center) - np.asarray(self.half_extents)

    @property
    def hi(self) -> np.ndarray:
        return np.asarray(self.center) + np.asarray(self.half_extents)


@dataclass(frozen=True)
class Area:
    """A circular area of interest; an atomic proposition of the same name holds inside it."""

    name: str
    """Name, e.g. ``A1``; the LTL proposition ``A1`` is true when the robot centre is inside."""
    center: tuple[float, float]
    """Centre (x, y) in metres."""
    radius: float
    """Radius in metres (the true radius; the relaxed labelling radius is a parameter of the env)."""


@dataclass(frozen=True)
class Layout:
    """A workspace. The arena is [0, width] x [0, height]."""

    name: str
    """Name (built-in name, ``random:SEED``, ``random5:SEED`` or the JSON file's ``name``)."""
    arena: tuple[float, float]
    """(width, height) in metres; the lower-left corner is the origin."""
    start: tuple[float, float, float]
    """Start pose (x, y, theta) before jitter; theta in radians."""
    obstacles: tuple[Obstacle, ...]
    """Box obstacles."""
    areas: tuple[Area, ...]
    """Areas of interest (A1 .. An)."""

    @property
    def area_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.areas)

    def scaled(self, s: float) -> Layout:
        """The same layout with every length multiplied by ``s`` (angles unchanged)."""
        if s == 1.0:
            return self
        return replace(
            self,
            arena=(self.arena[0] * s, self.arena[1] * s),
            start=(self.start[0] * s, self.start[1] * s, self.start[2]),
            obstacles=tuple(
                Obstacle((o.center[0] * s, o.center[1] * s), (o.half_extents[0] * s, o.half_extents[1] * s))
                for o in self.obstacles
            ),
            areas=tuple(Area(a.name, (a.center[0] * s, a.center[1] * s), a.radius * s) for a in self.areas),
        )

    def to_json(self) -> dict:
        """The layout as a JSON-ready dict (the schema read by :func:`from_json`)."""
        return {
            "name": self.name,
            "arena": list(self.arena),
            "start": list(self.start),
            "obstacles": [{"center": list(o.center), "half_extents": list(o.half_extents)} for o in self.obstacles],
            "areas": [{"name": a.name, "center": list(a.center), "radius": a.radius} for a in self.areas],
        }

    # --- numpy geometry, used for validation and planning (the jitted versions are in geometry.py)

    def clearance(self, xy: np.ndarray) -> np.ndarray:
        """Signed distance [...] from points xy [..., 2] to the nearest obstacle or wall."""
        xy = np.asarray(xy, dtype=np.float64)
        d = np.minimum.reduce([xy[..., 0], xy[..., 1], self.arena[0] - xy[..., 0], self.arena[1] - xy[..., 1]])
        for o in self.obstacles:
            d = np.minimum(d, _box_sd(xy, o))
        return d


def _box_sd(xy: np.ndarray, o: Obstacle) -> np.ndarray:
    q = np.abs(xy - np.asarray(o.center)) - np.asarray(o.half_extents)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


# ----------------------------------------------------------------------------------- JSON parsing


def _number(value, field: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(field, f"expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise ConfigError(field, f"must be positive, got {value!r}")
    return float(value)


def _vector(value, n: int, field: str, positive: bool = False) -> tuple[float, ...]:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigError(field, f"expected a list of {n} numbers, got {value!r}")
    return tuple(_number(v, f"{field}[{i}]", positive) for i, v in enumerate(value))


def _get(obj: dict, key: str, field: str):
    if not isinstance(obj, dict):
        raise ConfigError(field, f"expected an object, got {obj!r}")
    if key not in obj:
        raise ConfigError(f"{field}.{key}", "missing")
    return obj[key]


def from_json(data: dict, default_name: str = "custom") -> Layout:
    """A validated layout from a dict with keys arena, start, obstacles, areas (and optional name)."""
    f = "layout"
    if not isinstance(data, dict):
        raise ConfigError(f, f"expected a JSON object, got {type(data).__name__}")
    unknown = set(data) - {"name", "description", "arena", "start", "obstacles", "areas"}
    if unknown:
        raise ConfigError(f, f"unknown keys {sorted(unknown)}")
    name = data.get("name", default_name)
    if not isinstance(name, str):
        raise ConfigError(f"{f}.name", f"expected a string, got {name!r}")
    arena = _vector(_get(data, "arena", f), 2, f"{f}.arena", positive=True)
    start = _vector(_get(data, "start", f), 3, f"{f}.start")
    obstacles_raw = _get(data, "obstacles", f)
    if not isinstance(obstacles_raw, list):
        raise ConfigError(f"{f}.obstacles", "expected a list")
    obstacles = tuple(
        Obstacle(
            _vector(_get(o, "center", g), 2, f"{g}.center"),
            _vector(_get(o, "half_extents", g), 2, f"{g}.half_extents", positive=True),
        )
        for i, o in enumerate(obstacles_raw)
        for g in [f"{f}.obstacles[{i}]"]
    )
    areas_raw = _get(data, "areas", f)
    if not isinstance(areas_raw, list):
        raise ConfigError(f"{f}.areas", "expected a list")
    areas = []
    for i, a in enumerate(areas_raw):
        g = f"{f}.areas[{i}]"
        area_name = _get(a, "name", g)
        if not isinstance(area_name, str) or not area_name.strip():
            raise ConfigError(f"{g}.name", f"expected a non-empty string, got {area_name!r}")
        areas.append(
            Area(area_name, _vector(_get(a, "center", g), 2, f"{g}.center"),
                 _number(_get(a, "radius", g), f"{g}.radius", positive=True))
        )
    layout = Layout(name, arena, start, obstacles, tuple(areas))
    validate(layout)
    return layout


def validate(layout: Layout) -> None:
    """Geometric checks that do not depend on the robot. Raises ConfigError naming the field.

    The start must lie inside the arena and outside every obstacle; every area disk must lie inside
    the arena and must not overlap an obstacle; area names must be unique. The checks that need the
    robot's size (start clearance, reachability) are in :func:`check_robot_fits`.
    """
    w, h = layout.arena
    if not (w > 0 and h > 0):
        raise ConfigError("layout.arena", f"sizes must be positive, got {layout.arena}")
    for i, o in enumerate(layout.obstacles):
        if min(o.half_extents) <= 0:
            raise ConfigError(f"layout.obstacles[{i}].half_extents", f"must be positive, got {o.half_extents}")
        if not (0 <= o.center[0] <= w and 0 <= o.center[1] <= h):
            raise ConfigError(f"layout.obstacles[{i}].center", f"{o.center} is outside the arena {layout.arena}")
    sx, sy, _ = layout.start
    if not (0 < sx < w and 0 < sy < h):
        raise ConfigError("layout.start", f"{layout.start[:2]} is outside the arena {layout.arena}")
    for i, o in enumerate(layout.obstacles):
        if _box_sd(np.array([sx, sy]), o) <= 0:
            raise ConfigError("layout.start", f"{layout.start[:2]} is inside obstacle {i}")
    seen: set[str] = set()
    for i, a in enumerate(layout.areas):
        if a.radius <= 0:
            raise ConfigError(f"layout.areas[{i}].radius", f"must be positive, got {a.radius}")
        if a.name in seen:
            raise ConfigError(f"layout.areas[{i}].name", f"duplicate area name {a.name!r}")
        seen.add(a.name)
        cx, cy = a.center
        if min(cx, cy, w - cx, h - cy) < a.radius:
            raise ConfigError(f"layout.areas[{i}]", f"area {a.name} (centre {a.center}, radius {a.radius}) "
                              f"is not inside the workspace {layout.arena}")
        for j, o in enumerate(layout.obstacles):
            if _box_sd(np.array(a.center), o) <= a.radius:
                raise ConfigError(f"layout.areas[{i}]", f"area {a.name} overlaps obstacle {j}")


# ------------------------------------------------------------------------- robot-dependent checks


def free_grid(layout: Layout, robot_radius: float, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Cells whose centre the robot can occupy: (free bool [ny, nx], centres [ny, nx, 2]).

    A cell is free when its centre has clearance > robot_radius + resolution / 2. Every point of
    the segment joining two 4-neighbours lies within resolution / 2 of one of them, so moving
    between neighbouring free cells is collision-free (a conservative discretisation).
    """
    w, h = layout.arena
    xs = (np.arange(math.ceil(w / resolution)) + 0.5) * resolution
    ys = (np.arange(math.ceil(h / resolution)) + 0.5) * resolution
    centres = np.stack(np.meshgrid(xs, ys), axis=-1)
    return layout.clearance(centres) > robot_radius + 0.5 * resolution, centres


def reachable_grid(layout: Layout, robot_radius: float, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Free cells 4-connected to the start cell: (reachable bool [ny, nx], centres [ny, nx, 2])."""
    free, centres = free_grid(layout, robot_radius, resolution)
    labels, _ = ndimage.label(free)
    iy = min(int(layout.start[1] / resolution), free.shape[0] - 1)
    ix = min(int(layout.start[0] / resolution), free.shape[1] - 1)
    start_label = labels[iy, ix]
    if start_label == 0:
        return np.zeros_like(free), centres
    return labels == start_label, centres


def check_robot_fits(layout: Layout, robot_radius: float, start_jitter_xy: float = 0.0) -> None:
    """The robot fits at the start (with jitter) and can reach every area; ConfigError otherwise.

    Reachability is a breadth-first search on a grid (resolution ~1/100 of the arena, at most
    0.05 m, but at most 1000 cells a side) over the free space inflated by the robot radius.
    """
    worst = robot_radius + start_jitter_xy * math.sqrt(2.0)
    if layout.clearance(np.array(layout.start[:2])) <= worst:
        raise ConfigError("layout.start", f"the robot (radius {robot_radius}, start jitter {start_jitter_xy}) "
                          f"at {layout.start[:2]} would touch an obstacle or wall")
    resolution = max(min(0.05, max(layout.arena) / 100.0), max(layout.arena) / 1000.0)  # <= 1000 cells a side
    reach, centres = reachable_grid(layout, robot_radius, resolution)
    for i, a in enumerate(layout.areas):
        inside = np.linalg.norm(centres - np.asarray(a.center), axis=-1) <= a.radius
        if not np.any(reach & inside):
            raise ConfigError(f"layout.areas[{i}]", f"area {a.name} cannot be reached from the start by a robot "
                              f"of radius {robot_radius}")


# ----------------------------------------------------------------------------------- letters


def feasible_letters(layout: Layout, aps: tuple[str, ...], label_mode: str) -> list[int]:
    """Letters (bitmasks over ``aps``) that labelling can actually produce in this layout.

    A letter is the set of propositions true at one position: the areas that contain the robot
    centre together. A set of areas can hold together iff their disks have a common point; for
    disks, the intersection (if non-empty) contains either one of the centres or an intersection
    point of two circles, so those candidate points are checked. Propositions with no area of the
    same name are always false. The empty letter is included under ``step`` labelling only
    (``event`` labelling never reads it).
    """
    bit = {name: 1 << i for i, name in enumerate(aps)}
    centres = np.array([a.center for a in layout.areas], dtype=np.float64).reshape(-1, 2)
    radii = np.array([a.radius for a in layout.areas], dtype=np.float64)
    candidates = [c for c in centres]
    for i, j in itertools.combinations(range(len(radii)), 2):
        candidates.extend(_circle_intersections(centres[i], radii[i], centres[j], radii[j]))
    letters = {0}
    for p in candidates:
        inside = np.linalg.norm(centres - p, axis=-1) <= radii * (1 + 1e-9) + 1e-12
        letters.add(sum(bit.get(a.name, 0) for a, ok in zip(layout.areas, inside) if ok))
    if label_mode == "event":
        letters.discard(0)
    return sorted(letters)


def _circle_intersections(c1, r1, c2, r2) -> list[np.ndarray]:
    d = float(np.linalg.norm(c2 - c1))
    if d == 0 or d > r1 + r2 or d < abs(r1 - r2):
        return []
    a = (r1 * r1 - r2 * r2 + d * d) / (2 * d)
    hh = math.sqrt(max(r1 * r1 - a * a, 0.0))
    u = (c2 - c1) / d
    mid = c1 + a * u
    perp = np.array([-u[1], u[0]])
    return [mid + hh * perp, mid - hh * perp]


# ----------------------------------------------------------------------------------- loading


def load(name_or_path: str) -> Layout:
    """A validated layout by built-in name, ``random[:SEED]`` (``envs.generator``), ``random5[:SEED]``
    (``random_layout``), or JSON file path."""
    if not isinstance(name_or_path, str) or not name_or_path:
        raise ConfigError("layout", f"expected a layout name or a JSON path, got {name_or_path!r}")
    if name_or_path in BUILTIN:
        text = resources.files("d2spo.envs").joinpath("layouts", f"{name_or_path}.json").read_text()
        return from_json(json.loads(text), default_name=name_or_path)
    kind, _, seed_text = name_or_path.partition(":")
    if kind in RANDOM_KINDS and (seed_text or name_or_path == kind):
        seed_text = seed_text or "0"
        try:
            seed = int(seed_text)
        except ValueError:
            raise ConfigError("layout", f"random layout seed must be an integer, got {seed_text!r}") from None
        if seed < 0:
            raise ConfigError("layout", f"random layout seed must be non-negative, got {seed}")
        if kind == "random5":
            return random_layout(seed)
        from d2spo.envs import generator  # it builds on this module

        return generator.generate(seed)
    path = Path(name_or_path)
    if path.suffix == ".json" or path.exists():
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as e:
            raise ConfigError("layout", f"cannot read {path}: {e.strerror}") from None
        except UnicodeDecodeError as e:
            raise ConfigError("layout", f"{path}: not UTF-8 text (byte {e.start})") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            where = f"line {e.lineno}, column {e.colno}"
            raise ConfigError("layout", f"{path}: malformed JSON: {e.msg} ({where})") from None
        return from_json(data, default_name=path.stem)
    raise ConfigError("layout", f"unknown layout {name_or_path!r}; use one of {list(BUILTIN)}, "
                      "'random[:SEED]', 'random5[:SEED]' or a path to a .json file")


def random_layout(seed: int, n_obstacles: int = 6, n_areas: int = 4) -> Layout:
    """A procedural 5 m x 5 m layout, a deterministic function of ``seed``: ``random5:SEED`` (it was
    ``random:SEED`` until 2026-11-23, when ``envs.generator`` took that name).

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


def _rounded(values: np.ndarray) -> tuple[float, ...]:
    return tuple(round(float(v), 3) for v in values)
