"""The tables and figures of bench/generalisation.py, from its measured cases (split from it: the
script measures, this module reports). ``cases`` maps a task to its entry: ``layouts`` (names),
``refused``, ``filter`` and ``alone`` (each ``{"per_layout": [rates per layout]}``) and, for ϕ1 and ϕ2,
``paths`` (a few trajectories per layout)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

DEEPLTL = 0.931
"""DeepLTL's mean success on ZoneEnv's finite-horizon test formulas (ICLR 2025, issue 16): the mark."""


def generalist_on(cases: dict, task: str, layout: str, mode: str) -> dict | None:
    """The generalist's result on one (task, layout) case, or None (task not run, or layout refused)."""
    entry = cases.get(task)
    if entry is None or layout not in entry["layouts"]:
        return None
    return entry[mode]["per_layout"][entry["layouts"].index(layout)]


def per_layout_table(per: list[dict], cases: dict) -> list[str]:
    lines = ["| case (task on layout) | specialist: completion / safety, filter (%) | generalist: completion / "
             "safety, filter (%) | specialist: completion / safety, alone (%) | generalist: completion / safety, "
             "alone (%) | specialist's run |", "|---|---:|---:|---:|---:|---|"]
    pair = lambda r: "-" if r is None else f"{100 * r['completion_rate']:.1f} / {100 * r['safety_rate']:.1f}"  # noqa: E731
    for p in per:
        g = {mode: generalist_on(cases, p["task"], p["layout"], mode) for mode in ("filter", "alone")}
        lines.append(f"| {p['task']} on `{p['layout']}` | {pair(p['filter'])} | {pair(g['filter'])} | "
                     f"{pair(p['alone'])} | {pair(g['alone'])} | `{p['run']}` |")
    return lines


def per_layout_plot(per: list[dict], cases: dict, out: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(max(5.0, 1.4 * len(per) + 2), 4.0))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    x = np.arange(len(per))
    for k, (who, label) in enumerate((("specialist", "per-layout specialist"), ("generalist", "generalist (zero-shot)"))):
        rs = [p["filter"] if who == "specialist" else generalist_on(cases, p["task"], p["layout"], "filter") for p in per]
        ax.bar(x + (k - 0.5) * 0.4, [np.nan if r is None else 100 * r["completion_rate"] for r in rs], 0.4,
               label=f"completion, {label}")
        ax.plot(x + (k - 0.5) * 0.4, [np.nan if r is None else 100 * r["safety_rate"] for r in rs], "k^" if k == 0 else "kv",
                label=f"safety, {label}")
    ax.set_xticks(x, [f"{p['task']}\n{p['layout']}" for p in per], fontsize=8)
    ax.set_ylabel("% of episodes (runtime filter on)")
    ax.set_ylim(0, 105)
    ax.set_title("Each case's own specialist against the generalist")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2)
    fig.tight_layout()
    path = out / "per_layout_specialists.png"
    fig.savefig(path, dpi=100)
    return path


def mean(xs) -> float:
    return float(np.mean(xs)) if len(xs) else float("nan")


