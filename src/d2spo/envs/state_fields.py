"""The shaping distance per automaton state, and the check that a task can be done on a layout.

The default shaping potential (``envs.geodesic``) measures the path to the nearest area whose
entry makes progress, round the obstacles but straight through every area, and the same in every
automaton state. For phi2 on ``paper`` that path leads from A1 to A3 through A4, whose entry there
rejects the task (docs/ltl.md, "Reward"). With ``shaping_metric="geodesic-per-state"`` the
potential reads instead one field per automaton state q, computed here once per layout:

* every grid node carries the letter the robot would produce there (the areas whose disk holds
  the node, true radii); reading letter a in state q is a *target* when it leads to a state
  strictly closer to acceptance, *forbidden* when it leads to a rejecting state or farther from
  acceptance, *neutral* otherwise (e.g. it stays in q). Working on letters, not on areas, makes
  overlapping areas exact (the lens of A1 and A2 is the letter {A1, A2});
* the field is the length of the shortest path to a target read that makes no forbidden read. A
  move between neighbouring nodes reads the letter of the node it enters under ``step``
  labelling, and under ``event`` labelling only when that letter differs from the last one and
  is not empty: so moving inside an area reads nothing. A robot that has just entered an area
  which is forbidden in its new state (A1 in phi2's state "A3 must be next") may therefore leave
  it freely, and a robot inside a target area must leave it and come back (event labelling);
* a forbidden read costs ``BLOCKED_COST`` arena diagonals instead of being impossible, so every
  field is finite; approaching a forbidden node closer than the shaping clearance costs
  ``BLOCKED_COST`` times the approach (leaving costs nothing). A step costs its length times
  the mean of its nodes' multipliers: 1 in the open, ``clearance_cost`` (2) closer than the
  clearance to an obstacle or wall, ``collide_cost`` (100) closer than the robot's radius, the
  tiers of the generalist's field bank (``envs.layout_bank``). The clearance tier is mild because
  a narrow opening lies almost wholly in it: at 10 (until 2026-11-25) the field rose by a metre
  for 0.1 m sideways at a 0.79-m opening's mouth, and the policy dithered there (docs/ltl.md).

Each field is one Dijkstra search (scipy) from the target reads backwards over the directed grid.

``check_task`` searches the product of the automaton and a conservative grid of the positions a
robot of the given radius can occupy (as ``layouts.reachable_grid``), reading letters as the
environment does; it raises ``ConfigError`` when no path reaches acceptance: a proposition that
names no area, a letter the layout cannot produce, or forbidden areas that cut every way to a target.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from d2spo.envs import geodesic, layouts
from d2spo.envs.layouts import Layout
from d2spo.errors import ConfigError, TaskWarning
from d2spo.ltl.automaton import UNREACHABLE, Automaton

NEUTRAL, TARGET, FORBIDDEN = 0, 1, 2
"""Roles of a letter read in a state."""
_SHIFTS8 = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]
_SHIFTS4 = [(-1, 0), (1, 0), (0, -1), (0, 1)]


@dataclass(frozen=True, eq=False)
class StateFields:
    """Per automaton state: its target and forbidden areas and its shaping distance field."""

    targets: tuple[tuple[str, ...], ...]
    """Per state, the areas whose entry (alone) moves the automaton closer to acceptance."""
    forbidden: tuple[tuple[str, ...], ...]
    """Per state, the areas whose entry (alone) rejects the task or moves it farther from acceptance."""
    field: np.ndarray
    """float32 [Q, ny, nx]: path length (m) from each grid node to a target read that avoids the
    forbidden reads (0 in states with no target: accepting, rejecting, dead); nodes as in
    ``envs.geodesic`` (spacing ``geodesic.SPACING``, node (0, 0) at the origin)."""
    target_cells: np.ndarray
    """bool [Q, ny, nx]: nodes whose letter is a target in state q."""
    forbidden_cells: np.ndarray
    """bool [Q, ny, nx]: nodes whose letter is forbidden in state q."""


def letter_roles(aut: Automaton, distance: list[int | None], event: bool) -> np.ndarray:
    """int8 [Q, 2**n_aps]: the role (NEUTRAL, TARGET, FORBIDDEN) of reading each letter in each state.

    ``distance`` is ``aut.distances(feasible_letters)``. States that are accepting, rejecting or
    cannot reach acceptance give every letter NEUTRAL. Under event labelling the empty letter is
    never read, so it is NEUTRAL.
    """
    d = np.array([UNREACHABLE if x is None else x for x in distance], np.int64)
    delta = np.asarray(aut.delta, np.int64).reshape(aut.n_states, aut.n_letters)
    rejecting = np.zeros(aut.n_states, bool)
    rejecting[sorted(aut.rejecting)] = True
    live = (d < UNREACHABLE) & (d > 0)
    target = (d[delta] < d[:, None]) & live[:, None]
    forbidden = (rejecting[delta] | (d[delta] > d[:, None])) & live[:, None]
    roles = np.where(target, TARGET, np.where(forbidden, FORBIDDEN, NEUTRAL)).astype(np.int8)
    if event:
        roles[:, 0] = NEUTRAL
    return roles


def _letters_at(points: np.ndarray, layout: Layout, aps: tuple[str, ...]) -> np.ndarray:
    """int [...]: the letter at each point [..., 2] (bit i <=> the robot centre is inside area aps[i])."""
    out = np.zeros(points.shape[:-1], np.int64)
    for a in layout.areas:
        if a.name in aps:
            inside = np.hypot(points[..., 0] - a.center[0], points[..., 1] - a.center[1]) <= a.radius
            out |= np.where(inside, 1 << aps.index(a.name), 0)
    return out


def _pairs(ny: int, nx: int, shifts) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Per grid shift: flat indices of source and destination nodes and the step length in cells."""
    idx = np.arange(ny * nx).reshape(ny, nx)
    out = []
    for dy, dx in shifts:
        src = idx[max(0, -dy):ny - max(0, dy), max(0, -dx):nx - max(0, dx)]
        dst = idx[max(0, dy):ny - max(0, -dy), max(0, dx):nx - max(0, -dx)]
        out.append((src.ravel(), dst.ravel(), math.hypot(dx, dy)))
    return out


