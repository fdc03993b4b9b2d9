"""The run loop: compile a learner once, run its chunks, log, checkpoint, resume, summarise.

Everything per step happens inside the learner's jitted ``chunk`` (a ``lax.scan`` over steps of
``num_envs`` vmapped environments). Between chunks the host only receives a small ``ChunkLog``:
finished episodes and scalar metrics. The final evaluation's rollouts are ``d2spo.rollout``'s.
"""

from __future__ import annotations

import contextlib
import math
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from d2spo.algos.base import ChunkLog
from d2spo.checkpoint import Checkpoints, fingerprint, has_checkpoint, run_fingerprint
from d2spo.config import TrainConfig, config_differences, config_from_dict, config_to_dict
from d2spo.envs.nav import check_barrier_margin, check_episode_time
from d2spo.errors import ConfigError, NaNError, RunDirError, RunDirWarning
from d2spo.rollout import make_rollout, rates
from d2spo.runio import (
    EpisodeWriter,
    RunLock,
    atomic_write_bytes,
    atomic_write_json,
    read_json,
    remove_file,
    remove_tmp_files,
    window_rates,
)

ProgressFn = Callable[[dict], None]


def build(cfg: TrainConfig):
    """(env, env_params, learner) for a config. Raises ConfigError on bad input."""
    from d2spo.algos import make_learner
    from d2spo.envs import make_env

    if cfg.generalist:
        return _build_generalist(cfg)
    env, params = make_env(cfg.env_config(), task=cfg.task)
    learner = make_learner(cfg, env, params)
    return env, params, learner


GENERALIST_MAX_STEPS = 400
"""The generalist's episode limit when ``max_steps`` is unset: routes in 10 m arenas are long."""


def _build_generalist(cfg: TrainConfig):
    """(env, params, learner) of ``--generalist``: the bank random:0 .. random:N-1, GeneralistD2SPO."""
    from d2spo.algos.generalist import build_generalist
    from d2spo.envs import layout_bank

    bank = layout_bank.build_bank(range(cfg.generalist_layouts))
    return build_generalist(cfg, bank, cfg.env.max_steps or GENERALIST_MAX_STEPS)


def _rows_from_log(log: ChunkLog, first_episode: int, limit: int) -> list[tuple]:
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


def _prepare_dir(out: Path, cfg: TrainConfig, resume: bool) -> None:
    """With the directory's lock held: temporary files a kill left are removed; a resume checks
    ``cfg`` against config.json; a new run writes config.json (over a run killed before its first
    checkpoint, whose policy snapshots go too)."""
    remove_tmp_files(out)
    cfg_path = out / "config.json"
    if resume:
        theirs = load_run_config(out)
        if theirs != cfg:
            diffs = config_differences(theirs, cfg) or ["settings this learner does not read"]
            raise RunDirError(f"{out}: resuming takes the run's own config.json, and this config differs "
                              f"({'; '.join(diffs)})")
        return
    if (out / "summary.json").exists() or has_checkpoint(out):
        raise RunDirError(f"{out}: already holds a run; use --resume {out} or another --out")
    for p in out.glob("policy-*.msgpack"):
        remove_file(p)
    atomic_write_json(cfg_path, config_to_dict(cfg))


def load_run_config(run_dir: Path) -> TrainConfig:
    return config_from_dict(read_json(Path(run_dir) / "config.json", "the run's config"))


class _NaNGuard:
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


