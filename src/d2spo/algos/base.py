"""What every learner gives the run loop.

A learner is compiled once into two pure functions: ``init(key) -> carry`` and
``chunk(carry) -> (carry, ChunkLog)``. The chunk steps all environments ``chunk_steps`` times
inside one ``lax.scan`` (acting, stepping the env, storing, updating); the run loop in
``d2spo.train`` only moves the small ``ChunkLog`` to the host between chunks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp

from d2spo.ltl.anneal import AnnealConfig, annealed_params


class ChunkLog(NamedTuple):
    """What one chunk tells the host. Episode arrays are [chunk_steps, num_envs]."""

    done: jax.Array
    """bool: an episode ended at this (step, env)."""
    ep_return: jax.Array
    ep_cost: jax.Array
    ep_length: jax.Array
    ep_collided: jax.Array
    ep_completed: jax.Array
    """Completed under the true labelling (robot inside the area)."""
    ep_completed_relaxed: jax.Array
    """Completed under the annealed training labelling."""
    ep_end_xy: jax.Array
    """[chunk_steps, num_envs, 2]: where the robot was when the episode ended (before the reset)."""
    metrics: dict[str, jax.Array]
    """Scalars per step, [chunk_steps], namespaced (``losses/qf``, ``charts/lambda``); NaN = no value."""
    nonfinite: jax.Array
    """bool []: some parameter is NaN/inf at the end of the chunk (a NaN loss poisons them)."""
    accepting_visit: jax.Array | None = None
    """bool [chunk_steps, num_envs]: the step was an accepting visit of a Büchi task (true labelling;
    ``info["accepting_visit"]``); None for a monitor task."""


def episode_log(done: jax.Array, info: dict[str, jax.Array], metrics: dict[str, jax.Array]) -> ChunkLog:
    """One step's slice of a ChunkLog from the env's info dict (stacked by lax.scan)."""
    return ChunkLog(
        done=done,
        ep_return=info["ep_return"],
        ep_cost=info["ep_cost"],
        ep_length=info["ep_length"],
        ep_collided=info["ep_collided"],
        ep_completed=info["ep_completed"],
        ep_completed_relaxed=info["ep_completed_relaxed"],
        ep_end_xy=info["next_pose"][..., :2],
        metrics=metrics,
        nonfinite=jnp.zeros((), bool),
        accepting_visit=info.get("accepting_visit"),
    )


class Learner(Protocol):
    """A compiled learner for one (env, task, config)."""

    def init(self, key: jax.Array) -> Any:
        """All training state: env states, networks, optimisers, buffers, counters, key."""

    def chunk(self, carry: Any) -> tuple[Any, ChunkLog]:
        """Advance every env ``chunk_steps`` steps, learning as it goes."""

    def policy(self, carry: Any) -> Any:
        """The parameters the deterministic evaluation policy needs (a pytree)."""

    def act(self, policy: Any, obs: jax.Array, env_state: Any, key: jax.Array) -> jax.Array:
        """Deterministic action for one observation (no exploration noise).

        ``env_state`` gives access to the measured pose s(t) that the paper assumes observable
        (D²SPO's runtime filter uses it); most learners ignore it.
        """


@dataclass(frozen=True)
class AnnealSchedule:
    """The env params a learner trains on after ``episodes`` finished episodes: its layout's, with
    the labelling radius annealed as in Sec. IV-C (``ltl.anneal``); k2 is fixed by the run's length."""

    cfg: AnnealConfig
    k2: float

    @classmethod
    def for_run(cls, cfg: AnnealConfig, total_episodes: int) -> AnnealSchedule:
        return cls(cfg, cfg.rate(total_episodes))

    def env_params(self, params: Any, episodes: jax.Array) -> Any:
        return annealed_params(params, episodes, self.cfg, self.k2)


def params_finite(tree: Any) -> jax.Array:
    """bool []: every leaf of ``tree`` is finite (the parameters' half of ``ChunkLog.nonfinite``).
    The floating leaves are checked as one flat vector (integer ones, e.g. optimiser step counts,
    always are): a handful of ops in the chunk's program, not three or four per leaf (XLA compiles
    op by op; the agents' trees with their optimiser states hold about a hundred leaves)."""
    leaves = [jnp.ravel(x) for x in jax.tree_util.tree_leaves(tree) if jnp.issubdtype(jnp.result_type(x), jnp.inexact)]
    if not leaves:
        return jnp.asarray(True)
    return jnp.all(jnp.isfinite(jnp.concatenate([x.astype(jnp.float32) for x in leaves])))
