"""``d2spo compare RUN ...``: a user's own runs side by side, on any task and layout (``d2spo
reproduce`` does this for the paper's tasks only).

One row per learner (its seeds' runs averaged, mean ± std): what Tables II–III compare, from each
run's summary.json (safety and completion over its window; a patrol's accepting visits per episode
and their share of the route-optimal count instead of completion), and, from episodes.csv, the
collisions over *all* training episodes, which the window does not see: D²SPO's claim is safety
during training as well as after it. The figure beside the table: the return's moving average and
the cumulative collisions over training, per learner.

Runs of different tasks, layouts or episode limits are not compared (one line, exit 2): their
figures do not measure the same thing."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from d2spo.errors import RunDirError
from d2spo.runio import read_episodes, read_json
from d2spo.tables import METHOD_NAMES

SAME = ("task", "layout")
"""The summary.json fields every compared run must share."""


def load(dirs: Sequence[Path]) -> list[dict]:
    """Each run's summary.json with its episodes.csv's ``collided`` column (``_collided``); a directory that is not a finished run, a run given twice, or runs of different
    tasks or layouts are a RunDirError."""
    runs, seen = [], set()
    for d in map(Path, dirs):
        if not (d / "summary.json").is_file():
            what = "not a run directory" if not (d / "config.json").is_file() else \
                "an unfinished run (no summary.json yet: let it finish, or `d2spo train --resume` it)"
            raise RunDirError(f"{d}: {what}")
        if d.resolve() in seen:
            raise RunDirError(f"{d}: given twice")
        seen.add(d.resolve())
        summary = read_json(d / "summary.json", "summary")
        config = read_json(d / "config.json", "config") if (d / "config.json").is_file() else {}
        episodes = read_episodes(d / "episodes.csv")
        rows = np.asarray(episodes, dtype=np.float64).reshape(len(episodes), -1)
        runs.append({**summary, "_dir": d, "_generalist": bool(config.get("generalist")),
                     "_collided": rows[:, 3] > 0 if len(rows) else np.zeros(0, bool)})
    for field in SAME:
        values = {str(r.get(field)) for r in runs}
        if len(values) > 1:
            first = runs[0]
            other = next(r for r in runs if str(r.get(field)) != str(first.get(field)))
            raise RunDirError(f"runs of different {field}s are not compared: {first['_dir']} has "
                              f"{first.get(field)!r}, {other['_dir']} {other.get(field)!r}")
    optima = {r.get("route_optimal_visits") for r in runs}
    if len(optima) > 1:  # a patrol over different episode limits: its visits count different things
        raise RunDirError(f"runs of different episode limits are not compared: route-optimal counts {sorted(map(str, optima))} "
                          "(train them with one --max-steps)")
    return runs


def label(run: dict) -> str:
    """A run's row: its learner as the paper names it, ``(generalist)`` for a generalist."""
    name = METHOD_NAMES.get(run.get("algo"), str(run.get("algo")))
    return name + (" (generalist)" if run.get("_generalist") else "")


def groups(runs: list[dict]) -> dict[str, list[dict]]:
    """The runs by ``label``, in the order given."""
    by: dict[str, list[dict]] = {}
    for r in runs:
        by.setdefault(label(r), []).append(r)
    return by


def _pm(values: Sequence[float], scale: float = 100.0, digits: int = 2) -> str:
    a = scale * np.asarray(values, float)
    return f"{a.mean():.{digits}f} ± {a.std():.{digits}f}" if len(a) > 1 else f"{a.mean():.{digits}f}"


def rows(runs: list[dict]) -> list[dict]:
    """One row per learner: its seeds, rates over the window (mean ± std over seeds, the population
    std), the collisions over all training episodes (count per run and share), episodes and wall time."""
    out = []
    for name, rs in groups(runs).items():
        patrol = rs[0].get("route_optimal_visits") is not None
        collisions = [int(r["_collided"].sum()) for r in rs]
        episodes = [len(r["_collided"]) for r in rs]
        row = {"learner": name, "algo": rs[0].get("algo"), "seeds": len(rs),
               "seed_list": " ".join(str(r.get("seed")) for r in rs),
               "window": min(int(r.get("window_episodes", r.get("window", 0))) for r in rs),
               "safety_mean": float(np.mean([r["safety_rate"] for r in rs])),
               "safety_std": float(np.std([r["safety_rate"] for r in rs])),
               "collisions_all": collisions, "episodes": episodes,
               "collision_rate_all_mean": float(np.mean([c / max(e, 1) for c, e in zip(collisions, episodes)])),
               "wall_seconds_mean": float(np.mean([r.get("wall_seconds", float("nan")) for r in rs])),
               "_safety": _pm([r["safety_rate"] for r in rs])}
        if patrol:
            visits = [r["accepting_visits_per_episode"] for r in rs]
            row.update(visits_mean=float(np.mean(visits)), route_optimal_visits=rs[0]["route_optimal_visits"],
                       visit_fraction_mean=float(np.mean([r.get("visit_fraction") or 0.0 for r in rs])),
                       _score=f"{_pm(visits, 1.0)} of {rs[0]['route_optimal_visits']} "
                              f"({_pm([r.get('visit_fraction') or 0.0 for r in rs], digits=1)}%)")
        else:
            row.update(completion_mean=float(np.mean([r["completion_rate"] for r in rs])),
                       completion_std=float(np.std([r["completion_rate"] for r in rs])),
                       _score=_pm([r["completion_rate"] for r in rs]))
        out.append(row)
    return out


