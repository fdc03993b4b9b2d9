"""Train D²SPO on every task of the example suite (``d2spo.ltl.tasks.SUITE``) and tabulate the results.

    .venv/bin/python bench/task_suite.py [--episodes 20000] [--seed 0] [--layout paper]
        [--tasks ...] [--metrics geodesic-per-state geodesic] [--eval-episodes 100] [--out runs/task-suite]
        [--results bench/RESULTS.md]

Each (task, shaping metric) pair is one ``d2spo train --algo d2spo`` run with the defaults apart from
``--shaping-metric``, in OUT/TASK-METRIC-sSEED; finished runs are reused, interrupted ones resume
(``reproduce.train_one``). A task that cannot be done on the layout (``a1-and-a2``) must fail before
training with one clear line; its row says so. The table (safety and completion over the last
2000 training episodes, the final evaluation, wall time) is printed and appended to ``--results``
as a dated section; ``--results -`` only prints it.
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
from d2spo.ltl.tasks import SUITE, TASKS
from d2spo.progress import train_with_progress
from d2spo.runio import read_json


def run_one(task: str, metric: str, episodes: int, seed: int, layout: str, out: Path, eval_episodes: int = 100
            ) -> dict | str:
    """The summary of one finished run, or the one-line error that stopped it before training."""
    cfg = TrainConfig(algo="d2spo", task=task, episodes=episodes, seed=seed, eval_episodes=eval_episodes,
                      env=EnvConfig(layout=layout, reward=RewardConfig(shaping_metric=metric)))
    if episodes < cfg.window:
        cfg = dataclasses.replace(cfg, window=episodes, checkpoint_every=episodes)
    d = out / f"{task}-{metric}-s{seed}"
    if not (d / "summary.json").is_file():
        resume = d if (d / "checkpoint.json").is_file() else None
        try:
            train_with_progress(cfg, d, resume, show=False)
        except UserError as e:
            return str(e)
    return read_json(d / "summary.json", "the run's summary")


def row(task: str, metric: str, result: dict | str) -> str:
    if isinstance(result, str):
        return f"| `{task}` | {metric} | refused before training: {result} | | | |"
    ev = result.get("eval", {})
    evtext = f"{100 * ev['safety_rate']:.0f} / {100 * ev['completion_rate']:.0f}" if ev else "-"
    return (f"| `{task}` | {metric} | {100 * result['safety_rate']:.2f} | {100 * result['completion_rate']:.2f} | "
            f"{evtext} | {result['wall_seconds']:.0f} s |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--layout", default="paper")
    ap.add_argument("--tasks", nargs="+", default=list(SUITE), choices=sorted(TASKS))
    ap.add_argument("--metrics", nargs="+", default=[RewardConfig().shaping_metric],
                    help="shaping metrics to train each task with (default: the default metric only)")
    ap.add_argument("--eval-episodes", type=int, default=100)
    ap.add_argument("--out", type=Path, default=Path("runs/task-suite"))
    ap.add_argument("--machine", default=f"{os.cpu_count()}-core {platform.machine()} CPU machine",
                    help="machine description written with the table")
    ap.add_argument("--results", default="bench/RESULTS.md", help="file to append the table to; '-' prints only")
    args = ap.parse_args()
    lines = ["| task | shaping metric | safety, last window (%) | completion, last window (%) | "
             "eval safety / completion (%) | wall time |", "|---|---|---:|---:|---:|---:|"]
    for task in args.tasks:
        for metric in args.metrics:
            result = run_one(task, metric, args.episodes, args.seed, args.layout, args.out, args.eval_episodes)
            lines.append(row(task, metric, result))
            print(lines[-1], flush=True)
    window = min(args.episodes, TrainConfig().window)
    section = "\n".join([
        f"\n### Task suite: D²SPO on every example task, `{args.layout}` ({datetime.date.today().isoformat()})\n",
        f"`bench/task_suite.py --episodes {args.episodes} --seed {args.seed} --layout {args.layout}`: one run per "
        f"task and shaping metric, defaults otherwise; \"last window\" is the last {window} training episodes, "
        f"eval {args.eval_episodes} deterministic episodes. Machine: {args.machine}.\n",
        *lines, ""])
    print(section)
    if args.results != "-":
        with open(args.results, "a") as f:
            f.write(section)


if __name__ == "__main__":
    main()
