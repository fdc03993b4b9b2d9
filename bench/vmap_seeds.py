"""Training throughput of seeds vmapped into one program, against one seed alone.

    .venv/bin/python bench/vmap_seeds.py [--algos ppo-lag d2spo ...] [--seeds 3] [--chunks 3]

For each learner it times ``jax.jit(jax.vmap(learner.chunk))`` over 1 and over ``--seeds`` keys,
as ``d2spo.train.train_seeds`` runs them (compile and one warm-up chunk excluded), and prints the
total env steps/s of each and their ratio. The last line is one JSON object
{algo: {"1": steps_per_s, "N": steps_per_s, "gain": ratio}}.
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp

# bench/ is on sys.path when a bench script runs
from train_throughput import time_chunks

from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.run import build


def measure(algo: str, task: str, layout: str, n_seeds: int, chunks: int) -> float:
    cfg = TrainConfig(algo=algo, task=task, env=EnvConfig(layout=layout)).check()
    _, _, learner = build(cfg)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in range(n_seeds)])
    carry = jax.jit(jax.vmap(learner.init))(keys)
    chunk = jax.jit(jax.vmap(learner.chunk), donate_argnums=0)
    carry, log = chunk(carry)
    jax.block_until_ready(log.done)
    return n_seeds * chunks * cfg.chunk_steps * cfg.num_envs / time_chunks(chunk, carry, chunks)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--algos", nargs="+", default=["ppo-lag", "d2spo"])
    ap.add_argument("--task", default="phi1")
    ap.add_argument("--layout", default="paper")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--chunks", type=int, default=3)
    args = ap.parse_args()
    out = {}
    for algo in args.algos:
        one = measure(algo, args.task, args.layout, 1, args.chunks)
        many = measure(algo, args.task, args.layout, args.seeds, args.chunks)
        print(f"{algo:8s} 1 seed {one:10,.0f}   {args.seeds} seeds {many:10,.0f} env steps/s   "
              f"gain {many / one:.2f}x", flush=True)
        out[algo] = {"1": round(one, 1), str(args.seeds): round(many, 1), "gain": round(many / one, 3)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
