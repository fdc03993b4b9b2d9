"""Obstacle-aware distance to each area, for the reward's shaping potential.

A straight-line distance to the next area pulls the robot into whatever lies on the line: on the
`paper` layout, obstacle O1 sits on the segment from the start to A1, and TD3 settles in front of
it (docs/ltl.md, "Shaping"). The shaping potential therefore uses the length of the shortest path
through free space, computed once per layout on a grid; it uses the layout's map only, never the
dynamics.

The grid has nodes every ``spacing`` metres over the arena. A node whose disk of the robot's
radius touches an obstacle or a wall is *blocked*; moving through blocked nodes costs
``blocked_cost`` times the length, so every node has a finite distance (the robot can be near a
wall) and paths go round obstacles. Distances are relaxed over the 8-neighbourhood with numpy
sweeps until nothing changes (a Bellman-Ford on a grid, a few hundred sweeps).
"""

from __future__ import annotations

import functools
import math

import jax.numpy as jnp
import numpy as np

from d2spo.errors import ConfigError

NEIGHBOURS8 = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))
"""The eight moves (row, column) from a grid node to its neighbours, shared by every grid search."""

SPACING = 0.05
"""Grid spacing in metres."""
BLOCKED_COST = 10.0
"""Multiplier of the path length through nodes where the robot would touch an obstacle or a wall."""
CLEARANCE_COST = 2.0
"""The per-state fields' and the field bank's multiplier of the path length through nodes closer
than the shaping clearance to an obstacle or a wall (``envs.state_fields``, ``envs.layout_bank``;
the default ``RewardConfig.shaping_clearance_cost``)."""
COLLIDE_COST = 100.0
"""Their multiplier where the robot would collide (the default ``RewardConfig.shaping_collide_cost``)."""
MAX_NODES = 170_000
"""Largest grid accepted: an arena of 20 m x 20 m at ``SPACING`` (160 801 nodes), whose fields take
about 18 s on a 2-core CPU. The sweeps grow with the number of nodes times the grid's width (a
40 m arena took 283 s, 200 m minutes and over 6 GB), so a larger arena is refused up front."""


def clearance(xs: np.ndarray, ys: np.ndarray, box_lo: np.ndarray, box_hi: np.ndarray, arena: tuple,
              disks=()) -> np.ndarray:
    """Distance from each node to the nearest obstacle box, disk (cx, cy, r) or wall (0 inside an obstacle)."""
    px, py = np.meshgrid(xs, ys)  # [ny, nx]
    walls = np.minimum.reduce([px, py, arena[0] - px, arena[1] - py])
    best = walls
    for lo, hi in zip(box_lo, box_hi):
        dx = np.maximum.reduce([lo[0] - px, np.zeros_like(px), px - hi[0]])
        dy = np.maximum.reduce([lo[1] - py, np.zeros_like(py), py - hi[1]])
        best = np.minimum(best, np.hypot(dx, dy))
    for cx, cy, r in disks:
        best = np.minimum(best, np.maximum(np.hypot(px - cx, py - cy) - r, 0.0))
    return best


@functools.lru_cache(maxsize=64)
def _fields(arena: tuple, boxes: tuple, areas: tuple, robot_radius: float, spacing: float,
            blocked_cost: float, disks: tuple = ()) -> np.ndarray:
    nx = int(round(arena[0] / spacing)) + 1
    ny = int(round(arena[1] / spacing)) + 1
    xs = np.linspace(0.0, arena[0], nx)
    ys = np.linspace(0.0, arena[1], ny)
    box_lo = np.array([b[0] for b in boxes], float).reshape(-1, 2)
    box_hi = np.array([b[1] for b in boxes], float).reshape(-1, 2)
    blocked = clearance(xs, ys, box_lo, box_hi, arena, disks) < robot_radius
    mult = np.where(blocked, blocked_cost, 1.0)
    px, py = np.meshgrid(xs, ys)
    out = np.empty((len(areas), ny, nx), np.float32)
    for k, (cx, cy, r) in enumerate(areas):
        euclid = np.hypot(px - cx, py - cy)
        d = np.where(euclid <= max(r, spacing), euclid, np.inf)
        for _ in range(4 * (nx + ny) * int(blocked_cost)):
            new = d.copy()
            for dy, dx in NEIGHBOURS8:
                step = spacing * math.hypot(dx, dy)
                # value arriving at node (i, j) from neighbour (i + dy, j + dx)
                src = np.full_like(d, np.inf)
                src_m = np.ones_like(d)
                ys_dst = slice(max(0, -dy), ny - max(0, dy))
                xs_dst = slice(max(0, -dx), nx - max(0, dx))
                ys_src = slice(max(0, dy), ny - max(0, -dy))
                xs_src = slice(max(0, dx), nx - max(0, -dx))
                src[ys_dst, xs_dst] = d[ys_src, xs_src]
                src_m[ys_dst, xs_dst] = mult[ys_src, xs_src]
                new = np.minimum(new, src + step * 0.5 * (mult + src_m))
            if np.array_equal(new, d):
                break
            d = new
        out[k] = d
    return out


