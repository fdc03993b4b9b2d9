"""A bank of layouts with a distance field per (target area, forbidden areas), for subgoal features.

An automaton state names target areas and forbidden ones (``envs.state_fields``). A policy that
serves every formula and layout reads, instead of the state's index, the distance and direction to
the nearest target along a path that goes round obstacles and round the forbidden areas. For a
layout with four areas there are 4 targets x 8 forbidden subsets of the other three: 32 fields,
all computed up front (``bank_of``, ``build_bank``), then read inside jit (``field_at``,
``nearest``).

Field (i, f) at a grid node is the length of the shortest 8-neighbour grid path from the node to
area i's disk (the last step is the straight distance to the disk), where

* a step costs its length times the mean of its two nodes' multipliers: 1 in the open,
  ``CLEARANCE_COST`` (2) where the node is closer than ``clearance`` (0.3 m, the reward's
  shaping clearance) to an obstacle or wall, and ``COLLIDE_COST`` (100) where it is closer than
  the robot's radius (0.15 m). The clearance tier is 2, not nav's 10: a 0.6-0.8 m opening lies
  wholly in it, and at 10x the path length jumped by metres for a step sideways across the
  opening's mouth (6 m for 0.2 m on ``random:2``), in the shaping reward and in the observation's
  direction; the first generalist trained with 10x stopped in front of such openings. The third
  tier is not in ``envs.geodesic``: without it a thin wall costs the same as the opening beside it,
  and the field would cross a corridor's wall rather than take a long detour to an opening;
* entering the disk of an area of subset f costs ``BLOCKED_COST`` arena diagonals (finite, as in
  ``envs.state_fields``: a target walled off by forbidden areas still has a field), leaving it
  nothing; coming closer than ``clearance`` to such a disk costs ``BLOCKED_COST`` times the approach.

Subset f is a bitmask over the other three areas in increasing order: for target A2 (index 1),
bit 0 is A1, bit 1 is A3, bit 2 is A4.

The grid has ``G`` x ``G`` nodes over each layout's own square arena (spacing side / (G - 1):
0.079 m at 5 m, 0.159 m at 10 m), node (row y, column x) at (x, y) * spacing. ``G`` = 64 resolves
the narrowest gap ``generator.GAP_WIDTH`` allows (0.6 m) at the largest arena (10 m): the node
nearest the gap's centre line is at most half a spacing (0.08 m) off it, so the opening always holds
a line of nodes with clearance >= 0.22 m > the robot radius (cost 2x), while the wall makes a band
of >= 0.4 m of 100x nodes that no step (0.16 m) jumps. It takes G >= 35 (spacing < 0.3 m); 64 keeps
about four nodes across the opening (docs/layouts.md, "Field bank").

Two solvers give the same fields: ``fields_numpy`` (scipy's Dijkstra, one per field, like
``envs.state_fields``) and ``fields_jax`` (pure JAX, vmappable over layouts, so fresh layouts could
be drawn inside a jitted loop): Gauss-Seidel sweeps of the grid in four directions (each row takes
its neighbours in the previous row, then a min-plus scan along itself), repeated until nothing
changes. bench/layout_fields.py times both.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from d2spo.envs import generator, geodesic
from d2spo.envs.workspace import Layout
from d2spo.errors import ConfigError

G = 64
"""Grid nodes per side (module docstring: why 64)."""
N_AREAS = generator.N_AREAS
"""Areas per layout in a bank."""
N_SUBSETS = 2 ** (N_AREAS - 1)
"""Forbidden subsets per target: every subset of the other areas."""
M_MAX = generator.MAX_BOXES
"""Obstacle slots per layout (unused slots are masked)."""
CLEARANCE = 0.3
"""Nodes closer than this (m) to an obstacle or wall cost ``CLEARANCE_COST`` times their length (the
default ``RewardConfig.shaping_clearance``); coming this close to a forbidden area costs
``geodesic.BLOCKED_COST`` times the approach."""
ROBOT_RADIUS = 0.15
"""Nodes closer than this (m) to an obstacle or wall cost ``COLLIDE_COST`` times (default preset's robot)."""
CLEARANCE_COST = geodesic.CLEARANCE_COST
"""Multiplier of the path length through nodes closer than ``CLEARANCE`` to an obstacle or wall
(module docstring: why 2)."""
COLLIDE_COST = geodesic.COLLIDE_COST
"""Multiplier of the path length through nodes where the robot would collide."""
TOL = 1e-4
"""``fields_jax`` stops after a round of sweeps that lowers no value by more than this (m). Two rounds
settle every field of the layouts tried to 1e-5 m; later ones only reorder float sums."""
MAX_SWEEPS = 100
"""Most rounds of four sweeps ``fields_jax`` runs."""

_OTHERS = np.array([[j for j in range(N_AREAS) if j != i] for i in range(N_AREAS)])  # [4, 3]
_IN_SUBSET = np.array([[[(f >> k) & 1 for k in range(N_AREAS - 1)] for f in range(N_SUBSETS)]], bool)  # [1, 8, 3]
_FORBIDS = np.zeros((N_AREAS, N_SUBSETS, N_AREAS), bool)  # [i, f, j]: subset f of target i holds area j
for _i in range(N_AREAS):
    _FORBIDS[_i][:, _OTHERS[_i]] = _IN_SUBSET[0]


class LayoutBank(NamedTuple):
    """B layouts as fixed-shape arrays (a pytree), with their fields."""

    arena: jax.Array
    """float32 [B, 2]: (width, height) in metres; width == height."""
    box_lo: jax.Array
    """float32 [B, M_MAX, 2]: lower-left corners of the obstacles (unused slots: 0)."""
    box_hi: jax.Array
    """float32 [B, M_MAX, 2]: upper-right corners of the obstacles (unused slots: 0)."""
    box_mask: jax.Array
    """bool [B, M_MAX]: which obstacle slots hold an obstacle."""
    area_center: jax.Array
    """float32 [B, 4, 2]: centres of A1 .. A4."""
    area_radius: jax.Array
    """float32 [B, 4]: radii of A1 .. A4."""
    start: jax.Array
    """float32 [B, 3]: start pose (x, y, theta)."""
    fields: jax.Array
    """float32 [B, 4, 8, G, G]: field (target i, forbidden subset f), row y, column x (module docstring).
    float32, not float16: the direction is a difference of neighbouring values 0.08-0.16 m apart,
    and float16 resolves 0.03 m between 32 and 64 m (a route in a 10 m arena), a 20-40% error."""


# ------------------------------------------------------------------------------------ packing


def pack(layouts: Sequence[Layout]) -> LayoutBank:
    """The layouts as arrays, fields not computed yet (``fields`` empty: [B, 0])."""
    for lay in layouts:
        if lay.disks:
            raise ConfigError("layout.obstacles", f"{lay.name}: a bank holds box obstacles only, got "
                              f"{len(lay.disks)} disks")
        if lay.arena[0] != lay.arena[1]:
            raise ConfigError("layout.arena", f"{lay.name}: a bank holds square arenas, got {lay.arena}")
        if len(lay.areas) != N_AREAS:
            raise ConfigError("layout.areas", f"{lay.name}: a bank holds {N_AREAS} areas, got {len(lay.areas)}")
        if len(lay.obstacles) > M_MAX:
            raise ConfigError("layout.obstacles", f"{lay.name}: a bank holds at most {M_MAX} obstacles, "
                              f"got {len(lay.obstacles)}")
    b = len(layouts)
    lo, hi, mask = np.zeros((b, M_MAX, 2)), np.zeros((b, M_MAX, 2)), np.zeros((b, M_MAX), bool)
    for k, lay in enumerate(layouts):
        for m, o in enumerate(lay.obstacles):
            lo[k, m], hi[k, m], mask[k, m] = o.lo, o.hi, True
    f32 = lambda x: jnp.asarray(np.asarray(x, np.float64), jnp.float32)  # noqa: E731
    return LayoutBank(
        arena=f32([lay.arena for lay in layouts]), box_lo=f32(lo), box_hi=f32(hi), box_mask=jnp.asarray(mask),
        area_center=f32([[a.center for a in lay.areas] for lay in layouts]),
        area_radius=f32([[a.radius for a in lay.areas] for lay in layouts]),
        start=f32([lay.start for lay in layouts]), fields=jnp.zeros((b, 0), jnp.float32))


def bank_of(layouts: Sequence[Layout], method: str = "numpy", chunk: int = 64, grid: int = G) -> LayoutBank:
    """The layouts with their fields on ``grid`` x ``grid`` nodes, computed by ``fields_numpy`` (one
    at a time; the faster on a CPU: bench/RESULTS.md) or ``fields_jax`` (``chunk`` layouts a call)."""
    bank = pack(layouts)
    args = (bank.arena, bank.box_lo, bank.box_hi, bank.box_mask, bank.area_center, bank.area_radius)
    if method == "jax":
        out = [_fields_batch(*(a[s:s + chunk] for a in args), grid) for s in range(0, len(layouts), chunk)]
    elif method == "numpy":
        out = [fields_numpy(*(a[k] for a in args), grid)[None] for k in range(len(layouts))]
    else:
        raise ConfigError("method", f"expected 'jax' or 'numpy', got {method!r}")
    return bank._replace(fields=jnp.concatenate([jnp.asarray(o) for o in out]))


def build_bank(seeds: Sequence[int], method: str = "numpy", chunk: int = 64, grid: int = G) -> LayoutBank:
    """The layouts ``random:SEED`` (``generator.generate``) for ``seeds``, with their fields."""
    return bank_of([generator.generate(int(s)) for s in seeds], method, chunk, grid)


# ------------------------------------------------------------------------------------ step costs


def step_costs(arena, box_lo, box_hi, box_mask, area_center, area_radius, grid: int = G):
    """(cost [3, 3, 4, 8, G, G], start [4, 8, G, G]) of one layout, pure JAX.

    ``cost[dy + 1, dx + 1, i, f, y, x]``: cost of the step from node (y, x) to (y + dy, x + dx) in
    field (i, f) (inf off the grid). ``start[i, f, y, x]``: the straight distance from the node to
    area i's disk where that is at most one diagonal step (0 inside), inf elsewhere.
    """
    w, h = arena[0], arena[1]
    spacing = w / (grid - 1)
    px, py = jnp.meshgrid(jnp.arange(grid) * spacing, jnp.arange(grid) * spacing)  # [G, G]
    p = jnp.stack([px, py], -1)[..., None, :]  # [G, G, 1, 2]
    out = jnp.maximum(jnp.maximum(box_lo - p, 0.0), p - box_hi)  # [G, G, M, 2]
    boxes = jnp.where(box_mask, jnp.linalg.norm(out, axis=-1), jnp.inf).min(-1)
    clear = jnp.minimum(jnp.minimum(jnp.minimum(px, py), jnp.minimum(w - px, h - py)), boxes)
    mult = jnp.where(clear < ROBOT_RADIUS, COLLIDE_COST, jnp.where(clear < CLEARANCE, CLEARANCE_COST, 1.0))
    gap = jnp.maximum(jnp.linalg.norm(p[..., 0, :][None] - area_center[:, None, None], axis=-1)
                      - area_radius[:, None, None], 0.0)  # [4, G, G]: distance to each disk
    forbids = jnp.asarray(_FORBIDS)[..., None, None]  # [4, 8, 4, 1, 1]
    inside = jnp.any(forbids & (gap == 0.0), axis=2)  # [4, 8, G, G]: in a forbidden disk
    depth = jnp.max(jnp.where(forbids, jnp.maximum(CLEARANCE - gap, 0.0), 0.0), axis=2)  # into the keep-out ring
    penalty = geodesic.BLOCKED_COST * jnp.hypot(w, h)
    rows = []
    for dy in (-1, 0, 1):
        row = []
        for dx in (-1, 0, 1):
            m_n, in_n, depth_n = (_shifted(a, dy, dx) for a in (mult, inside, depth))
            c = spacing * math.hypot(dx, dy) * 0.5 * (mult + m_n)
            c = c + geodesic.BLOCKED_COST * jnp.maximum(depth_n - depth, 0.0) + jnp.where(in_n & ~inside, penalty, 0.0)
            on_grid = _shifted(jnp.ones((grid, grid), bool), dy, dx)
            row.append(jnp.where(on_grid & ((dy, dx) != (0, 0)), c, jnp.inf))
        rows.append(jnp.stack(row))
    start = jnp.where(gap <= spacing * math.sqrt(2.0), gap, jnp.inf)  # [4, G, G]
    return jnp.stack(rows), jnp.broadcast_to(start[:, None], (N_AREAS, N_SUBSETS, grid, grid))


_step_costs_jit = jax.jit(step_costs, static_argnums=6)


def _shifted(a: jax.Array, dy: int, dx: int) -> jax.Array:
    """a[..., y + dy, x + dx] at [..., y, x] (False / 0 off the grid; ``step_costs`` masks those)."""
    g = a.shape[-1]
    pad = [(0, 0)] * (a.ndim - 2) + [(max(-dy, 0), max(dy, 0)), (max(-dx, 0), max(dx, 0))]
    padded = jnp.pad(a, pad)
    return padded[..., max(dy, 0):max(dy, 0) + g, max(dx, 0):max(dx, 0) + g]


# ------------------------------------------------------------------------------------ solvers


def fields_numpy(arena, box_lo, box_hi, box_mask, area_center, area_radius, grid: int = G) -> np.ndarray:
    """float32 [4, 8, G, G]: the fields of one layout by scipy's Dijkstra (one search per field,
    from a source joined to every node by the node's ``start`` distance, over the reversed steps)."""
    cost, start = (np.asarray(a, np.float64) for a in _step_costs_jit(arena, box_lo, box_hi, box_mask, area_center,
                                                                      area_radius, grid))
    n = grid * grid
    idx = np.arange(n).reshape(grid, grid)
    out = np.empty((N_AREAS, N_SUBSETS, grid, grid), np.float32)
    for i in range(N_AREAS):
        for f in range(N_SUBSETS):
            rows, cols, data = [], [], []
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    c = cost[dy + 1, dx + 1, i, f]
                    src = idx[np.isfinite(c)]
                    dst = src + dy * grid + dx
                    rows.append(dst)  # reversed: a search from the disk reaches src through dst
                    cols.append(src)
                    data.append(c.ravel()[src])
            s = start[i, f].ravel()
            ends = np.flatnonzero(np.isfinite(s))
            rows.append(np.full(ends.shape, n))
            cols.append(ends)
            data.append(np.maximum(s[ends], 1e-9))  # an explicit zero would be no edge
            graph = sparse.csr_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))),
                                      shape=(n + 1, n + 1))
            dist = csgraph.dijkstra(graph, directed=True, indices=n)[:n]
            out[i, f] = np.where(s <= 1e-9, 0.0, dist).reshape(grid, grid)
    return out


