"""Progress of training runs (a live bar on a terminal, plain lines in a log) and the summary table
around ``d2spo.train.train`` (CLI side only)."""

from __future__ import annotations

import time
from pathlib import Path

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Column, Table
from rich.text import Text

from d2spo.checkpoint import has_checkpoint
from d2spo.config import TrainConfig
from d2spo.run import default_out, load_run_config
from d2spo.train import train, train_seeds


def summary_table(summary: dict, title: str):
    t = Table(title=title)
    t.add_column("metric")
    t.add_column("value", justify="right")
    pct = lambda v: f"{100 * v:.2f}%"
    t.add_row("episodes", str(summary["episodes"]))
    t.add_row("env steps", f"{summary['env_steps']:,}")
    t.add_row("wall time, training", f"{summary['wall_seconds']:.0f} s ({summary['env_steps_per_second']:,.0f} steps/s)")
    if "wall_seconds_total" in summary:  # summaries written before compilation was timed lack it
        t.add_row("wall time, all (env, compiling, final eval)",
                  f"{summary['wall_seconds_total']:.0f} s (compiling {summary['compile_seconds']:.0f} s)")
        if summary.get("compile_seconds_saved", 0.0) >= 0.5:  # programs loaded from the persistent cache
            t.add_row("compile time the cache saved", f"{summary['compile_seconds_saved']:.0f} s")
    recurrence = "route_optimal_visits" in summary  # no episode completes it: scored by its visits
    t.add_row(f"safety rate (last {summary['window_episodes']})", pct(summary["safety_rate"]))
    if "collisions_all" in summary:  # absent from a summary.json written before 2026-12-03
        t.add_row(f"collisions, all {summary['episodes']} training episodes", f"{summary['collisions_all']:,}")
    if not recurrence:
        t.add_row(f"completion rate (last {summary['window_episodes']})", pct(summary["completion_rate"]))
        t.add_row("completion rate, relaxed labelling", pct(summary["completion_rate_relaxed"]))
    if summary.get("rejection_rate", 0.0) > 0.0:  # what the task forbids entered (a 'never' part, an order)
        t.add_row(f"rejected by the task (last {summary['window_episodes']})", pct(summary["rejection_rate"]))
    if "accepting_visits_per_episode" in summary:  # a Büchi task
        t.add_row(f"accepting visits per episode (last {summary['window_episodes']})",
                  f"{summary['accepting_visits_per_episode']:.2f}")
        if summary.get("visit_fraction") is not None:  # a recurrence on one layout
            t.add_row("  of the route-optimal visits per episode",
                      f"{summary['accepting_visits_per_episode']:.2f} of {summary['route_optimal_visits']} "
                      f"({100 * summary['visit_fraction']:.1f}%)")
    if "eval" in summary:
        e = summary["eval"]
        t.add_row(f"final policy: safety ({e['episodes']} episodes)", pct(e["safety_rate"]))
        if not recurrence:
            t.add_row(f"final policy: completion ({e['episodes']} episodes)", pct(e["completion_rate"]))
        if "accepting_visits_per_episode" in e:
            t.add_row("final policy: accepting visits per episode", f"{e['accepting_visits_per_episode']:.2f}")
    if "eval_best" in summary:  # the validated policy (`d2spo eval`'s default), on the same episodes
        e = summary["eval_best"]
        at = (summary.get("validation") or {}).get("best", {}).get("episodes")
        kept = "kept policy" + (f" (episode {at})" if at is not None else "")
        t.add_row(f"{kept}: safety", pct(e["safety_rate"]))
        if not recurrence:
            t.add_row(f"{kept}: completion", pct(e["completion_rate"]))
        if "accepting_visits_per_episode" in e:
            t.add_row(f"{kept}: accepting visits per episode", f"{e['accepting_visits_per_episode']:.2f}")
    return t


def train_with_progress(cfg: TrainConfig, out: Path | None, resume: Path | None, show: bool) -> int:
    console = Console(stderr=True)
    if resume is not None:
        cfg = load_run_config(resume)
        out = resume
    cfg = cfg.check()
    out = Path(out) if out is not None else default_out(cfg)
    with progress_display(console, show) as display:
        on_event = display.add(_label(cfg), cfg.episodes)
        try:
            summary = train(cfg, out, resume=resume is not None, progress=on_event)
        except KeyboardInterrupt as e:  # the CLI's "interrupted" line says how to go on, where it can
            if has_checkpoint(out):  # of the same type: Ctrl-C's, or SIGTERM's (interrupts.Terminated)
                raise type(e)(f"`d2spo train --resume {out}` continues from its last checkpoint") from None
            raise
    Console().print(summary_table(summary, f"{cfg.algo} on {cfg.task} / {summary.get('layout', cfg.layout)} (seed {cfg.seed}) → {out}"))
    return 0


