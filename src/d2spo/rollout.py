"""Acting with a policy: deterministic rollouts, their safety and completion rates, and the safety
of random proposals executed through D²SPO's π_Ω.

Only the learners' protocol (``d2spo.algos.base.Learner``: ``act``, ``params``) is used here, so
the run loop (``d2spo.train``, final evaluation), ``d2spo eval`` (``d2spo.evaluate``) and the
figures share one rollout.
"""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import numpy as np

from d2spo import memo
from d2spo.algos.base import Learner
from d2spo.runio import rejected


def acting_on(learner: Learner, params) -> Learner:
    """``learner`` acting on env ``params`` (another layout of the same array shapes): a shallow
    copy whose ``params`` are replaced. Acting reads the layout only through ``learner.params``
    (D²SPO's sensed obstacles and arena), so ``params`` may be traced."""
    other = copy.copy(learner)
    other.params = params
    return other


def make_rollout(learner: Learner, env, episodes: int, max_steps: int, slot_per_episode: bool = False,
                 with_slot: bool = False):
    """A jitted ``(params, policy, key) -> (collided, completed, return, length, poses)``: ``episodes``
    envs in parallel, one deterministic episode each; poses are [E, T + 1, 3]. The env params are an
    argument, so one compilation serves every layout with the same array shapes. For a Büchi task
    (``params.aut.visit`` set) the tuple ends with each episode's accepting visits [E] too.
    ``slot_per_episode`` (a generalist's env): episode e starts in slot e of the bank, not a drawn one;
    ``with_slot`` (a generalist's env): the tuple ends with each episode's slot [E] too.
    Made once per learner and arguments in a process (``d2spo.memo``): a second evaluation of the
    same learner runs the program already compiled."""
    return memo.per_object(learner, ("rollout", env, episodes, max_steps, slot_per_episode, with_slot),
                           lambda: _make_rollout(learner, env, episodes, max_steps, slot_per_episode, with_slot))


def _make_rollout(learner: Learner, env, episodes: int, max_steps: int, slot_per_episode: bool, with_slot: bool):

    def run(params, policy, key):
        # Time outside, episodes inside: ``lax.scan`` over steps of the vmapped (act, step). The
        # other nesting, ``vmap`` of a per-episode scan, computes the same arrays but makes JAX
        # batch the scan's whole body again until its carry settles: tracing it cost seconds per
        # rollout (about 100 s of the test suite's 2-core time, 2026-11-28).
        # Evaluation reads the task with the areas' true radii: a relaxed radius (``--label-radius``)
        # is a training aid, and an episode it ended early would pass for one the task rejected.
        params = params.replace(label_radius=params.area_radius)
        lrn = acting_on(learner, params)
        k0, k1 = jnp.moveaxis(jax.vmap(jax.random.split)(jax.random.split(key, episodes)), 1, 0)
        if slot_per_episode:
            state, obs = jax.vmap(env.reset_in_slot, in_axes=(0, None, 0))(k0, params, jnp.arange(episodes, dtype=jnp.int32))
        else:
            state, obs = jax.vmap(env.reset, in_axes=(0, None))(k0, params)
        act = jax.vmap(lrn.act, in_axes=(None, 0, 0, 0))
        step = jax.vmap(env.step, in_axes=(0, 0, 0, None))

        def body(c, k):
            (state, obs, alive, ret, length, collided, completed), visits = c[:7], c[7:]
            a = act(policy, obs, state, k)
            state2, obs2, r, _, done, info = step(k, state, a, params)
            if visits:
                visits = (visits[0] + (alive & info["accepting_visit"]).astype(jnp.int32),)
            ret = ret + jnp.where(alive, r, 0.0)
            length = length + alive.astype(jnp.int32)
            collided = collided | (alive & info["collided"])
            completed = completed | (alive & info["completed"])
            pose = jnp.where(alive[:, None], info["next_pose"], jnp.full_like(info["next_pose"], jnp.nan))
            return (state2, obs2, alive & ~done, ret, length, collided, completed, *visits), pose

        false = jnp.zeros(episodes, bool)
        init = (state, obs, ~false, jnp.zeros(episodes, jnp.float32), jnp.zeros(episodes, jnp.int32), false, false)
        if params.aut.visit is not None:
            init = (*init, jnp.zeros(episodes, jnp.int32))
        step_keys = jnp.moveaxis(jax.vmap(lambda k: jax.random.split(k, max_steps))(k1), 1, 0)  # [T, E, 2]
        (_, _, _, ret, length, collided, completed, *visits), poses = jax.lax.scan(body, init, step_keys)
        poses = jnp.concatenate([state.pose[None], poses], 0)  # [T + 1, E, 3]
        slot = (state.layout,) if with_slot else ()
        return collided, completed, ret, length, jnp.moveaxis(poses, 1, 0), *visits, *slot

    return jax.jit(run)


