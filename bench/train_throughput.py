"""Env steps per second of training (acting, env step, buffers and every update), per learner.

    .venv/bin/python bench/train_throughput.py [--algos d2spo tlgrl ...] [--chunks 4]
        [--shaping-metric geodesic] [--observe-path off] [--td3-hidden 256 256 --td3-batch 256 --learning-starts 0]

Compile time is excluded (one warm-up chunk); each figure is the mean over ``--chunks`` timed chunks.
The last line of output is one JSON object {algo: env_steps_per_second}.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax

from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.ltl.reward import RewardConfig
from d2spo.run import build


def measure(algo: str, task: str, layout: str, chunks: int, num_envs: int, hidden=None, batch=None,
            learning_starts=None, shaping_metric: str = RewardConfig.shaping_metric,
            observe_path: bool | None = None) -> tuple[float, float]:
    env = EnvConfig(layout=layout, reward=RewardConfig(shaping_metric=shaping_metric), observe_path=observe_path)
    cfg = TrainConfig(algo=algo, task=task, env=env, num_envs=num_envs)
    changes = {k: v for k, v in (("hidden", tuple(hidden) if hidden else None), ("batch_size", batch),
                                 ("learning_starts", learning_starts)) if v is not None}
    if changes:  # TD3-based learners only (td3, tlgrl, sl, d2spo)
        cfg = dataclasses.replace(cfg, td3=dataclasses.replace(cfg.td3, **changes))
    cfg = cfg.check()
    _, _, learner = build(cfg)
    t0 = time.perf_counter()
    carry = jax.jit(learner.init)(jax.random.PRNGKey(0))
    chunk = jax.jit(learner.chunk)
    carry, log = chunk(carry)
    jax.block_until_ready(log.done)
    warm = time.perf_counter() - t0
    return chunks * cfg.chunk_steps * cfg.num_envs / time_chunks(chunk, carry, chunks), warm


def time_chunks(chunk, carry, chunks: int) -> float:
    """Seconds for ``chunks`` further calls of a compiled, warmed-up ``chunk`` (also used by vmap_seeds.py)."""
    t0 = time.perf_counter()
    for _ in range(chunks):
        carry, log = chunk(carry)
    jax.block_until_ready(log.done)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--algos", nargs="+", default=["d2spo", "tlgrl"])
    ap.add_argument("--task", default="phi1")
    ap.add_argument("--layout", default="paper")
    ap.add_argument("--shaping-metric", default=RewardConfig.shaping_metric,
                    help="geodesic-per-state (default), geodesic or euclidean")
    ap.add_argument("--observe-path", choices=["auto", "on", "off"], default="auto",
                    help="the path direction in the observation (auto: on with geodesic-per-state)")
    ap.add_argument("--chunks", type=int, default=4)
    ap.add_argument("--num-envs", type=int, default=TrainConfig().num_envs)
    ap.add_argument("--td3-hidden", type=int, nargs="+", help="TD3 widths (td3, tlgrl, sl, d2spo)")
    ap.add_argument("--td3-batch", type=int, help="TD3 minibatch (td3, tlgrl, sl, d2spo)")
    ap.add_argument("--learning-starts", type=int, help="TD3 warm-up transitions (0: learn from the first chunk)")
    args = ap.parse_args()
    out = {}
    for algo in args.algos:
        sps, warm = measure(algo, args.task, args.layout, args.chunks, args.num_envs, args.td3_hidden,
                            args.td3_batch, args.learning_starts, args.shaping_metric,
                            {"auto": None, "on": True, "off": False}[args.observe_path])
        print(f"{algo:8s} {sps:10,.0f} env steps/s   (init + compile + first chunk: {warm:.1f} s)", flush=True)
        out[algo] = round(sps, 1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
