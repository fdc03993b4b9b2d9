"""Seconds per step of a plain Python loop over ``GymnaxNav.step`` (jitted, as gymnax's own step is).

    python bench/gymnax_loop.py [--steps 500] [--task F A1] [--layout open]

The first call compiles; the figure is the mean over the following ``--steps`` calls, each waited
for (``block_until_ready``). Figures in bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from d2spo.envs.gymnax_env import GymnaxNav


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--task", default="F A1")
    ap.add_argument("--layout", default="open")
    args = ap.parse_args()
    env, params = GymnaxNav.make(task=args.task, layout=args.layout)
    obs, state = env.reset(jax.random.key(0), params)
    action = jnp.array([1.0, 0.2])
    t0 = time.perf_counter()
    obs, state, *_ = env.step(jax.random.key(1), state, action, params)
    jax.block_until_ready(obs)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for t in range(args.steps):
        obs, state, *_ = env.step(jax.random.key(t), state, action, params)
        jax.block_until_ready(obs)
    per = (time.perf_counter() - t0) / args.steps
    print(f"first step (compiling): {first:.2f} s; then {1e3 * per:.3f} ms per step over {args.steps} steps")


if __name__ == "__main__":
    main()