def rates(collided, completed, ret, length, poses=None, visits=None, *, max_steps: int | None = None) -> dict:
    """Safety and completion (true labelling) of finished evaluation episodes; with the [E, T + 1, 3]
    poses of ``make_rollout`` also the mean distance driven (m), which tells a safe policy that
    moves from one that stands still; with a Büchi task's ``visits`` [E], their mean per episode;
    with the episodes' ``max_steps``, ``rejection_rate``: the share the task rejected (``rejected``)."""
    collided, completed = np.asarray(collided), np.asarray(completed)
    out = {
        "episodes": int(collided.shape[0]),
        "safety_rate": float(1.0 - collided.mean()),
        "completion_rate": float(completed.mean()),
        "mean_return": float(np.asarray(ret).mean()),
        "mean_length": float(np.asarray(length).mean()),
    }
    if poses is not None:
        step = np.linalg.norm(np.diff(np.asarray(poses)[..., :2], axis=1), axis=-1)  # NaN after the end
        out["mean_distance"] = float(np.nansum(step, axis=1).mean())
    if visits is not None:
        out["accepting_visits_per_episode"] = float(np.asarray(visits).mean())
    if max_steps is not None:
        out["rejection_rate"] = float(rejected(collided, completed, length, max_steps).mean())
    return out


def visit_optimum(task, max_steps: int, cfg, visits: float | None, margin: float | None = None) -> dict:
    """For a recurrence compiled on one layout (``task``, a ``CompiledTask``; None for a bank of
    layouts): its route-optimal visits per episode of ``max_steps`` steps under the resolved env
    config ``cfg`` (``CompiledTask.optimal_visits``) and ``visits`` (the mean per episode) as a
    fraction of it; {} for any other task. With ``margin`` (the barrier's margin d of a learner that
    keeps it) wider than the robot's radius, also ``route_optimal_visits_margin``: the same count
    on routes that keep ``margin`` from every obstacle and wall: a layout whose every route passes
    closer, where the barrier may hold the robot back (as training's barrier-margin warning says), is
    flagged. A hint, not a bound: a robot may still pass a little closer than d (grid routes at 0.29 m
    have been driven)."""
    if task is None or task.distance is None or not task.recurrence:
        return {}
    v = cfg.v_max * cfg.v_gain
    best = task.optimal_visits(int(max_steps), cfg.dt, v)
    out = {"route_optimal_visits": best, "visit_fraction": None if visits is None or best == 0 else visits / best}
    if margin is not None and margin > task.robot_radius:
        out["margin"] = float(margin)
        out["route_optimal_visits_margin"] = task.optimal_visits(int(max_steps), cfg.dt, v, radius=margin)
    return out


def random_proposal_safety(learner, carry, env, params, shielded: bool, episodes: int = 64, seed: int = 3) -> float:
    """Fraction of episodes without collision when uniform random proposals u_rl ~ U[-1, 1]^2 are
    executed through D²SPO's π_Ω (``shielded``, ``learner.execute``) or directly: safety of pure
    exploration."""

    def one(key):
        k0, k1 = jax.random.split(key)
        state, obs = env.reset(k0, params)

        def body(c, k):
            state, obs, alive, hit = c
            ka, ks = jax.random.split(k)
            u = jax.random.uniform(ka, (2,), minval=-1.0, maxval=1.0)
            if shielded:
                u = learner.execute(carry.safety, obs, u, state.pose)
            state, obs, _, _, done, info = env.step(ks, state, u, params)
            return (state, obs, alive & ~done, hit | (alive & info["collided"])), None

        (_, _, _, hit), _ = jax.lax.scan(body, (state, obs, True, False), jax.random.split(k1, int(params.max_steps)))
        return hit

    hits = jax.jit(jax.vmap(one))(jax.random.split(jax.random.PRNGKey(seed), episodes))
    return float(1.0 - np.mean(np.asarray(hits)))
