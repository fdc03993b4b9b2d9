"""The largest clearance a task's routes keep from obstacles and walls, per (task, layout).

    .venv/bin/python bench/barrier_margin.py [--tasks phi1 phi2 ...] [--layouts paper random:100012 ...]

For each pair, ``routes.route_length`` with the robot's radius replaced by a clearance m,
bisected (``--halvings`` times over [``--low``, ``--high``] m; ``>= high`` when even that leaves one) for the largest m that still leaves
a route that completes the task: the clearance from every obstacle and wall the task lets a robot
keep. D²SPO's barrier keeps about d = 0.3 m (``--cbf.d``); ``preflight.check_margin`` warns
below it. Prints one row per pair (``-`` when even the robot's radius leaves no route).
"""

from __future__ import annotations

import argparse
import math

from d2spo.envs import routes
from d2spo.envs.layouts import load
from d2spo.ltl import task_formula, translate


def largest_clearance(task: str, layout: str, low: float, high: float, halvings: int) -> float | None:
    aut, lay = translate(task_formula(task)), load(layout)
    if not math.isfinite(routes.route_length(aut, lay, "event", low)):
        return None
    if math.isfinite(routes.route_length(aut, lay, "event", high)):
        return high  # printed as ">= high"
    for _ in range(halvings):
        mid = 0.5 * (low + high)
        if math.isfinite(routes.route_length(aut, lay, "event", mid)):
            low = mid
        else:
            high = mid
    return low


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", nargs="+", default=["phi1", "phi2", "strict4", "never-a4"])
    ap.add_argument("--layouts", nargs="+", default=["paper", "random:100007", "random:100008", "random:100010",
                                                      "random:100012"])
    ap.add_argument("--low", type=float, default=0.15, help="the robot's radius (m)")
    ap.add_argument("--high", type=float, default=0.45)
    ap.add_argument("--halvings", type=int, default=7)
    args = ap.parse_args()
    print("| task | layout | largest clearance of a route (m) |\n|---|---|---:|")
    for layout in args.layouts:
        for task in args.tasks:
            m = largest_clearance(task, layout, args.low, args.high, args.halvings)
            shown = "-" if m is None else (f">= {m:.3f}" if m == args.high else f"{m:.3f}")
            print(f"| `{task}` | `{layout}` | {shown} |", flush=True)


if __name__ == "__main__":
    main()