def distance_fields(arena, box_lo, box_hi, area_center, area_radius, robot_radius: float,
                    spacing: float = SPACING, blocked_cost: float = BLOCKED_COST, disks=()) -> np.ndarray:
    """float32 [N, ny, nx]: path length from grid node (row y, column x) to the centre of area i,
    round the boxes and the disk obstacles ``disks`` ((cx, cy, r) each).

    Nodes inside area i (within its radius of the centre) hold their straight-line distance.
    Cached per (layout, robot radius): random-layout sweeps and tests build the same env often.
    """
    arena = (float(arena[0]), float(arena[1]))
    nodes = (round(arena[0] / spacing) + 1) * (round(arena[1] / spacing) + 1)
    if nodes > MAX_NODES:
        raise ConfigError("layout.arena", f"an arena of {arena[0]:g} m x {arena[1]:g} m needs a geodesic shaping grid "
                          f"of {nodes} nodes at {spacing:g} m; at most MAX_NODES={MAX_NODES} (20 m x 20 m) are "
                          "supported: draw the layout smaller, or train on it alone with --shaping-metric euclidean "
                          "(a generalist always needs the fields); is the layout in metres?")
    boxes = tuple((tuple(map(float, lo)), tuple(map(float, hi))) for lo, hi in zip(np.asarray(box_lo), np.asarray(box_hi)))
    areas = tuple((float(c[0]), float(c[1]), float(r)) for c, r in zip(np.asarray(area_center), np.asarray(area_radius)))
    disks = tuple(tuple(map(float, d)) for d in disks)
    return _fields(arena, boxes, areas, float(robot_radius), float(spacing), float(blocked_cost), disks)


def lookup(fields: jnp.ndarray, xy: jnp.ndarray, spacing: float = SPACING, index=slice(None)) -> jnp.ndarray:
    """Bilinear interpolation of every field at the point xy: [N]. Points outside are clamped to the grid.

    ``index`` (an int32 scalar) interpolates the single field ``fields[index]`` instead (a scalar),
    reading four grid values, not four per field.
    """
    ny, nx = fields.shape[-2], fields.shape[-1]
    fx = jnp.clip(xy[0] / spacing, 0.0, nx - 1.0)
    fy = jnp.clip(xy[1] / spacing, 0.0, ny - 1.0)
    x0 = jnp.clip(jnp.floor(fx).astype(jnp.int32), 0, nx - 2)
    y0 = jnp.clip(jnp.floor(fy).astype(jnp.int32), 0, ny - 2)
    tx, ty = fx - x0, fy - y0
    f00 = fields[index, y0, x0]
    f01 = fields[index, y0, x0 + 1]
    f10 = fields[index, y0 + 1, x0]
    f11 = fields[index, y0 + 1, x0 + 1]
    return (1 - ty) * ((1 - tx) * f00 + tx * f01) + ty * ((1 - tx) * f10 + tx * f11)


def descent(fields: jnp.ndarray, xy: jnp.ndarray, index, eps: float = 2 * SPACING,
            spacing: float = SPACING) -> jnp.ndarray:
    """[2]: unit vector of steepest descent of the bilinear field ``fields[index]`` at xy, by central
    differences ``eps`` either side (two grid spacings: the 8-neighbour fields bend at single
    nodes); 0 where the field is flat."""
    at = lambda d: lookup(fields, xy + d, spacing, index=index)  # noqa: E731
    grad = jnp.stack([at(jnp.array([eps, 0.0])) - at(jnp.array([-eps, 0.0])),
                      at(jnp.array([0.0, eps])) - at(jnp.array([0.0, -eps]))])
    norm = jnp.sqrt(grad[0] * grad[0] + grad[1] * grad[1])
    return jnp.where(norm > 0, -grad / jnp.where(norm > 0, norm, 1.0), 0.0)