def table(cases: dict, n_layouts: int) -> list[str]:
    lines = ["| task | layouts run / refused | completion, filter (%) | lowest layout, filter (%) | "
             "safety, filter (%) | completion, π_Ω alone (%) | safety, π_Ω alone (%) |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for task, e in cases.items():
        f, a = e["filter"]["per_layout"], e["alone"]["per_layout"]
        pct = lambda rs, k: f"{100 * mean([r[k] for r in rs]):.1f}"  # noqa: E731
        low = f"{100 * min(r['completion_rate'] for r in f):.0f}" if f else "-"
        lines.append(f"| `{task}` | {len(f)} / {len(e['refused'])} | {pct(f, 'completion_rate')} | {low} | "
                     f"{pct(f, 'safety_rate')} | {pct(a, 'completion_rate')} | {pct(a, 'safety_rate')} |")
    allf = [r for e in cases.values() for r in e["filter"]["per_layout"]]
    alla = [r for e in cases.values() for r in e["alone"]["per_layout"]]
    task_means = [mean([r["completion_rate"] for r in e["filter"]["per_layout"]]) for e in cases.values()
                  if e["filter"]["per_layout"]]
    lines.append(f"| **all** (mean of task means) | {len(allf)} / {sum(len(e['refused']) for e in cases.values())} | "
                 f"**{100 * mean(task_means):.1f}** | {100 * min(task_means):.0f} (task) | "
                 f"{100 * mean([r['safety_rate'] for r in allf]):.2f} | "
                 f"{100 * mean([r['completion_rate'] for r in alla]):.1f} | "
                 f"{100 * mean([r['safety_rate'] for r in alla]):.2f} |")
    return lines


def plots(cases: dict, names: list[str], out: Path) -> list[Path]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from d2spo.envs import layouts
    from d2spo.envs.render import draw_layout
    from d2spo.plots import draw_trajectories

    tasks = list(cases)
    paths = []
    fig = Figure(figsize=(max(6.0, 0.7 * len(tasks)), 4.6), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    x = np.arange(len(tasks))
    for k, (mode, label) in enumerate((("filter", "with runtime filter"), ("alone", "π_Ω alone"))):
        comp = [100 * mean([r["completion_rate"] for r in cases[t][mode]["per_layout"]]) for t in tasks]
        safe = [100 * mean([r["safety_rate"] for r in cases[t][mode]["per_layout"]]) for t in tasks]
        ax.bar(x + (k - 0.5) * 0.4, comp, 0.4, label=f"completion, {label}")
        ax.plot(x + (k - 0.5) * 0.4, safe, "k^" if k == 0 else "kv", label=f"safety, {label}")
    ax.axhline(100 * DEEPLTL, color="gray", linestyle="--", label="DeepLTL's mean success (no safety)")
    ax.set_xticks(x, tasks, rotation=45, ha="right")
    ax.set_ylabel("% of episodes")
    ax.set_ylim(0, 105)
    ax.set_title("Zero-shot on unseen layouts, per task (mean over layouts)")
    fig.legend(fontsize=7, loc="outside lower center", ncol=3)  # below the rotated task names
    paths.append(out / "success_per_task.png")
    fig.savefig(paths[-1], dpi=100)

    grid = np.full((len(tasks), len(names)), np.nan)
    for i, t in enumerate(tasks):
        for lay, r in zip(cases[t]["layouts"], cases[t]["filter"]["per_layout"]):
            grid[i, names.index(lay)] = 100 * r["completion_rate"]
    fig = Figure(figsize=(max(6.0, 0.45 * len(names) + 2), 0.4 * len(tasks) + 2))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    im = ax.imshow(grid, vmin=0, vmax=100, cmap="viridis", aspect="auto")
    ax.set_xticks(range(len(names)), [n.split(":")[-1] for n in names], rotation=90, fontsize=7)
    ax.set_yticks(range(len(tasks)), tasks, fontsize=8)
    ax.set_xlabel("layout random:SEED (blank: the task cannot be done there)")
    ax.set_title("Completion (%) with the runtime filter, per task and layout")
    fig.colorbar(im, ax=ax)
    fig.tight_layout()
    paths.append(out / "success_per_layout.png")
    fig.savefig(paths[-1], dpi=100)

    shown = [(t, i) for t in ("phi1", "phi2") if t in cases and cases[t].get("paths") for i in range(2)]
    if shown:
        fig = Figure(figsize=(4.0 * len(shown), 4.2))
        FigureCanvasAgg(fig)
        for k, (t, i) in enumerate(shown):
            if i >= len(cases[t]["paths"]):
                continue
            ax = fig.add_subplot(1, len(shown), k + 1)
            name = cases[t]["layouts"][i]
            draw_layout(layouts.load(name), ax, show_sensing=False)
            draw_trajectories(ax, *(np.asarray(a) for a in cases[t]["paths"][i]))
            ax.set_title(f"{t} on {name} (unseen)", fontsize=9)
        fig.tight_layout()
        paths.append(out / "trajectories.png")
        fig.savefig(paths[-1], dpi=100)
    return paths
