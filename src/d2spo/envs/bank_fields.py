"""The step costs and the two solvers of the field bank's fields (``envs.layout_bank``, whose
docstring says what a field is): ``step_costs`` per slot, then ``fields_numpy`` (scipy's Dijkstra,
one per field, like ``envs.state_fields``) or ``fields_jax`` (pure JAX, vmappable over slots, so
fresh layouts can be drawn while a run trains: Gauss-Seidel sweeps of the grid in four directions,
each row taking its neighbours in the previous row, then a min-plus scan along itself, repeated
until nothing changes). They give the same fields; bench/layout_fields.py times both.

A slot's arguments are ``layout_bank._slot_args``: arena, boxes, disks, areas, and per state the
target and forbidden areas.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.envs import geodesic

G = 96
"""Grid nodes per side (``envs.layout_bank``'s docstring: why 96)."""
CLEARANCE = 0.3
"""Nodes closer than this (m) to an obstacle or wall cost ``CLEARANCE_COST`` times their length (the
default ``RewardConfig.shaping_clearance``); coming this close to a forbidden area costs
``geodesic.BLOCKED_COST`` times the approach."""
ROBOT_RADIUS = 0.15
"""Nodes closer than this (m) to an obstacle or wall cost ``COLLIDE_COST`` times (default preset's robot)."""
CLEARANCE_COST = geodesic.CLEARANCE_COST
"""Multiplier of the path length through nodes closer than ``CLEARANCE`` to an obstacle or wall
(``envs.layout_bank``'s docstring: why 2)."""
COLLIDE_COST = geodesic.COLLIDE_COST
"""Multiplier of the path length through nodes where the robot would collide."""
TOL = 1e-4
"""``fields_jax`` stops after a round of sweeps that lowers no value by more than this (m). Two rounds
settle every field of the layouts tried to 1e-5 m; later ones only reorder float sums."""
MAX_SWEEPS = 100
"""Most rounds of four sweeps ``fields_jax`` runs."""


# ------------------------------------------------------------------------------------ step costs


def step_costs(arena, box_lo, box_hi, box_mask, disk_center, disk_radius, disk_mask, area_center, area_radius,
               area_mask, target, forbidden, grid: int = G):
    """(cost [3, 3, S, G, G], start [S, G, G]) of one slot, pure JAX.

    ``cost[dy + 1, dx + 1, s, y, x]``: cost of the step from node (y, x) to (y + dy, x + dx) in
    field s (inf off the grid). ``start[s, y, x]``: the straight distance from the node to the
    nearest disk of a target area of s where that is at most one diagonal step (0 inside), inf elsewhere.
    """
    w, h = arena[0], arena[1]
    spacing = jnp.maximum(w, h) / (grid - 1)
    px, py = jnp.meshgrid(jnp.arange(grid) * spacing, jnp.arange(grid) * spacing)  # [G, G]
    p = jnp.stack([px, py], -1)  # [G, G, 2]
    out = jnp.maximum(jnp.maximum(box_lo - p[..., None, :], 0.0), p[..., None, :] - box_hi)  # [G, G, M, 2]
    boxes = jnp.where(box_mask, jnp.linalg.norm(out, axis=-1), jnp.inf).min(-1)
    disks = jnp.where(disk_mask, jnp.linalg.norm(p[..., None, :] - disk_center, axis=-1) - disk_radius,
                      jnp.inf).min(-1)
    walls = jnp.minimum(jnp.minimum(px, py), jnp.minimum(w - px, h - py))  # negative outside the arena
    clear = jnp.minimum(jnp.minimum(walls, boxes), disks)
    mult = jnp.where(clear < ROBOT_RADIUS, COLLIDE_COST, jnp.where(clear < CLEARANCE, CLEARANCE_COST, 1.0))
    gap = jnp.maximum(jnp.linalg.norm(p[None] - area_center[:, None, None], axis=-1)
                      - area_radius[:, None, None], 0.0)  # [N, G, G]: distance to each disk
    gap = jnp.where(area_mask[:, None, None], gap, jnp.inf)
    forbids = forbidden[..., None, None]  # [S, N, 1, 1]
    inside = jnp.any(forbids & (gap == 0.0), axis=1)  # [S, G, G]: in a forbidden disk
    depth = jnp.max(jnp.where(forbids, jnp.maximum(CLEARANCE - gap, 0.0), 0.0), axis=1)  # into the keep-out ring
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
    nearest_target = jnp.min(jnp.where(target[..., None, None], gap[None], jnp.inf), axis=1)  # [S, G, G]
    start = jnp.where(nearest_target <= spacing * math.sqrt(2.0), nearest_target, jnp.inf)
    return jnp.stack(rows), start


_step_costs_jit = jax.jit(step_costs, static_argnums=12)


def _shifted(a: jax.Array, dy: int, dx: int) -> jax.Array:
    """a[..., y + dy, x + dx] at [..., y, x] (False / 0 off the grid; ``step_costs`` masks those)."""
    g = a.shape[-1]
    pad = [(0, 0)] * (a.ndim - 2) + [(max(-dy, 0), max(dy, 0)), (max(-dx, 0), max(dx, 0))]
    padded = jnp.pad(a, pad)
    return padded[..., max(dy, 0):max(dy, 0) + g, max(dx, 0):max(dx, 0) + g]


# ------------------------------------------------------------------------------------ solvers


def fields_numpy(*slot, grid: int = G) -> np.ndarray:
    """float32 [S, G, G]: the fields of one slot (``layout_bank._slot_args`` of one slot) by scipy's
    Dijkstra (one search per field, from a source joined to every node by the node's ``start``
    distance, over the reversed steps). A state with no target gets inf everywhere."""
    from scipy import sparse  # scipy: imported when first needed, not with d2spo
    from scipy.sparse import csgraph
    cost, start = (np.asarray(a, np.float64) for a in _step_costs_jit(*slot, grid))
    n = grid * grid
    idx = np.arange(n).reshape(grid, grid)
    out = np.empty(start.shape, np.float32)
    for s in range(start.shape[0]):
        rows, cols, data = [], [], []
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                c = cost[dy + 1, dx + 1, s]
                src = idx[np.isfinite(c)]
                dst = src + dy * grid + dx
                rows.append(dst)  # reversed: a search from the disk reaches src through dst
                cols.append(src)
                data.append(c.ravel()[src])
        st = start[s].ravel()
        ends = np.flatnonzero(np.isfinite(st))
        rows.append(np.full(ends.shape, n))
        cols.append(ends)
        data.append(np.maximum(st[ends], 1e-9))  # an explicit zero would be no edge
        graph = sparse.csr_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))),
                                  shape=(n + 1, n + 1))
        dist = csgraph.dijkstra(graph, directed=True, indices=n)[:n]
        out[s] = np.where(st <= 1e-9, 0.0, dist).reshape(grid, grid)
    return out


def fields_jax(*slot, grid: int = G) -> jax.Array:
    """float32 [S, G, G]: the fields of one slot, pure JAX (jit and vmap over slots)."""
    cost, d = step_costs(*slot, grid)
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


fields_batch = jax.jit(jax.vmap(lambda *a: fields_jax(*a[:-1], grid=a[-1]), in_axes=(0,) * 12 + (None,)),
                        static_argnums=12)


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
