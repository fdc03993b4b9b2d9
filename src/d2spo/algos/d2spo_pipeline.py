"""The learner's side of D²SPO's pipelined chunk (``--d2spo.pipeline``; the runner is d2spo/pipelined.py).

``pipelined.Pipelined`` runs ``td3_batches``, then ``rollout`` and ``td3_chunk`` side by side in two
threads: XLA:CPU runs one program's operations one after another, so a single fused chunk keeps one
core busy (bench/concurrency.py); two programs take both. Chunk k's rollout acts with the actor
θ_{k-1} and trains (Ω, Θ) as before; its TD3 updates, as many as in the fused chunk and gated on the
step count the same way, are drawn from the buffer as chunk k-1 left it, with π_Ω as it was then.
The run is as deterministic as the fused one (every input is fixed before the two start); only the
actor that acts lags by one chunk.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from d2spo import replay
from d2spo.algos.base import ChunkLog, params_finite
from d2spo.algos.td3 import TD3Agent, no_updates, ready_to_learn, updates_on


@struct.dataclass
class TD3Work:
    """A pipelined chunk's TD3 updates, fixed before its rollout starts (``td3_batches``)."""

    agent: TD3Agent
    """The actor and critics to update (a copy: the rollout acts with the original)."""
    safety: Any
    """π_Ω for the actor loss (a copy of the ``SafetyState``)."""
    batches: Any
    """Minibatches [chunk_steps, updates_per_step, batch_size, ...] from the buffer before the rollout."""
    keys: jax.Array
    """One key per update [chunk_steps, updates_per_step]."""
    ready: jax.Array
    """bool [chunk_steps]: whether the fused chunk's step would update (``learning_starts``)."""


_TD3_STREAM = 0x7D3  # td3_batches' keys: fold_in(carry key, this), a stream the rollout's splits never give


class PipelinedChunks:
    """``D2SPOLearner``'s three programs for the pipelined chunk (it has ``_chunk`` and ``_execute_fn``)."""

    def rollout(self, carry) -> tuple[Any, ChunkLog]:
        """The chunk without TD3's updates (the actor fixed): lines 6-11 and 16-17. (Starting it with one
        more UPDATE(Ω, Θ), to show π_Ω the actor it acts with, was tried and undone: ϕ1 with --fast
        then did not learn, and over ϕ1 seeds 0-4 it collided as often as without; bench/RESULTS.md,
        "2026-12-01, evening" and "night".)"""
        return self._chunk(carry, learn=False)

    def td3_batches(self, carry) -> TD3Work:
        """The next ``td3_chunk``'s inputs, from ``carry`` before its rollout: copies of the actor and
        π_Ω (copies, not the carry's arrays passed through: the rollout donates those), and every
        minibatch drawn from the buffer now."""
        n, u = self.chunk_steps, self.cfg.updates_per_step
        keys = jax.random.split(jax.random.fold_in(carry.td3.key, _TD3_STREAM), (n, u, 2))
        batches = jax.vmap(jax.vmap(lambda k: replay.sample(carry.buffer, k, self.cfg.batch_size)))(keys[:, :, 0])
        steps = carry.steps + 1 + jnp.arange(n)  # the step count each slot's fused update would have seen
        ready = ready_to_learn(steps, self.num_envs, self.cfg) & (carry.buffer.size >= self.cfg.batch_size)
        copy = functools.partial(jax.tree_util.tree_map, jnp.copy)
        return TD3Work(copy(carry.agent), copy(carry.safety), batches, keys[:, :, 1], ready)

    def td3_chunk(self, work: TD3Work) -> tuple[TD3Agent, dict, jax.Array]:
        """Lines 12-15 for a whole chunk: (actor and critics, per-step metrics, whether all are finite)."""
        execute_fn = self._execute_fn(work.safety)

        def slot(agent, x):
            batches, keys, ready = x
            return jax.lax.cond(ready, lambda a: updates_on(self.nets, a, batches, keys, self.cfg, execute_fn,
                                                            self.d2.proposal_weight),
                                lambda a: (a, no_updates()), agent)

        agent, metrics = jax.lax.scan(slot, work.agent, (work.batches, work.keys, work.ready))
        return agent, metrics, params_finite(agent)
