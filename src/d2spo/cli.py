"""The ``d2spo`` command line. Built with tyro from the frozen config dataclasses.

Every mistake a user can make (a formula, a layout, a flag, a run directory) ends in one line on
stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import re
import sys
from pathlib import Path
from typing import Annotated, Union

import tyro

from d2spo.config import TrainConfig
from d2spo.errors import LTLSyntaxError, NaNError, UserError


def _stderr(msg: str) -> None:
    print(f"d2spo: error: {msg}", file=sys.stderr)


# --------------------------------------------------------------------------------------- ltl
@dataclasses.dataclass
class LtlCmd:
    """Translate an LTL formula (or a task name: phi1, phi1-printed, phi2, relaxed) to an automaton."""

    formula: tyro.conf.Positional[str]
    """The formula, e.g. '(!A2 U A1) & F A2', or a named task."""
    json: bool = False
    """Print exactly one JSON object (aps, initial, accepting, rejecting, delta, distance)."""
    dot: bool = False
    """Print the automaton in Graphviz dot format."""
    layout: str | None = None
    """Restrict distances to letters that can occur on this layout (name or JSON file)."""
    label_mode: str = "event"
    """Labelling the distances assume: 'event' (no empty letter) or 'step'."""
    plot: Path | None = None
    """With --layout: draw per automaton state its shaping distance field (--shaping-metric
    geodesic-per-state) with its target and forbidden areas into this PNG, then check the task can be done."""

    def run(self) -> int:
        from d2spo.ltl import task_formula, translate

        if self.json and self.dot:
            raise UserError("--json and --dot are exclusive; choose one")
        if self.plot is not None and self.layout is None:
            raise UserError("--plot needs --layout")
        aut = translate(task_formula(self.formula))
        feasible = None
        if self.layout is not None:
            from d2spo.envs import layouts

            feasible = layouts.feasible_letters(layouts.load(self.layout), aut.aps, self.label_mode)
        if self.json:
            print(json.dumps(aut.to_json(feasible)))
        elif self.dot:
            print(aut.to_dot())
        else:
            print(aut.pretty(feasible))
        if self.plot is not None:
            from d2spo.envs.state_fields import plot_state_fields

            plot_state_fields(aut, self.formula, self.layout, self.label_mode, self.plot)
            print(f"wrote {self.plot}")
        return 0


# --------------------------------------------------------------------------------------- env
@dataclasses.dataclass
class EnvShowCmd:
    """Draw a layout: obstacles, labelled areas, the start and the sensing radius."""

    layout: str = "paper"
    """Built-in layout name (paper, relaxed, open, random[:SEED], physical-1..4) or a JSON file."""
    out: Path = Path("layout.png")
    """Where to write the PNG."""
    rollout_steps: int = 0
    """If > 0, also draw a random-action rollout of this many steps."""
    seed: int = 0
    """Seed for the rollout."""

    def run(self) -> int:
        from d2spo.envs import layouts
        from d2spo.envs.render import save_layout_png

        lay = layouts.load(self.layout)
        trajs = None
        if self.rollout_steps > 0:
            from d2spo.demo import random_rollout

            trajs = [random_rollout(self.layout, self.rollout_steps, self.seed)]
        save_layout_png(lay, self.out, trajectories=trajs)
        print(f"wrote {self.out}")
        return 0


# --------------------------------------------------------------------------------------- demo
@dataclasses.dataclass
class DemoCmd:
    """The main job, short: what `make demo` runs."""

    out: Path = Path("demo_out")
    """Directory for the demo's outputs."""
    seed: int = 0
    """Random seed."""
    episodes: int = 500
    """Training episodes of the short D²SPO run."""

    def run(self) -> int:
        from d2spo.demo import run_demo

        return run_demo(self.out, self.seed, self.episodes)


# ------------------------------------------------------------------------------------- train
@dataclasses.dataclass
class TrainCmd:
    """Train a learner on an LTL task; writes config.json, episodes.csv, summary.json, checkpoints."""

    cfg: Annotated[TrainConfig, tyro.conf.arg(name="")]
    out: Path | None = None
    """Run directory (default: runs/ALGO-TASK-LAYOUT-sSEED)."""
    resume: Path | None = None
    """Continue the interrupted run in this directory (its config.json wins over other flags)."""
    progress: bool = True
    """Show a progress bar."""

    def run(self) -> int:
        from d2spo.progress import train_with_progress

        return train_with_progress(self.cfg, self.out, self.resume, self.progress)


@dataclasses.dataclass
class EvalCmd:
    """Run a trained policy without exploration noise; prints safety and completion rates (per layout with
    --layout-seeds) and writes them to RUN_DIR/eval-LAYOUT[xN]-DYNAMICS[-filter-aA-iN].json."""

    run_dir: tyro.conf.Positional[Path]
    """A run directory written by `d2spo train`."""
    episodes: int = 100
    """Evaluation episodes (run in parallel)."""
    layout: str | None = None
    """Evaluate on another layout (name or JSON file); default: the training layout."""
    dynamics: str | None = None
    """Evaluate under another dynamics preset (ideal, default, turtlebot)."""
    seed: int = 0
    """Seed of the evaluation episodes."""
    layout_seeds: int = 1
    """With --layout random: average over this many random layouts (seeds seed..seed+n-1)."""
    runtime_filter: bool | None = None
    """D²SPO only: switch the runtime safety filter on or off for this evaluation; default: as trained on
    the training layout and dynamics, on elsewhere (π_Ω alone transfers poorly to unseen layouts)."""
    filter_iters: int | None = None
    """D²SPO only: linearise-and-project iterations of the runtime filter; default: as trained."""
    filter_alpha: float | None = None
    """D²SPO only: coefficient of α in the runtime filter's condition (smaller brakes earlier); default: as trained."""

    def run(self) -> int:
        from d2spo.evaluate import eval_command

        return eval_command(self)


