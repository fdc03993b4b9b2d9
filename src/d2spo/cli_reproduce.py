"""The ``d2spo reproduce``, ``d2spo report`` and ``d2spo compare`` commands (``cli.commands`` lists
them): the paper's tables and figures, trained and rendered by ``d2spo.reproduce`` and gathered by
``d2spo.report``; a user's own runs side by side (``d2spo.compare``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import tyro

from d2spo.errors import ConfigError
from d2spo.fields import check_fields
from d2spo.report import build_report
from d2spo.reproduce import reproduce


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
    """'local' (in this process: the seeds of a setting vmapped as one program, settings one after another;
    --no-vmap-seeds for one run at a time) or 'ray' (one Ray task per run)."""
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
        if self.address is not None and self.backend != "ray":  # else 18 runs of 20000 episodes start here
            raise ConfigError("address", f"is a Ray cluster's, for --backend ray (given: --backend {self.backend}); "
                              "add --backend ray, or leave --address out")
        reproduce(self.targets, self.out, self.seeds, self.episodes, self.backend, self.address, self.methods,
                  self.progress, train=self.train, vmap_seeds=self.vmap_seeds, allow_stale=self.allow_stale)
        return 0


@dataclasses.dataclass
class ReportCmd:
    """Gather the tables and figures of `d2spo reproduce` into OUT/report.md."""

    out: tyro.conf.Positional[Path] = Path("results")
    """The --out directory of `d2spo reproduce`."""

    def run(self) -> int:
        print(build_report(self.out))
        return 0


@dataclasses.dataclass
class CompareCmd:
    """Compare your own runs (any learners, seeds, task and layout: `d2spo train --algo A --seed S ...`):
    one row per learner with safety, completion (a patrol: its visits of the route-optimal count) and
    the collisions over all training episodes; writes OUT/compare.md, compare.csv and compare.png."""

    runs: tyro.conf.Positional[list[Path]]
    """Run directories of `d2spo train`, finished, of one task on one layout; runs of one learner are
    its seeds."""
    out: Path | None = Path("compare")
    """Where to write compare.md, compare.csv and compare.png (the return and the cumulative collisions
    over training); None (`--out None`): print the table only."""
    smooth: int = 200
    """Episodes per point of the return's moving average (at most a fifth of a short run)."""

    def run(self) -> int:
        from d2spo.compare import compare

        check_fields(self, count=("smooth",))
        text, written = compare(self.runs, self.out, self.smooth)
        print(text, end="")
        for path in written:
            print(f"wrote {path}")
        return 0
