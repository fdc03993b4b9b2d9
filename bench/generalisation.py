"""Zero-shot generalisation of one generalist: unseen random layouts x tasks, with and without the runtime filter.

    .venv/bin/python bench/generalisation.py [--run RUN] [--specialist RUN] [--per-layout RUN ...]
        [--layouts 20] [--first-seed 100000] [--tasks phi1 phi2 relaxed tour3 ...] [--episodes 50]
        [--out runs/generalisation] [--results bench/RESULTS.md]

* The generalist is ``--run`` (a ``d2spo train --generalist`` directory); without it one is trained
  with the defaults into OUT/generalist (an interrupted one resumes).
* The layouts are ``random:SEED`` for SEED = first-seed .. first-seed + layouts - 1: seeds the
  generalist never trained on (refused if they overlap its bank random:0 .. random:N-1).
* For each task and layout the pair is checked as for training (``zero_shot.generalist_layout``).
  A pair that cannot be done (an area the forbidden ones wall off, ...) is left out of that task's
  means and counted in the "refused" column, with the first reason given.
* Every task runs with the runtime filter on and off (π_Ω alone). With ``--specialist`` (a run
  trained on one layout, e.g. ϕ1 on ``paper``), that run is evaluated on the same layouts for its
  own task, and both are evaluated on the specialist's training layout.
* ``--per-layout`` takes specialists trained on some of the unseen layouts themselves (e.g.
  ``d2spo train --algo d2spo --task phi1 --layout random:100007``). Each is evaluated on its own
  (layout, task) case, beside the generalist's result on that same case: what training a policy for
  the case would have bought. OUT/per_layout_specialists.png draws them. ``--train-per-layout
  TASK@LAYOUT ...`` trains such specialists first (defaults, into OUT/specialists; reused when
  finished, resumed when interrupted): about 10 min for a 5 m layout and 35 min for a 10 m one on
  a 2-core CPU, so all 20 x 13 cases (about 70 CPU-hours) are left to the user's choice.

Each task's results are kept in OUT/cases/ as soon as they are measured: a rerun with the same run,
policy, layouts and episodes (an interrupted one, or one adding ``--specialist``) reuses them.

Writes OUT/generalisation.json, three figures (OUT/success_per_task.png, OUT/success_per_layout.png,
OUT/trajectories.png) and a dated table appended to ``--results`` ('-' prints only); the tables and
figures are bench/generalisation_report.py's.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
from pathlib import Path

import numpy as np
from generalisation_report import mean, per_layout_plot, per_layout_table, plots, table

from d2spo.errors import UserError
from d2spo.ltl.tasks import SUITE

DEFAULT_TASKS = ["phi1", "phi2", "relaxed", *[t for t in SUITE if t != "a1-and-a2"]]
"""ϕ1, ϕ2, the relaxed task and every task of the suite that can be done (a1-and-a2 cannot)."""


def generalist_run(args) -> Path:
    if args.run is not None:
        return args.run
    from d2spo.config import TrainConfig
    from d2spo.progress import train_with_progress

    out = args.out / "generalist"
    if not (out / "summary.json").is_file():
        resume = out if (out / "checkpoint.json").is_file() else None
        train_with_progress(TrainConfig(algo="d2spo", generalist=True), out, resume, show=True)
    return out


def _cache_file(cache: Path, task: str) -> Path:
    from d2spo.evalfiles import task_tag

    return cache / f"{task_tag(task)}.json"


def policy_hash(policy) -> str:
    """A digest of the policy's weights: a run trained again in the same directory is not taken for
    the one whose results were stored."""
    import hashlib

    import jax
    from flax import serialization

    return hashlib.sha256(serialization.to_bytes(jax.device_get(policy))).hexdigest()[:16]


def cached(cache: Path, task: str, key: tuple) -> dict | None:
    """A task's results stored by an earlier call with the same key (run, policy and its weights,
    layouts, episodes, paths kept), or None: an interrupted benchmark resumes, and adding ``--specialist``
    later does not evaluate the generalist again."""
    path = _cache_file(cache, task)
    if not path.is_file():
        return None
    try:
        stored = json.loads(path.read_text())
    except ValueError:  # a damaged file is evaluated again
        return None
    return stored["entry"] if stored.get("key") == json.loads(json.dumps(list(key))) else None


def store(cache: Path, task: str, key: tuple, entry: dict) -> None:
    from d2spo.runio import atomic_write_bytes

    cache.mkdir(parents=True, exist_ok=True)
    body = json.dumps({"key": list(key), "entry": entry}, default=lambda a: np.asarray(a).tolist())  # the paths' arrays
    atomic_write_bytes(_cache_file(cache, task), body.encode())


def evaluate_cases(run: Path, tasks: list[str], names: list[str], episodes: int, keep_paths: int,
                   cache: Path) -> tuple[dict, str]:
    """({task: {"filter": {...}, "alone": {...}, "refused": {layout: reason}}}, which policy) of the
    generalist (its validated best where it has one: ``run.load_policy``). Each task's results
    go to ``cache`` as soon as they are measured (``cached``)."""
    import dataclasses

    from d2spo.evaluate import eval_env_config
    from d2spo.run import load_policy
    from d2spo.zero_shot import generalist_layout, generalist_on, rollouts, seen_forbidden_range

    cfg, _, policy, meta = load_policy(run)
    print(f"{run}: its {meta['policy']} policy (checkpoint after {meta.get('episodes')} training episodes)",
          flush=True)
    if not cfg.generalist:
        raise UserError(f"{run}: not a generalist run (d2spo train --generalist)")
    env_cfg = seen_forbidden_range(eval_env_config(cfg, None))  # as d2spo eval sees it
    key = (str(run), meta["policy"], policy_hash(policy), names, episodes, keep_paths)
    out = {}
    for task in tasks:
        done = cached(cache, task, key)
        if done is not None:
            out[task] = done
            print(f"{task}: taken from {cache} (same run, policy, layouts and episodes)", flush=True)
            continue
        checked, refused = [], {}
        for name in names:
            try:
                checked.append(generalist_layout(env_cfg, name, task, cfg.cbf.d))
            except UserError as e:
                refused[name] = str(e)
        entry = {"refused": refused, "layouts": [lay.name for lay, _ in checked]}
        for mode, on in (("filter", True), ("alone", False)):
            c = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, runtime_filter=on))
            res, limit = [], 0
            if checked:
                env, params, learner, limit = generalist_on(c, env_cfg, task, checked)
                res = rollouts(env, params, learner, policy, checked, episodes, 0, limit, keep_paths)
            paths = [r.pop("paths")[1:] for r in res] if keep_paths else None  # (poses, collided, completed)
            entry[mode] = {"per_layout": res, "max_steps": limit}
            if mode == "filter" and keep_paths:
                entry["paths"] = paths
        out[task] = entry
        store(cache, task, key, entry)
        done = [r["completion_rate"] for r in entry["filter"]["per_layout"]]
        print(f"{task}: {len(checked)} layouts, {len(refused)} refused; completion with filter "
              f"{100 * np.mean(done) if done else float('nan'):.1f}%", flush=True)
    return out, meta["policy"]


def specialist_cases(run: Path, names: list[str], episodes: int, own_episodes: int) -> dict:
    """The specialist on the same layouts (its own task) and on its own layout, filter on and off."""
    from d2spo.evaluate import EvalConfig, evaluate_run
    from d2spo.run import load_run_config

    cfg = load_run_config(run)
    out = {"task": cfg.task, "layout": cfg.layout}
    for mode, on in (("filter", True), ("alone", False)):
        try:  # one compilation for all the layouts
            first, n = names[0].partition(":")[2], len(names)
            unseen = evaluate_run(run, EvalConfig(episodes, f"random:{first}", layout_seeds=n, runtime_filter=on))["per_layout"]
        except UserError:  # some layout refuses the task: one at a time, to say which
            unseen = []
            for name in names:
                try:
                    unseen.append(evaluate_run(run, EvalConfig(episodes, name, runtime_filter=on))["per_layout"][0])
                except UserError as e:
                    unseen.append({"layout": name, "refused": str(e)})
        out[mode] = {"unseen": unseen, "own": evaluate_run(run, EvalConfig(own_episodes, None, runtime_filter=on))}
    return out


def train_per_layout(cases: list[str], names: list[str], out: Path) -> list[Path]:
    """Train (or resume, or reuse) a D²SPO specialist with the defaults for each TASK@LAYOUT case,
    into OUT/specialists/TASK-LAYOUT; the layout must be one of the benchmark's."""
    from d2spo.config import TrainConfig
    from d2spo.envs import EnvConfig, make_env
    from d2spo.progress import train_with_progress

    pairs = [case.partition("@")[::2] for case in cases]
    for case, (task, layout) in zip(cases, pairs, strict=True):
        if not task or layout not in names:
            raise UserError(f"--train-per-layout {case!r}: expected TASK@LAYOUT with LAYOUT one of the benchmark's "
                            f"layouts {names[0]} .. {names[-1]}")
        make_env(EnvConfig(layout=layout), task)  # a task the layout refuses stops here, before any training
    runs = []
    for task, layout in pairs:
        d = out / "specialists" / f"{task}-{layout.replace(':', '')}"
        if not (d / "summary.json").is_file():
            resume = d if (d / "checkpoint.json").is_file() else None
            train_with_progress(TrainConfig(algo="d2spo", task=task, env=EnvConfig(layout=layout)), d, resume, show=True)
        runs.append(d)
    return runs


