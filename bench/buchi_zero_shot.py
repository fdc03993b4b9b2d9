"""Generalists zero-shot on the Büchi suite (issue 34's generalist targets): one row per run, then the mean.

    .venv/bin/python bench/buchi_zero_shot.py --runs GEN-s0 GEN-s1 ... [--tasks patrol2 patrol3 respond reach-never]
        [--layouts 20] [--first-seed 100000] [--episodes 50] [--max-steps N] [--forbidden-range R]
        [--results bench/RESULTS.md]

Each run is a ``d2spo train --algo d2spo --generalist`` directory (train them first, one seed each:
``d2spo train --algo d2spo --generalist --task phi1 --seed S --out GEN-sS``). Each task runs as
``d2spo eval RUN --task T --layout random:FIRST --layout-seeds N --episodes E`` does: the validated
policy, the runtime filter on. An evaluation that RUN already holds with those settings (the JSON
``d2spo eval`` writes into it) is read instead of run again. A patrol is scored by its accepting
visits as a fraction of each layout's route-optimal count, averaged over the layouts; a task with a
never part by its completion. Prints a Markdown table (appended to ``--results`` with the date and
machine; '-' prints only), then per patrol the same average over only the layouts where some route
keeps the barrier's margin d (``route_optimal_visits_margin`` > 0; a hint, not the issue's measure:
on the others the barrier may hold the robot back by design), and a table per layout (the mean over
the runs). Figures in bench/RESULTS.md, "2026-11-29, night" and "late night".

``--handmade`` evaluates the same way on layouts no generator drew (tests/data/layouts/ and its
handmade/): the suite on each hand-made layout with areas A1..A4, and on each layout with its own
labels (rooms, docks, stairs) a patrol and a reach-with-a-never-part of its own (``OWN_TASKS``). A
case the checks refuse (no route, a limit too short) is a line, not a figure. Printed beside the
generator's table, one row per (layout, task).
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys
from pathlib import Path

from d2spo.evalfiles import write_evaluation
from d2spo.evaluate import EvalConfig, evaluate_run
from d2spo.report import cpu_model
from d2spo.run import load_run_config
from d2spo.zero_shot import seen_forbidden_range

TASKS = ("patrol2", "patrol3", "respond", "reach-never")
DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "layouts"
OWN_TASKS = {  # a hand-made layout with labels of its own: a patrol, then a reach with a never part
    "lab-6x4": ("GF lab1 & GF dock & G !stairs", "GF lab1 & GF lab2 & G !stairs", "G !stairs & F (lab1 & F lab2)"),
    "lab-12x6": ("GF desk & GF kitchen", "G !door & F (desk & F kitchen)"),
    "warehouse-16": ("GF dock & GF A1 & G !A2", "G !A2 & F (dock & F A1)"),
    "rooms-12x8": ("GF dock & GF lab & G !hazard", "G !hazard & F (storage & F office)"),
    "twelve-areas": ("GF printer & GF desk & G !server", "G !server & F (kitchen & F lounge)"),
    "office": ("GF desk & GF kitchen", "F (kitchen & F desk)"),
}


def _matches(res: dict, cfg: EvalConfig, seen: float) -> bool:
    """Whether a stored evaluation is the one ``cfg`` asks for (the validated policy, the filter on),
    ``seen`` the forbidden range it runs with (``_seen_range``): a file written before ``d2spo eval``'s
    default range changed is evaluated again."""
    return (res.get("task") == cfg.task and res.get("layouts") == cfg.layouts()
            and res.get("episodes") == cfg.episodes * cfg.layout_seeds and res.get("seed") == cfg.seed
            and res.get("runtime_filter") is True and res.get("dynamics") == "default"
            and str(res.get("policy", "")).startswith("best")
            and (res.get("max_steps") == cfg.max_steps if res.get("max_steps_given") else cfg.max_steps is None)
            and _range(res.get("forbidden_range")) == seen)


def _seen_range(run: Path, cfg: EvalConfig) -> float:
    """The forbidden range ``d2spo eval`` runs ``run`` with under ``cfg`` (``zero_shot.seen_forbidden_range``)."""
    return _range(seen_forbidden_range(load_run_config(run).env, cfg.forbidden_range).forbidden_range)


def _range(r: float | None) -> float:
    """A stored evaluation's forbidden range as ``--forbidden-range`` gives it (None: ``inf``)."""
    return float("inf") if r is None else r


def evaluation(run: Path, cfg: EvalConfig) -> dict:
    seen = _seen_range(run, cfg)
    for path in sorted(run.glob("eval-*.json")):
        res = json.loads(path.read_text())
        if _matches(res, cfg, seen):
            return res
    res = evaluate_run(run, cfg)
    write_evaluation(run, res)
    return res