def fields_jax(arena, box_lo, box_hi, box_mask, area_center, area_radius, grid: int = G) -> jax.Array:
    """float32 [4, 8, G, G]: the fields of one layout, pure JAX (jit and vmap over layouts)."""
    cost, d = step_costs(arena, box_lo, box_hi, box_mask, area_center, area_radius, grid)
    t = lambda a: jnp.swapaxes(a, -1, -2)  # noqa: E731
    flip = lambda a: jnp.flip(a, -2)  # noqa: E731
    # the sweep runs down the rows of each view of the grid: (view, its inverse, the view of the costs)
    views = [(lambda a: a, lambda a: a, cost),
             (flip, flip, jnp.flip(flip(cost), 0)),  # up
             (t, t, t(jnp.swapaxes(cost, 0, 1))),  # right
             (lambda a: flip(t(a)), lambda a: t(flip(a)), jnp.flip(flip(t(jnp.swapaxes(cost, 0, 1))), 0))]  # left

    def one_round(d):
        for view, unview, c in views:
            d = unview(_sweep_down(view(d), c))
        return d

    def body(carry):
        d, _, k = carry
        new = one_round(d)
        change = jnp.where(jnp.isfinite(new), d - new, 0.0)  # inf - inf: still unreached, no change
        return new, jnp.any(change > TOL), k + 1

    d, _, _ = jax.lax.while_loop(lambda c: c[1] & (c[2] < MAX_SWEEPS), body, (d, jnp.array(True), 0))
    return d


