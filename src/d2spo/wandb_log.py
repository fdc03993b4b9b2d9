"""The optional Weights & Biases copy of a run's scalars (``--wandb``; ``pip install 'd2spo[wandb]'``).

``d2spo.record.RunRecord`` hands every scalar it writes to TensorBoard to the run's ``WandbRun``
too: the same tags, each at the same step, which W&B holds as the tag's own x axis
(``define_metric``): ``env_steps`` for the learner's metrics and ``charts/``, ``episode`` (the
episode's index) for ``episode/``. wandb is imported here only, and only for a config with
``wandb``. docs/runs.md, "Weights & Biases", says what a user sees.
"""

from __future__ import annotations

import contextlib
import secrets
from collections.abc import Iterator
from pathlib import Path

from d2spo.config import TrainConfig, config_to_dict
from d2spo.errors import UserError
from d2spo.runio import atomic_write_bytes

RUN_ID = "wandb-run-id"
"""The run directory's file holding its W&B run's id, so that a resumed run logs to the same W&B run."""


def require_wandb():
    """The wandb module; a UserError (one line, exit status 2) where it does not import."""
    try:
        import wandb
    except ImportError as e:
        raise UserError(f"--wandb needs the wandb package, which does not import here ({e}): "
                        "pip install 'd2spo[wandb]'") from None
    return wandb


class WandbRun:
    """A run directory's W&B run: named after the directory, its files under DIR/wandb/, the run's
    config.json as its config. ``continuing`` (the run goes on from a checkpoint): the W&B run whose
    id DIR/wandb-run-id holds; otherwise a new one, whose id replaces it."""

    def __init__(self, cfg: TrainConfig, out: Path, continuing: bool):
        wandb = require_wandb()
        path = Path(out) / RUN_ID
        run_id = path.read_text().strip() if continuing and path.is_file() else ""
        if not run_id:
            run_id = secrets.token_hex(8)  # W&B's ids are letters and digits
            atomic_write_bytes(path, run_id.encode())  # before the W&B run starts: a kill leaves it named
        try:
            self.run = wandb.init(project=cfg.wandb_project, name=Path(out).name, id=run_id, resume="allow",
                                  dir=str(out), config=config_to_dict(cfg), reinit="create_new",
                                  # the progress bar is not copied (DIR holds every output)
                                  settings=wandb.Settings(console="off"))
        except wandb.errors.Error as e:  # no API key, an unknown entity, ...
            raise UserError(f"W&B did not start the run ({e}); WANDB_MODE=offline logs without an account") from None
        self.axis: dict[str, str] = {}  # tag -> its x axis, as declared to W&B

    def log(self, scalars: dict[str, float], axis: str, step: int) -> None:
        """``scalars`` at ``step`` of the x axis ``axis`` ("env_steps" or "episode")."""
        for tag in scalars.keys() - self.axis.keys():
            self.run.define_metric(tag, step_metric=axis)
            self.axis[tag] = axis
        self.run.log({axis: step, **scalars})

    def summary(self, summary: dict) -> None:
        """summary.json's content as the W&B run's summary."""
        self.run.summary.update(summary)

    def close(self, exit_code: int = 0) -> None:
        """Finish the W&B run (a second call does nothing); a non-zero ``exit_code`` marks it failed."""
        if self.run is not None:
            run, self.run = self.run, None
            run.finish(exit_code=exit_code)


@contextlib.contextmanager
def wandb_run(cfg: TrainConfig, out: Path, continuing: bool) -> Iterator[WandbRun | None]:
    """The run's ``WandbRun`` (None without ``cfg.wandb``), finished on the way out: failed on an
    exception (an interrupt included), which a failure of W&B's own does not replace."""
    run = WandbRun(cfg, out, continuing) if cfg.wandb else None
    try:
        yield run
    except BaseException:
        if run is not None:
            with contextlib.suppress(Exception):
                run.close(exit_code=1)
        raise
    if run is not None:
        run.close()
