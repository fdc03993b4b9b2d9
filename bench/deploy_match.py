"""How closely the exported policy (``d2spo.deploy``, numpy) acts as the run's JAX policy, along the
run's own trajectories rather than at random states.

    .venv/bin/python bench/deploy_match.py RUN [--episodes 20] [--policy best|last]

Exports RUN into a temporary directory, rolls out ``--episodes`` deterministic episodes of the JAX
policy without the runtime filter (the run's env and dynamics, seed ``--seed``, the areas' true
radii as ``d2spo eval`` reads them) and at every step compares, with the filter off (its ties:
docs/deploy.md, "How exactly it matches the JAX policy"): the observation deploy builds from the
lidar scan, pose and q with the env's; the action from the env's observation (``act_observation``),
from the readings at the true pose (``act``) and at the pose read back off the observation
(``pose_of_observation``, as examples/deploy_gym_loop.py acts) with JAX's. Prints the number of
states and, per comparison, the max |difference| and its 99th and 50th percentiles.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.algos import has_runtime_filter, make_learner
from d2spo.deploy import Policy
from d2spo.envs import sensors
from d2spo.export import ExportConfig, export_run
from d2spo.rollout import acting_on
from d2spo.run import build, load_policy, load_run_config


def trajectories(run: Path, episodes: int, policy_name: str, seed: int):
    """(poses [N, 3], q [N], observations [N, D], scans [N, K], JAX's actions [N, 2]) at every step of
    ``episodes`` episodes of the run's policy, filter off."""
    cfg = load_run_config(run)
    if has_runtime_filter(cfg.algo):
        cfg = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, runtime_filter=False))
    env, params, learner = build(cfg)
    _, _, policy, _ = load_policy(run, policy_name, learner)
    params = params.replace(label_radius=params.area_radius)  # as the rollouts of d2spo eval
    lrn = acting_on(make_learner(cfg, env, params), params)
    everything = jnp.ones((params.geom.n_obstacles,), bool)
    steps = int(params.max_steps)

    @jax.jit
    def run_all(key):
        k0, k1 = jax.random.split(key)
        state, obs = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k0, episodes), params)

        def body(c, k):
            state, obs, alive = c
            a = jax.vmap(lrn.act, in_axes=(None, 0, 0, 0))(policy, obs, state, jax.random.split(k, episodes))
            scan = jax.vmap(lambda p: sensors.lidar(p, params.geom, everything, env.n_rays,
                                                    params.sensing_radius))(state.pose)
            state2, obs2, _, _, done, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(k, episodes), state, a, params)
            return (state2, obs2, alive & ~done), (state.pose, state.q, obs, scan, a, alive)

        init = (state, obs, jnp.ones(episodes, bool))
        return jax.lax.scan(body, init, jax.random.split(k1, steps))[1]

    pose, q, obs, scan, a, alive = (np.asarray(x) for x in run_all(jax.random.PRNGKey(seed)))
    keep = alive.reshape(-1)
    return tuple(x.reshape(-1, *x.shape[2:])[keep] for x in (pose, q, obs, scan, a))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run directory of d2spo train (one layout; not PPO-Lag, CPO or a generalist)")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--policy", default="best", choices=("best", "last"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    pose, q, obs, scan, want = trajectories(args.run, args.episodes, args.policy, args.seed)
    with tempfile.TemporaryDirectory(prefix="d2spo-match-") as tmp:
        export_run(args.run, Path(tmp) / "export", ExportConfig(policy=args.policy))
        policy = Policy.load(Path(tmp) / "export")
    off = False if policy.runtime_filter is not None else None
    built = np.stack([policy.observation(scan[i], pose[i], int(q[i])) for i in range(len(q))])
    from_obs = np.stack([policy.act_observation(o, filter=off) for o in obs])
    from_readings = np.stack([policy.act(scan[i], pose[i], int(q[i]), filter=off) for i in range(len(q))])
    read_back = np.stack([policy.act(scan[i], policy.pose_of_observation(obs[i]), int(q[i]), filter=off)
                          for i in range(len(q))])
    print(f"{args.run}: {len(q)} states of {args.episodes} episodes (seed {args.seed}), filter off")
    for name, got, ref in [("observation", built, obs), ("action from the observation", from_obs, want),
                           ("action from the readings", from_readings, want),
                           ("action from the readings, pose read off the observation", read_back, want)]:
        d = np.abs(got - ref).max(axis=1)
        print(f"  {name}: max {d.max():.2g}, 99th percentile {np.quantile(d, 0.99):.2g}, median {np.median(d):.2g}")


if __name__ == "__main__":
    main()