def train_seeds_with_progress(cfgs: list[TrainConfig], outs: list[Path], show: bool) -> list[dict]:
    """``d2spo.train.train_seeds`` (seeds vmapped together) with one progress row per seed."""

    console = Console(stderr=True)
    cfgs = [c.check() for c in cfgs]
    with progress_display(console, show) as display:
        callbacks = [display.add(f"{_label(c)} s{c.seed}", c.episodes) for c in cfgs]
        summaries = train_seeds(cfgs, outs, progress=callbacks)
    for cfg, out, summary in zip(cfgs, outs, summaries):
        Console().print(summary_table(summary, f"{cfg.algo} on {cfg.task} / {summary.get('layout', cfg.layout)} (seed {cfg.seed}) → {out}"))
    return summaries


def _label(cfg: TrainConfig, width: int = 22) -> str:
    text = f"{cfg.algo} {cfg.task}"
    return text if len(text) <= width else text[: width - 1] + "…"


# ----------------------------------------------------------------------------------- displays
# ``train`` calls a run's callback with {"phase": "compiling"}, {"phase": "compiled",
# "compile_seconds"}, then once per chunk with the counters and rates (no "phase"), and
# {"phase": "evaluating"} before the final evaluation.


def _stats(d: dict, eps_per_s: float) -> str:
    pct = lambda v: "–" if v != v else f"{100 * v:.1f}%"  # NaN before the first episode ends
    visits = f" · visits {d['accepting_visits']:.2f}/ep" if "accepting_visits" in d else ""  # a Büchi task
    done = "" if d.get("recurrence") else (  # a patrol: no episode completes it
        f" · done {pct(d['completion_rate'])} (relaxed {pct(d['completion_rate_relaxed'])})")
    rejected = f" · rejected {pct(d['rejection_rate'])}" if d.get("rejection_rate", 0.0) > 0.0 else ""
    window = f" · last {d['window_episodes']}:" if "window_episodes" in d else " ·"
    return f"{eps_per_s:.1f} ep/s{window} safe {pct(d['safety_rate'])}{visits}{done}{rejected}"


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def progress_display(console, show: bool):
    """A context manager whose ``add(label, total)`` returns the progress callback of one run: a
    live bar on a terminal; plain periodic lines when the output is a log, CI or nohup; nothing
    with ``show=False``."""
    if not show:
        return _Silent()
    if console.is_terminal:
        return _Bars(console)
    return _Lines(console.file)


class _Silent:
    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def add(self, label: str, total: int):
        return None


class _Bars:
    """rich bars, two lines per run, so that at 80 columns the first keeps the episode count and the
    ETA: ``label [bar] 1200/20000 episodes 0:01:02 eta 0:10:00``, then the phase or the rates."""

    def __init__(self, console):
        class TwoLines(Progress):
            def get_renderables(self):
                for task in self.tasks:
                    yield self.make_tasks_table([task])
                    yield Text("  " + task.fields["stats"], style="dim", no_wrap=True, overflow="ellipsis")

        self.bar = TwoLines(
            TextColumn("[bold]{task.description}"), BarColumn(bar_width=None, table_column=Column(ratio=1)),
            MofNCompleteColumn(), TextColumn("episodes"), TimeElapsedColumn(), TextColumn("eta"),
            TimeRemainingColumn(), console=console, expand=True,
        )

    def __enter__(self):
        self.bar.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.bar.__exit__(*exc)

    def add(self, label: str, total: int):
        bar = self.bar
        task = bar.add_task(label, total=total, stats="starting…")
        t_train = [0.0]

        def on_event(d: dict) -> None:
            phase = d.get("phase")
            if phase == "compiling":
                bar.update(task, completed=d["episodes"], stats="compiling the learner (once per run)…")
            elif phase == "compiled":
                t_train[0] = time.perf_counter()
                bar.update(task, stats=f"compiled in {d['compile_seconds']:.0f} s; training…")
            elif phase == "evaluating":
                bar.update(task, stats=f"evaluating the final policy ({d['episodes']} episodes)…")
            else:
                eps_per_s = d["episodes"] / max(d["wall_seconds"], 1e-9)
                bar.update(task, completed=d["episodes"], stats=_stats(d, eps_per_s))

        return on_event


