"""The routes that complete a task on a layout: the automaton states a robot can reach
(``reachable_states``) and the length of the shortest route (``route_length``).

Both search the product of the automaton and a conservative grid of the positions a robot of the
given radius can occupy (``workspace.free_grid``, as ``workspace.reachable_grid``), reading letters
as the environment reads them.
"""

from __future__ import annotations

import math

import numpy as np

from d2spo.envs import geodesic, workspace
from d2spo.envs.layouts import letters_at
from d2spo.envs.workspace import Layout
from d2spo.ltl.automaton import Automaton

_SHIFTS4 = [(-1, 0), (1, 0), (0, -1), (0, 1)]
OCTILE_EXCESS = math.sqrt(4 - 2 * math.sqrt(2))
"""The most an 8-neighbour grid path exceeds the straight segment it follows (1.082, at 22.5°)."""


def _task_grid(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float):
    """The grid the task checks search: (free [ny, nx], letters [ny, nx], delta [Q, 2**n], resolution,
    start (q0, iy, ix)) with q0 the state after the start cell's letter is read as the env reads it."""
    # 5 cm, finer in arenas under 5 m, coarser above 20 m (at most 400 x 400 cells: route_length
    # searches states x cells)
    resolution = max(min(0.05, max(layout.arena) / 100.0), max(layout.arena) / 400.0)
    free, centres = workspace.free_grid(layout, robot_radius, resolution)
    letters = letters_at(centres, layout, aut.aps)
    ny, nx = free.shape
    delta = np.asarray(aut.delta, np.int64).reshape(aut.n_states, aut.n_letters)
    iy = min(int(layout.start[1] / resolution), ny - 1)
    ix = min(int(layout.start[0] / resolution), nx - 1)
    first = letters[iy, ix]
    q0 = int(delta[aut.initial, first]) if (first != 0 or label_mode != "event") else aut.initial
    return free, letters, delta, resolution, (q0, iy, ix)


def reachable_states(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float) -> list[bool]:
    """Per automaton state, whether a robot of ``robot_radius`` can drive from the start into it:
    a search over (automaton state, grid cell) with 4-neighbour moves between cells the robot can
    occupy (``workspace.free_grid``, conservative) and letters read as the environment reads them."""
    free, letters, delta, _, start = _task_grid(aut, layout, label_mode, robot_radius)
    return _reachable(delta, letters, free, start, label_mode == "event", sorted(aut.accepting | aut.rejecting))


def _reachable(delta: np.ndarray, letters: np.ndarray, free: np.ndarray, start: tuple[int, int, int], event: bool,
               absorbing: list[int]) -> list[bool]:
    """Per automaton state, whether the robot can be in it: a search over (state, grid cell).

    In state q the robot moves freely through the cells whose letter is not read (event labelling:
    the empty letter and the letter of the cell it stands in) or leaves q where it is (delta[q, a] == q);
    so each state's cells are one flood fill (scipy), and every move across the fill's border into
    a cell whose letter leads elsewhere seeds that state there.
    """
    from scipy import ndimage  # scipy: imported when first needed, not with d2spo
    n_states = delta.shape[0]
    four = ndimage.generate_binary_structure(2, 1)
    stays = (delta[:, letters] == np.arange(n_states)[:, None, None]) & free  # [Q, ny, nx]
    if event:
        stays |= (letters == 0) & free
    seeds = np.zeros((n_states,) + letters.shape, bool)
    reached = np.zeros_like(seeds)
    regions = np.zeros(letters.shape, np.int64)  # connected cells of one non-empty letter
    for a in np.unique(letters[free & (letters != 0)]):
        lab, _ = ndimage.label(free & (letters == a), four)
        regions = np.where(lab > 0, lab + regions.max(), regions)
    q0, iy, ix = start
    seeds[q0, iy, ix] = True
    todo = [q0]
    while todo:
        q = todo.pop()
        if q in absorbing:
            reached[q] |= seeds[q]
            continue
        mask = stays[q].copy()
        if event:  # the areas it stands in when it enters q: it may move inside them without a read
            mask |= np.isin(regions, np.unique(regions[seeds[q] & (regions > 0)]))
        else:  # a seed on a cell whose letter leads elsewhere moves on at the next step
            moved = seeds[q] & ~stays[q]
            for y, x in zip(*np.nonzero(moved), strict=True):
                t = delta[q, letters[y, x]]
                if not seeds[t, y, x]:
                    seeds[t, y, x] = True
                    todo.append(t)
        fill = ndimage.binary_propagation(seeds[q] & mask, four, mask) | seeds[q]
        new = fill & ~reached[q]
        reached[q] |= fill
        if not new.any():
            continue
        for dy, dx in _SHIFTS4:  # moves from the fill into a cell whose letter is read and leads elsewhere
            src = np.roll(new, (dy, dx), axis=(0, 1))
            if dy:
                src[0 if dy > 0 else -1, :] = False
            if dx:
                src[:, 0 if dx > 0 else -1] = False
            prev = np.roll(letters, (dy, dx), axis=(0, 1))
            reads = (letters != prev) & (letters != 0) if event else np.ones_like(src)
            ys, xs = np.nonzero(src & free & reads)
            t = delta[q, letters[ys, xs]]
            fresh = (t != q) & ~seeds[t, ys, xs]
            seeds[t[fresh], ys[fresh], xs[fresh]] = True
            todo.extend(int(u) for u in np.unique(t[fresh]) if u not in todo)
    return [bool(r.any()) for r in reached]