def per_layout_cases(runs: list[Path], names: list[str], episodes: int) -> list[dict]:
    """Each specialist trained on one of the benchmark's layouts, on its own (layout, task) case,
    filter on and off, ``episodes`` deterministic episodes (as the generalist's cases)."""
    from d2spo.evaluate import EvalConfig, evaluate_run
    from d2spo.run import load_run_config

    out = []
    for run in runs:
        cfg = load_run_config(run)
        if cfg.generalist or cfg.layout not in names:
            raise UserError(f"--per-layout {run}: trained on {'many layouts' if cfg.generalist else cfg.layout!r}, "
                             f"not on one of the benchmark's layouts {names[0]} .. {names[-1]}")
        res = {mode: evaluate_run(run, EvalConfig(episodes, None, runtime_filter=on)) for mode, on in (("filter", True), ("alone", False))}
        print(f"per-layout specialist {run} ({cfg.task} on {cfg.layout}): completion with filter "
              f"{100 * res['filter']['completion_rate']:.1f}%", flush=True)
        out.append({"run": str(run), "task": cfg.task, "layout": cfg.layout, **res})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, help="a generalist run directory (default: train one into OUT/generalist)")
    ap.add_argument("--specialist", type=Path, help="a run trained on one layout, evaluated on the same cases")
    ap.add_argument("--per-layout", type=Path, nargs="+", default=[], metavar="RUN",
                    help="specialists each trained on one of the unseen layouts, evaluated on their own case")
    ap.add_argument("--train-per-layout", nargs="+", default=[], metavar="TASK@LAYOUT",
                    help="train a specialist with the defaults for each case (into OUT/specialists), then as --per-layout")
    ap.add_argument("--layouts", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=100_000)
    ap.add_argument("--tasks", nargs="+", default=DEFAULT_TASKS, help="task names or formulas over A1..A4")
    ap.add_argument("--episodes", type=int, default=50, help="deterministic episodes per (task, layout, filter)")
    ap.add_argument("--own-layout", default="paper", help="without --specialist: the layout on which the "
                    "generalist also runs its training task (with one: the specialist's layout)")
    ap.add_argument("--own-episodes", type=int, default=100, help="episodes on that one layout")
    ap.add_argument("--trajectories", type=int, default=6, help="paths drawn per shown layout")
    ap.add_argument("--out", type=Path, default=Path("runs/generalisation"))
    ap.add_argument("--machine", default=f"{os.cpu_count()}-core {platform.machine()} CPU machine")
    ap.add_argument("--results", default="bench/RESULTS.md", help="file to append the table to; '-' prints only")
    args = ap.parse_args()
    from d2spo import compile_cache

    compile_cache.enable()  # the commands' cache: a second seed or mode of the same program compiles nothing
    args.out.mkdir(parents=True, exist_ok=True)
    run = generalist_run(args)
    from d2spo.run import load_run_config

    trained = load_run_config(run)
    if args.first_seed < trained.generalist_layouts:
        raise UserError(f"--first-seed {args.first_seed}: the generalist trained on random:0 .. "
                         f"random:{trained.generalist_layouts - 1}; choose unseen seeds")
    names = [f"random:{args.first_seed + i}" for i in range(args.layouts)]
    trained_here = train_per_layout(args.train_per_layout, names, args.out)
    cases, which = evaluate_cases(run, args.tasks, names, args.episodes, args.trajectories, args.out / "cases")
    spec = specialist_cases(args.specialist, names, args.episodes, args.own_episodes) if args.specialist else None
    per = per_layout_cases([*args.per_layout, *trained_here], names, args.episodes)
    # The generalist on the specialist's own layout and task; without a specialist, on --own-layout
    # with its training task (the specialist's numbers are then not measured).
    from d2spo.evaluate import EvalConfig, evaluate_run

    own_layout, own_task = (spec["layout"], spec["task"]) if spec is not None else (args.own_layout, trained.task)
    own = {mode: evaluate_run(run, EvalConfig(args.own_episodes, own_layout, runtime_filter=on, task=own_task))
           for mode, on in (("filter", True), ("alone", False))}
    figures = plots(cases, names, args.out) + ([per_layout_plot(per, cases, args.out)] if per else [])
    for c in cases.values():
        c.pop("paths", None)
    (args.out / "generalisation.json").write_text(json.dumps(
        {"run": str(run), "policy": which, "layouts": names, "episodes": args.episodes, "cases": cases, "specialist": spec,
         "generalist_on_specialist_layout": own, "per_layout_specialists": per}, indent=1))
    lines = table(cases, len(names))
    who = f"Specialist `{args.specialist}` ({spec['task']} on `{spec['layout']}`) and the generalist" \
        if spec is not None else f"The generalist on `{own_layout}` ({own_task}; no specialist given)"
    lines += ["", f"{who}, {args.own_episodes} episodes on the one layout:",
              "", "| policy | where | completion, filter (%) | safety, filter (%) | completion, alone (%) | "
              "safety, alone (%) |", "|---|---|---:|---:|---:|---:|"]
    rows = [("specialist", f"its own layout `{spec['layout']}`", spec["filter"]["own"], spec["alone"]["own"])] \
        if spec is not None else []
    rows.append(("generalist", f"`{own_layout}`, {own_task}", own["filter"], own["alone"]))
    for who, where, f, a in rows:
        lines.append(f"| {who} | {where} | {100 * f['completion_rate']:.1f} | {100 * f['safety_rate']:.1f} | "
                     f"{100 * a['completion_rate']:.1f} | {100 * a['safety_rate']:.1f} |")
    if spec is not None:
        for mode in ("filter", "alone"):
            ok = [r for r in spec[mode]["unseen"] if "refused" not in r]
            lines.append(f"| specialist | the {len(ok)} unseen layouts, {spec['task']}, {mode} | "
                         f"{100 * mean([r['completion_rate'] for r in ok]):.1f} | "
                         f"{100 * mean([r['safety_rate'] for r in ok]):.1f} | | |")
    if per:
        lines += ["", f"Per-layout specialists on their own case, {args.episodes} episodes each, beside the "
                  "generalist's episodes on the same case:", "", *per_layout_table(per, cases)]
    section = "\n".join([
        f"\n### Generalisation: one generalist on unseen layouts ({datetime.date.today().isoformat()})\n",
        f"`bench/generalisation.py --run {run} --layouts {args.layouts} --first-seed {args.first_seed} "
        f"--episodes {args.episodes}{f' --specialist {args.specialist}' if args.specialist else ''}"
        f"{' --per-layout ' + ' '.join(map(str, args.per_layout)) if args.per_layout else ''}"
        f"{' --train-per-layout ' + ' '.join(args.train_per_layout) if args.train_per_layout else ''}"
        f"{f' --own-layout {args.own_layout}' if args.own_layout != 'paper' and not args.specialist else ''}"
        f"{f' --own-episodes {args.own_episodes}' if args.own_episodes != 100 else ''}`: layouts "
        f"random:{args.first_seed} .. random:{args.first_seed + args.layouts - 1}, {args.episodes} deterministic "
        f"episodes per (task, layout, filter); the generalist's {which} policy. Machine: {args.machine}. Figures: "
        + ", ".join(str(p) for p in figures) + ".\n", *lines, ""])
    print(section)
    if args.results != "-":
        with open(args.results, "a") as f:
            f.write(section)


if __name__ == "__main__":
    try:
        main()
    except UserError as e:  # a wrong run, layout range or case: one line, exit 2 (as the CLI)
        import sys

        print(f"generalisation.py: {e}", file=sys.stderr)
        raise SystemExit(2) from None
