"""A workspace: a rectangular arena, box and disk obstacles, labelled circular areas of interest, a start.

``Layout`` is the value; ``validate`` checks its geometry and ``check_robot_fits`` that a robot of
a given radius fits at the start and reaches every area (on ``free_grid``, a conservative grid of
the positions it can occupy). Layouts are plain Python (numpy at most); the environment turns them
into arrays once. Where layouts come from (built-in names, ``random:SEED``, JSON files):
``envs.layouts``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from d2spo.errors import ConfigError, UserError
from d2spo.ltl.formula import Prop
from d2spo.ltl.parser import parse


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
class DiskObstacle:
    """A disk (a round pillar)."""

    center: tuple[float, float]
    """Centre (x, y) in metres."""
    radius: float
    """Radius in metres."""


@dataclass(frozen=True)
class Area:
    """A circular area of interest; the atomic proposition ``label`` holds while the robot is inside it."""

    name: str
    """Name, e.g. ``A1`` or ``desk-1``: unique in a layout, for display."""
    center: tuple[float, float]
    """Centre (x, y) in metres."""
    radius: float
    """Radius in metres (the true radius; the relaxed labelling radius is a parameter of the env)."""
    label: str | None = None
    """The LTL proposition the area makes true, e.g. ``desk``; several areas may share it (it holds
    in any of them). None: the area's name (after construction ``label`` is always a string)."""

    def __post_init__(self) -> None:
        if self.label is None:
            object.__setattr__(self, "label", self.name)


@dataclass(frozen=True)
class Layout:
    """A workspace. The arena is [0, width] x [0, height]."""

    name: str
    """Name (built-in name, ``random:SEED``, ``random5:SEED`` or the JSON file's ``name``)."""
    arena: tuple[float, float]
    """(width, height) in metres; the lower-left corner is the origin."""
    start: tuple[float, float, float]
    """Start pose (x, y, theta) before jitter; theta in radians."""
    obstacles: tuple[Obstacle | DiskObstacle, ...]
    """Obstacles, boxes and disks in any order (the order of the JSON file)."""
    areas: tuple[Area, ...]
    """Areas of interest (A1 .. An)."""

    @property
    def area_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.areas)

    @property
    def labels(self) -> tuple[str, ...]:
        """The areas' labels (the propositions the layout can make true), each once, in order of first use."""
        return tuple(dict.fromkeys(a.label for a in self.areas))

    def describe_areas(self) -> str:
        """The areas by name, each followed by its label where that differs: ``desk-1 (desk), kitchen``;
        ``none (no task can name an area here)`` for a layout without any."""
        if not self.areas:
            return "none (no task can name an area here)"
        return ", ".join(a.name if a.label == a.name else f"{a.name} ({a.label})" for a in self.areas)

    @property
    def boxes(self) -> tuple[Obstacle, ...]:
        """The box obstacles, in order."""
        return tuple(o for o in self.obstacles if isinstance(o, Obstacle))

    @property
    def disks(self) -> tuple[DiskObstacle, ...]:
        """The disk obstacles, in order (the arrays hold the boxes first, then the disks)."""
        return tuple(o for o in self.obstacles if isinstance(o, DiskObstacle))

    def scaled(self, s: float) -> Layout:
        """The same layout with every length multiplied by ``s`` (angles unchanged)."""
        if s == 1.0:
            return self
        return replace(
            self,
            arena=(self.arena[0] * s, self.arena[1] * s),
            start=(self.start[0] * s, self.start[1] * s, self.start[2]),
            obstacles=tuple(
                DiskObstacle((o.center[0] * s, o.center[1] * s), o.radius * s) if isinstance(o, DiskObstacle) else
                Obstacle((o.center[0] * s, o.center[1] * s), (o.half_extents[0] * s, o.half_extents[1] * s))
                for o in self.obstacles
            ),
            areas=tuple(replace(a, center=(a.center[0] * s, a.center[1] * s), radius=a.radius * s) for a in self.areas),
        )

    def to_json(self) -> dict:
        """The layout as a JSON-ready dict (the schema read by :func:`from_json`)."""
        return {
            "name": self.name,
            "arena": list(self.arena),
            "start": list(self.start),
            "obstacles": [{"center": list(o.center), "radius": o.radius} if isinstance(o, DiskObstacle) else
                          {"center": list(o.center), "half_extents": list(o.half_extents)} for o in self.obstacles],
            "areas": [{"name": a.name, "center": list(a.center), "radius": a.radius}
                      | ({} if a.label == a.name else {"label": a.label}) for a in self.areas],
        }

    # --- numpy geometry, used for validation and planning (the jitted versions are in geometry.py)

    def clearance(self, xy: np.ndarray) -> np.ndarray:
        """Signed distance [...] from points xy [..., 2] to the nearest obstacle or wall."""
        xy = np.asarray(xy, dtype=np.float64)
        d = np.minimum.reduce([xy[..., 0], xy[..., 1], self.arena[0] - xy[..., 0], self.arena[1] - xy[..., 1]])
        for o in self.obstacles:
            d = np.minimum(d, _signed_distance(xy, o))
        return d