def markdown(runs: list[dict], table: list[dict]) -> str:
    first = runs[0]
    patrol = first.get("route_optimal_visits") is not None
    windows = sorted({int(r.get("window_episodes", 0)) for r in runs})
    score = "accepting visits per episode of the route-optimal count" if patrol else "completion (%)"
    lines = [f"Task `{first.get('task')}` on layout `{first.get('layout')}`: safety (%) and {score} over each run's "
             f"last {' or '.join(map(str, windows))} training episodes, mean ± std over seeds (the population std); "
             "\"collisions, all episodes\": every training episode that collided, per run (the window sees only "
             "its end).", "",
             f"| learner | seeds | safety | {'visits' if patrol else 'completion'} | collisions, all episodes | "
             "episodes | wall time / run |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in table:
        coll = ", ".join(map(str, r["collisions_all"])) + f" ({100 * r['collision_rate_all_mean']:.2f}%)"
        eps = ", ".join(sorted(set(map(str, r["episodes"]))))
        lines.append(f"| {r['learner']} | {r['seeds']} | {r['_safety']} | {r['_score']} | {coll} | {eps} | "
                     f"{r['wall_seconds_mean']:.0f} s |")
    return "\n".join(lines) + "\n"


def write_csv(path: Path, table: list[dict]) -> None:
    keys = [k for k in dict.fromkeys(k for r in table for k in r) if not k.startswith("_")]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in table:
            w.writerow({k: (" ".join(map(str, v)) if isinstance(v, list) else
                            float(f"{v:.12g}") if isinstance(v, float) else v) for k, v in r.items() if k in keys})


def figure(path: Path, runs: list[dict], smooth: int = 200) -> Path:
    """Two panels: the return's moving average (``plots.reward_curves``: mean over seeds, ± 1 std) and
    the cumulative collisions over training (mean over seeds), per learner; seeds cut to the shortest run."""
    from d2spo.plots import CURVE_COLOURS, _figure, draw_reward_curves, reward_curves
    from d2spo.plotstyle import save_figure

    fig = _figure(2)
    ret_ax, coll_ax = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    ret_ax.set_prop_cycle(color=CURVE_COLOURS)
    coll_ax.set_prop_cycle(color=CURVE_COLOURS)
    by = groups(runs)
    curves = reward_curves({name: [r["_dir"] for r in rs] for name, rs in by.items()}, smooth)
    for name, rs in by.items():
        n = min(len(r["_collided"]) for r in rs)
        if n == 0:
            continue
        cum = np.stack([np.cumsum(r["_collided"][:n]) for r in rs]).mean(0)
        coll_ax.plot(np.arange(1, n + 1), cum, label=f"{name}: mean over {len(rs)} seed{'s' * (len(rs) != 1)}")
    draw_reward_curves(ret_ax, curves, f"return: {runs[0].get('task')!r} on {runs[0].get('layout')!r}")
    coll_ax.set_xlabel("training episodes")
    coll_ax.set_ylabel("collisions so far (cumulative)")
    coll_ax.set_title("collisions during training")
    if curves:
        coll_ax.legend(fontsize=7)
    return save_figure(fig, path, "out")


def compare(dirs: Sequence[Path], out: Path | None, smooth: int = 200) -> tuple[str, list[Path]]:
    """The table as markdown and the files written (OUT/compare.md, .csv, .png; none without ``out``)."""
    runs = load(dirs)
    table = rows(runs)
    text = markdown(runs, table)
    written: list[Path] = []
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "compare.md").write_text(text)
        write_csv(out / "compare.csv", table)
        written = [out / "compare.md", out / "compare.csv", figure(out / "compare.png", runs, smooth)]
    return text, written
