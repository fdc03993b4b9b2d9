"""Where a recurrence specialist's accepting visits go: its laps, its speed, and the routes the barrier leaves.

    .venv/bin/python bench/patrol_laps.py RUN [--episodes 8] [--margins 0.2 0.25 0.3] [--plot laps.png]
        [--policy last|best]

RUN is a finished `d2spo train` of a recurrence task (``patrol2``, ...) on one layout. Its last
policy (``--policy best``: its validated one, ``--patrol-validation``) drives ``--episodes``
deterministic episodes (π_Ω, and the runtime filter as trained), and the script prints:

* the accepting visits of each episode, and the steps at which episode 0 made them (its laps in
  steps and metres);
* the speed: the mean distance per step against the most the dynamics allow on average
  (v_max · v_gain · (1 − slip / 2) · dt), and how often the actor's and the executed linear
  action are saturated (|a₀| > 0.99) and reversing (a₀ < 0);
* the route search's shortest lap (``routes.visit_lengths``: 8-neighbour grid routes, up to 8.2%
  longer than continuous ones) keeping the robot's radius and each ``--margins`` clearance from
  obstacles and walls (the barrier keeps about ``--cbf.d``), with the visits such routes fit in an
  episode at the speed above, 8.2% allowed for the grid.

With ``--plot`` it draws the first two episodes' paths, forward green, reversing magenta.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import jax
import numpy as np

from d2spo.envs import routes
from d2spo.run import load_policy
from d2spo.safety.joint_policy import safe_action


def rollout(learner, policy, episodes: int, seed: int = 0):
    """Per step [T, E, ...]: the actor's action, the executed one, pose before and after, visit flags."""
    env, params = learner.env, learner.params
    steps = int(params.max_steps)
    actor, safety = policy

    def run(key):
        k0, k1 = jax.random.split(key)
        state, obs = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k0, episodes), params)

        def body(c, k):
            state, obs = c
            keys = jax.random.split(k, episodes)
            u_rl = jax.vmap(lambda o: learner.nets.actor.apply(actor, o))(obs)
            a = jax.vmap(learner.act, in_axes=(None, 0, 0, 0))(policy, obs, state, keys)
            u_om = jax.vmap(lambda o, u: safe_action(learner.safety_nets, safety, learner.x_of_obs(o), u))(obs, u_rl)
            state2, obs2, _, _, _, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(keys, state, a, params)
            return (state2, obs2), (u_rl, u_om, a, info["pose"], info["next_pose"], info["accepting_visit"])

        return jax.lax.scan(body, (state, obs), jax.random.split(k1, steps))[1]

    return tuple(np.asarray(x) for x in jax.jit(run)(jax.random.PRNGKey(seed)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--margins", type=float, nargs="*", default=[0.2, 0.25, 0.3])
    ap.add_argument("--plot", type=Path, default=None)
    ap.add_argument("--policy", choices=("last", "best"), default="last")
    args = ap.parse_args()

    cfg, learner, policy, meta = load_policy(args.run, args.policy)
    task, dyn = learner.env.task, learner.env.config
    if task.distance is None or not task.recurrence:
        raise SystemExit(f"bench/patrol_laps.py: {args.run} is not a recurrence task's run")
    steps = int(learner.params.max_steps)
    u_rl, u_om, a, pose, nxt, visit = rollout(learner, policy, args.episodes)
    print(f"{args.run}: {meta.get('policy')}; {steps} steps per episode; runtime filter {learner.d2.runtime_filter}")
    print("accepting visits per episode:", visit.sum(0).tolist())
    at = np.flatnonzero(visit[:, 0])
    step_len = np.linalg.norm(nxt[..., :2] - pose[..., :2], axis=-1)
    metres = [float(step_len[s:e, 0].sum()) for s, e in zip(at, at[1:])]
    print(f"episode 0: visits at steps {at.tolist()}; laps {np.diff(at).tolist()} steps, "
          f"{[round(m, 2) for m in metres]} m")
    attainable = float(dyn.v_max * dyn.v_gain * (1 - dyn.slip / 2) * dyn.dt)
    print(f"speed: {step_len.mean():.4f} m per step, {100 * step_len.mean() / attainable:.1f}% of the "
          f"{attainable:.4f} the dynamics allow on average")
    for name, u in (("actor", u_rl), ("pi_Omega", u_om), ("executed", a)):
        print(f"  {name:9s} |a0| > 0.99 on {100 * np.mean(np.abs(u[..., 0]) > 0.99):.1f}% of steps, "
              f"a0 < 0 on {100 * np.mean(u[..., 0] < 0):.1f}%, |a1| > 0.99 on {100 * np.mean(np.abs(u[..., 1]) > 0.99):.1f}%")
    reach = steps * float(step_len.mean()) * routes.OCTILE_EXCESS
    for r in [task.robot_radius, *args.margins]:
        lengths = routes.visit_lengths(task.automaton, task.layout, task.label_mode, r, math.inf, 8)
        laps = np.diff(lengths) if len(lengths) > 1 else []
        fit = sum(x <= reach for x in lengths)
        print(f"routes keeping {r:.2f} m: first visit {lengths[0] if lengths else math.inf:.2f} m, lap "
              f"{laps[-1] if len(laps) else math.inf:.2f} m (grid); {fit} visits fit in {steps} steps at this speed")
    if args.plot:
        _plot(task.layout, pose, a, args.plot)
        print("wrote", args.plot)


def _plot(layout, pose, a, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from d2spo.envs.render import draw_layout

    fig, ax = plt.subplots(figsize=(5, 5))
    draw_layout(layout, ax)
    for e in range(min(2, pose.shape[1])):
        ax.scatter(pose[:, e, 0], pose[:, e, 1], s=2, c=np.where(a[:, e, 0] >= 0, "tab:green", "tab:purple"))
    fig.savefig(out, dpi=110, bbox_inches="tight")


if __name__ == "__main__":
    main()