def _signed_distance(xy: np.ndarray, o: Obstacle | DiskObstacle) -> np.ndarray:
    """Signed distance [...] from points xy [..., 2] to one obstacle (negative inside)."""
    if isinstance(o, DiskObstacle):
        return np.linalg.norm(xy - np.asarray(o.center), axis=-1) - o.radius
    q = np.abs(xy - np.asarray(o.center)) - np.asarray(o.half_extents)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


PROPOSITION_RULE = ("a letter or _, then letters, digits or _; not one of true false X F G U R W, nor a word of "
                    "X, F and G only, which reads as those operators: GF is G F")
"""What ``is_proposition`` accepts, in words (for error messages)."""


def is_proposition(label: str) -> bool:
    """Whether ``label`` is a proposition name of the LTL parser (``ltl.parser``: an identifier, no keyword)."""
    try:
        return isinstance(label, str) and parse(label) == Prop(label)
    except UserError:
        return False


MAX_ARENA = 1000.0
"""The largest arena side, in metres: the env holds positions in float32, whose spacing at 1 km is
about 0.1 mm; at 10 km it reaches 1 mm, a tenth of a step, and larger arenas overflow the searches."""


def validate(layout: Layout) -> None:
    """Geometric checks that do not depend on the robot. Raises ConfigError naming the field.

    Every obstacle centre must lie inside the arena, the start inside the arena and outside every
    obstacle; every area disk must lie inside the arena and must not overlap an obstacle; area names
    must be unique, and a label other than the area's name must be a proposition name
    (``is_proposition``). The checks that need the robot's size (start clearance, reachability) are
    in :func:`check_robot_fits`.
    """
    numbers = [("layout.arena", layout.arena), ("layout.start", layout.start)]
    numbers += [(f"layout.obstacles[{i}]", (*o.center, *((o.radius,) if isinstance(o, DiskObstacle) else o.half_extents)))
                for i, o in enumerate(layout.obstacles)]
    numbers += [(f"layout.areas[{i}]", (*a.center, a.radius)) for i, a in enumerate(layout.areas)]
    for field, values in numbers:  # a NaN passes every comparison below as if it were in range
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(field, f"holds a number that is not finite: {tuple(values)}")
    w, h = layout.arena
    if not (w > 0 and h > 0):
        raise ConfigError("layout.arena", f"sizes must be positive, got {layout.arena}")
    if max(w, h) > MAX_ARENA:
        raise ConfigError("layout.arena", f"{layout.arena} is larger than the {MAX_ARENA:g} m a side d2spo "
                          "handles (float32 positions); is the layout in metres?")
    for i, o in enumerate(layout.obstacles):
        if isinstance(o, DiskObstacle):
            if not o.radius > 0:
                raise ConfigError(f"layout.obstacles[{i}].radius", f"must be positive, got {o.radius}")
        elif min(o.half_extents) <= 0:
            raise ConfigError(f"layout.obstacles[{i}].half_extents", f"must be positive, got {o.half_extents}")
        if not (0 <= o.center[0] <= w and 0 <= o.center[1] <= h):
            raise ConfigError(f"layout.obstacles[{i}].center", f"{o.center} is outside the arena {layout.arena}")
    sx, sy, _ = layout.start
    if not (0 < sx < w and 0 < sy < h):
        raise ConfigError("layout.start", f"{layout.start[:2]} is outside the arena {layout.arena}")
    for i, o in enumerate(layout.obstacles):
        if _signed_distance(np.array([sx, sy]), o) <= 0:
            raise ConfigError("layout.start", f"{layout.start[:2]} is inside obstacle {i}")
    seen: set[str] = set()
    for i, a in enumerate(layout.areas):
        if a.radius <= 0:
            raise ConfigError(f"layout.areas[{i}].radius", f"must be positive, got {a.radius}")
        if a.name in seen:
            raise ConfigError(f"layout.areas[{i}].name", f"duplicate area name {a.name!r}")
        seen.add(a.name)
        if a.label != a.name and not is_proposition(a.label):
            raise ConfigError(f"layout.areas[{i}].label", f"{a.label!r} is not a proposition name ({PROPOSITION_RULE})")
        cx, cy = a.center
        if min(cx, cy, w - cx, h - cy) < a.radius:
            raise ConfigError(f"layout.areas[{i}]", f"area {a.name} (centre {a.center}, radius {a.radius}) "
                              f"is not inside the workspace {layout.arena}")
        for j, o in enumerate(layout.obstacles):
            if _signed_distance(np.array(a.center), o) <= a.radius:
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
    from scipy import ndimage  # scipy: imported when first needed, not with d2spo
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
            coarse = (f" (searched on a grid of {resolution:g} m cells, the finest of at most 1000 a side: a "
                      "passage narrower than about two cells may not show; is the layout in metres?)"
                      if resolution > 0.05 else "")
            raise ConfigError(f"layout.areas[{i}]", f"area {a.name} cannot be reached from the start by a robot "
                              f"of radius {robot_radius}{coarse}")