def route_length(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float) -> float:
    """Length (m) of the shortest grid route from the start that completes the task. A robot of
    ``robot_radius`` drives at least ``route_length / OCTILE_EXCESS`` (the grid's 8 directions make a
    route up to 8.2% longer than the continuous one; turning and braking only add to the drive).

    Dijkstra over (automaton state, grid cell): 8-neighbour moves between free cells of
    ``workspace.free_grid`` (a diagonal move also needs its two 4-neighbours free), letters read as the
    environment reads them, rejecting states excluded. ``inf`` when no route exists.
    """
    from scipy import sparse  # scipy: imported when first needed, not with d2spo
    from scipy.sparse import csgraph
    rows, cols, weights, _, n, start, cells = _product_edges(aut, layout, label_mode, robot_radius)
    if start // cells in aut.accepting:
        return 0.0
    if not aut.accepting:
        return math.inf
    graph = sparse.csr_matrix((weights, (rows, cols)), shape=(n, n))
    dist = csgraph.dijkstra(graph, indices=start)
    return float(min(dist[q * cells:(q + 1) * cells].min() for q in aut.accepting))


def visit_lengths(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float, max_length: float,
                  max_visits: int = 10_000) -> list[float]:
    """Lengths (m) of the shortest grid routes from the start that make 1, 2, ... accepting visits of a
    Büchi task (``BuchiTask.visits``), as many as fit within ``max_length`` (at most ``max_visits``):
    what a perfect robot driving ``max_length`` could score. Empty when no visit can be made within it.

    A search by layers over ``route_length``'s graph: layer k holds the shortest length to each
    (automaton state, grid cell) with k visits made; layer k + 1 starts where a visit move leaves layer
    k (one Dijkstra per layer from a node joined to those starts by their lengths). The difference of
    consecutive lengths tends to the shortest cycle through the accepting set.
    """
    from scipy import sparse  # scipy: imported when first needed, not with d2spo
    from scipy.sparse import csgraph
    rows, cols, weights, visit, n, start, _ = _product_edges(aut, layout, label_mode, robot_radius)
    plain = sparse.csr_matrix((weights[~visit], (rows[~visit], cols[~visit])), shape=(n + 1, n + 1))
    v_src, v_dst, v_w = rows[visit], cols[visit], weights[visit]
    dist = csgraph.dijkstra(plain, indices=start)[:n]
    out: list[float] = []
    while len(out) < max_visits:
        arrive = np.full(n, np.inf)
        np.minimum.at(arrive, v_dst, dist[v_src] + v_w)
        best = float(arrive.min()) if arrive.size else math.inf
        if not (math.isfinite(best) and best <= max_length):  # inf: no visit, even with max_length inf
            break
        out.append(best)
        ends = np.flatnonzero(arrive <= max_length)
        seed = sparse.csr_matrix((arrive[ends], (np.full(ends.shape, n), ends)), shape=(n + 1, n + 1))
        dist = csgraph.dijkstra(plain + seed, indices=n)[:n]
    return out


def _product_edges(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float):
    """The (automaton state, grid cell) graph ``route_length`` and ``visit_lengths`` search: (rows, cols,
    weights, visit, n nodes, start node, cells per automaton state; node = q * cells + cell), one entry
    per move of a live state (not accepting, not rejecting) that does not reject; ``visit`` marks the
    moves that are a Büchi task's accepting visit (``BuchiTask.visits``; none for a monitor)."""
    event = label_mode == "event"
    free, letters, delta, resolution, (q0, iy, ix) = _task_grid(aut, layout, label_mode, robot_radius)
    ny, nx = free.shape
    n_states = aut.n_states
    rejecting = np.zeros(n_states, bool)
    rejecting[sorted(aut.rejecting)] = True
    live = ~rejecting
    live[sorted(aut.accepting)] = False
    visits = np.asarray(getattr(aut, "visits", None) or np.zeros(delta.shape, bool), bool).reshape(delta.shape)
    cell = np.arange(ny * nx).reshape(ny, nx)
    rows, cols, weights, marks = [], [], [], []
    for dy, dx in geodesic.NEIGHBOURS8:
        ys, xs = np.nonzero(free)
        ty, tx = ys + dy, xs + dx
        ok = (ty >= 0) & (ty < ny) & (tx >= 0) & (tx < nx)
        ys, xs, ty, tx = ys[ok], xs[ok], ty[ok], tx[ok]
        ok = free[ty, tx]
        if dy and dx:  # no corner cutting
            ok &= free[ys + dy, xs] & free[ys, xs + dx]
        ys, xs, ty, tx = ys[ok], xs[ok], ty[ok], tx[ok]
        a, b = letters[ys, xs], letters[ty, tx]
        reads = (b != a) & (b != 0) if event else np.ones_like(b, bool)
        for q in np.nonzero(live)[0]:
            t = np.where(reads, delta[q, b], q)
            keep = ~rejecting[t]
            rows.append(q * ny * nx + cell[ys[keep], xs[keep]])
            cols.append(t[keep] * ny * nx + cell[ty[keep], tx[keep]])
            weights.append(np.full(int(keep.sum()), resolution * math.hypot(dy, dx)))
            marks.append((reads & visits[q, b])[keep])
    n = n_states * ny * nx
    return (np.concatenate(rows), np.concatenate(cols), np.concatenate(weights), np.concatenate(marks), n,
            q0 * ny * nx + cell[iy, ix], ny * nx)
