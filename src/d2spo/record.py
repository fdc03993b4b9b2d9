"""The record of a run as it trains: episodes.csv, TensorBoard (and W&B with ``--wandb``), the
counters, the NaN guard, policy snapshots, checkpoints, the kept policy of a validation
(``d2spo.validation``), and summary.json with the final evaluation.

``d2spo.train``'s loops hand every chunk's ``ChunkLog`` to a ``RunRecord`` (one per run directory;
``train_seeds`` has one per seed); the run directory's files are ``d2spo.run``'s and ``runio``'s.
"""

from __future__ import annotations

import errno
import math
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
from flax import serialization
from tensorboardX import SummaryWriter

from d2spo.algos.base import ChunkLog
from d2spo.checkpoint import Checkpoints
from d2spo.config import TrainConfig
from d2spo.errors import NaNError
from d2spo.rollout import make_rollout, rates, visit_optimum
from d2spo.run import best_policy_path, load_best_policy, save_snapshot, snapshot_path
from d2spo.runio import EpisodeWriter, atomic_write_bytes, atomic_write_json, window_rates
from d2spo.validation import PatrolValidation, Validation, better_validation
from d2spo.wandb_log import WandbRun

ProgressFn = Callable[[dict], None]
"""What a run reports its progress to: one dict per event (``d2spo.progress`` draws them)."""
EPISODE_SCALARS = {"episode/return": 1, "episode/cost": 2, "episode/completed": 4}
"""TensorBoard's per-episode scalars (x: the episode's index) and their columns in ``rows_from_log``'s rows."""
ENV_STEPS, EPISODE = "env_steps", "episode"
"""The two x axes of the scalars: the vectorised env steps so far, and the episode's index."""


def rows_from_log(log: ChunkLog, first_episode: int, limit: int) -> list[tuple]:
    """Finished episodes of a chunk, in (step, env) order, at most ``limit`` of them."""
    done = np.asarray(log.done)
    steps, envs = np.nonzero(done)
    if len(steps) == 0 or limit <= 0:
        return []
    steps, envs = steps[:limit], envs[:limit]
    cols = [np.asarray(a)[steps, envs] for a in (
        log.ep_return, log.ep_cost, log.ep_collided, log.ep_completed, log.ep_completed_relaxed, log.ep_length)]
    end = np.asarray(log.ep_end_xy)[steps, envs]
    rows = []
    for i in range(len(steps)):
        rows.append((
            first_episode + i, round(float(cols[0][i]), 5), float(cols[1][i]), int(cols[2][i]),
            int(cols[3][i]), int(cols[4][i]), int(cols[5][i]), round(float(end[i, 0]), 3), round(float(end[i, 1]), 3),
        ))
    return rows


def visits_per_episode(visit, done, running: np.ndarray | None) -> tuple[list[int], np.ndarray]:
    """A Büchi task's accepting visits per episode that ends in a chunk, in ``rows_from_log``'s
    (step, env) order, and each env's count so far in its unfinished episode. ``visit`` and ``done``
    are [chunk_steps, num_envs]; ``running`` the counts the previous chunk left (None: zeros)."""
    visit, done = np.asarray(visit, np.int64), np.asarray(done)
    running = np.zeros(visit.shape[1], np.int64) if running is None else running.copy()
    counts = []
    for t in range(visit.shape[0]):
        running += visit[t]
        for e in np.flatnonzero(done[t]):
            counts.append(int(running[e]))
            running[e] = 0
    return counts, running


class NaNGuard:
    """Stops a run at the first non-finite value it produces, before that chunk's rows are written.

    Parameters (the learner's ``nonfinite`` flag), episode returns and costs, and every metric must
    stay finite. NaN is also how a metric says "no value this step" (no update ran), so a ``losses/``
    metric counts as diverged only once it has had values at some rhythm and then none for twice its
    longest gap seen so far (and at least two chunks)."""

    def __init__(self, chunk_steps: int):
        self.chunk_steps = chunk_steps
        self.last: dict[str, int] = {}  # metric -> vectorised step of its last finite value
        self.gap: dict[str, int] = {}  # metric -> longest run of NaN steps between two values

    def problem(self, log: ChunkLog, rows: list[tuple], first_step: int) -> str | None:
        if bool(log.nonfinite):
            return "non-finite parameters"
        bad = [r[0] for r in rows if not (math.isfinite(r[1]) and math.isfinite(r[2]))]
        if bad:
            return f"a non-finite return or cost in episode {bad[0]}"
        inf = sorted(k for k, v in log.metrics.items() if np.any(np.isinf(np.asarray(v))))
        if inf:
            return f"infinite metrics {inf}"
        end = first_step + self.chunk_steps
        for k, v in log.metrics.items():
            if not k.startswith("losses/"):
                continue
            for i in np.flatnonzero(np.isfinite(np.asarray(v))):
                step = first_step + int(i)
                if k in self.last:
                    self.gap[k] = max(self.gap.get(k, 0), step - self.last[k] - 1)
                self.last[k] = step
            if k in self.gap and end - self.last[k] - 1 > max(2 * self.gap[k], 2 * self.chunk_steps):
                return f"{k} has been NaN for {end - self.last[k] - 1} steps since its last value"
        return None


