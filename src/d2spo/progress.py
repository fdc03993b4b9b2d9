"""Rich progress bar and summary table around ``d2spo.train.train`` (CLI side only)."""

from __future__ import annotations

from pathlib import Path

from d2spo.config import TrainConfig


def default_out(cfg: TrainConfig) -> Path:
    task = cfg.task if cfg.task.replace("-", "").isalnum() else "custom"
    layout = Path(cfg.layout).stem if cfg.layout.endswith(".json") else cfg.layout.replace(":", "")
    return Path("runs") / f"{cfg.algo}-{task}-{layout}-s{cfg.seed}"


def summary_table(summary: dict, title: str):
    from rich.table import Table

    t = Table(title=title)
    t.add_column("metric")
    t.add_column("value", justify="right")
    pct = lambda v: f"{100 * v:.2f}%"
    t.add_row("episodes", str(summary["episodes"]))
    t.add_row("env steps", f"{summary['env_steps']:,}")
    t.add_row("wall time", f"{summary['wall_seconds']:.0f} s ({summary['env_steps_per_second']:,.0f} steps/s)")
    t.add_row(f"safety rate (last {summary['window_episodes']})", pct(summary["safety_rate"]))
    t.add_row(f"completion rate (last {summary['window_episodes']})", pct(summary["completion_rate"]))
    t.add_row("completion rate, relaxed labelling", pct(summary["completion_rate_relaxed"]))
    if "eval" in summary:
        e = summary["eval"]
        t.add_row(f"final policy: safety ({e['episodes']} episodes)", pct(e["safety_rate"]))
        t.add_row(f"final policy: completion ({e['episodes']} episodes)", pct(e["completion_rate"]))
    return t


def train_with_progress(cfg: TrainConfig, out: Path | None, resume: Path | None, show: bool) -> int:
    from rich.console import Console

    from d2spo.train import load_run_config, train

    console = Console(stderr=True)
    if resume is not None:
        cfg = load_run_config(resume)
        out = resume
    cfg = cfg.check()
    out = Path(out) if out is not None else default_out(cfg)
    with _progress(console, show) as bar:
        on_chunk = _bar_task(bar, f"{cfg.algo} {cfg.task}", cfg.episodes)
        summary = train(cfg, out, resume=resume is not None, progress=on_chunk)
    Console().print(summary_table(summary, f"{cfg.algo} on {cfg.task} / {cfg.layout} (seed {cfg.seed}) → {out}"))
    return 0


def _progress(console, show: bool):
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = [
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("episodes"),
        TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), TextColumn("{task.fields[stats]}"),
    ]
    return Progress(*columns, console=console, disable=not show, transient=False)


def _bar_task(bar, description: str, total: int):
    """A progress row and the callback that ``train`` calls after each chunk."""
    task = bar.add_task(description, total=total, stats="compiling…")

    def on_chunk(d: dict) -> None:
        eps_per_s = d["episodes"] / max(d["wall_seconds"], 1e-9)
        stats = (f"{eps_per_s:.1f} ep/s  safe {100 * d['safety_rate']:.1f}%  "
                 f"done {100 * d['completion_rate']:.1f}% (relaxed {100 * d['completion_rate_relaxed']:.1f}%)")
        bar.update(task, completed=d["episodes"], stats=stats)

    return on_chunk


def train_seeds_with_progress(cfgs: list[TrainConfig], outs: list[Path], show: bool) -> list[dict]:
    """``d2spo.train.train_seeds`` (seeds vmapped together) with one progress row per seed."""
    from rich.console import Console

    from d2spo.train import train_seeds

    console = Console(stderr=True)
    cfgs = [c.check() for c in cfgs]
    with _progress(console, show) as bar:
        callbacks = [_bar_task(bar, f"{c.algo} {c.task} s{c.seed}", c.episodes) for c in cfgs]
        summaries = train_seeds(cfgs, outs, progress=callbacks)
    for cfg, out, summary in zip(cfgs, outs, summaries):
        Console().print(summary_table(summary, f"{cfg.algo} on {cfg.task} / {cfg.layout} (seed {cfg.seed}) → {out}"))
    return summaries
