"""The ``d2spo certify`` command (``cli.commands`` lists it): Propositions 1-2 checked on a run's
learned CBF (``d2spo.certify``), and with ``--repair`` trained on its counterexamples
(``d2spo.repair``; docs/certify.md)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

from d2spo.certify import CertifyConfig, certify_run, write_outputs
from d2spo.certify_load import load_cbf_run, with_policy
from d2spo.console import print_certify, print_repair_round
from d2spo.errors import UserError
from d2spo.fields import check_choice
from d2spo.progress import StageProgress
from d2spo.repair import RepairConfig, repair_run
from d2spo.run import POLICY_CHOICES


@dataclasses.dataclass
class CertifyCmd:
    """Check Propositions 1-2 (the learned CBF) on a trained d2spo/sl run; writes RUN/certify.json and
    RUN/certify.png. With --repair, trains h and π_Ω on the counterexamples into a new run directory."""

    run_dir: tyro.conf.Positional[Path]
    """A run directory written by `d2spo train --algo d2spo` (or sl)."""
    check: Annotated[CertifyConfig, tyro.conf.arg(name="")] = dataclasses.field(default_factory=CertifyConfig)
    repair: bool = False
    """Add the counterexamples to the datasets and train h and π_Ω until the certified fraction stops rising."""
    out: Path | None = None
    """With --repair: the new run directory (default: RUN-repaired)."""
    fix: Annotated[RepairConfig, tyro.conf.arg(name="")] = dataclasses.field(default_factory=RepairConfig)
    policy: str | None = None
    """Which policy's barrier, π_Ω and actor to check: best (the default: a validated run's kept policy, where
    there is one; the newest checkpoint's otherwise) or last (the newest checkpoint's), as d2spo eval and
    d2spo export take it. --repair trains on from the newest checkpoint: last."""
    progress: bool = True
    """Show which stage runs (a spinner on a terminal, a line per stage if not)."""

    def run(self) -> int:
        console = Console()
        if not console.is_terminal and "COLUMNS" not in os.environ:  # a log or a pipe: rich's 80 columns cut
            console = Console(width=160)  # the table's numbers short ("0.0005…"); a file has room for them all
        if self.repair:
            if self.policy not in (None, "last"):
                raise UserError("--policy: --repair trains on from the newest checkpoint (last), not a kept "
                                "policy; leave --policy out or give last")
            out = self.out or self.run_dir.with_name(self.run_dir.name + "-repaired")
            res = repair_run(self.run_dir, out, self.check, self.fix,
                             progress=lambda r: print_repair_round(console, r, self.fix.eval_episodes))
            print_certify(console, res["after"])
            if res["kept"]:
                print(f"wrote the repaired run {out} (round {res['kept']} kept; certify.json, certify.png, checkpoint)")
            else:  # no round was better in something and worse in nothing, or the kept one evaluated worse
                print(f"no round improved on the original: {out} holds its h, π_Ω and f_n unchanged "
                      "(certify.json, certify.png, checkpoint)")
            return 0
        self._refuse_repair_flags()
        if self.policy is not None:
            check_choice(self, "policy", POLICY_CHOICES)
        run = with_policy(load_cbf_run(self.run_dir), self.run_dir, self.policy or "best")
        with StageProgress(Console(stderr=True), self.progress, f"certify {self.run_dir.name}") as on_stage:
            summary, nets = certify_run(self.run_dir, self.check, run=run, on_stage=on_stage)
            if on_stage is not None:
                on_stage("drawing certify.png")
            j, p = write_outputs(self.run_dir, run, self.check, summary, nets)
        print_certify(console, summary)
        print(f"wrote {j} and {p}")
        return 0

    def _refuse_repair_flags(self) -> None:
        """Without --repair, the flags whose help begins "With --repair:" would be ignored: refused."""
        given = ["--out"] if self.out is not None else []
        given += [f"--{f.name.replace('_', '-')}" for f in dataclasses.fields(RepairConfig)
                  if getattr(self.fix, f.name) != f.default]
        if given:
            one = len(given) == 1
            raise UserError(f"{', '.join(given)} {'acts' if one else 'act'} only with --repair; add --repair, "
                            f"or leave {'it' if one else 'them'} out")