class RunRecord:
    """The host-side bookkeeping of one run directory: episodes.csv, TensorBoard (and ``wandb``,
    the run's W&B run with ``--wandb``), counters, snapshots, checkpoints and the summary. ``train``
    has one; ``train_seeds`` one per seed."""

    def __init__(self, cfg: TrainConfig, out: Path, meta: dict | None, checkpoints: Checkpoints,
                 overhead: dict | None = None, validation: Validation | PatrolValidation | None = None, wandb: WandbRun | None = None,
                 visits: bool = False, recurrence: bool = False, max_steps: int | None = None):
        self.max_steps = max_steps  # the episode limit: an episode that ends before it unfinished was rejected
        self.cfg, self.out, self.checkpoints, self.validation = cfg, Path(out), checkpoints, validation
        self.recurrence = recurrence  # a patrol: no episode completes it, the progress shows no completion
        self.wandb = wandb
        self.meta = dict(meta or {"episodes": 0, "env_steps": 0, "chunks": 0, "wall_seconds": 0.0})
        # Time outside the training loop, summed over the sessions of a resumed run (0 in checkpoints
        # written before these were counted): compiling the learner, and the rest (building the env).
        for k, v in (overhead or {}).items():
            self.meta[k] = self.meta.get(k, 0.0) + v
        # a Büchi task with accepting visits (``visits``, a patrol): each row ends with its count
        self.writer = EpisodeWriter(self.out / "episodes.csv", keep_rows=self.meta["episodes"], visits=visits)
        self.tb, self.tb_part = _tensorboard(self.out / "tb"), 0
        every = cfg.checkpoint_every
        self.next_ckpt = (self.meta["episodes"] // every + 1) * every
        if validation is not None:
            self.next_validation = (self.meta["episodes"] // cfg.validate_every + 1) * cfg.validate_every
        self.t_start = time.perf_counter() - self.meta["wall_seconds"]
        self.guard = NaNGuard(cfg.chunk_steps)
        # a Büchi task's accepting visits: per episode (the last ``visits_kept``), and per env in its
        # unfinished episode; kept in the checkpoint's meta, so a resumed run counts on exactly
        self.visits: list[int] = list(self.meta.get("visits", []))
        self.visit_run: np.ndarray | None = (None if self.meta.get("visit_run") is None
                                             else np.asarray(self.meta["visit_run"], np.int64))
        self.visits_kept = max(cfg.window, 200)

    @property
    def done(self) -> bool:
        return len(self.writer) >= self.cfg.episodes

    def record(self, log: ChunkLog, progress: ProgressFn | None) -> None:
        """Take in one chunk's log (NaN check, episodes, counters, TensorBoard and W&B, progress)."""
        cfg, writer, meta = self.cfg, self.writer, self.meta
        rows = rows_from_log(log, len(writer), cfg.episodes - len(writer))
        problem = self.guard.problem(log, rows, meta["chunks"] * cfg.chunk_steps)
        if problem is not None:
            last = self.checkpoints.latest
            where = (f"the last checkpoint, after episode {last['episodes']}, is {self.out / 'checkpoint.json'}"
                     if last is not None else f"no checkpoint was written in {self.out} before it")
            raise NaNError(f"training stopped at episode {len(writer)}: {problem}; episodes.csv holds the "
                           f"episodes before it and {where}")
        counts = None
        if log.accepting_visit is not None:  # a Büchi task (``ltl.buchi_task``)
            counts, self.visit_run = visits_per_episode(log.accepting_visit, log.done, self.visit_run)
            counts = counts[:len(rows)]
            self.visits = (self.visits + counts)[-self.visits_kept:]
            meta["visits"], meta["visit_run"] = list(self.visits), self.visit_run.tolist()
        if writer.visits:
            rows = [row + (int(c),) for row, c in zip(rows, counts, strict=True)]
        writer.append(rows)
        meta["chunks"] += 1
        meta["env_steps"] += cfg.chunk_steps * cfg.num_envs
        meta["episodes"] = len(writer)
        meta["wall_seconds"] = time.perf_counter() - self.t_start
        scalars = {}
        for k, v in log.metrics.items():
            v = np.asarray(v, dtype=np.float64)
            if np.any(np.isfinite(v)):
                scalars[k] = float(np.nanmean(v))
        if rows:
            rates = window_rates(writer.rows, 100)
            scalars.update({"charts/safety_rate_100": rates["safety_rate"],
                            "charts/completion_rate_100": rates["completion_rate"],
                            "charts/completion_rate_relaxed_100": rates["completion_rate_relaxed"]})
        self.scalars(scalars, ENV_STEPS, meta["env_steps"])
        for i, row in enumerate(rows):  # per finished episode, at its index (about 0.1 ms each)
            episode = {tag: row[col] for tag, col in EPISODE_SCALARS.items()}
            if counts is not None:
                episode["episode/accepting_visits"] = counts[i]
            self.scalars(episode, EPISODE, row[0])
        if progress is not None:
            progress({"episodes": len(writer), "total": cfg.episodes, "env_steps": meta["env_steps"],
                      "wall_seconds": meta["wall_seconds"], **window_rates(writer.rows, 200, self.max_steps),
                      **({"accepting_visits": float(np.mean(self.visits[-200:]))} if self.visits else {}),
                      **({"recurrence": True} if self.recurrence else {})})

    def save(self, learner, carry, force: bool = False) -> bool:
        """Snapshots that are due, and the checkpoint every ``checkpoint_every`` episodes (or now).
        Returns whether a checkpoint was written."""
        n_done = len(self.writer)
        for n in self.cfg.snapshots:
            if n_done >= n and not snapshot_path(self.out, n).exists():
                save_snapshot(self.out, n, learner.policy(carry))
        if self.validation is not None and (n_done >= self.next_validation or self.done):
            self.validate(learner.policy(carry))
        if force or n_done >= self.next_ckpt or self.done:
            self.writer.sync()
            self.tb_part += 1  # TensorBoard survives a kill as far as the checkpoint does
            self.tb = durable_tensorboard(self.tb, self.out / "tb", self.tb_part)
            self.checkpoints.save(carry, self.meta)
            every = self.cfg.checkpoint_every
            self.next_ckpt = (n_done // every + 1) * every
            return True
        return False

    def validate(self, policy) -> None:
        """Run the validation (``Validation``) on ``policy`` and keep it as DIR/policy-best.msgpack if
        it is at least as good as every earlier one (``better_validation``); the scores go into the
        counters."""
        n_done = len(self.writer)
        history = self.meta.setdefault("validation", [])
        if history and history[-1]["episodes"] == n_done:
            return
        t = time.perf_counter()
        entry = {"episodes": n_done, **self.validation(policy)}
        best = self.meta.get("best")
        if best is None or better_validation(entry, best):
            atomic_write_bytes(best_policy_path(self.out), serialization.to_bytes(jax.device_get(policy)))
            self.meta["best"] = entry
        history.append(entry)
        self.meta["validation_seconds"] = self.meta.get("validation_seconds", 0.0) + time.perf_counter() - t
        every = self.cfg.validate_every
        self.next_validation = (n_done // every + 1) * every
        self.scalars({"charts/validation_success": entry["success_rate"]}, ENV_STEPS, self.meta["env_steps"])

    def scalars(self, scalars: dict[str, float], axis: str, step: int) -> None:
        """Scalars at ``step`` of the x axis ``axis`` (``ENV_STEPS`` or ``EPISODE``): to TensorBoard,
        and to W&B with ``--wandb``."""
        check_tensorboard(self.tb, self.out / "tb")
        for tag, value in scalars.items():
            self.tb.add_scalar(tag, value, step)
        if self.wandb is not None and scalars:
            self.wandb.log(scalars, axis, step)

    def finish(self, learner, carry, env, params, progress: ProgressFn | None = None, untrained=None) -> dict:
        """summary.json. Wall times: ``wall_seconds`` is the training loop alone (no compilation; the
        steps per second use it), ``compile_seconds`` the compilation of the learner (with
        ``compile_seconds_saved`` what the persistent cache saved of it, by JAX's reckoning), and
        ``wall_seconds_total`` everything ``train`` spent: building the env, compiling, training and
        the final evaluation, over every session of a resumed run."""
        cfg = self.cfg
        wall = time.perf_counter() - self.t_start
        self.tb.close()
        summary = {
            "algo": cfg.algo, "task": cfg.task, "seed": cfg.seed,
            "layout": f"{cfg.generalist_world}:0..{cfg.generalist_layouts - 1}" if cfg.generalist else cfg.layout,
            "episodes": len(self.writer), "env_steps": self.meta["env_steps"], "wall_seconds": round(wall, 2),
            "compile_seconds": round(self.meta.get("compile_seconds", 0.0), 2),
            "compile_seconds_saved": round(self.meta.get("compile_seconds_saved", 0.0), 2),
            "env_steps_per_second": round(self.meta["env_steps"] / max(wall, 1e-9), 1),
            "window": cfg.window, **window_rates(self.writer.rows, cfg.window, int(params.max_steps)),
            # every training episode's collisions, which the window does not see (D²SPO: safe while it learns)
            "collisions_all": int(sum(row[3] for row in self.writer.rows)),
            "device": jax.devices()[0].platform,
        }
        if params.aut.visit is not None:  # a Büchi task: mean over the window
            summary["accepting_visits_per_episode"] = float(np.mean(self.visits[-cfg.window:])) if self.visits else None
            summary.update(visit_optimum(env.task, params.max_steps, env.config, summary["accepting_visits_per_episode"]))
        t_eval = time.perf_counter()
        if cfg.eval_episodes > 0:
            if progress is not None:
                progress({"phase": "evaluating", "episodes": cfg.eval_episodes})
            rollout = make_rollout(learner, env, cfg.eval_episodes, int(params.max_steps))
            key = jax.random.PRNGKey(cfg.seed + 10_000)
            summary["eval"] = rates(*rollout(params, learner.policy(carry), key))
            if untrained is not None:  # ``cfg.eval_untrained``: the same episodes, the same compilation
                summary["eval_untrained"] = rates(*rollout(params, untrained, key))
            if self.meta.get("best") is not None:  # the validated policy, on the same episodes
                summary["eval_best"] = rates(*rollout(params, load_best_policy(self.out, learner), key))
        if self.validation is not None:
            summary["validation"] = {"layouts": self.validation.layouts, "episodes": self.validation.episodes,
                                     "seconds": round(self.meta.get("validation_seconds", 0.0), 2),
                                     "best": self.meta.get("best"), "history": self.meta.get("validation", [])}
        total = (wall + self.meta.get("compile_seconds", 0.0) + self.meta.get("setup_seconds", 0.0)
                 + time.perf_counter() - t_eval)
        summary["wall_seconds_total"] = round(total, 2)
        atomic_write_json(self.out / "summary.json", summary)
        if self.wandb is not None:
            self.wandb.summary(summary)
            self.wandb.close()
        return summary


def _tensorboard(path: Path, part: int = 0) -> SummaryWriter:
    """A writer of a new event file in ``path``, numbered ``part`` (``durable_tensorboard``).

    tensorboardX names the file after the second it opens it in; the nanosecond clock and the part
    make the name unique, so that a resumed session's files never take (and truncate) the names of
    the files an earlier session of the run opened in the same second: a short run resumed at
    once lost its first chunks' scalars that way. Names sort in the order the files were opened."""
    # a queue long enough that a chunk's scalars never wait on it: when the writer thread has died
    # (a full disk), ``check_tensorboard`` says so at the next call instead of a put that blocks forever
    return SummaryWriter(str(path), flush_secs=30, max_queue=TB_QUEUE,
                         filename_suffix=f".{time.time_ns():020d}.{part:06d}")


TB_QUEUE = 100_000
"""Events tensorboardX may hold for its writer thread (its default, 10, blocked the run for good
once the thread had died on a full disk: a user trial, 2026-12-02)."""


def check_tensorboard(writer: SummaryWriter, path: Path) -> None:
    """OSError when ``writer``'s thread has stopped (tensorboardX's thread dies on a write error, such
    as a full disk, after printing it): the run stops with one line (exit 1) instead of hanging."""
    thread = getattr(getattr(getattr(writer, "file_writer", None), "event_writer", None), "_worker", None)
    if thread is not None and not thread.is_alive():
        raise OSError(errno.EIO, "TensorBoard's event writer stopped (its error is printed above: a full "
                      "disk or a file-size limit?); free space and `d2spo train --resume` the run", str(path))


def durable_tensorboard(writer: SummaryWriter, path: Path, part: int) -> SummaryWriter:
    """Every scalar ``writer`` was given, on disk; returns the writer to go on with.

    tensorboardX hands events to a writer thread through a queue, and its ``flush()`` writes out
    only what that thread has already taken: under load, the scalars of the last chunks before a
    checkpoint could still be queued when the run was killed, and were lost (the W&B test saw it:
    TensorBoard lacked two episodes W&B had). Closing the writer drains the queue first; the run
    goes on in a new event file of the same directory (number ``part``), which TensorBoard reads as
    one run."""
    check_tensorboard(writer, path)
    writer.close()
    return _tensorboard(path, part)
