"""Environment throughput: full steps per second (dynamics, collision, labelling, reward, lidar
observation, same-step autoreset) with uniformly random actions, for 1, 64, 1024 and 16384
parallel environments.

Each measurement runs ``n_steps`` steps of all environments inside one jit-compiled
``lax.scan``; compile time is excluded (one warm-up call) and timing waits on
``block_until_ready``. The observations, rewards and costs feed a checksum so that no part of the
step can be optimised away.

    python bench/env_throughput.py [--layout paper] [--task phi1] [--repeats 3] [--observe-path off]

The last line of output is a JSON object {"1": steps/s, "64": ..., "1024": ..., "16384": ...}
(wall clock). Each line before it also gives steps per CPU-second of the process, which is less
sensitive to other jobs on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp

from d2spo.envs import EnvConfig, make_env

# Steps per scan for each batch size: roughly 1-2 s of work per call on a 2-core CPU.
STEPS = {1: 20_000, 64: 4_000, 1024: 1_000, 16384: 100}


def make_runner(env, params, n_envs: int, n_steps: int):
    def one_step(carry, key):
        state, checksum = carry
        k_act, k_env = jax.random.split(key)
        action = jax.random.uniform(k_act, (n_envs, 2), minval=-1.0, maxval=1.0)
        state, obs, reward, cost, done, info = env.step_batch(k_env, state, action, params)
        checksum = checksum + jnp.sum(obs) + jnp.sum(info["next_obs"]) + jnp.sum(reward) + jnp.sum(cost)
        return (state, checksum), None

    @jax.jit
    def run(state, key):
        (state, checksum), _ = jax.lax.scan(one_step, (state, jnp.float32(0)), jax.random.split(key, n_steps))
        return state, checksum

    return run


def measure(env, params, n_envs: int, n_steps: int, repeats: int) -> tuple[float, float]:
    """Best of ``repeats``: (steps per wall-clock second, steps per CPU second of this process)."""
    state, _ = env.reset_batch(jax.random.key(0), params, n_envs)
    run = make_runner(env, params, n_envs, n_steps)
    state, checksum = run(state, jax.random.key(1))  # compile + warm-up
    jax.block_until_ready(checksum)
    wall = cpu = float("inf")
    for r in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        state, checksum = run(state, jax.random.key(2 + r))
        jax.block_until_ready((state, checksum))
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return n_envs * n_steps / wall, n_envs * n_steps / cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--layout", default="paper")
    parser.add_argument("--task", default="phi1")
    parser.add_argument("--preset", default="default")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sizes", default="1,64,1024,16384")
    parser.add_argument("--observe-path", choices=["auto", "on", "off"], default="auto",
                        help="the path direction in the observation (auto: on with the default shaping)")
    args = parser.parse_args()

    observe_path = {"auto": None, "on": True, "off": False}[args.observe_path]
    env, params = make_env(EnvConfig(layout=args.layout, preset=args.preset, observe_path=observe_path), args.task)
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}; layout={args.layout} task={args.task} "
          f"preset={args.preset} obs={env.observation_size} rays={env.n_rays} obstacles={env.n_obstacles}")
    results = {}
    for n in (int(s) for s in args.sizes.split(",")):
        sps, per_cpu = measure(env, params, n, STEPS.get(n, max(100, 1_000_000 // n)), args.repeats)
        results[str(n)] = round(sps)
        print(f"{n:>6} envs: {sps:>12,.0f} steps/s   ({per_cpu:>12,.0f} steps per CPU-second)")
    print(json.dumps(results))


if __name__ == "__main__":
    main()