def score(res: dict) -> float:
    """A patrol's fraction of the route-optimal visits; else the completion rate."""
    return res["visit_fraction"] if "visit_fraction" in res else res["completion_rate"]


def fraction(layout: dict) -> float:
    """One layout's accepting visits per episode as a fraction of its route-optimal count."""
    return layout["accepting_visits_per_episode"] / max(layout["route_optimal_visits"], 1)


def passable(res: dict) -> tuple[float, int] | None:
    """A patrol's mean fraction over the layouts where a route keeps the barrier's margin, and their
    number; None for a task that completes or an evaluation without the margin's counts."""
    per = res.get("per_layout") or []
    kept = [r for r in per if r.get("route_optimal_visits") and r.get("route_optimal_visits_margin", 0) > 0]
    if "visit_fraction" not in res or not kept:
        return None
    return sum(map(fraction, kept)) / len(kept), len(kept)


def margin_lines(runs: list[Path], tasks: list[str], results: dict) -> list[str]:
    """Per patrol: each run's average over the layouts a route keeping the margin d passes."""
    lines = []
    for t in tasks:
        got = [(run, passable(results[run, t])) for run in runs]
        if any(g is None for _, g in got):
            continue
        cells = ", ".join(f"{run.name} {100 * f:.1f}% of {n} (d = {results[run, t]['per_layout'][0].get('margin')} m)"
                          for run, (f, n) in got)
        mean = sum(f for _, (f, _) in got) / len(got)
        lines.append(f"- `{t}` over the layouts where a route keeps the barrier's margin: {cells}; mean **{100 * mean:.1f}%**")
    return lines