class _Run:
    """The host-side bookkeeping of one run directory: episodes.csv, TensorBoard, counters,
    snapshots, checkpoints and the summary. ``train`` has one; ``train_seeds`` one per seed."""

    def __init__(self, cfg: TrainConfig, out: Path, meta: dict | None, checkpoints: Checkpoints,
                 overhead: dict | None = None, validation: _Validation | None = None):
        self.cfg, self.out, self.checkpoints, self.validation = cfg, Path(out), checkpoints, validation
        self.meta = dict(meta or {"episodes": 0, "env_steps": 0, "chunks": 0, "wall_seconds": 0.0})
        # Time outside the training loop, summed over the sessions of a resumed run (0 in checkpoints
        # written before these were counted): compiling the learner, and the rest (building the env).
        for k, v in (overhead or {}).items():
            self.meta[k] = self.meta.get(k, 0.0) + v
        self.writer = EpisodeWriter(self.out / "episodes.csv", keep_rows=self.meta["episodes"])
        self.tb = _tensorboard(self.out / "tb")
        every = cfg.checkpoint_every
        self.next_ckpt = (self.meta["episodes"] // every + 1) * every
        if validation is not None:
            self.next_validation = (self.meta["episodes"] // cfg.validate_every + 1) * cfg.validate_every
        self.t_start = time.perf_counter() - self.meta["wall_seconds"]
        self.guard = _NaNGuard(cfg.chunk_steps)

    @property
    def done(self) -> bool:
        return len(self.writer) >= self.cfg.episodes

    def record(self, log: ChunkLog, progress: ProgressFn | None) -> None:
        """Take in one chunk's log (NaN check, episodes, counters, TensorBoard, progress)."""
        cfg, writer, meta = self.cfg, self.writer, self.meta
        rows = _rows_from_log(log, len(writer), cfg.episodes - len(writer))
        problem = self.guard.problem(log, rows, meta["chunks"] * cfg.chunk_steps)
        if problem is not None:
            last = self.checkpoints.latest
            where = (f"the last checkpoint, after episode {last['episodes']}, is {self.out / 'checkpoint.json'}"
                     if last is not None else f"no checkpoint was written in {self.out} before it")
            raise NaNError(f"training stopped at episode {len(writer)}: {problem}; episodes.csv holds the "
                           f"episodes before it and {where}")
        writer.append(rows)
        meta["chunks"] += 1
        meta["env_steps"] += cfg.chunk_steps * cfg.num_envs
        meta["episodes"] = len(writer)
        meta["wall_seconds"] = time.perf_counter() - self.t_start
        if self.tb is not None:
            for k, v in log.metrics.items():
                v = np.asarray(v, dtype=np.float64)
                if np.any(np.isfinite(v)):
                    self.tb.add_scalar(k, float(np.nanmean(v)), meta["env_steps"])
            if rows:
                rates = window_rates(writer.rows, 100)
                self.tb.add_scalar("charts/safety_rate_100", rates["safety_rate"], meta["env_steps"])
                self.tb.add_scalar("charts/completion_rate_100", rates["completion_rate"], meta["env_steps"])
                self.tb.add_scalar("charts/completion_rate_relaxed_100", rates["completion_rate_relaxed"],
                                   meta["env_steps"])
        if progress is not None:
            progress({"episodes": len(writer), "total": cfg.episodes, "env_steps": meta["env_steps"],
                      "wall_seconds": meta["wall_seconds"], **window_rates(writer.rows, 200)})

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
            self.checkpoints.save(carry, self.meta)
            every = self.cfg.checkpoint_every
            self.next_ckpt = (n_done // every + 1) * every
            return True
        return False

    def validate(self, policy) -> None:
        """Run the validation (``_Validation``) on ``policy`` and keep it as DIR/policy-best.msgpack if
        it fails fewer validation episodes than every earlier one; the scores go into the counters."""
        n_done = len(self.writer)
        history = self.meta.setdefault("validation", [])
        if history and history[-1]["episodes"] == n_done:
            return
        t = time.perf_counter()
        entry = {"episodes": n_done, **self.validation(policy)}
        best = self.meta.get("best")
        if best is None or entry["success_rate"] > best["success_rate"]:
            atomic_write_bytes(best_policy_path(self.out), serialization.to_bytes(jax.device_get(policy)))
            self.meta["best"] = entry
        history.append(entry)
        self.meta["validation_seconds"] = self.meta.get("validation_seconds", 0.0) + time.perf_counter() - t
        every = self.cfg.validate_every
        self.next_validation = (n_done // every + 1) * every
        if self.tb is not None:
            self.tb.add_scalar("charts/validation_success", entry["success_rate"], self.meta["env_steps"])

    def finish(self, learner, carry, env, params, progress: ProgressFn | None = None, untrained=None) -> dict:
        """summary.json. Wall times: ``wall_seconds`` is the training loop alone (no compilation; the
        steps per second use it), ``compile_seconds`` the compilation of the learner, and
        ``wall_seconds_total`` everything ``train`` spent: building the env, compiling, training and
        the final evaluation, over every session of a resumed run."""
        cfg = self.cfg
        wall = time.perf_counter() - self.t_start
        if self.tb is not None:
            self.tb.close()
        summary = {
            "algo": cfg.algo, "task": cfg.task, "seed": cfg.seed,
            "layout": f"random:0..{cfg.generalist_layouts - 1}" if cfg.generalist else cfg.layout,
            "episodes": len(self.writer), "env_steps": self.meta["env_steps"], "wall_seconds": round(wall, 2),
            "compile_seconds": round(self.meta.get("compile_seconds", 0.0), 2),
            "env_steps_per_second": round(self.meta["env_steps"] / max(wall, 1e-9), 1),
            "window": cfg.window, **window_rates(self.writer.rows, cfg.window),
            "device": jax.devices()[0].platform,
        }
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
            summary["validation"] = {"layouts": self.validation.layouts, "episodes": cfg.validation_episodes,
                                     "seconds": round(self.meta.get("validation_seconds", 0.0), 2),
                                     "best": self.meta.get("best"), "history": self.meta.get("validation", [])}
        total = (wall + self.meta.get("compile_seconds", 0.0) + self.meta.get("setup_seconds", 0.0)
                 + time.perf_counter() - t_eval)
        summary["wall_seconds_total"] = round(total, 2)
        atomic_write_json(self.out / "summary.json", summary)
        return summary


def check_barrier(cfg: TrainConfig, env) -> None:
    """For a learner that executes π_Ω (D²SPO, SL): a warning when no route of the task keeps the
    barrier's margin ``cfg.cbf.d`` (``nav.check_barrier_margin``), before training."""
    from d2spo.algos import has_runtime_filter

    if has_runtime_filter(cfg.algo):
        check_barrier_margin(env, cfg.cbf.d, repr(cfg.task))


def train(
    cfg: TrainConfig, out: Path, resume: bool = False, progress: ProgressFn | None = None,
    stop_after_chunks: int | None = None,
) -> dict | None:
    """Train, writing the run directory. Returns the summary (None if stopped early on purpose).

    The directory is locked while training (``runio.RunLock``). ``resume`` continues from the
    newest usable checkpoint (``d2spo.checkpoint``), or from the start if the run was stopped
    before its first. ``stop_after_chunks`` simulates an interruption (used by the resume test).
    """
    t_enter = time.perf_counter()
    out = Path(out)
    built = build(cfg)  # a config that cannot be built is refused before anything is written
    check_barrier(cfg, built[0])
    check_episode_time(built[0], built[1], repr(cfg.task))
    if resume and cfg.eval_untrained and has_checkpoint(out):
        raise ConfigError("eval_untrained", "the initial policy of a resumed run is gone; "
                          "evaluate it in a run that starts from its first episode")
    with RunLock(out):
        return _train_locked(cfg, out, built, resume, progress, stop_after_chunks, t_enter)


def _train_locked(cfg: TrainConfig, out: Path, built, resume: bool, progress: ProgressFn | None,
                  stop_after_chunks: int | None, t_enter: float) -> dict | None:
    env, params, learner = built
    _prepare_dir(out, cfg, resume)
    checkpoints = Checkpoints(out, run_fingerprint(out))
    key = jax.random.PRNGKey(cfg.seed)
    chunk = learner_program(learner, "chunk", donate=True)
    meta = None
    if resume and has_checkpoint(out):
        carry, meta = checkpoints.load(jax.eval_shape(learner.init, key))
        checkpoints.tidy()
        carry = jax.tree_util.tree_map(jnp.asarray, carry)
    t_compile = _compiling([progress], [meta], cfg)
    if not (resume and meta is not None):
        if resume:
            warnings.warn(f"{out}: no checkpoint was written before it stopped; training from the first episode",
                          RunDirWarning, stacklevel=3)
        carry = learner_program(learner, "init")(key)
    untrained = None
    if cfg.eval_untrained and cfg.eval_episodes > 0 and meta is None:
        untrained = jax.tree_util.tree_map(jnp.copy, learner.policy(carry))  # ``chunk`` donates the carry
    overhead = _compiled(chunk, carry, t_enter, t_compile, [progress], [meta], cfg)
    validation = _Validation(cfg, env, params, learner) if cfg.generalist and cfg.validation_layouts else None
    run = _Run(cfg, out, meta, checkpoints, overhead, validation)
    chunks_this_call = 0
    while not run.done:
        carry, log = chunk(carry)
        run.record(log, progress)
        run.save(learner, carry)
        chunks_this_call += 1
        if stop_after_chunks is not None and chunks_this_call >= stop_after_chunks:
            run.save(learner, carry, force=True)
            return None
    return run.finish(learner, carry, env, params, progress, untrained)


class _ParamsArgument:
    """A jitted learner method that takes the env params as an argument instead of folding them
    into the program as constants: the generalist's are the field bank (128 MiB for 256 layouts),
    which XLA took tens of minutes to compile as constants. ``lower`` as a jitted function has."""

    def __init__(self, learner, name: str, vmapped: bool, donate: bool):
        from d2spo.rollout import acting_on

        def run(x, params):
            fn = getattr(acting_on(learner, params), name)
            return (jax.vmap(fn) if vmapped else fn)(x)

        self.params = learner.params
        self.fn = jax.jit(run, donate_argnums=(0,) if donate else ())

    def __call__(self, x):
        return self.fn(x, self.params)

    def lower(self, x):
        return self.fn.lower(x, self.params)


def learner_program(learner, name: str, vmapped: bool = False, donate: bool = False):
    """The jitted ``learner.<name>`` (``init`` or ``chunk``), vmapped over seeds if asked, donating
    its argument if asked. Learners with ``params_as_argument`` (the generalist) get their env
    params as an argument (``_ParamsArgument``); the others keep them as constants, as before."""
    if getattr(learner, "params_as_argument", False):
        return _ParamsArgument(learner, name, vmapped, donate)
    fn = getattr(learner, name)
    return jax.jit(jax.vmap(fn) if vmapped else fn, donate_argnums=0 if donate else ())


def _compiling(progress: list[ProgressFn | None], metas: list[dict | None], cfg: TrainConfig) -> float:
    """Tell the progress callbacks (one per run) that compilation starts; returns the time it does."""
    for fn, meta in zip(progress, metas):
        if fn is not None:
            fn({"phase": "compiling", "episodes": (meta or {}).get("episodes", 0), "total": cfg.episodes})
    return time.perf_counter()


def _compiled(chunk, carry, t_enter: float, t_compile: float, progress: list[ProgressFn | None],
              metas: list[dict | None], cfg: TrainConfig) -> dict:
    """Compile ``chunk`` ahead of its first call (the calls reuse the compilation), so that its time
    is known and shown; returns the overhead times for ``_Run``."""
    chunk.lower(carry).compile()
    now = time.perf_counter()
    for fn, meta in zip(progress, metas):
        if fn is not None:
            fn({"phase": "compiled", "compile_seconds": now - t_compile, "episodes": (meta or {}).get("episodes", 0),
                "total": cfg.episodes})
    return {"compile_seconds": now - t_compile, "setup_seconds": t_compile - t_enter}


def _seed_slice(tree, i: int):
    """Seed ``i``'s part of a host (numpy) pytree."""
    return jax.tree_util.tree_map(lambda x: x[i], tree)


@jax.jit
def _take_seed(tree, i: jax.Array):
    """Seed ``i``'s part of a device pytree: one compiled program for every index (slicing leaf by
    leaf in eager mode compiles a program per leaf, and was seen to hang on a fresh 2-core machine)."""
    return jax.tree_util.tree_map(lambda x: x[i], tree)


GROUP_PREFIX = ".group-"


def group_dir(outs: list[Path]) -> Path:
    """Where ``train_seeds`` checkpoints the group of runs ``outs``: ``OUT[0]/../.group-<names>``."""
    return Path(outs[0]).parent / (GROUP_PREFIX + "+".join(Path(o).name for o in outs))


def train_seeds(
    cfgs: list[TrainConfig], outs: list[Path], progress: list[ProgressFn | None] | None = None,
    stop_after_chunks: int | None = None,
) -> list[dict] | None:
    """Train several seeds of one configuration together: one program, ``jax.vmap`` over seeds.

    ``cfgs`` may differ only in ``seed``; each seed writes its own ordinary run directory in
    ``outs``. A seed that reaches its episode count gets its final checkpoint, evaluation and
    summary then; it keeps being stepped (and is ignored) until the slowest seed is done. The
    group's state is checkpointed in ``OUT[0]/../.group-<names>/`` so an interrupted group resumes
    exactly; calling again with the same arguments resumes. A seed in a group is deterministic,
    but not bit-identical to the same seed trained alone (batched arithmetic rounds differently).
    ``stop_after_chunks`` simulates an interruption (for the tests).
    """
    if not cfgs or len(cfgs) != len(outs):
        raise ValueError("train_seeds: one output directory per config")
    base = dict(config_to_dict(cfgs[0]), seed=None)
    for c in cfgs[1:]:
        if dict(config_to_dict(c), seed=None) != base:
            raise ConfigError("seed", "train_seeds: the configs may differ only in their seed")
    t_enter = time.perf_counter()
    outs = [Path(o) for o in outs]
    built = build(cfgs[0])
    check_barrier(cfgs[0], built[0])
    check_episode_time(built[0], built[1], repr(cfgs[0].task))
    with contextlib.ExitStack() as locks:
        for out in outs:
            locks.enter_context(RunLock(out))
        return _train_seeds_locked(cfgs, outs, built, progress, stop_after_chunks, t_enter)


def _train_seeds_locked(cfgs: list[TrainConfig], outs: list[Path], built, progress: list[ProgressFn | None] | None,
                        stop_after_chunks: int | None, t_enter: float) -> list[dict] | None:
    env, params, learner = built
    group = group_dir(outs)
    resume = has_checkpoint(group)
    for cfg, out in zip(cfgs, outs):
        _prepare_dir(out, cfg, resume)
    prints = [run_fingerprint(o) for o in outs]
    checkpoints = Checkpoints(group, fingerprint(prints))
    keys = jnp.stack([jax.random.PRNGKey(c.seed) for c in cfgs])
    chunk = learner_program(learner, "chunk", vmapped=True, donate=True)
    progress = progress or [None] * len(cfgs)
    if resume:
        remove_tmp_files(group)
        carry, gmeta = checkpoints.load(jax.eval_shape(jax.vmap(learner.init), keys))
        checkpoints.tidy()
        carry = jax.tree_util.tree_map(jnp.asarray, carry)
        metas = gmeta["runs"]
        t_compile = _compiling(progress, metas, cfgs[0])
    else:
        group.mkdir(parents=True, exist_ok=True)
        metas = [None] * len(cfgs)
        t_compile = _compiling(progress, metas, cfgs[0])
        carry = learner_program(learner, "init", vmapped=True)(keys)
    overhead = _compiled(chunk, carry, t_enter, t_compile, progress, metas, cfgs[0])
    summaries: list[dict | None] = [read_json(o / "summary.json", "summary") if (o / "summary.json").is_file()
                                    else None for o in outs]
    runs = [None if s_ is not None else _Run(c, o, m, Checkpoints(o, p), overhead)
            for c, o, m, s_, p in zip(cfgs, outs, metas, summaries, prints)]
    chunks_this_call = 0
    while any(s_ is None for s_ in summaries):
        carry, log = chunk(carry)
        carry = jax.block_until_ready(carry)
        log = jax.device_get(log)
        saved = False
        for i, run in enumerate(runs):
            if summaries[i] is not None:
                continue
            run.record(_seed_slice(log, i), progress[i])
            mine = _take_seed(carry, jnp.int32(i))
            saved |= run.save(learner, mine)
            if run.done:
                summaries[i] = run.finish(learner, mine, env, params, progress[i])
        chunks_this_call += 1
        interrupted = stop_after_chunks is not None and chunks_this_call >= stop_after_chunks
        if saved or interrupted:
            metas = [r.meta if r is not None else m for r, m in zip(runs, metas)]
            checkpoints.save(carry, {"runs": metas})
        if interrupted and any(s_ is None for s_ in summaries):
            return None
    import shutil

    shutil.rmtree(group, ignore_errors=True)
    return summaries


class _Validation:
    """The generalist's model selection (``TrainConfig.validation_layouts``): ``policy -> rates`` of
    ``validation_episodes`` deterministic episodes on the held-out layouts random:VALIDATION_SEED ..,
    the training task(s), the same episodes (key) every time. ``success_rate`` is the fraction of
    episodes that complete the task without a collision: what the best policy is chosen by."""

    def __init__(self, cfg: TrainConfig, env, params, learner):
        from d2spo.config import VALIDATION_SEED
        from d2spo.envs import layout_bank
        from d2spo.envs.generalist import view

        n = cfg.validation_layouts
        self.layouts = f"random:{VALIDATION_SEED}..{VALIDATION_SEED + n - 1}"
        bank = layout_bank.build_bank(range(VALIDATION_SEED, VALIDATION_SEED + n))
        self.params = view(params.replace(bank=bank), jnp.zeros((), jnp.int32))
        self.rollout = make_rollout(learner, env, cfg.validation_episodes, int(params.max_steps))
        self.key = jax.random.PRNGKey(cfg.seed + 20_000)

    def __call__(self, policy) -> dict:
        collided, completed, *rest = self.rollout(self.params, policy, self.key)
        out = rates(collided, completed, *rest)
        ok = np.asarray(completed) & ~np.asarray(collided)
        return {"success_rate": float(np.mean(ok)), "completion_rate": out["completion_rate"],
                "safety_rate": out["safety_rate"]}


BEST_POLICY = "policy-best.msgpack"
"""A validated generalist's best policy (``_Run.validate``), in the run directory."""


def best_policy_path(run_dir: Path) -> Path:
    return Path(run_dir) / BEST_POLICY


def load_best_policy(run_dir: Path, learner, key: jax.Array | None = None):
    """The policy ``_Run.validate`` kept; shapes come from the learner (nothing is trained)."""
    path = best_policy_path(run_dir)
    if not path.is_file():
        raise RunDirError(f"{run_dir}: no validated policy ({path.name})")
    key = jax.random.PRNGKey(0) if key is None else key
    template = jax.eval_shape(lambda k: learner.policy(learner.init(k)), key)
    return serialization.from_bytes(template, path.read_bytes())


def snapshot_path(run_dir: Path, episodes: int) -> Path:
    return Path(run_dir) / f"policy-{episodes}.msgpack"


def save_snapshot(run_dir: Path, episodes: int, policy) -> None:
    """The policy's parameters after ``episodes`` training episodes (``TrainConfig.snapshots``)."""
    atomic_write_bytes(snapshot_path(run_dir, episodes), serialization.to_bytes(jax.device_get(policy)))


def load_snapshot(run_dir: Path, episodes: int, learner, key: jax.Array | None = None):
    """The policy saved by ``save_snapshot``; shapes come from the learner (nothing is trained)."""
    path = snapshot_path(run_dir, episodes)
    if not path.is_file():
        raise RunDirError(f"{run_dir}: no policy snapshot after {episodes} episodes ({path.name})")
    key = jax.random.PRNGKey(0) if key is None else key
    template = jax.eval_shape(lambda k: learner.policy(learner.init(k)), key)
    return serialization.from_bytes(template, path.read_bytes())


def _tensorboard(path: Path):
    try:
        from tensorboardX import SummaryWriter
    except ImportError:  # pragma: no cover - tensorboardX is a pinned dependency
        return None
    return SummaryWriter(str(path), flush_secs=30)
