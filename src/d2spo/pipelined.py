"""D²SPO's pipelined chunk (``--d2spo.pipeline``): the rollout and TD3's updates as two programs
run side by side, so that a 2-core CPU keeps both cores busy. The programs are the learner's
(``algos.d2spo_pipeline.PipelinedChunks``); this runs them.

XLA:CPU runs the operations of one program one after another, and a D²SPO step's matrix products
are too small for it to split over threads: the fused chunk keeps one core busy while TD3's update
(about half of the step) and the rest wait on each other (bench/concurrency.py, bench/RESULTS.md
"2026-12-01, midday"). Two programs started from two Python threads do run at once. So a chunk is

1. ``td3_batches(carry)``: every minibatch of the chunk's TD3 updates, drawn now from the buffer as
   the previous chunk left it, with copies of the actor, the critics and π_Ω (small, synchronous);
2. at once, in two threads: ``rollout(carry)`` (Algorithm 1's lines 6-11 and 16-17 with the actor
   fixed) and ``td3_chunk(work)`` (lines 12-15, as many updates as the fused chunk makes);
3. the carry takes the updated actor and critics; the log takes TD3's metrics.

Every input of both programs is fixed before they start, so a run is as deterministic as the fused
one and resumes the same way; only the actor that acts lags one chunk behind.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import jax


class Pipelined:
    """Called like the jitted ``chunk`` it stands for: ``(carry) -> (carry, log)``, with ``lower``
    (whose ``compile`` compiles all three programs, the two large ones in two threads) and, for
    learners that take their env params as an argument, a settable ``params``."""

    def __init__(self, program: Callable[[str, bool], object], donate: bool):
        """``program(name, donate)``: the jitted learner method ``name`` (``train.learner_program``'s)."""
        self.batches = program("td3_batches", False)
        self.rollout = program("rollout", donate)
        self.learn = program("td3_chunk", False)
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="d2spo-td3")  # its thread starts at the first submit

    @property
    def params(self):
        return self.rollout.params

    @params.setter
    def params(self, value) -> None:
        for p in (self.batches, self.rollout, self.learn):
            p.params = value

    def __call__(self, carry):
        work = jax.block_until_ready(self.batches(carry))  # read before the rollout takes the buffer
        future = self._pool.submit(lambda: jax.block_until_ready(self.learn(work)))
        try:
            carry, log = jax.block_until_ready(self.rollout(carry))
        finally:
            agent, metrics, finite = future.result()
        carry = carry.replace(td3=carry.td3.replace(agent=agent))
        return carry, log._replace(metrics={**log.metrics, **metrics}, nonfinite=log.nonfinite | ~finite)

    def lower(self, carry) -> _Lowered:
        return _Lowered(self, carry)


class _Lowered:
    def __init__(self, pipe: Pipelined, carry):
        self.pipe, self.carry = pipe, carry

    def compile(self) -> None:
        pipe = self.pipe
        pipe.batches.lower(self.carry).compile()
        work = jax.eval_shape(pipe.batches, self.carry)
        future = pipe._pool.submit(lambda: pipe.learn.lower(work).compile())
        try:
            pipe.rollout.lower(self.carry).compile()
        finally:
            future.result()
