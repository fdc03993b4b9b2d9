"""The ``d2spo`` command line. Built with tyro from the frozen config dataclasses.

Every mistake a user can make (a formula, a layout, a flag, a run directory) ends in one line on
stderr and exit status 2, never a traceback; a fault of the machine (a full disk, a read-only
directory) in one line and exit status 1.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import sys
import threading
import warnings
from pathlib import Path
from typing import Annotated, Union

import tyro
from rich.console import Console

from d2spo import compile_cache, interrupts
from d2spo.algos import LEARNERS, config_sections
from d2spo.cli_certify import CertifyCmd
from d2spo.cli_docs import DocsCmd
from d2spo.cli_env import ENV_SUBCOMMANDS, EnvCmd
from d2spo.cli_export import ExportCmd
from d2spo.cli_ltl import LtlCmd
from d2spo.cli_reproduce import CompareCmd, ReportCmd, ReproduceCmd
from d2spo.config import CBF_FILLED_FIELDS, TrainConfig, config_file
from d2spo.config_diff import flags_given, other_learners_flag
from d2spo.config_flags import algo_named, config_file_named, flags_for, plain
from d2spo.console import (
    as_typed,
    error,
    flag_of_value,
    forbidden_note,
    print_evaluation,
    show_warning,
    tyro_error_line,
    version,
)
from d2spo.demo import run_demo
from d2spo.envs.dynamics import load_dynamics
from d2spo.errors import ConfigError, D2SPOWarning, LTLSyntaxError, NaNError, UserError
from d2spo.evalfiles import write_evaluation
from d2spo.evaluate import EvalConfig, evaluate_run
from d2spo.fields import check_fields
from d2spo.plotstyle import check_picture_path
from d2spo.progress import EvalProgress, train_with_progress


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
        return run_demo(self.out, self.seed, self.episodes)


@dataclasses.dataclass
class TrainCmd:
    """Train a learner on an LTL task; writes config.json, episodes.csv, summary.json, checkpoints. The
    flags listed are those of the learner --algo names (default d2spo): `d2spo train --algo cpo --help`."""

    cfg: Annotated[TrainConfig, tyro.conf.arg(name="")]
    from_config: Annotated[Path | None, tyro.conf.arg(name="config")] = None
    """Train from this config.json (as a run directory holds it); flags given beside it override its fields."""
    out: Path | None = None
    """Run directory; None: runs/ALGO-TASK-LAYOUT-sSEED."""
    resume: Path | None = None
    """Resume this run directory (its config.json wins)."""
    progress: bool = True
    """Show a progress bar (plain lines if not a terminal)."""
    dynamics: Path | None = None
    """JSON file of the robot's dynamics (docs/env.md): replaces the preset's; flags like --v-gain override it."""

    def config(self) -> TrainConfig:
        """The run's config: the flags, with the --dynamics file filling the dynamics fields they leave unset."""
        cfg = plain(self.cfg)
        if self.resume is not None and self.from_config is not None:
            raise ConfigError("resume", "continues the run with its own config.json; leave out --config")
        if self.resume is not None:  # the run's own config.json wins: a flag beside it would be ignored
            given = [f for f, v in (("--out", self.out), ("--dynamics", self.dynamics)) if v is not None]
            if given := given + flags_given(cfg):
                raise ConfigError("resume", f"continues the run with its own config.json; leave out {', '.join(given)}")
        base = config_file(self.from_config) if self.from_config is not None else None
        typed = getattr(self, "typed", ())  # the command line as typed (parse sets it)
        if base is not None and base.fast and not cfg.fast:
            cfg = without_fast(cfg, self.from_config, typed)
        if self.dynamics is None:
            return cfg
        values = load_dynamics(self.dynamics)
        # A field no flag set takes the file's value: None, or with --config the file's default (its
        # config.json records every value of a robot given before, which the new file replaces) unless
        # typed again (`--config RUN/config.json --dynamics new.json --v-gain 0.85`, the config's value)

        def unset(section: str, k: str) -> bool:
            now = getattr(getattr(cfg, section), k)
            return now is None or (base is not None and now == getattr(getattr(base, section), k)
                                   and not flag_typed(f"{section}.{k}" if section == "cbf" else k, typed,
                                                      exact=section == "env"))

        env = dataclasses.replace(cfg.env, **{k: v for k, v in values.items() if unset("env", k)})
        # UPDATE(Ω, Θ)'s step counts and minibatch the flags left unset follow the file's robot, not the preset's
        filled = set(getattr(cfg, "filled_cbf_fields", ()))
        if base is not None:
            filled |= {k for k in CBF_FILLED_FIELDS if unset("cbf", k)}
        cbf = dataclasses.replace(cfg.cbf, **dict.fromkeys(sorted(filled)))
        return dataclasses.replace(cfg, env=env, cbf=cbf)

    def run(self) -> int:
        return train_with_progress(self.config(), self.out, self.resume, self.progress)