_fields_batch = jax.jit(jax.vmap(fields_jax, in_axes=(0, 0, 0, 0, 0, 0, None)), static_argnums=6)


def _sweep_down(d: jax.Array, cost: jax.Array) -> jax.Array:
    """One Gauss-Seidel pass over the rows y = 0 .. G-1: each row takes its three neighbours in the
    row before (steps with dy = -1), then the best along itself both ways (a min-plus scan)."""
    inf_row = jnp.full(d.shape[:-2] + d.shape[-1:], jnp.inf, d.dtype)

    def step(prev, xs):
        row, c = xs  # row [..., G], c [3, 3, ..., G]
        from_prev = jnp.minimum(jnp.minimum(_shift_row(prev, -1) + c[0, 0], prev + c[0, 1]),
                                _shift_row(prev, 1) + c[0, 2])
        row = jnp.minimum(row, from_prev)
        row = _min_plus_scan(row, c[1, 0])
        row = jnp.flip(_min_plus_scan(jnp.flip(row, -1), jnp.flip(c[1, 2], -1)), -1)
        return row, row

    _, rows = jax.lax.scan(step, inf_row, (jnp.moveaxis(d, -2, 0), jnp.moveaxis(cost, -2, 0)))
    return jnp.moveaxis(rows, 0, -2)