def _field(roles: np.ndarray, letters: np.ndarray, mult: np.ndarray, gap: np.ndarray, in_area: np.ndarray,
           event: bool, margin: float, spacing: float, penalty: float) -> np.ndarray:
    """One state's field [ny, nx]; ``roles`` [2**n_aps] are that state's letter roles."""
    ny, nx = letters.shape
    n = ny * nx
    role = roles[letters].ravel()
    if not np.any(role == TARGET):
        return np.zeros((ny, nx), np.float32)
    forbidden = (role == FORBIDDEN).reshape(ny, nx)
    if forbidden.any() and margin > 0:
        near = ndimage.distance_transform_edt(~forbidden, sampling=spacing)
        depth = np.maximum(margin - near, 0.0).ravel()  # how far inside the keep-out ring
    else:
        depth = np.zeros(n)
    lab, m = letters.ravel(), mult.ravel()
    rows, cols, data = [], [], []  # the transposed graph: an edge dst -> src for each move src -> dst
    sink_cost = np.full(n, np.inf)
    for src, dst, cells in _pairs(ny, nx, _SHIFTS8):
        reads = ((lab[dst] != lab[src]) & (lab[dst] != 0)) if event else np.ones(src.shape, bool)
        hit = reads & (role[dst] == TARGET)
        # a target read ends the path: its cost is the distance from src to the disk of the area entered
        g = np.where(in_area[:, dst[hit]], gap[:, src[hit]], np.inf).min(axis=0)
        np.minimum.at(sink_cost, src[hit], np.maximum(g, 1e-6))
        keep = ~hit
        s, d = src[keep], dst[keep]
        cost = spacing * cells * 0.5 * (m[s] + m[d])
        cost = cost + geodesic.BLOCKED_COST * np.maximum(depth[d] - depth[s], 0.0)
        cost = cost + np.where(reads[keep] & (role[d] == FORBIDDEN), penalty, 0.0)
        rows.append(d)
        cols.append(s)
        data.append(cost)
    if not event:  # standing on a target node reads it again at the next step
        np.minimum.at(sink_cost, np.flatnonzero(role == TARGET), 1e-6)
    ends = np.flatnonzero(np.isfinite(sink_cost))
    rows.append(np.full(ends.shape, n))
    cols.append(ends)
    data.append(sink_cost[ends])
    graph = sparse.csr_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))),
                              shape=(n + 1, n + 1))
    dist = csgraph.dijkstra(graph, directed=True, indices=n)[:n]
    if not np.all(np.isfinite(dist)):  # no target read on the grid
        return np.zeros((ny, nx), np.float32)
    return dist.reshape(ny, nx).astype(np.float32)


_CACHE: dict[tuple, StateFields] = {}
_CACHE_SIZE = 32