def flag_typed(field: str, typed: tuple[str, ...], exact: bool = False) -> bool:
    """Whether a flag of the command line ``typed`` sets the config field ``field`` (``num_envs``,
    ``td3.hidden``, ``v_gain``): --num-envs, --td3.hidden, --td3-lag.td3.hidden, --v-gain=0.85, --v_gain ...
    A field of a section is named with it (``cbf.d``): the flag's last parts must match; ``exact``:
    only --FIELD itself (the env's fields, whose flags have no section: --v-max, --dt)."""
    name = field.replace("_", "-")
    flags = [a.split("=", 1)[0].replace("_", "-") for a in typed if a.startswith("--")]  # tyro takes --v_max too
    return any(f == f"--{name}" or (not exact and f.endswith(f".{name}")) for f in flags)


def without_fast(cfg: TrainConfig, path: Path, typed: tuple[str, ...]) -> TrainConfig:
    """``--config`` of a ``--fast`` run with ``--no-fast`` (or the config.json of a --fast run given
    to another learner, which must say --no-fast): the values --fast filled (``FAST_SETTINGS``, and
    UPDATE(Ω, Θ)'s step counts and minibatch) that no flag of ``typed`` (the command line) sets are unset, so that
    this learner's own defaults fill them, and a warning names each change. They used to stay: a
    baseline trained on a D²SPO --fast run's config took its 32 envs, half its own update rate,
    without a word (a user trial, 2026-12-03)."""
    def free(field: str) -> bool:
        return not flag_typed(field, typed)

    filled = {k: None for k in CBF_FILLED_FIELDS if free(f"cbf.{k}")}
    new = dataclasses.replace(cfg, num_envs=None if free("num_envs") else cfg.num_envs,
                              td3=dataclasses.replace(cfg.td3, hidden=None) if free("td3.hidden") else cfg.td3,
                              cbf=dataclasses.replace(cfg.cbf, **filled))
    changed = [f"{name} {was} -> {now}" for name, was, now in (
        ("num_envs", cfg.num_envs, new.num_envs), ("td3.hidden", list(cfg.td3.hidden), list(new.td3.hidden)),
        *((f"cbf.{k}", getattr(cfg.cbf, k), getattr(new.cbf, k)) for k in filled if "cbf" in config_sections(new.algo)))
               if was != now]
    if changed:
        warnings.warn(f"{path} is a --fast run's config; without --fast, the values --fast gave it follow "
                      f"{new.algo}'s defaults: {', '.join(changed)} (give them as flags to keep them)",
                      D2SPOWarning, stacklevel=2)
    return new


@dataclasses.dataclass
class EvalCmd:
    """Run a trained policy without exploration noise; prints safety and completion rates (per layout with
    --layout-seeds) and writes them to RUN_DIR/eval-LAYOUT[xN]-DYNAMICS[-TASK][-TSTEPS][-sSEED][-rR][-best][-filter-aA-iN].json
    (LAYOUT a layout file's stem and its content's hash; docs/runs.md)."""

    run_dir: tyro.conf.Positional[Path]
    """A run directory written by `d2spo train`."""
    cfg: Annotated[EvalConfig, tyro.conf.arg(name="")]
    plot: Path | None = None
    """Also draw the trajectories of the first --plot-episodes episodes on each layout (the first 6
    layouts of --layout-seeds), coloured by outcome, into this picture (.png at 300 dpi, .pdf or .svg)."""
    plot_episodes: int = 8
    """With --plot: episodes drawn per layout."""
    progress: bool = True
    """Show the layouts' progress (a bar on a terminal, plain lines if not)."""

    def run(self) -> int:
        keep = 0
        if self.plot is not None:  # checked before the rollouts, which may take minutes
            check_fields(self, count=("plot_episodes",))
            check_picture_path(self.plot, "plot")
            keep = self.plot_episodes
        with EvalProgress(Console(stderr=True), self.progress, f"eval {self.run_dir.name}") as on_layout:  # as train's
            res = evaluate_run(self.run_dir, self.cfg, keep_paths=keep, on_layout=on_layout)
        paths = res.pop("paths", None)
        print_evaluation(res, write_evaluation(self.run_dir, res), filter_asked=self.cfg.runtime_filter)
        if paths is not None:
            from d2spo.plots import evaluation_figure  # matplotlib: imported only to draw

            filt = "" if res["runtime_filter"] is None else f", runtime filter {'on' if res['runtime_filter'] else 'off'}"
            evaluation_figure(self.plot, paths, res["per_layout"],
                              f"{self.run_dir.name}: {res['task']} / {res['dynamics']}{filt}{forbidden_note(res)}")
            print(f"wrote {self.plot}")
        return 0


