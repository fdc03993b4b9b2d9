"""The shortest continuous routes of a two-area patrol that keep a margin: what any policy could score.

    .venv/bin/python bench/route_bound.py [--layout paper] [--areas A1 A3] [--forbid A4]
                                          [--margins 0.15 0.25 0.3] [--steps 600]

A patrol ``GF X & GF Y & G !Z...`` (``patrol2`` is ``GF A1 & GF A3 & G !A4``) makes an accepting
visit each time the robot, having been in X, enters Y. For each margin c this script finds the
shortest routes for the robot's centre that keep c from every box and wall and never enter a
forbidden area: from the start to X and on to Y (the first visit), then Y -> X -> Y (each lap).
It works in the plane, not on a grid: a visibility graph over polygons that enclose each box grown
by c (their edges tangent to its rounded corners), the forbidden disks, and points on the targets'
rims; Dijkstra (scipy) chains the legs. The polygons lie just outside the true grown boxes, so the
lengths are upper bounds of the exact ones, within 0.1%.

``routes.visit_lengths`` (the route-optimal count of summary.json and ``bench/patrol_laps.py``)
searches an 8-neighbour grid instead, whose routes are up to 8.2% longer; it allows for that
excess when it counts visits. This script needs no such allowance. For each margin it prints the
first visit and the lap in metres, and at which step each visit could come at the most speed the
dynamics allow on average (v_max · v_gain · (1 - slip / 2) · dt; turning, braking and reversing
cost nothing here), and how many fit in ``--steps``. ``--forward-only`` also counts the visits of a
robot that cannot reverse and turns round in place at each area (pi at the most turn rate the
dynamics allow on average: 13.6 steps), as the generalist's forward-only actor must; it is an
estimate, not a bound (a loop with room to swing round may turn while it drives).
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from d2spo.envs import layouts
from d2spo.envs.dynamics import PRESETS


def _rounded_box(center, half, c: float, per_corner: int) -> np.ndarray:
    """[m, 2] convex polygon, counter-clockwise, enclosing the box grown by c: its corner arcs'
    tangents at ``per_corner`` + 1 angles each (so the polygon lies outside the true set)."""
    step = (math.pi / 2) / per_corner
    r = c / math.cos(step / 2)  # vertices at this radius give edges tangent to the arc of radius c
    pts = []
    for k, (sx, sy) in enumerate(((1, 1), (-1, 1), (-1, -1), (1, -1))):
        corner = np.array([center[0] + sx * half[0], center[1] + sy * half[1]])
        for j in range(per_corner):
            a = k * math.pi / 2 + (j + 0.5) * step
            pts.append(corner + r * np.array([math.cos(a), math.sin(a)]))
    return np.asarray(pts)


def _disk(center, radius: float, n: int) -> np.ndarray:
    """[n, 2] polygon, counter-clockwise, enclosing the disk (edges tangent to it)."""
    r = radius / math.cos(math.pi / n)
    a = (np.arange(n) + 0.5) * 2 * math.pi / n
    return np.stack([center[0] + r * np.cos(a), center[1] + r * np.sin(a)], axis=1)


def _blocked(p: np.ndarray, q: np.ndarray, poly: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """bool [S]: segment p[s] -> q[s] passes through the open interior of the convex ``poly``
    (separating axes: the polygon's edge normals and the segment's normal)."""
    edges = np.roll(poly, -1, axis=0) - poly
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)  # [m, 2]
    proj_poly = poly @ normals.T  # [m, m]: vertex i on axis j
    lo, hi = proj_poly.min(0), proj_poly.max(0)  # [m]
    pp, qp = p @ normals.T, q @ normals.T  # [S, m]
    sep = (np.maximum(pp, qp) <= lo + eps) | (np.minimum(pp, qp) >= hi - eps)
    blocked = ~sep.any(axis=1)
    d = q - p
    n_seg = np.stack([d[:, 1], -d[:, 0]], axis=1)  # [S, 2]
    vp = n_seg @ poly.T  # [S, m]
    sp = np.einsum("sk,sk->s", n_seg, p)
    scale = np.linalg.norm(n_seg, axis=1) + 1e-12
    sep2 = (vp.max(1) <= sp + eps * scale) | (vp.min(1) >= sp - eps * scale)
    return blocked & ~sep2


def _inside(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """bool [P]: strictly inside the convex counter-clockwise ``poly``."""
    edges = np.roll(poly, -1, axis=0) - poly
    rel = points[:, None, :] - poly[None, :, :]
    cross = edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]
    return (cross > 1e-9).all(axis=1)


def bound(layout, areas: tuple[str, str], forbid: list[str], c: float, per_corner: int = 16,
          rim: int = 180, forbid_margin: float = 0.0) -> tuple[float, float]:
    """(first visit, lap) in metres for margin c: start -> X -> Y, then Y -> X -> Y. The centre
    keeps ``forbid_margin`` from the forbidden areas' rims too (0: it may touch them)."""
    by_name = {a.name: a for a in layout.areas}
    polys = [_rounded_box(o.center, o.half_extents, c, per_corner) for o in layout.obstacles]
    polys += [_disk(by_name[z].center, by_name[z].radius + forbid_margin, 4 * per_corner) for z in forbid]
    w, h = layout.arena
    targets = []
    for name in areas:
        a = by_name[name]
        t = np.arange(rim) * 2 * math.pi / rim
        targets.append(np.stack([a.center[0] + (a.radius - 1e-6) * np.cos(t),
                                 a.center[1] + (a.radius - 1e-6) * np.sin(t)], axis=1))
    start = np.array([layout.start[:2]])
    nodes = np.concatenate([start, *targets, *polys])
    keep = (nodes[:, 0] >= c) & (nodes[:, 0] <= w - c) & (nodes[:, 1] >= c) & (nodes[:, 1] <= h - c)
    for poly in polys:
        keep &= ~_inside(nodes, poly)
    keep[0] = True
    index = np.cumsum(keep) - 1
    n_x = len(targets[0])
    x_ids = index[1:1 + n_x][keep[1:1 + n_x]]
    y_ids = index[1 + n_x:1 + 2 * n_x][keep[1 + n_x:1 + 2 * n_x]]
    nodes = nodes[keep]
    n = len(nodes)
    i, j = np.triu_indices(n, 1)
    ok = np.ones(len(i), bool)
    for poly in polys:
        ok &= ~_blocked(nodes[i], nodes[j], poly)
    i, j = i[ok], j[ok]
    length = np.linalg.norm(nodes[i] - nodes[j], axis=1)
    # one extra node, a source joined to given nodes at given costs, chains the legs
    src = n

    def leg(costs: np.ndarray, from_ids: np.ndarray) -> np.ndarray:
        reached = np.isfinite(costs)
        if not reached.any():
            return np.full(n, np.inf)  # nothing to start from: no route keeps c
        costs, from_ids = costs[reached], from_ids[reached]
        base = costs.min()
        rows = np.concatenate([i, j, np.full(len(from_ids), src)])
        cols = np.concatenate([j, i, from_ids])
        vals = np.concatenate([length, length, costs - base + 1e-12])
        graph = csr_matrix((vals, (rows, cols)), shape=(n + 1, n + 1))
        return dijkstra(graph, indices=src)[:n] + base

    d0 = leg(np.zeros(1), np.array([0]))
    at_x = leg(d0[x_ids], x_ids)
    at_y = leg(at_x[y_ids], y_ids)
    first = float(at_y[y_ids].min())
    if not math.isfinite(first):
        return math.inf, math.inf  # no route keeps c (not inf - inf = nan)
    back_x = leg(at_y[y_ids], y_ids)
    second = leg(back_x[x_ids], x_ids)
    lap = float(second[y_ids].min()) - first
    return first, lap


