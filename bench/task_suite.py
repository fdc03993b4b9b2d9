"""Train D²SPO on every task of the example suite (``d2spo.ltl.tasks.SUITE``, or with ``--suite buchi``
the tasks no finite run completes, ``BUCHI_SUITE``) and tabulate the results.

    .venv/bin/python bench/task_suite.py [--suite examples|buchi] [--episodes 20000] [--seed 0] [--layout paper]
        [--tasks ...] [--metrics geodesic-per-state geodesic] [--fast] [--eval-episodes 100]
        [--out runs/task-suite] [--results bench/RESULTS.md]

Each (task, shaping metric) pair is one ``d2spo train --algo d2spo`` run with the defaults apart from
``--shaping-metric``, in OUT/TASK-METRIC-sSEED; finished runs are reused, interrupted ones resume
(``reproduce.train_one``). A task that cannot be done on the layout (``a1-and-a2``) must fail before
training with one clear line; its row says so. The table (safety and completion over the last
2000 training episodes, the final evaluation, wall time; for a recurrence also its accepting visits
per episode over that window, the route-optimal count and the fraction) is printed and appended to
``--results`` as a dated section; ``--results -`` only prints it. A formula with no deterministic
Büchi automaton (``persist``) is refused in one line, and its row says so.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
from pathlib import Path

from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.errors import UserError
from d2spo.ltl.reward import RewardConfig
from d2spo.ltl.tasks import BUCHI_SUITE, SUITE, TASKS
from d2spo.progress import train_with_progress
from d2spo.runio import read_json


def run_one(task: str, metric: str, episodes: int, seed: int, layout: str, out: Path, eval_episodes: int = 100,
            fast: bool = False) -> dict | str:
    """The summary of one finished run, or the one-line error that stopped it before training."""
    try:
        cfg = TrainConfig(algo="d2spo", task=task, episodes=episodes, seed=seed, eval_episodes=eval_episodes,
                          fast=fast, env=EnvConfig(layout=layout, reward=RewardConfig(shaping_metric=metric)))
    except UserError as e:
        return str(e)
    if episodes < cfg.window:
        cfg = dataclasses.replace(cfg, window=episodes, checkpoint_every=episodes)
    d = out / f"{task}-{metric}{'-fast' if fast else ''}-s{seed}"
    if not (d / "summary.json").is_file():
        resume = d if (d / "checkpoint.json").is_file() else None
        try:
            train_with_progress(cfg, d, resume, show=False)
        except (UserError, ValueError) as e:  # ValueError: NoDeterministicBuchi, raised as the task is built
            return str(e)
    return read_json(d / "summary.json", "the run's summary")


def row(task: str, metric: str, result: dict | str) -> str:
    if isinstance(result, str):
        return f"| `{task}` | {metric} | refused before training: {result} | | | | |"
    ev = result.get("eval_best") or result.get("eval", {})  # a patrol's kept policy where it has one
    evtext = "-"
    if ev and result.get("visit_fraction") is not None:  # a recurrence: its visits, not a completion
        evtext = f"{100 * ev['safety_rate']:.0f} / {ev['accepting_visits_per_episode']:.2f} visits"
    elif ev:
        evtext = f"{100 * ev['safety_rate']:.0f} / {100 * ev['completion_rate']:.0f}"
    visits = "-"
    if result.get("accepting_visits_per_episode") is not None:
        visits = f"{result['accepting_visits_per_episode']:.2f}"
        if result.get("visit_fraction") is not None:
            visits += f" of {result['route_optimal_visits']} ({100 * result['visit_fraction']:.1f}%)"
    return (f"| `{task}` | {metric} | {100 * result['safety_rate']:.2f} | {100 * result['completion_rate']:.2f} | "
            f"{visits} | {evtext} | {result['wall_seconds']:.0f} s |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--layout", default="paper")
    ap.add_argument("--suite", choices=("examples", "buchi"), default="examples",
                    help="the tasks when --tasks is not given: SUITE or BUCHI_SUITE")
    ap.add_argument("--tasks", nargs="+", default=None, choices=sorted(TASKS))
    ap.add_argument("--fast", action="store_true", help="train with --fast (TrainConfig.fast)")
    ap.add_argument("--metrics", nargs="+", default=[RewardConfig().shaping_metric],
                    help="shaping metrics to train each task with (default: the default metric only)")
    ap.add_argument("--eval-episodes", type=int, default=100)
    ap.add_argument("--out", type=Path, default=Path("runs/task-suite"))
    ap.add_argument("--machine", default=f"{os.cpu_count()}-core {platform.machine()} CPU machine",
                    help="machine description written with the table")
    ap.add_argument("--results", default="bench/RESULTS.md", help="file to append the table to; '-' prints only")
    args = ap.parse_args()
    tasks = args.tasks or list(BUCHI_SUITE if args.suite == "buchi" else SUITE)
    lines = ["| task | shaping metric | safety, last window (%) | completion, last window (%) | "
             "visits/episode, last window (of the route-optimal) | eval safety (%) / completion (%) or visits "
             "(the kept policy, where validated) | wall time |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for task in tasks:
        for metric in args.metrics:
            result = run_one(task, metric, args.episodes, args.seed, args.layout, args.out, args.eval_episodes,
                             args.fast)
            lines.append(row(task, metric, result))
            print(lines[-1], flush=True)
    window = min(args.episodes, TrainConfig().window)
    section = "\n".join([
        f"\n### Task suite: D²SPO on every example task, `{args.layout}` ({datetime.date.today().isoformat()})\n",
        f"`bench/task_suite.py --suite {args.suite} --episodes {args.episodes} --seed {args.seed} "
        f"--layout {args.layout}{' --fast' if args.fast else ''}`: one run per "
        f"task and shaping metric, defaults otherwise; \"last window\" is the last {window} training episodes, "
        f"eval {args.eval_episodes} deterministic episodes (of a patrol's kept policy, `--patrol-validation`). "
        f"Machine: {args.machine}.\n",
        *lines, ""])
    print(section)
    if args.results != "-":
        with open(args.results, "a") as f:
            f.write(section)


if __name__ == "__main__":
    main()