class _Lines:
    """Plain lines for a log: the phases, the first chunk that ends an episode, then a line once
    ``every`` seconds have passed since the last, and the last one, e.g.
    ``label: 1200/20000 episodes (6%), 0:01:02, eta 0:10:00, 26.1 ep/s · safe …``. The first line's
    ETA is ``…``: its few episodes are those that ended first; later lines take the pace since the first
    line that ended episodes (``…`` while none has ended since), and the last says ``eta 0:00:00``."""

    def __init__(self, file, every: float = 30.0):
        self.file, self.every = file, every

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def _print(self, text: str) -> None:
        print(text, file=self.file, flush=True)

    def add(self, label: str, total: int):
        t = {"start": time.perf_counter(), "train": None, "episodes0": 0, "last": None}

        def on_event(d: dict) -> None:
            now = time.perf_counter()
            phase = d.get("phase")
            if phase == "compiling":
                t["episodes0"] = d["episodes"]
                self._print(f"{label}: compiling the learner (once per run)…")
            elif phase == "compiled":
                t["train"] = now
                self._print(f"{label}: compiled in {d['compile_seconds']:.1f} s; training "
                            f"{total - d['episodes']} episodes")
            elif phase == "evaluating":
                self._print(f"{label}: evaluating the final policy ({d['episodes']} episodes)…")
            elif ((t["last"] is None and d["episodes"] > t["episodes0"]) or d["episodes"] >= total
                  or now - (t["last"] or t["train"] or t["start"]) >= self.every):
                since = t["train"] if t["train"] is not None else t["start"]
                first = t.get("first")
                if first is not None and now > first[0] and d["episodes"] > first[1]:
                    # the pace since the first line that ended episodes, past the start's ramp
                    rate = (d["episodes"] - first[1]) / (now - first[0])
                    eta = _clock((total - d["episodes"]) / rate)
                else:  # no pace yet: the first episodes are few (every env started at once), or none since
                    rate = (d["episodes"] - t["episodes0"]) / max(now - since, 1e-9)
                    eta = "…"
                    if first is None and d["episodes"] > t["episodes0"]:
                        t["first"] = (now, d["episodes"])
                if d["episodes"] >= total:  # done: nothing left, whichever line it is
                    eta = _clock(0)
                t["last"] = now
                self._print(f"{label}: {d['episodes']}/{total} episodes ({100 * d['episodes'] / total:.0f}%), "
                            f"{_clock(now - t['start'])}, eta {eta}, {_stats(d, rate)}")

        return on_event


class EvalProgress:
    """``with EvalProgress(console, show, label) as on_layout: evaluate_run(..., on_layout=on_layout)``:
    the layouts of a `d2spo eval` as they run (the first compiles the rollout). A transient bar on a
    terminal; on a log, a line for the first layout, then at most one per ``every`` seconds, and one
    when all are done; nothing with ``show=False`` (the callback is then None)."""

    def __init__(self, console, show: bool, label: str, every: float = 30.0):
        self.console, self.show, self.label, self.every = console, show, label, every
        self.bar = self.task = None
        self.start = self.last = 0.0

    def __enter__(self):
        if not self.show:
            return None
        self.start = time.perf_counter()
        if self.console.is_terminal:
            self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                TextColumn("layouts"), TimeElapsedColumn(), console=self.console, transient=True)
            self.bar.__enter__()
        return self._on_layout

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.__exit__(*exc)

    def _on_layout(self, k: int, n: int, name: str | None) -> None:
        now = time.perf_counter()
        doing = ("done" if k == n else f"layout {name!r}" + (" (compiling the rollout first)" if k == 0 else ""))
        if self.bar is not None:
            if self.task is None:
                self.task = self.bar.add_task(self.label, total=n)
            self.bar.update(self.task, completed=k, description=f"{self.label}: {doing}")
        elif k == 0 or k == n or now - self.last >= self.every:
            self.last = now
            print(f"{self.label}: {k}/{n} layouts evaluated, {_clock(now - self.start)}; {doing}",
                  file=self.console.file, flush=True)


class StageProgress:
    """``with StageProgress(console, show, label) as on_stage: certify_run(..., on_stage=on_stage)``:
    the stages of a command whose parts cannot be counted ahead (``d2spo certify``). A transient spinner
    with the stage and the time so far on a terminal; on a log a line as each stage starts; nothing with
    ``show=False`` (the callback is then None)."""

    def __init__(self, console, show: bool, label: str):
        self.console, self.show, self.label = console, show, label
        self.bar = self.task = None
        self.start = 0.0

    def __enter__(self):
        if not self.show:
            return None
        self.start = time.perf_counter()
        if self.console.is_terminal:
            self.bar = Progress(SpinnerColumn(), TextColumn("[bold]{task.description}"), TimeElapsedColumn(),
                                console=self.console, transient=True)
            self.bar.__enter__()
            self.task = self.bar.add_task(self.label, total=None)
        return self._on_stage

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.__exit__(*exc)

    def _on_stage(self, stage: str) -> None:
        if self.bar is not None:
            self.bar.update(self.task, description=f"{self.label}: {stage}")
        else:
            print(f"{self.label}: {stage} ({_clock(time.perf_counter() - self.start)} so far)",
                  file=self.console.file, flush=True)
