"""The shaping distance per automaton state: the path to what makes progress, round what rejects the task.

The default shaping potential (``envs.geodesic``) measures the path to the nearest area whose
entry makes progress, round the obstacles but straight through every area, and the same in every
automaton state. For phi2 on ``paper`` that path leads from A1 to A3 through A4, whose entry there
rejects the task (docs/ltl.md, "Reward"). With ``shaping_metric="geodesic-per-state"`` the
potential reads instead one field per automaton state q, computed here once per compiled task
(``envs.compiled_task``):

* every grid node carries the letter the robot would produce there (the labels of the areas whose
  disk holds the node, true radii); reading letter a in state q is a *target* when it leads to a state
  strictly closer to acceptance, *forbidden* when it leads to a rejecting state or farther from
  acceptance, *neutral* otherwise (e.g. it stays in q; ``letter_roles``). Working on letters, not
  on areas, makes overlapping areas exact (the lens of A1 and A2 is the letter {A1, A2});
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
  a narrow opening lies almost wholly in it: a steep one makes the field rise sharply sideways at
  an opening's mouth, where the policy then dithers (docs/ltl.md).

Each field is one Dijkstra search (scipy) from the target reads backwards over the directed grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from d2spo.envs import geodesic
from d2spo.envs.layouts import letters_at
from d2spo.envs.workspace import Layout
from d2spo.errors import ConfigError
from d2spo.ltl.automaton import UNREACHABLE, Automaton
from d2spo.ltl.buchi_task import BuchiTask

NEUTRAL, TARGET, FORBIDDEN = 0, 1, 2
"""Roles of a letter read in a state."""
_SHIFTS = {8: geodesic.NEIGHBOURS8,
           16: geodesic.NEIGHBOURS8 + tuple((dy, dx) for dy in (-2, -1, 1, 2) for dx in (-2, -1, 1, 2) if abs(dy) != abs(dx))}
"""The grid moves per ``neighbours``: 16 adds knight moves, a path at most 2.7% longer than its segment."""


@dataclass(frozen=True, eq=False)
class StateFields:
    """Per automaton state: its target and forbidden areas and its shaping distance field."""

    targets: tuple[tuple[str, ...], ...]
    """Per state, the areas (names; every area of a label) whose entry (alone) moves the automaton
    closer to acceptance."""
    forbidden: tuple[tuple[str, ...], ...]
    """Per state, the areas (names) whose entry (alone) rejects the task or moves it farther from acceptance."""
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
    never read, so it is NEUTRAL. A Büchi task's accepting visit (``BuchiTask.visits``) is a TARGET,
    although the distance restarts after it.
    """
    d = np.array([UNREACHABLE if x is None else x for x in distance], np.int64)
    delta = np.asarray(aut.delta, np.int64).reshape(aut.n_states, aut.n_letters)
    rejecting = np.zeros(aut.n_states, bool)
    rejecting[sorted(aut.rejecting)] = True
    live = (d < UNREACHABLE) & (d > 0)
    target = (d[delta] < d[:, None]) & live[:, None]
    if isinstance(aut, BuchiTask):
        target = target | np.asarray(aut.visits, bool).reshape(delta.shape)
    forbidden = (rejecting[delta] | (d[delta] > d[:, None])) & live[:, None]
    roles = np.where(target, TARGET, np.where(forbidden, FORBIDDEN, NEUTRAL)).astype(np.int8)
    if event:
        roles[:, 0] = NEUTRAL
    return roles


def named_areas(aut: Automaton, layout: Layout, roles: np.ndarray, role: int) -> tuple[tuple[str, ...], ...]:
    """Per automaton state, the areas of ``layout`` whose entry alone has ``role`` (``TARGET`` or
    ``FORBIDDEN``) there, by name: every area of each label that has it; ``roles`` is
    ``letter_roles``. Areas whose label is no proposition of ``aut`` have none."""
    bits = [aut.letter([a.label]) if a.label in aut.aps else 0 for a in layout.areas]
    return tuple(tuple(a.name for a, b in zip(layout.areas, bits, strict=True) if b and roles[q, b] == role)
                 for q in range(aut.n_states))


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
           event: bool, margin: float, spacing: float, penalty: float, shifts=_SHIFTS[8]) -> np.ndarray:
    """One state's field [ny, nx]; ``roles`` [2**n_aps] are that state's letter roles; ``shifts`` the grid moves."""
    from scipy import ndimage, sparse  # scipy: imported when first needed, not with d2spo
    from scipy.sparse import csgraph
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
    for src, dst, cells in _pairs(ny, nx, shifts):
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