def _compute(aut: Automaton, layout: Layout, event: bool, clearance: float, costs: tuple[float, float, float],
             spacing: float) -> StateFields:
    aps = aut.aps
    distance = aut.distances(layouts.feasible_letters(layout, aps, "event" if event else "step"))
    roles = letter_roles(aut, distance, event)
    w, h = layout.arena
    nx, ny = round(w / spacing) + 1, round(h / spacing) + 1
    xs, ys = np.linspace(0.0, w, nx), np.linspace(0.0, h, ny)
    px, py = np.meshgrid(xs, ys)
    letters = _letters_at(np.stack([px, py], -1), layout, aps)
    box_lo = np.array([o.lo for o in layout.obstacles], float).reshape(-1, 2)
    box_hi = np.array([o.hi for o in layout.obstacles], float).reshape(-1, 2)
    robot_radius, clearance_cost, collide_cost = costs
    clear = geodesic.clearance(xs, ys, box_lo, box_hi, layout.arena)
    mult = np.where(clear < robot_radius, collide_cost, np.where(clear < clearance, clearance_cost, 1.0))
    centre_dist = np.stack([np.hypot(px - a.center[0], py - a.center[1]).ravel() for a in layout.areas])
    radius = np.array([a.radius for a in layout.areas])[:, None]
    gap = np.maximum(centre_dist - radius, 0.0)
    in_area = centre_dist <= radius
    penalty = geodesic.BLOCKED_COST * math.hypot(w, h)
    fields = np.stack([_field(roles[q], letters, mult, gap, in_area, event, clearance, spacing, penalty)
                       for q in range(aut.n_states)])
    bits = [aut.letter([a.name]) if a.name in aps else 0 for a in layout.areas]

    def named(role: int) -> tuple[tuple[str, ...], ...]:
        return tuple(tuple(a.name for a, b in zip(layout.areas, bits, strict=True) if b and roles[q, b] == role)
                     for q in range(aut.n_states))

    return StateFields(targets=named(TARGET), forbidden=named(FORBIDDEN), field=fields,
                       target_cells=roles[:, letters] == TARGET, forbidden_cells=roles[:, letters] == FORBIDDEN)


def _key(aut: Automaton, layout: Layout) -> tuple:
    return (aut.aps, aut.initial, tuple(sorted(aut.accepting)), tuple(sorted(aut.rejecting)), aut.delta,
            layout.arena, tuple((o.center, o.half_extents) for o in layout.obstacles),
            tuple((a.name, a.center, a.radius) for a in layout.areas))


def state_fields(aut: Automaton, layout: Layout, label_mode: str, clearance: float, robot_radius: float = 0.0,
                 clearance_cost: float = geodesic.CLEARANCE_COST, collide_cost: float = geodesic.COLLIDE_COST,
                 spacing: float = geodesic.SPACING) -> StateFields:
    """Target and forbidden areas and the shaping distance field of every state of ``aut`` on
    ``layout`` (cached). ``clearance``: the path keeps this far from obstacles, walls and
    forbidden areas where it can (the reward's ``shaping_clearance``): a step costs its length
    times ``clearance_cost`` where a node is closer than ``clearance`` to an obstacle or wall, times
    ``collide_cost`` where it is closer than ``robot_radius`` (the reward's ``shaping_clearance_cost``
    and ``shaping_collide_cost``), and coming closer than ``clearance`` to a forbidden area costs
    ``BLOCKED_COST`` times the approach."""
    nodes = (round(layout.arena[0] / spacing) + 1) * (round(layout.arena[1] / spacing) + 1)
    if nodes > geodesic.MAX_NODES:
        raise ConfigError("layout.arena", f"an arena of {layout.arena[0]:g} m x {layout.arena[1]:g} m needs shaping "
                          f"fields of {nodes} nodes at {spacing:g} m; at most MAX_NODES={geodesic.MAX_NODES} (20 m x "
                          "20 m) are supported: use a smaller arena or layout scale, or --shaping-metric euclidean")
    costs = (float(robot_radius), float(clearance_cost), float(collide_cost))
    key = ("fields", *_key(aut, layout), label_mode, float(clearance), costs, float(spacing))
    return _memo(key, lambda: _compute(aut, layout, label_mode == "event", float(clearance), costs, float(spacing)))


def _memo(key: tuple, compute):
    """``compute()``, cached under ``key`` (the oldest entry goes when ``_CACHE_SIZE`` are held)."""
    if key not in _CACHE:
        if len(_CACHE) >= _CACHE_SIZE:
            del _CACHE[next(iter(_CACHE))]
        _CACHE[key] = compute()
    return _CACHE[key]