def commands(algo: str, base: TrainConfig | None = None):
    """The subcommands, ``train`` with the flags of the learner ``algo`` (``config_flags.flags_for``), their
    defaults ``base``'s (the ``--config`` file's) if given."""
    flags = flags_for(algo)
    train = dataclasses.make_dataclass("TrainCmd", [("cfg", Annotated[flags, tyro.conf.arg(name="")])],
                                       bases=(TrainCmd,))
    train.__doc__ = TrainCmd.__doc__
    default = None if base is None else train(cfg=flags(**{f.name: getattr(base, f.name)
                                                            for f in dataclasses.fields(TrainConfig)}))
    return Union[(Annotated[train, tyro.conf.subcommand("train", default=default)],
                  *(Annotated[cmd, tyro.conf.subcommand(name)] for name, cmd in SUBCOMMANDS.items()))]


SUBCOMMANDS = {"eval": EvalCmd, "ltl": LtlCmd, "env": EnvCmd, "demo": DemoCmd, "reproduce": ReproduceCmd,
               "report": ReportCmd, "compare": CompareCmd, "certify": CertifyCmd, "export": ExportCmd,
               "docs": DocsCmd}
"""The subcommands after ``train`` (whose flags depend on ``--algo``: ``commands``), by name."""


def help_command(args: list[str]) -> str:
    """The help a usage error points to: the subcommand's (``d2spo env show --help``) when ``args``
    name one, else ``d2spo --help``; for ``train``, whose help lists the chosen learner's flags,
    with the ``--algo`` the command line gave."""
    words = ["d2spo"]
    if args and (args[0] == "train" or args[0] in SUBCOMMANDS):
        words.append(args[0])
        if args[0] == "env" and len(args) > 1 and args[1] in ENV_SUBCOMMANDS:
            words.append(args[1])
        if args[0] == "train" and algo_named(args) in LEARNERS and (
                "--algo" in args or any(a.startswith("--algo=") for a in args)):
            words += ["--algo", algo_named(args)]
    return " ".join([*words, "--help"])


def usage_hint(args: list[str]) -> str:
    """What a usage error's line ends with: ``see`` the help (``help_command``); for a flag of
    another learner's section, which learners read it and their help."""
    if args[:1] == ["train"] and (other := other_learners_flag(args, algo_named(args))) is not None:
        flag, algos = other
        return (f"{flag} is a flag of --algo {' or --algo '.join(algos)}, not of --algo {algo_named(args)}: "
                f"see d2spo train --algo {algos[0]} --help")
    return f"see {help_command(args)}"


def parse(args: list[str]):
    """Parse the command line; on a usage error print one line and exit 2."""
    if args in (["--version"], ["-V"]):
        print(f"d2spo {version()}")
        raise SystemExit(0)
    base = config_file_named(args)  # `train --config FILE`: its fields are the flags' defaults
    buf = io.StringIO()
    try:
        with contextlib.redirect_stderr(buf):
            cmd = tyro.cli(commands(algo_named(args, base), base), args=args, prog="d2spo",
                           description="D²SPO: safe RL with LTL tasks and learned control barrier functions. "
                                       "`d2spo --version` prints the version.")
    except SystemExit as e:
        if e.code not in (0, None):
            error(as_typed(tyro_error_line(buf.getvalue(), args), args) + f" ({usage_hint(args)})")
            raise SystemExit(2) from None
        raise
    if isinstance(cmd, TrainCmd):  # the flags as typed: which of a --config file's values a flag set again
        cmd.typed = tuple(args)
    return cmd


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    command = argv is None and threading.current_thread() is threading.main_thread()  # the `d2spo` command
    if command:
        interrupts.install()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", D2SPOWarning)
            warnings.showwarning = show_warning
            cmd = parse(args)
            compile_cache.enable()  # before the first compilation: d2spo/compile_cache.py
            status = int(cmd.run() or 0)
            if command:
                interrupts.finished(status)  # a Ctrl-C in teardown now leaves with this status
            return status
    except LTLSyntaxError as e:
        flag = flag_of_value(e.formula, args)  # "--task: LTL syntax error at column 6: ..."
        error(f"{flag + ': ' if flag else ''}{e} in {e.formula!r}")
        if sys.stderr.isatty():  # an interactive user also gets the caret under the column
            print("\n".join(e.pretty().splitlines()[1:]), file=sys.stderr)
        return 2
    except UserError as e:
        error(as_typed(str(e), args))
        return 2
    except NaNError as e:
        error(str(e))
        return 3
    except BrokenPipeError:  # output piped into `head` and the like
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as e:  # the machine's fault: a full disk, a read-only or vanished directory
        error(f"{e.filename}: {e.strerror}" if e.filename and e.strerror else str(e))
        return 1
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (interrupts.Terminated): its line and status
        line, status = interrupts.ending(e)
        error(line + (f"; {e}" if str(e) else ""))  # the hint to resume, where there is one
        if argv is None:  # the `d2spo` command (a caller's main(args) returns): leave now, for an XLA
            sys.stdout.flush()  # compilation still running on another thread would hold the exit for
            sys.stderr.flush()  # its seconds, and interpreter teardown under it has crashed
            os._exit(status)
        return status


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
