"""The training loops: compile a learner once, run its chunks, hand each chunk's log to the run's
record, checkpoint, resume; one run (``train``) or several seeds vmapped together (``train_seeds``).

Everything per step happens inside the learner's jitted ``chunk`` (a ``lax.scan`` over steps of
``num_envs`` vmapped environments). Between chunks the host only receives a small ``ChunkLog``:
finished episodes and scalar metrics, which ``d2spo.record.RunRecord`` writes down. The run
directory (the learner a config names, config.json, the policies) is ``d2spo.run``'s.
"""

from __future__ import annotations

import contextlib
import shutil
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp

from d2spo import compile_cache, memo
from d2spo._xla import chunk_options, long_running_options
from d2spo.algos import runs_a_recurrence
from d2spo.algos.base import schedule_values, with_schedule
from d2spo.algos.generalist import Redraw
from d2spo.checkpoint import Checkpoints, fingerprint, has_checkpoint, run_fingerprint
from d2spo.config import TrainConfig, config_to_dict
from d2spo.errors import ConfigError, RunDirError, RunDirWarning
from d2spo.pipelined import Pipelined
from d2spo.record import ProgressFn, RunRecord
from d2spo.rollout import acting_on
from d2spo.run import (
    GROUP_PREFIX,
    RESUME_REMEDY,
    build,
    carry_template,
    check_layout_unchanged,
    check_new_run_dir,
    group_dir,
    preflight_checks,
    prepare_dir,
)
from d2spo.runio import RunLock, read_json, remove_tmp_files
from d2spo.validation import validation_for
from d2spo.wandb_log import require_wandb, wandb_run


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
    cfg.check()  # the memory it needs (config.TrainConfig.check), before anything is built
    if cfg.wandb:
        require_wandb()
    if resume:  # before the build reads the layout file
        check_layout_unchanged(out, cfg, RESUME_REMEDY)
        _refuse_a_group_member(out)
    built = build(cfg)  # a config that cannot be built is refused before anything is written
    preflight_checks(cfg, *built[:2])
    if resume and cfg.eval_untrained and has_checkpoint(out):
        raise ConfigError("eval_untrained", "the initial policy of a resumed run is gone; "
                          "evaluate it in a run that starts from its first episode")
    if not resume:  # a user's folder: not emptied of its files (before the lock file is made in it)
        check_new_run_dir(out)
    with RunLock(out):
        return _train_locked(cfg, out, built, resume, progress, stop_after_chunks, t_enter)


def _refuse_a_group_member(out: Path) -> None:
    """RunDirError when ``out`` is an unfinished seed of an unfinished group (``train_seeds``, as
    ``d2spo reproduce`` trains seeds together), whose checkpoint holds it: resumed alone, from the
    seed's own checkpoint or from its first episode, it would go on as a solo run, which rounds
    differently, where the group's other seeds are the group's (a user trial, 2026-12-02)."""
    if (out / "summary.json").is_file():
        return
    for group in sorted(out.parent.glob(GROUP_PREFIX + "*")):
        if out.name in group.name[len(GROUP_PREFIX):].split("+") and has_checkpoint(group):
            raise RunDirError(f"{out}: one of the seeds trained together in {group.name}, whose checkpoint holds "
                              "them; resume them together with the same `d2spo reproduce` command (resumed alone "
                              "it would go on as a solo run, which rounds differently)")