def _task_grid(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float):
    """The grid the task checks search: (free [ny, nx], letters [ny, nx], delta [Q, 2**n], resolution,
    start (q0, iy, ix)) with q0 the state after the start cell's letter is read as the env reads it."""
    # 5 cm, finer in arenas under 5 m, coarser above 20 m (at most 400 x 400 cells: route_length
    # searches states x cells)
    resolution = max(min(0.05, max(layout.arena) / 100.0), max(layout.arena) / 400.0)
    free, centres = layouts.free_grid(layout, robot_radius, resolution)
    letters = _letters_at(centres, layout, aut.aps)
    ny, nx = free.shape
    delta = np.asarray(aut.delta, np.int64).reshape(aut.n_states, aut.n_letters)
    iy = min(int(layout.start[1] / resolution), ny - 1)
    ix = min(int(layout.start[0] / resolution), nx - 1)
    first = letters[iy, ix]
    q0 = int(delta[aut.initial, first]) if (first != 0 or label_mode != "event") else aut.initial
    return free, letters, delta, resolution, (q0, iy, ix)


def _reachable(delta: np.ndarray, letters: np.ndarray, free: np.ndarray, start: tuple[int, int, int], event: bool,
               absorbing: list[int]) -> list[bool]:
    """Per automaton state, whether the robot can be in it: a search over (state, grid cell).

    In state q the robot moves freely through the cells whose letter is not read (event labelling:
    the empty letter and the letter of the cell it stands in) or leaves q where it is (delta[q, a] == q);
    so each state's cells are one flood fill (scipy), and every move across the fill's border into
    a cell whose letter leads elsewhere seeds that state there.
    """
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


def check_task(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float, name: str,
               robot: str | None = None) -> None:
    """ConfigError unless a robot of ``robot_radius`` can drive from the start to an accepting state.
    ``robot`` names that robot in the error (default: "a robot of radius R m"); with ``robot_radius``
    set to a barrier's margin it is the check of ``nav.check_barrier_margin``.

    Propositions must name areas of the layout. Then a breadth-first search over (automaton state,
    grid cell), with 4-neighbour moves between cells the robot can occupy (``layouts.free_grid``,
    conservative) and letters read as the environment reads them. The error names the farthest
    state reached and its target and forbidden areas.
    """
    missing = [p for p in aut.aps if p not in layout.area_names]
    if missing:
        raise ConfigError("task", f"{name}: proposition {missing[0]!r} names no area of layout {layout.name!r} "
                          f"(its areas: {', '.join(layout.area_names)})")
    distance = aut.distances(layouts.feasible_letters(layout, aut.aps, label_mode))
    if distance[aut.initial] is None:
        raise ConfigError("task", f"{name} cannot be completed on layout {layout.name!r}: no sequence of the "
                          "letters it can produce (areas entered alone, or together where they overlap) does it")
    free, letters, delta, _, start = _task_grid(aut, layout, label_mode, robot_radius)
    reached = _reachable(delta, letters, free, start, label_mode == "event", sorted(aut.accepting | aut.rejecting))
    open_states = np.ones(aut.n_states, bool)
    open_states[sorted(aut.accepting | aut.rejecting)] = False
    if any(reached[q] for q in aut.accepting):
        return
    live = [q for q in range(aut.n_states) if reached[q] and open_states[q] and distance[q] is not None]
    if not live:
        raise ConfigError("task", f"{name} cannot be completed on layout {layout.name!r}: the first area the robot "
                          "can enter from the start rejects it")
    q = min(live, key=lambda s: (distance[s], s))
    sf = state_fields(aut, layout, label_mode, 0.0)
    goal = " or ".join(sf.targets[q]) or "an area that makes progress"
    why = f" without entering {', '.join(sf.forbidden[q])} (forbidden there)" if sf.forbidden[q] else ""
    raise ConfigError("task", f"{name} cannot be completed on layout {layout.name!r}: in automaton state {q} "
                      f"({aut.state_formulas[q]}) {robot or f'a robot of radius {robot_radius:g} m'} cannot "
                      f"reach {goal}{why}")


def default_fields(aut: Automaton, layout_name: str, label_mode: str):
    """(layout, fields, distances, robot radius) of ``aut`` on a layout as the default environment
    config computes them (robot radius, shaping clearance): what ``d2spo ltl --plot`` draws
    (``plots.state_fields_figure``) before it runs ``check_task``."""
    from d2spo.envs.env_config import EnvConfig

    cfg = EnvConfig(layout=layout_name, label_mode=label_mode).resolved()
    layout = layouts.load(layout_name).scaled(cfg.layout_scale)
    sf = state_fields(aut, layout, label_mode, **cfg.reward.field_costs(cfg.robot_radius))
    distance = aut.distances(layouts.feasible_letters(layout, aut.aps, label_mode))
    return layout, sf, distance, cfg.robot_radius


