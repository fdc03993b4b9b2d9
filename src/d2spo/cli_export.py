"""The ``d2spo export`` command (``cli.commands`` lists it): a run's policy as the small directory a
robot runs with ``d2spo.deploy`` (``d2spo.export``; docs/deploy.md)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated

import tyro

from d2spo.errors import RunDirError
from d2spo.export import ExportConfig, export_run
from d2spo.runio import read_json


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
        trained_on = m["config"].get("d2spo", {}).get("runtime_filter")
        if filt is not None and self.cfg.runtime_filter is None and not trained_on:
            print(FILTER_NOTE)
        print(evaluated_line(self.run_dir, m))
        return 0


FILTER_NOTE = ("note: the runtime filter is on by default in an export: a robot's dynamics are not the simulator's, "
               "and `d2spo eval` turns it on under other dynamics; the run trained and was evaluated without it: "
               "--runtime-filter False, or act(..., filter=False), for π_Ω alone")
"""Said by an export whose filter is on by default because nobody asked, of a run that trained with it
off (D²SPO's default): the figures the export's last line quotes are π_Ω's alone."""


def evaluated_line(run_dir: Path, manifest: dict) -> str:
    """What the run says of the exported policy: its evaluation at the end of training (summary.json),
    or that the run is unfinished and the policy unevaluated."""
    try:
        summary = read_json(run_dir / "summary.json", "the run's summary")
    except RunDirError:  # none (unfinished), or damaged: nothing to quote either way
        summary = None
    if summary is None:
        done, total = manifest["source"].get("episodes"), manifest["config"].get("episodes")
        state = (f"is unfinished ({done} of {total} episodes)" if isinstance(done, int) and isinstance(total, int)
                 and done < total else "has no summary.json")
        return (f"note: the run {state}: this policy has not been evaluated; "
                f"d2spo eval {run_dir} --policy {str(manifest['source']['policy']).split()[0]} first")
    best = str(manifest["source"]["policy"]).startswith("best") and "eval_best" in summary
    e = summary.get("eval_best" if best else "eval")
    if not isinstance(e, dict):
        return "note: summary.json holds no final evaluation of this policy (--eval-episodes 0); d2spo eval it first"
    score = (f"{e['accepting_visits_per_episode']:.2f} accepting visits per episode" if "route_optimal_visits" in summary
             else f"{100 * e['completion_rate']:.2f}% complete")
    return f"evaluated at the end of training ({e['episodes']} episodes): {100 * e['safety_rate']:.2f}% safe, {score}"