def _shift_row(row: jax.Array, dx: int) -> jax.Array:
    """row[..., x + dx] at x (inf off the row)."""
    pad = [(0, 0)] * (row.ndim - 1) + [(max(-dx, 0), max(dx, 0))]
    padded = jnp.pad(row, pad, constant_values=jnp.inf)
    return padded[..., max(dx, 0):max(dx, 0) + row.shape[-1]]


def _min_plus_scan(value: jax.Array, step: jax.Array) -> jax.Array:
    """out[x] = min(value[x], out[x - 1] + step[x]) along the last axis, as an associative scan of
    the maps v -> min(v + step[x], value[x]) (3x faster on CPU than log2(G) rounds of shifted minima)."""
    def compose(first, then):
        (a1, b1), (a2, b2) = first, then
        return a1 + a2, jnp.minimum(b1 + a2, b2)

    return jax.lax.associative_scan(compose, (step, value), axis=-1)[1]


# ------------------------------------------------------------------------------------ lookup


def field_at(bank: LayoutBank, b, i, f, xy: jax.Array) -> jax.Array:
    """Field (target i, forbidden subset f) of layout b, bilinear at xy [2] (clamped to the arena),
    as ``geodesic.lookup``; it gathers the four nodes from the whole bank, so no slice of a field is
    copied when b, i, f are traced (inside the training step)."""
    g = bank.fields.shape[-1]
    spacing = bank.arena[b, 0] / (g - 1)
    fx = jnp.clip(xy[0] / spacing, 0.0, g - 1.0)
    fy = jnp.clip(xy[1] / spacing, 0.0, g - 1.0)
    x0 = jnp.clip(jnp.floor(fx).astype(jnp.int32), 0, g - 2)
    y0 = jnp.clip(jnp.floor(fy).astype(jnp.int32), 0, g - 2)
    tx, ty = fx - x0, fy - y0
    f00, f01 = bank.fields[b, i, f, y0, x0], bank.fields[b, i, f, y0, x0 + 1]
    f10, f11 = bank.fields[b, i, f, y0 + 1, x0], bank.fields[b, i, f, y0 + 1, x0 + 1]
    return (1 - ty) * ((1 - tx) * f00 + tx * f01) + ty * ((1 - tx) * f10 + tx * f11)