TIGHT_FRACTION = 0.6
"""``check_time`` warns when the shortest route needs more than this fraction of the episode's steps
at full speed. A trained policy drives more than the shortest route: on `paper` D²SPO's phi1
episodes take a median of 123 steps for a 10.1 m route (1.22x)."""


ROOM = 2.0
"""``default_max_steps`` gives a longer task this many times its shortest route at full speed."""


def _route(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float) -> float:
    key = ("route", *_key(aut, layout), label_mode, float(robot_radius))
    return _memo(key, lambda: route_length(aut, layout, label_mode, robot_radius))


def default_max_steps(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float, dt: float,
                      v_max: float, base: int) -> int:
    """The step limit of ``EnvConfig.max_steps=None``: ``base`` (``EnvConfig.base_max_steps``), or,
    when the task's shortest route at ``v_max`` needs more than ``TIGHT_FRACTION`` of those steps,
    ``ROOM`` times the route's steps rounded up to a multiple of 50 (then over ``base``). ``base``
    too when no route exists (``check_time`` then says so)."""
    need = _route(aut, layout, label_mode, robot_radius) / (v_max * dt)
    if not math.isfinite(need) or need <= TIGHT_FRACTION * base:
        return int(base)
    return int(50 * math.ceil(ROOM * need / 50))


def check_time(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float, max_steps: int, dt: float,
               v_max: float, name: str) -> None:
    """A ``TaskWarning`` when no route completes the task within ``max_steps`` steps at ``v_max``
    (every episode will time out), or when the shortest route needs more than ``TIGHT_FRACTION`` of
    them. A warning, not an error: short episodes are how smoke runs and tests exercise the machinery."""
    length = _route(aut, layout, label_mode, robot_radius)
    need = length / (v_max * dt)
    budget = f"{max_steps} steps of {dt:g} s at {v_max:g} m/s"
    if need / OCTILE_EXCESS > max_steps:  # only what no continuous route could do
        warnings.warn(TaskWarning(
            f"{name} cannot be completed on layout {layout.name!r} within {budget}: its shortest route is "
            f"{length:.1f} m ({math.ceil(need)} steps at full speed), so every episode will time out "
            "(--max-steps raises the limit; unset, it follows the task)"), stacklevel=3)
    elif need > TIGHT_FRACTION * max_steps:
        warnings.warn(TaskWarning(
            f"{name}: the shortest route on layout {layout.name!r} is {length:.1f} m, {math.ceil(need)} of the "
            f"{max_steps} steps at full speed ({need / max_steps:.0%}); a policy that drives about 1.2x the shortest "
            "route may run out of time (--max-steps raises the limit; unset, it follows the task)"), stacklevel=3)


OCTILE_EXCESS = math.sqrt(4 - 2 * math.sqrt(2))
"""The most an 8-neighbour grid path exceeds the straight segment it follows (1.082, at 22.5°)."""


def route_length(aut: Automaton, layout: Layout, label_mode: str, robot_radius: float) -> float:
    """Length (m) of the shortest grid route from the start that completes the task. A robot of
    ``robot_radius`` drives at least ``route_length / OCTILE_EXCESS`` (the grid's 8 directions make a
    route up to 8.2% longer than the continuous one; turning and braking only add to the drive).

    Dijkstra over (automaton state, grid cell): 8-neighbour moves between free cells of
    ``layouts.free_grid`` (a diagonal move also needs its two 4-neighbours free), letters read as the
    environment reads them, rejecting states excluded. ``inf`` when no route exists.
    """
    event = label_mode == "event"
    free, letters, delta, resolution, (q0, iy, ix) = _task_grid(aut, layout, label_mode, robot_radius)
    ny, nx = free.shape
    n_states = aut.n_states
    rejecting = np.zeros(n_states, bool)
    rejecting[sorted(aut.rejecting)] = True
    live = ~rejecting
    live[sorted(aut.accepting)] = False
    cell = np.arange(ny * nx).reshape(ny, nx)
    rows, cols, weights = [], [], []
    for dy, dx in _SHIFTS8:
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
    n = n_states * ny * nx
    graph = sparse.csr_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    if q0 in aut.accepting:
        return 0.0
    dist = csgraph.dijkstra(graph, indices=q0 * ny * nx + cell[iy, ix])
    return float(min(dist[q * ny * nx:(q + 1) * ny * nx].min() for q in aut.accepting)) if aut.accepting else math.inf
