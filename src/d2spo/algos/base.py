"""What every learner gives the run loop.

A learner is compiled once into two pure functions: ``init(key) -> carry`` and
``chunk(carry) -> (carry, ChunkLog)``. The chunk steps all environments ``chunk_steps`` times
inside one ``lax.scan`` (acting, stepping the env, storing, updating); the run loop in
``d2spo.train`` only moves the small ``ChunkLog`` to the host between chunks.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

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
class RunSchedule:
    """What a learner's programs read of the run's length (``--episodes``): the env params it trains
    on after ``episodes`` finished episodes, its layout's with the labelling radius annealed as in
    Sec. IV-C (``ltl.anneal``, at the rate ``k2`` the run's length fixes), and the share of the run
    one episode is (``per_episode``: TD3's noise decay, ``TD3Config.noise_at``).

    ``k2`` and ``per_episode`` are float32 numbers. ``train.learner_program`` passes them to the
    jitted programs as an argument (``schedule_values``, ``with_schedule``), so that runs differing
    only in ``--episodes`` are one program and share its compilation (``d2spo.compile_cache``);
    a learner's method traced alone folds them in as constants, which computes the same bits
    (XLA turns the division by a constant into a product with its float32 reciprocal, as
    ``per_episode`` is)."""

    cfg: AnnealConfig
    k2: Any
    per_episode: Any

    @classmethod
    def for_run(cls, cfg: AnnealConfig, total_episodes: int) -> RunSchedule:
        return cls(cfg, np.float32(cfg.rate(total_episodes)), np.float32(1) / np.float32(max(1, total_episodes)))

    def env_params(self, params: Any, episodes: jax.Array) -> Any:
        return annealed_params(params, episodes, self.cfg, self.k2)

    def values(self) -> tuple[Any, Any]:
        return self.k2, self.per_episode

    def at(self, values: tuple[Any, Any]) -> RunSchedule:
        """This schedule reading ``values`` (``values()``'s pair, traced in a program)."""
        return replace(self, k2=values[0], per_episode=values[1])


_SCHEDULED_PARTS = ("loop", "rollouts")
"""The attributes by which a learner holds a part with its own ``schedule`` (the baselines' shared
off-policy loop and on-policy rollouts)."""


def schedule_values(learner: Any) -> tuple[Any, Any]:
    """The run-length numbers of ``learner`` (``RunSchedule.values``), found on it or on its part."""
    for obj in (learner, *(getattr(learner, p) for p in _SCHEDULED_PARTS if hasattr(learner, p))):
        if isinstance(getattr(obj, "schedule", None), RunSchedule):
            return obj.schedule.values()
    raise TypeError(f"{type(learner).__name__} holds no RunSchedule")


def with_schedule(learner: Any, values: tuple[Any, Any]) -> Any:
    """A shallow copy of ``learner`` (and of its part that holds the schedule) whose schedule reads
    ``values``, which may be traced: what ``train.learner_program`` runs."""
    other = copy.copy(learner)
    if isinstance(getattr(learner, "schedule", None), RunSchedule):
        other.schedule = learner.schedule.at(values)
    for part in _SCHEDULED_PARTS:
        if hasattr(learner, part):
            setattr(other, part, with_schedule(getattr(learner, part), values))
    return other


def params_finite(tree: Any) -> jax.Array:
    """bool []: every leaf of ``tree`` is finite (the parameters' half of ``ChunkLog.nonfinite``).
    The floating leaves are checked as one flat vector (integer ones, e.g. optimiser step counts,
    always are): a handful of ops in the chunk's program, not three or four per leaf (XLA compiles
    op by op; the agents' trees with their optimiser states hold about a hundred leaves)."""
    leaves = [jnp.ravel(x) for x in jax.tree_util.tree_leaves(tree) if jnp.issubdtype(jnp.result_type(x), jnp.inexact)]
    if not leaves:
        return jnp.asarray(True)
    return jnp.all(jnp.isfinite(jnp.concatenate([x.astype(jnp.float32) for x in leaves])))