def visits_fit(first: float, lap: float, per_step: float, steps: int, turn_steps: float = 0.0) -> int:
    """Visits in ``steps`` steps at ``per_step`` metres a step; ``turn_steps`` > 0: a robot that
    cannot reverse turns round in place at each area, once before the first visit and twice a lap."""
    first_steps = first / per_step + turn_steps
    if first_steps > steps:
        return 0
    return 1 + int((steps - first_steps) // (lap / per_step + 2 * turn_steps))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--layout", default="paper")
    ap.add_argument("--layout-seeds", type=int, default=1,
                    help="with --layout FAMILY:SEED, this many consecutive seeds of the family")
    ap.add_argument("--areas", nargs=2, default=["A1", "A3"])
    ap.add_argument("--forbid", nargs="*", default=["A4"])
    ap.add_argument("--margins", type=float, nargs="*", default=[0.15, 0.25, 0.3])
    ap.add_argument("--forbid-margin", type=float, default=0.0,
                    help="keep this much from the forbidden areas too (0.06 closes paper's openings beside A4 at 0.3 m)")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--dynamics", default="default", choices=sorted(PRESETS))
    ap.add_argument("--forward-only", action="store_true",
                    help="also count the visits of a robot that turns round in place at each area instead of reversing")
    args = ap.parse_args()
    names = [args.layout]
    if args.layout_seeds > 1:
        drawn = layouts.random_seed(args.layout)
        if drawn is None:
            raise SystemExit(f"route_bound.py: --layout-seeds needs a drawn layout KIND:SEED, got {args.layout!r}")
        names = [f"{drawn[0]}:{drawn[1] + k}" for k in range(args.layout_seeds)]
    dyn = PRESETS[args.dynamics]
    per_step = dyn.v_max * dyn.v_gain * (1 - dyn.slip / 2) * dyn.dt
    # the heading turns by pi at the most turn rate the dynamics allow on average
    turn_steps = math.pi / (dyn.omega_max * dyn.omega_gain * (1 - dyn.slip / 2)) / dyn.dt
    print(f"GF {args.areas[0]} & GF {args.areas[1]}{''.join(f' & G !{z}' for z in args.forbid)}; "
          f"{args.steps} steps of at most {per_step:.4f} m; {args.forbid_margin} m kept from forbidden areas"
          + (f"; turning round in place takes {turn_steps:.1f} steps" if args.forward_only else ""))
    ratios: dict[float, list[float]] = {c: [] for c in args.margins}
    for name in names:
        layout = layouts.load(name)
        for c in args.margins:
            first, lap = bound(layout, tuple(args.areas), args.forbid, c, forbid_margin=args.forbid_margin)
            if not math.isfinite(first + lap):
                # no visits to compare: the layout is left out of the forward-only average
                print(f"{name}, margin {c:.2f} m: no route keeps it (an opening the patrol needs is narrower)")
                continue
            at = [math.ceil((first + k * lap) / per_step) for k in range(6)]
            fit = visits_fit(first, lap, per_step, args.steps)
            line = (f"{name}, margin {c:.2f} m: first visit {first:.3f} m, lap {lap:.3f} m; visits at steps "
                    f"{', '.join(map(str, at))}; {fit} fit in {args.steps}")
            if args.forward_only:
                fwd = visits_fit(first, lap, per_step, args.steps, turn_steps)
                line += f"; forward only {fwd}" + (f" ({100 * fwd / fit:.1f}%)" if fit else "")
                if fit:
                    ratios[c].append(fwd / fit)
            print(line)
    if args.forward_only and len(names) > 1:
        for c, r in ratios.items():
            print(f"margin {c:.2f} m: forward only, {100 * sum(r) / max(1, len(r)):.1f}% of the visits on average "
                  f"over the {len(r)} layouts with any")


if __name__ == "__main__":
    main()