def _train_locked(cfg: TrainConfig, out: Path, built, resume: bool, progress: ProgressFn | None,
                  stop_after_chunks: int | None, t_enter: float) -> dict | None:
    env, params, learner = built
    prepare_dir(out, cfg, resume)
    checkpoints = Checkpoints(out, run_fingerprint(out))
    key = jax.random.PRNGKey(cfg.seed)
    chunk = learner_program(learner, "chunk", donate=True)
    meta = None
    if resume and has_checkpoint(out):
        carry, meta = checkpoints.load(carry_template(learner))
        checkpoints.tidy()
        if meta["episodes"] >= cfg.episodes and (out / "summary.json").is_file():
            # finished: compiling, evaluating and rewriting summary.json again would add to its times
            try:
                summary = read_json(out / "summary.json", "the run's summary")
            except RunDirError as e:  # damaged: written again below, as when a kill came before it
                warnings.warn(f"{e}; the run finished ({meta['episodes']} episodes): evaluating it again to write "
                              "a new one", RunDirWarning, stacklevel=3)
            else:
                warnings.warn(f"{out}: the run finished ({meta['episodes']} episodes); its summary.json stands, "
                              "nothing was trained or evaluated again", RunDirWarning, stacklevel=3)
                return summary
        carry = jax.tree_util.tree_map(jnp.asarray, carry)
    with wandb_run(cfg, out, continuing=meta is not None) as wandb:  # None without --wandb
        started = _compiling([progress], [meta], cfg)
        if not (resume and meta is not None):
            if resume:
                warnings.warn(f"{out}: no checkpoint was written before it stopped; training from the first episode",
                              RunDirWarning, stacklevel=3)
            carry = learner_program(learner, "init")(key)
        untrained = None
        if cfg.eval_untrained and cfg.eval_episodes > 0 and meta is None:
            untrained = jax.tree_util.tree_map(jnp.copy, learner.policy(carry))  # ``chunk`` donates the carry
        overhead = _compiled(chunk, carry, t_enter, started, [progress], [meta], cfg)
        validation = validation_for(cfg, env, params, learner)
        run = RunRecord(cfg, out, meta, checkpoints, overhead, validation, wandb, visits=params.aut.visit is not None,
                        recurrence=runs_a_recurrence(env), max_steps=int(params.max_steps))
        redraw = Redraw(cfg, env) if cfg.generalist and cfg.generalist_redraw else None
        if redraw is not None:  # a resumed run's bank as its checkpoint left it
            chunk.params = redraw.apply(chunk.params, run.meta.get("redrawn", {}))
        chunks_this_call = 0
        while not run.done:
            carry, log = chunk(carry)
            run.record(log, progress)
            if redraw is not None:
                chunk.params, updates = redraw.next(chunk.params, carry.env_state.layout, run.meta)
                run.meta.update(updates)
            run.save(learner, carry)
            chunks_this_call += 1
            if stop_after_chunks is not None and chunks_this_call >= stop_after_chunks:
                run.save(learner, carry, force=True)
                return None
        return run.finish(learner, carry, env, params, progress, untrained)



class _Program:
    """A jitted learner method that takes what the run's length sets (``algos.base.RunSchedule``:
    the anneal rate, the share of the run an episode is) as an argument, so that runs differing only
    in ``--episodes`` are one program and share its compilation; and, for learners with
    ``params_as_argument`` (the generalist), the env params too, instead of folding them into the
    program as constants: the generalist's are the field bank (128 MiB for 256 layouts), which XLA
    took tens of minutes to compile as constants. Called and lowered as a jitted function is."""

    def __init__(self, learner, name: str, vmapped: bool, donate: bool, options: dict | None):
        params_argument = getattr(learner, "params_as_argument", False)

        def run(x, schedule, params):
            other = with_schedule(learner, schedule)
            fn = getattr(acting_on(other, params) if params_argument else other, name)
            return (jax.vmap(fn) if vmapped else fn)(x)

        self.schedule = schedule_values(learner)
        self.params = learner.params if params_argument else None  # a redraw replaces this wrapper's, never the learner's
        self.fn = memo.per_object(learner, ("program", name, vmapped, donate, _options_key(options)),
                                  lambda: jax.jit(run, donate_argnums=(0,) if donate else (), compiler_options=options))

    def __call__(self, x):
        return self.fn(x, self.schedule, self.params)

    def lower(self, x):
        return self.fn.lower(x, self.schedule, self.params)


def learner_program(learner, name: str, vmapped: bool = False, donate: bool = False):
    """The jitted ``learner.<name>`` (``init`` or ``chunk``), vmapped over seeds if asked, donating
    its argument if asked (``_Program``: the run-length numbers, and the generalist's env params, are
    arguments); a pipelined D²SPO learner's ``chunk`` is a ``pipelined.Pipelined`` of three.
    An ``init`` that pre-trains (``learner.long_init``) gets ``_xla.long_running_options()``, a
    ``chunk`` ``_xla.chunk_options()``."""
    if name == "chunk" and getattr(learner, "pipelined", False):  # D²SPO's --d2spo.pipeline: d2spo/pipelined.py
        def pipelined():
            return Pipelined(lambda part, d: learner_program(learner, part, vmapped, d), donate)

        if getattr(learner, "params_as_argument", False):  # a fresh wrapper: ``params`` is its own
            return pipelined()
        return memo.per_object(learner, ("pipelined", vmapped, donate), pipelined)
    options = None
    if name == "init" and getattr(learner, "long_init", False):
        options = long_running_options()
    elif name == "chunk":
        options = chunk_options()
    if getattr(learner, "params_as_argument", False):  # a fresh wrapper: ``params`` is its own
        return _Program(learner, name, vmapped, donate, options)
    # one program per learner and kind: traced and compiled once in this process (d2spo.memo)
    return memo.per_object(learner, ("wrapper", name, vmapped, donate, _options_key(options)),
                           lambda: _Program(learner, name, vmapped, donate, options))


