"""The ``d2spo export`` command (``cli.commands`` lists it): a run's policy as the small directory a
robot runs with ``d2spo.deploy`` (``d2spo.export``; docs/deploy.md)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated

import tyro

from d2spo.export import ExportConfig, export_run


@dataclasses.dataclass
class ExportCmd:
    """Write a trained policy (D²SPO: π_rl, π_Ω, the barrier h and the runtime filter's settings; other
    learners: their actor) with the map and the task's automaton into DIR, for `d2spo.deploy` (numpy only)."""

    run_dir: tyro.conf.Positional[Path]
    """A run directory written by `d2spo train`."""
    out: Path
    """The directory to write (manifest.json, weights.npz, with --onnx the .onnx graphs); an earlier export there is replaced."""
    cfg: Annotated[ExportConfig, tyro.conf.arg(name="")] = dataclasses.field(default_factory=ExportConfig)

    def run(self) -> int:
        m = export_run(self.run_dir, self.out, self.cfg)
        sizes = m["sizes"]
        files = ", ".join(f"{name} {size / 1024:.0f} KiB" for name, size in sizes.items())
        filt = m["filter"]
        line = "" if filt is None else (f"; runtime filter {'on' if filt['enabled'] else 'off'} by default "
                                        f"(alpha {filt['alpha_coef']:g}, {filt['iters']} iterations)")
        print(f"wrote {self.out}: {m['source']['algo']} on {m['source']['task']} / {m['source']['layout']}, "
              f"policy {m['source']['policy']}{line}")
        print(f"files: {files}; {sum(sizes.values()) / 1024:.0f} KiB in all")
        return 0
