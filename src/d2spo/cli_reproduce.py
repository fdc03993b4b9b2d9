"""The ``d2spo reproduce`` and ``d2spo report`` commands (``cli.commands`` lists them): the paper's
tables and figures, trained and rendered by ``d2spo.reproduce`` and gathered by ``d2spo.report``."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import tyro

from d2spo.errors import ConfigError
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