def _options_key(options: dict | None) -> tuple | None:
    return None if options is None else tuple(sorted(options.items()))


def _compiling(progress: list[ProgressFn | None], metas: list[dict | None], cfg: TrainConfig) -> tuple[float, float]:
    """Tell the progress callbacks (one per run) that compilation starts; returns the time it does
    and the compile time the cache had saved by then (``compile_cache.seconds_saved``)."""
    for fn, meta in zip(progress, metas):
        if fn is not None:
            fn({"phase": "compiling", "episodes": (meta or {}).get("episodes", 0), "total": cfg.episodes})
    return time.perf_counter(), compile_cache.seconds_saved()


def _compiled(chunk, carry, t_enter: float, started: tuple[float, float], progress: list[ProgressFn | None],
              metas: list[dict | None], cfg: TrainConfig) -> dict:
    """Compile ``chunk`` ahead of its first call (the calls reuse the compilation), so that its time
    is known and shown; returns the overhead times for ``RunRecord``, with the compile time the
    persistent cache saved since ``started`` (``_compiling``'s)."""
    chunk.lower(carry).compile()
    now = time.perf_counter()
    t_compile, saved = started
    for fn, meta in zip(progress, metas):
        if fn is not None:
            fn({"phase": "compiled", "compile_seconds": now - t_compile, "episodes": (meta or {}).get("episodes", 0),
                "total": cfg.episodes})
    return {"compile_seconds": now - t_compile, "setup_seconds": t_compile - t_enter,
            "compile_seconds_saved": max(0.0, compile_cache.seconds_saved() - saved)}  # reads can outlast tiny compiles


def _seed_slice(tree, i: int):
    """Seed ``i``'s part of a host (numpy) pytree."""
    return jax.tree_util.tree_map(lambda x: x[i], tree)


@jax.jit
def _take_seed(tree, i: jax.Array):
    """Seed ``i``'s part of a device pytree: one compiled program for every index (slicing leaf by
    leaf in eager mode compiles a program per leaf, and was seen to hang on a fresh 2-core machine)."""
    return jax.tree_util.tree_map(lambda x: x[i], tree)



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
    cfgs[0].check(seeds=len(cfgs))
    if cfgs[0].wandb:
        require_wandb()
    built = build(cfgs[0])
    preflight_checks(cfgs[0], *built[:2])
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
        # a seed that finished in an earlier start of this group, killed before the group's first
        # checkpoint, is kept as it is while the group trains again from the start
        prepare_dir(out, cfg, resume or (group.is_dir() and (out / "summary.json").is_file()))
    prints = [run_fingerprint(o) for o in outs]
    checkpoints = Checkpoints(group, fingerprint(prints))
    keys = jnp.stack([jax.random.PRNGKey(c.seed) for c in cfgs])
    chunk = learner_program(learner, "chunk", vmapped=True, donate=True)
    progress = progress or [None] * len(cfgs)
    if resume:
        remove_tmp_files(group)
        template = jax.tree_util.tree_map(lambda s: jax.ShapeDtypeStruct((len(cfgs), *s.shape), s.dtype),
                                          carry_template(learner))  # vmap's: a leading seed axis on every leaf
        carry, gmeta = checkpoints.load(template)
        checkpoints.tidy()
        carry = jax.tree_util.tree_map(jnp.asarray, carry)
        metas = gmeta["runs"]
        started = _compiling(progress, metas, cfgs[0])
    else:
        group.mkdir(parents=True, exist_ok=True)
        metas = [None] * len(cfgs)
        started = _compiling(progress, metas, cfgs[0])
        carry = learner_program(learner, "init", vmapped=True)(keys)
    summaries: list[dict | None] = [read_json(o / "summary.json", "summary") if (o / "summary.json").is_file()
                                    else None for o in outs]
    with contextlib.ExitStack() as stack:  # each unfinished seed's W&B run (None without --wandb)
        sinks = [None if s_ is not None else stack.enter_context(wandb_run(c, o, continuing=m is not None))
                 for c, o, m, s_ in zip(cfgs, outs, metas, summaries)]
        overhead = _compiled(chunk, carry, t_enter, started, progress, metas, cfgs[0])
        runs = [None if s_ is not None else RunRecord(c, o, m, Checkpoints(o, p), overhead,
                                                      validation_for(c, env, params, learner), wandb=w,
                                                      visits=params.aut.visit is not None,
                                                      recurrence=runs_a_recurrence(env),
                                                      max_steps=int(params.max_steps))
                for c, o, m, s_, p, w in zip(cfgs, outs, metas, summaries, prints, sinks)]
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
    shutil.rmtree(group, ignore_errors=True)
    return summaries