def subsets(forbidden: jax.Array) -> jax.Array:
    """int32 [4]: per target i, the index of the forbidden subset ``forbidden`` (bool [4]) names."""
    bits = jnp.asarray(forbidden)[jnp.asarray(_OTHERS)]  # [4, 3]
    return jnp.sum(bits * (1 << jnp.arange(N_AREAS - 1)), axis=-1).astype(jnp.int32)


def nearest(bank: LayoutBank, b, target: jax.Array, forbidden: jax.Array, xy: jax.Array):
    """(distance [], direction [2]) at xy to the nearest area of ``target`` (bool [4]) along a path
    avoiding the areas of ``forbidden`` (bool [4]; a target is never forbidden for itself).

    The direction is the unit vector of steepest descent of that target's bilinear field, by central
    differences half a grid spacing either side; with no target (or a flat field) both are 0.
    """
    f = subsets(forbidden)
    per_target = jax.vmap(lambda i, fi: field_at(bank, b, i, fi, xy))(jnp.arange(N_AREAS), f)
    per_target = jnp.where(target, per_target, jnp.inf)
    k = jnp.argmin(per_target)
    any_target = jnp.any(target)
    eps = 0.5 * bank.arena[b, 0] / (bank.fields.shape[-1] - 1)
    probe = lambda dxy: field_at(bank, b, k, f[k], xy + dxy)  # noqa: E731
    grad = jnp.stack([probe(jnp.array([eps, 0.0])) - probe(jnp.array([-eps, 0.0])),
                      probe(jnp.array([0.0, eps])) - probe(jnp.array([0.0, -eps]))]) / (2 * eps)
    norm = jnp.linalg.norm(grad)
    direction = jnp.where(any_target & (norm > 0), -grad / jnp.where(norm > 0, norm, 1.0), 0.0)
    return jnp.where(any_target, per_target[k], 0.0), direction