def state_fields(aut: Automaton, layout: Layout, roles: np.ndarray, label_mode: str, clearance: float,
                 robot_radius: float = 0.0, clearance_cost: float = geodesic.CLEARANCE_COST,
                 collide_cost: float = geodesic.COLLIDE_COST, spacing: float = geodesic.SPACING,
                 neighbours: int = 8) -> StateFields:
    """The shaping distance field of every state of ``aut`` on ``layout``, ``roles`` being its
    ``letter_roles``. ``clearance``: the path keeps this far from obstacles, walls and forbidden
    areas where it can (the reward's ``shaping_clearance``): a step costs its length times
    ``clearance_cost`` where a node is closer than ``clearance`` to an obstacle or wall, times
    ``collide_cost`` where it is closer than ``robot_radius`` (the reward's ``shaping_clearance_cost``
    and ``shaping_collide_cost``), and coming closer than ``clearance`` to a forbidden area costs
    ``BLOCKED_COST`` times the approach. ``neighbours``: the grid moves, 8 or 16 (knight moves too:
    a step's cost reads its two end nodes only, which at ``SPACING`` cannot jump a robot-radius band
    or an area; the reward's ``shaping_neighbours``). ConfigError when the arena needs more than
    ``geodesic.MAX_NODES`` nodes."""
    nodes = (round(layout.arena[0] / spacing) + 1) * (round(layout.arena[1] / spacing) + 1)
    if nodes > geodesic.MAX_NODES:
        raise ConfigError("layout.arena", f"an arena of {layout.arena[0]:g} m x {layout.arena[1]:g} m needs shaping "
                          f"fields of {nodes} nodes at {spacing:g} m; at most MAX_NODES={geodesic.MAX_NODES} (20 m x "
                          "20 m) are supported: draw the layout smaller, or train on it alone with --shaping-metric euclidean "
                          "(a generalist always needs the fields); is the layout in metres?")
    event = label_mode == "event"
    clearance, spacing, robot_radius = float(clearance), float(spacing), float(robot_radius)
    clearance_cost, collide_cost = float(clearance_cost), float(collide_cost)
    w, h = layout.arena
    nx, ny = round(w / spacing) + 1, round(h / spacing) + 1
    xs, ys = np.linspace(0.0, w, nx), np.linspace(0.0, h, ny)
    px, py = np.meshgrid(xs, ys)
    letters = letters_at(np.stack([px, py], -1), layout, aut.aps)
    box_lo = np.array([o.lo for o in layout.boxes], float).reshape(-1, 2)
    box_hi = np.array([o.hi for o in layout.boxes], float).reshape(-1, 2)
    clear = geodesic.clearance(xs, ys, box_lo, box_hi, layout.arena, [(*d.center, d.radius) for d in layout.disks])
    mult = np.where(clear < robot_radius, collide_cost, np.where(clear < clearance, clearance_cost, 1.0))
    centre_dist = np.stack([np.hypot(px - a.center[0], py - a.center[1]).ravel() for a in layout.areas])
    radius = np.array([a.radius for a in layout.areas])[:, None]
    gap = np.maximum(centre_dist - radius, 0.0)
    in_area = centre_dist <= radius
    penalty = geodesic.BLOCKED_COST * math.hypot(w, h)
    if neighbours not in _SHIFTS:
        raise ConfigError("reward.shaping_neighbours", f"must be one of {list(_SHIFTS)}, got {neighbours!r}")
    fields = np.stack([_field(roles[q], letters, mult, gap, in_area, event, clearance, spacing, penalty,
                              _SHIFTS[neighbours])
                       for q in range(aut.n_states)])
    return StateFields(targets=named_areas(aut, layout, roles, TARGET), forbidden=named_areas(aut, layout, roles, FORBIDDEN),
                       field=fields, target_cells=roles[:, letters] == TARGET,
                       forbidden_cells=roles[:, letters] == FORBIDDEN)
