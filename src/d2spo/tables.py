"""Tables II–III: our safety and completion rates beside the paper's, as markdown and CSV, written
from run directories (their ``summary.json`` and ``episodes.csv``). ``d2spo.reproduce`` chooses
the runs; ``d2spo report`` gathers the tables into one page."""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from d2spo.runio import read_episodes, read_json

METHOD_NAMES = {"cpo": "CPO", "ppo-lag": "LPPO", "td3-lag": "LTD3", "sac-lag": "LSAC", "rcrl": "RCRL",
                "d2spo": "D²SPO", "tlgrl": "TLGRL", "td3": "RL (sparse)", "sl": "SL"}
"""How the paper names each learner in its tables and figures."""
PAPER = {
    # Table II (ϕ1) and Table III (relaxed ϕ1): (safety %, completion %)
    "table2": {"cpo": (90.71, 19.44), "ppo-lag": (96.84, 0.0), "td3-lag": (83.08, 0.0), "sac-lag": (77.76, 96.74),
               "rcrl": (74.47, 77.52), "d2spo": (95.23, 99.31)},
    "table3": {"cpo": (94.49, 98.02), "ppo-lag": (91.59, 63.50), "td3-lag": (95.10, 97.11),
               "sac-lag": (93.94, 98.75), "rcrl": (94.19, 94.82), "d2spo": (97.94, 99.48)},
}
TITLES = {"table2": "Table II: ϕ1 on `paper`", "table3": "Table III: relaxed ϕ1 on `relaxed`"}


def run_summaries(runs: Mapping[str, Iterable[Path]]) -> dict[str, list[dict]]:
    """Per key, the summaries of its finished runs (unfinished ones are skipped), each with
    ``collision_rate_all``: the fraction of *all* training episodes that collided (the paper's
    window only sees the last 2000)."""
    by: dict[str, list[dict]] = {}
    for key, dirs in runs.items():
        for d in map(Path, dirs):
            if (d / "summary.json").is_file():
                summary = read_json(d / "summary.json", "summary")
                rows = read_episodes(d / "episodes.csv")
                summary["collision_rate_all"] = float(np.mean([r[3] for r in rows])) if rows else float("nan")
                by.setdefault(key, []).append(summary)
    return by


def _pm(values: list[float]) -> str:
    a = 100 * np.asarray(values, float)
    return f"{a.mean():.2f} ± {a.std():.2f}" if len(a) > 1 else f"{a.mean():.2f}"


def write_table(out: Path, target: str, runs: Mapping[str, Iterable[Path]], task: str, layout: str,
                episodes: int) -> Path:
    """OUT/TARGET.md and OUT/TARGET.csv (TARGET: table2 or table3), one row per learner (the keys of
    ``runs``, in order, each with its run directories): mean ± std over its finished runs beside
    the paper's numbers."""
    out = Path(out)
    by = run_summaries(runs)
    rows = []
    for m in runs:
        got = by.get(m, [])
        paper = PAPER[target].get(m)
        rows.append({
            "method": METHOD_NAMES.get(m, m), "algo": m, "seeds": len(got),
            "safety_mean": float(np.mean([g["safety_rate"] for g in got])) if got else float("nan"),
            "safety_std": float(np.std([g["safety_rate"] for g in got])) if got else float("nan"),
            "completion_mean": float(np.mean([g["completion_rate"] for g in got])) if got else float("nan"),
            "completion_std": float(np.std([g["completion_rate"] for g in got])) if got else float("nan"),
            "paper_safety": paper[0] / 100 if paper else float("nan"),
            "paper_completion": paper[1] / 100 if paper else float("nan"),
            "wall_seconds_mean": float(np.mean([g["wall_seconds"] for g in got])) if got else float("nan"),
            "collision_rate_all_mean": float(np.mean([g["collision_rate_all"] for g in got])) if got else float("nan"),
            "_safety": _pm([g["safety_rate"] for g in got]) if got else "not run",
            "_completion": _pm([g["completion_rate"] for g in got]) if got else "not run",
        })
    with open(out / f"{target}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[k for k in rows[0] if not k.startswith("_")])
        w.writeheader()
        # rates to 12 significant digits: 1 - 0.95 is 0.050000000000000044 in binary, 0.05 here
        w.writerows([{k: float(f"{v:.12g}") if isinstance(v, float) else v for k, v in r.items() if not k.startswith("_")}
                     for r in rows])
    ran = sorted({int(g.get("episodes", episodes)) for gs in by.values() for g in gs}) or [episodes]  # the rows'
    # each run's window (a short run: all of it); runs used with --allow-stale may differ
    windows = sorted({min(int(g["window"]), int(g.get("episodes", episodes))) for gs in by.values() for g in gs
                      if "window" in g})
    if len(windows) > 1:
        span = (f"each run's own window, the last {' or '.join(map(str, windows))} of its "
                f"{' or '.join(map(str, ran))} training episodes")
    else:
        window = windows[0] if windows else min(2000, max(ran))
        span = f"{f'the last {window} of' if window < min(ran) else 'all'} {' or '.join(map(str, ran))} training episodes"
    if ran != [episodes]:  # runs of another length, used with --allow-stale: say what the rows are
        span += (f" (the runs' own: {episodes} were asked, and runs trained with other settings were used as "
                 "they are, --allow-stale)")
    lines = [f"### {TITLES[target]}", "",
             f"Safety and completion rate (%) over {span}, mean ± std "
             f"over seeds (the population std, ddof 0); task `{task}`, layout `{layout}`; the paper's figures beside them. \"Collisions, all "
             f"episodes\": the share of every training episode that collided (mean over seeds).", "",
             "| method | seeds | safety | completion | paper safety | paper completion | collisions, all episodes | wall time / run |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        wall = f"{r['wall_seconds_mean']:.0f} s" if r["seeds"] else "–"
        ps = f"{100 * r['paper_safety']:.2f}" if np.isfinite(r["paper_safety"]) else "–"
        pc = f"{100 * r['paper_completion']:.2f}" if np.isfinite(r["paper_completion"]) else "–"
        coll = f"{100 * r['collision_rate_all_mean']:.2f}%" if r["seeds"] else "–"
        lines.append(f"| {r['method']} | {r['seeds']} | {r['_safety']} | {r['_completion']} | {ps} | {pc} | {coll} "
                     f"| {wall} |")
    path = out / f"{target}.md"
    path.write_text("\n".join(lines) + "\n")
    return path
