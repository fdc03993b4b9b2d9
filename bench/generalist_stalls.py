"""Where a generalist's zero-shot patrol loses time: its proposed speed and its stalls, layout by layout
(issue 34's generalist target).

    .venv/bin/python bench/generalist_stalls.py RUN [--task patrol2] [--layouts 20] [--first-seed 100000]
        [--episodes 16] [--policy best|last] [--probe]

RUN is a ``d2spo train --algo d2spo --generalist`` directory. Each layout ``random:FIRST+i`` gets
``--episodes`` deterministic episodes of the task's zero-shot limit, as ``d2spo eval RUN --task T``
runs them (π_Ω and the run's filter setting), recording at every step the actor's own proposal u_rl
(before π_Ω) and what it observes. Per layout it prints the accepting visits per episode, the mean
proposed linear speed (in units of v_max; the actor is forward-only), the share of steps the actor
*stalls* (speed under 0.05 v_max and turn rate under 0.3 of its bound: a deterministic policy in a
static world then sees almost the same observation at the next step) and the proposed speed on the
steps where the path to the target lies straight ahead (the observation's target direction, forward
component over 0.98), where nothing but the actor holds the robot back.

``--probe`` then takes the layout with the most stalled steps, its first stalled step of episode 0,
and prints the actor's output before its tanh and the twin critics' smaller Q over proposed speeds
0, 0.1, ..., 1 (turn rate 0), from the run's newest checkpoint: a Q that rises with the speed while
the actor sits at 0 is a stall the policy gradient cannot leave (the tanh's slope there is
1 - tanh(z)², tiny for z well below -2). The checkpoint's critic is the one of the run's end, not
necessarily that of the kept policy. Figures in bench/RESULTS.md, "2026-12-01, a later session".
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from d2spo import zero_shot
from d2spo.checkpoint import load_checkpoint, run_fingerprint
from d2spo.evaluate import eval_env_config
from d2spo.rollout import acting_on
from d2spo.run import carry_template, load_policy

STALL_SPEED, STALL_TURN, AHEAD = 0.05, 0.3, 0.98


def recorder(env, learner, episodes: int, steps: int):
    """A jitted (params, policy, key) -> (obs [T, E, O], u_rl [T, E, 2], accepting visits [T, E])."""

    def run(params, policy, key):
        lrn = acting_on(learner, params)
        k0, k1 = jnp.moveaxis(jax.vmap(jax.random.split)(jax.random.split(key, episodes)), 1, 0)
        state, obs = jax.vmap(env.reset, in_axes=(0, None))(k0, params)

        def body(c, k):
            state, obs = c
            u_rl = learner.nets.actor.apply(policy[0], obs)
            u = jax.vmap(lambda s, o: lrn.act(policy, o, s, None))(state, obs)
            state2, obs2, _, _, _, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(k, state, u, params)
            return (state2, obs2), (obs, u_rl, info["accepting_visit"])

        keys = jnp.moveaxis(jax.vmap(lambda k: jax.random.split(k, steps))(k1), 1, 0)
        return jax.lax.scan(body, (state, obs), keys)[1]

    return jax.jit(run)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("--task", default="patrol2")
    ap.add_argument("--layouts", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=100000)
    ap.add_argument("--episodes", type=int, default=16)
    ap.add_argument("--policy", default="best", choices=("best", "last"))
    ap.add_argument("--probe", action="store_true")
    args = ap.parse_args()

    cfg, _, _, _ = load_policy(args.run)
    env_cfg = zero_shot.seen_forbidden_range(eval_env_config(cfg, None))  # as d2spo eval sees it
    checked = [zero_shot.generalist_layout(env_cfg, f"random:{args.first_seed + i}", args.task, cfg.cbf.d)
               for i in range(args.layouts)]
    env, params, learner, limit = zero_shot.generalist_on(cfg, env_cfg, args.task, checked)
    _, _, policy, meta = load_policy(args.run, args.policy, learner)
    run = recorder(env, learner, args.episodes, limit)
    part = env.observation_slices["target"]
    print(f"{args.run}: {args.task}, policy {meta['policy']}, {args.episodes} episodes of {limit} steps per layout\n")
    print("| layout | visits / episode | proposed speed | stalled steps | speed with the target ahead (share of steps) |")
    print("|---|---:|---:|---:|---|")
    worst = (-1.0, None)
    for k, (lay, _) in enumerate(checked):
        p = params if k == 0 else zero_shot.view(params.replace(bank=env.bank([lay], max_steps=limit)),
                                                  jnp.zeros((), jnp.int32))
        obs, u_rl, visits = (np.asarray(a) for a in run(p, policy, jax.random.PRNGKey(0)))
        v, w = u_rl[..., 0], u_rl[..., 1]
        stall = (v < STALL_SPEED) & (np.abs(w) < STALL_TURN)
        ahead = obs[..., part][..., 1] > AHEAD
        ahead_v = f"{v[ahead].mean():.2f} ({ahead.mean():.0%})" if ahead.any() else "-"
        print(f"| `{lay.name}` | {visits.sum() / args.episodes:.2f} | {v.mean():.2f} | {stall.mean():.1%} | {ahead_v} |")
        if stall.mean() > worst[0] and stall[:, 0].any():
            worst = (float(stall.mean()), (lay.name, obs[np.argmax(stall[:, 0]), 0], int(np.argmax(stall[:, 0]))))
    if args.probe and worst[1] is not None:
        name, o, t = worst[1]
        carry, _ = load_checkpoint(args.run, carry_template(learner), run_fingerprint(args.run))
        z = learner.nets.actor.apply(policy[0], o, pre_tanh=True)
        speeds = jnp.linspace(0.0, 1.0, 11)
        q = learner.nets.critic.apply(carry.agent.critic, jnp.broadcast_to(o, (11, o.shape[0])),
                                      jnp.stack([speeds, jnp.zeros_like(speeds)], -1)).min(0)
        print(f"\nprobe: `{name}`, episode 0, step {t}: the actor's output before its tanh {np.round(np.asarray(z), 2)}")
        print("the newest checkpoint's critics, min Q at proposed speed 0, 0.1, ..., 1 (turn rate 0):",
              " ".join(f"{x:.2f}" for x in np.asarray(q)))


if __name__ == "__main__":
    main()