def per_layout(runs: list[Path], tasks: list[str], results: dict) -> str:
    """Per layout and patrol: the mean over the runs of its fraction, and its route-optimal counts
    (keeping the robot's radius / the first run's margin)."""
    patrols = [t for t in tasks if all("visit_fraction" in results[run, t] for run in runs)]
    if not patrols:
        return ""
    first = [results[runs[0], t]["per_layout"] for t in patrols]
    lines = ["| layout | " + " | ".join(f"`{t}` (optimum / keeping d)" for t in patrols) + " |",
             "|---" * (len(patrols) + 1) + "|"]
    for i, row in enumerate(first[0]):
        cells = []
        for t, rows in zip(patrols, first):
            mean = sum(fraction(results[run, t]["per_layout"][i]) for run in runs) / len(runs)
            cells.append(f"{100 * mean:.1f}% ({rows[i]['route_optimal_visits']} / {rows[i].get('route_optimal_visits_margin', '-')})")
        lines.append(f"| {row['layout']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table(runs: list[Path], tasks: list[str], results: dict) -> str:
    head = "| run | " + " | ".join(f"`{t}`" for t in tasks) + " | safe (every task) |"
    lines = [head, "|---" * (len(tasks) + 2) + "|"]
    for run in runs:
        rs = [results[run, t] for t in tasks]
        cells = [f"{100 * score(r):.1f}%" for r in rs]
        lines.append(f"| {run.name} | " + " | ".join(cells) + f" | {100 * min(r['safety_rate'] for r in rs):.2f}% |")
    means = [sum(score(results[run, t]) for run in runs) / len(runs) for t in tasks]
    worst = min(results[run, t]["safety_rate"] for run in runs for t in tasks)
    lines.append(f"| mean of {len(runs)} | " + " | ".join(f"**{100 * m:.1f}%**" for m in means) + f" | {100 * worst:.2f}% |")
    return "\n".join(lines)


def handmade_cases(tasks: list[str]) -> list[tuple[Path, str]]:
    """(layout file, task) of ``--handmade``: ``tasks`` on each hand-made layout labelled A1..A4, the
    ``OWN_TASKS`` on the others; a layout with neither (``lens``: three areas) is left out."""
    cases = []
    for path in sorted(DATA.glob("*.json")) + sorted((DATA / "handmade").glob("*.json")):
        labels = {a.get("label", a.get("name")) for a in json.loads(path.read_text()).get("areas", [])}
        own = OWN_TASKS.get(path.stem)
        if own is not None:
            cases += [(path, t) for t in own]
        elif {"A1", "A2", "A3", "A4"} <= labels:
            cases += [(path, t) for t in tasks]
    return cases


def handmade_table(runs: list[Path], cases: list[tuple[Path, str]], episodes: int, max_steps: int | None,
                   forbidden_range: float | None = None) -> str:
    """One row per hand-made case: each run's fraction of the route-optimal visits (a patrol) or
    completion, its safety; then the mean over the patrols and over the rest."""
    from d2spo.errors import UserError

    lines = ["| layout | task | " + " | ".join(f"{run.name}: score / safe" for run in runs) + " |",
             "|---|---" + "|---" * len(runs) + "|"]
    scores: dict[bool, list[float]] = {True: [], False: []}
    safe = []
    for path, task in cases:
        cells = []
        for run in runs:
            cfg = EvalConfig(episodes, str(path), task=task, runtime_filter=True, max_steps=max_steps,
                             forbidden_range=forbidden_range)
            try:
                res = evaluation(run, cfg)
            except UserError as e:
                cells.append(f"refused: {e}")
                continue
            patrol = "visit_fraction" in res
            scores[patrol].append(score(res))
            safe.append(res["safety_rate"])
            optimum = f" of {res['per_layout'][0]['route_optimal_visits']}" if patrol else " complete"
            cells.append(f"{100 * score(res):.1f}%{optimum} / {100 * res['safety_rate']:.2f}%")
            print(f"{run.name} {path.stem} {task!r}: {cells[-1]}", flush=True)
        lines.append(f"| {path.stem} | `{task}` | " + " | ".join(cells) + " |")
    mean = lambda xs: f"**{100 * sum(xs) / len(xs):.1f}%** ({len(xs)} case-runs)" if xs else "-"  # noqa: E731
    lines.append("")
    lines.append(f"Patrols: mean fraction of the route-optimal visits {mean(scores[True])}; the rest: mean "
                 f"completion {mean(scores[False])}; safety at worst {100 * min(safe, default=1.0):.2f}%.")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, nargs="+", required=True)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS))
    ap.add_argument("--layouts", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=100000)
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--max-steps", type=int, default=None,
                    help="episode limit (d2spo eval --max-steps); default: each layout's, as d2spo eval")
    ap.add_argument("--forbidden-range", type=float, default=None,
                    help="d2spo eval --forbidden-range R: a forbidden area seen only within R m (inf: at any "
                         "distance); default: as d2spo eval, the run's own range, else the robot's lidar range")
    ap.add_argument("--results", default="bench/RESULTS.md")
    ap.add_argument("--handmade", action="store_true",
                    help="also the hand-made layouts of tests/data/layouts (the module docstring)")
    ap.add_argument("--cases", type=int, default=None, help="with --handmade: the first N cases only (a check)")
    args = ap.parse_args()
    from d2spo import compile_cache

    compile_cache.enable()  # the commands' cache: a layout's rollout compiled once serves every run
    results = {}
    for run in args.runs:
        for task in args.tasks:
            cfg = EvalConfig(args.episodes, f"random:{args.first_seed}", task=task, layout_seeds=args.layouts,
                             runtime_filter=True, max_steps=args.max_steps, forbidden_range=args.forbidden_range)
            results[run, task] = evaluation(run, cfg)
            print(f"{run.name} {task}: {100 * score(results[run, task]):.1f}%", flush=True)
    limit = "" if args.max_steps is None else f" of {args.max_steps} steps"
    seen = "; a forbidden area seen as `d2spo eval` sees it by default" if args.forbidden_range is None else (
        "; a forbidden area always seen" if args.forbidden_range == float("inf")
        else f"; a forbidden area seen within {args.forbidden_range:g} m")
    text = (f"Generalists zero-shot on random:{args.first_seed}..+{args.layouts - 1}, {args.episodes} episodes{limit} "
            f"each, filter on{seen} ({datetime.date.today()}, {platform.machine()}, {cpu_model()}); a patrol's "
            "fraction of the route-optimal visits, else completion:\n\n" + table(args.runs, args.tasks, results))
    extra = margin_lines(args.runs, args.tasks, results)
    if extra:
        text += "\n\n" + "\n".join(extra)
    layouts = per_layout(args.runs, args.tasks, results)
    if layouts:
        text += "\n\nPer layout, the mean over the runs:\n\n" + layouts
    if args.handmade:
        cases = handmade_cases(args.tasks)[:args.cases]
        text += (f"\n\nThe same runs on the hand-made layouts (tests/data/layouts; {args.episodes} episodes{limit} "
                 f"each, filter on{seen}):\n\n" + handmade_table(args.runs, cases, args.episodes, args.max_steps,
                                                                     args.forbidden_range))
    print(text)
    if args.results != "-":
        with open(args.results, "a") as f:
            f.write("\n" + text + "\n")


if __name__ == "__main__":
    from d2spo.console import as_typed
    from d2spo.errors import UserError

    try:
        main()
    except UserError as e:  # a flag or run the evaluation refuses: its one line, as `d2spo eval` says it
        msg = as_typed(str(e), sys.argv[1:])
        if msg.startswith("layout_seeds: "):  # EvalConfig's name of this script's --layouts
            msg = "--layouts: " + msg.removeprefix("layout_seeds: ")
        print(f"buchi_zero_shot.py: error: {msg}", file=sys.stderr)
        sys.exit(2)