@dataclasses.dataclass
class EnvCheckCmd:
    """Validate a layout (built-in or JSON file) and print what it holds."""

    layout: str = "paper"
    """Built-in layout name or a JSON file."""
    task: str = "phi1"
    """Also check that this task can be completed on the layout."""

    def run(self) -> int:
        from d2spo.envs import EnvConfig, make_env

        env, params = make_env(EnvConfig(layout=self.layout), task=self.task)
        lay = env.layout
        print(f"layout {lay.name!r}: arena {lay.arena[0]:g} x {lay.arena[1]:g} m, {len(lay.obstacles)} obstacles, "
              f"areas {', '.join(lay.area_names)}; task {self.task!r} needs "
              f"{int(params.aut.distance[int(params.aut.initial)])} area visits; observation size {env.observation_size}")
        return 0


EnvCommands = Union[
    Annotated[EnvShowCmd, tyro.conf.subcommand("show", prefix_name=False)],
    Annotated[EnvCheckCmd, tyro.conf.subcommand("check", prefix_name=False)],
]


@dataclasses.dataclass
class EnvCmd:
    """Environment tools."""

    cmd: tyro.conf.OmitSubcommandPrefixes[EnvCommands]

    def run(self) -> int:
        return self.cmd.run()


@dataclasses.dataclass
class ReproduceCmd:
    """Reproduce the paper's tables and figures: trains the missing runs, then writes OUT/table2.md, fig2.png, ..."""

    targets: tyro.conf.Positional[list[str]]
    """table2, table3, fig2, fig3, fig4, fig5 or all."""
    seeds: int = 3
    """Seeds per (method, task)."""
    episodes: int = 20_000
    """Training episodes per run (the paper: 20000); smaller for a quick look (fig4 and fig5 scale with it)."""
    out: Path = Path("results")
    """Output directory; finished runs in OUT/runs are reused, interrupted ones resume."""
    backend: str = "local"
    """'local' (one run after another in this process) or 'ray' (one Ray task per run)."""
    address: str | None = None
    """Ray cluster address (with --backend ray); default: start a local Ray instance."""
    methods: tuple[str, ...] = ("cpo", "ppo-lag", "td3-lag", "sac-lag", "rcrl", "d2spo")
    """Rows of Tables II-III and curves of Fig. 2."""
    progress: bool = True
    """Show a progress bar per run (local backend)."""
    train: bool = True
    """Train the missing runs; --no-train only renders what has finished (seed counts are shown)."""
    vmap_seeds: bool = True
    """Local backend: train the seeds of one setting together, vmapped in one program
    (--no-vmap-seeds: one seed after another)."""
    allow_stale: bool = False
    """Use runs in OUT/runs that were trained with other settings than today's defaults (e.g. by
    an older d2spo) instead of stopping; the report counts them."""

    def run(self) -> int:
        from d2spo.reproduce import reproduce

        reproduce(self.targets, self.out, self.seeds, self.episodes, self.backend, self.address, self.methods,
                  self.progress, train=self.train, vmap_seeds=self.vmap_seeds, allow_stale=self.allow_stale)
        return 0


@dataclasses.dataclass
class ReportCmd:
    """Gather the tables and figures of `d2spo reproduce` into OUT/report.md."""

    out: tyro.conf.Positional[Path] = Path("results")
    """The --out directory of `d2spo reproduce`."""

    def run(self) -> int:
        from d2spo.report import build_report

        print(build_report(self.out))
        return 0


Commands = Union[
    Annotated[TrainCmd, tyro.conf.subcommand("train")],
    Annotated[EvalCmd, tyro.conf.subcommand("eval")],
    Annotated[LtlCmd, tyro.conf.subcommand("ltl")],
    Annotated[EnvCmd, tyro.conf.subcommand("env")],
    Annotated[DemoCmd, tyro.conf.subcommand("demo")],
    Annotated[ReproduceCmd, tyro.conf.subcommand("reproduce")],
    Annotated[ReportCmd, tyro.conf.subcommand("report")],
]

_BOX = re.compile(r"[╭╮╰╯│─]+")


def _tyro_error_line(text: str) -> str:
    """Condense tyro's boxed error message into one line."""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    title = ""
    body: list[str] = []
    for ln in lines:
        if ln.lstrip().startswith("╭"):
            title = _BOX.sub(" ", ln).strip()
            continue
        stripped = ln.strip().strip("│").strip()
        if not stripped or set(stripped) <= set("─╰╯"):
            if body:
                break
            continue
        body.append(stripped)
    msg = " ".join(body) or "invalid command line"
    return f"{title}: {msg}" if title else msg


def parse(args: list[str]):
    """Parse the command line; on a usage error print one line and exit 2."""
    buf = io.StringIO()
    try:
        with contextlib.redirect_stderr(buf):
            return tyro.cli(Commands, args=args, prog="d2spo")
    except SystemExit as e:
        if e.code not in (0, None):
            _stderr(_tyro_error_line(buf.getvalue()) + " (see d2spo --help)")
            raise SystemExit(2) from None
        raise


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    cmd = parse(args)
    try:
        return int(cmd.run() or 0)
    except LTLSyntaxError as e:
        _stderr(f"{e} in {e.formula!r}")
        if sys.stderr.isatty():  # an interactive user also gets the caret under the column
            print("\n".join(e.pretty().splitlines()[1:]), file=sys.stderr)
        return 2
    except UserError as e:
        _stderr(str(e))
        return 2
    except NaNError as e:
        _stderr(str(e))
        return 3
    except BrokenPipeError:  # output piped into `head` and the like
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        _stderr("interrupted")
        return 130


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
