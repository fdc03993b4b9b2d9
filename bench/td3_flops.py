"""Is TD3's update bound by arithmetic on this machine? Its floating-point work against the rate at
which this machine multiplies matrices of the same size.

    python bench/td3_flops.py [--repeats 5] [--updates 500] [--hidden 128 128] [--batch 128]

TD3's update is about half of each vectorised step of a D²SPO training (bench/profile_chunk.py), and
it runs on one core (1.36 of 2 cores busy over a ϕ1 run). This script says whether that half can be
made faster by running it better, or only by giving it less to do:

- **work per update**, in MFLOP: counted from the layer widths (two flops per multiply-add; the
  critics' step: the target actor and the twin target critics forward, the twin critics forward and
  backward; the actor's step, every ``policy_delay``-th update: the actor forward and backward, Q1
  forward and its gradient with respect to the action), and XLA's own count of the compiled update
  (``cost_analysis``; it counts both branches of the delayed actor step, so it compares with the
  critics' plus the actor's step);
- **rate**: a ``lax.scan`` of ``--updates`` plain TD3 updates (no safety layer), ms per update
  (best of ``--repeats``) and the GFLOP/s that makes at the average work per update;
- **this machine's rate at that size**: a chain of ``batch x hidden @ hidden x hidden`` products
  (tanh between), and of 512-wide ones (which XLA spreads over both cores), in GFLOP/s.

An update near the first reference is bound by arithmetic on one core: only fewer flops (a smaller
batch or network, fewer updates: algorithm settings) or larger products that XLA can share between
cores would make it faster. Prints one line per figure and a JSON line last.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import jax.numpy as jnp

import d2spo  # noqa: F401  (the XLA flags d2spo's commands run with: d2spo/_xla.py)
from d2spo.algos import td3
from d2spo.replay import Transition

OBS, ACT = 35, 2
"""The ϕ1 observation (lidar, the robot's state, the path features) and the unicycle's action."""


def macs(rows: int, sizes: list[int]) -> int:
    """Multiply-adds of a dense network's forward pass over ``rows`` inputs."""
    return rows * sum(a * b for a, b in zip(sizes[:-1], sizes[1:]))


def work(batch: int, hidden: list[int]) -> tuple[float, float]:
    """(critics' step, actor's step) of one TD3 update, in flops, from the widths."""
    actor, q = [OBS, *hidden, ACT], [OBS + ACT, *hidden, 1]
    first_q, first_actor = batch * q[0] * q[1], batch * actor[0] * actor[1]  # no input gradient there
    critics = macs(batch, actor) + 2 * macs(batch, q) + 2 * macs(batch, q) + 2 * (2 * macs(batch, q) - first_q)
    actor_step = macs(batch, actor) + macs(batch, q) + macs(batch, q) + (2 * macs(batch, actor) - first_actor)
    return 2.0 * critics, 2.0 * actor_step


def best(fn, arg, repeats: int) -> float:
    jax.block_until_ready(fn(arg))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(arg))
        times.append(time.perf_counter() - t)
    return min(times)


def chain_rate(rows: int, width: int, steps: int, repeats: int) -> float:
    """GFLOP/s of ``steps`` products ``rows x width @ width x width`` in a chain, tanh between."""
    x = jax.random.normal(jax.random.PRNGKey(0), (rows, width))
    w = jax.random.normal(jax.random.PRNGKey(1), (width, width)) / width ** 0.5
    fn = jax.jit(lambda x: jax.lax.fori_loop(0, steps, lambda i, x: jnp.tanh(x @ w), x))
    return 2.0 * rows * width * width * steps / best(fn, x, repeats) / 1e9


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--updates", type=int, default=500)
    ap.add_argument("--hidden", type=int, nargs="+", default=None, help="TD3's widths (default: TD3Config's)")
    ap.add_argument("--batch", type=int, default=None, help="TD3's batch size (default: TD3Config's)")
    args = ap.parse_args()
    cfg = td3.TD3Config()
    cfg = dataclasses.replace(cfg, hidden=tuple(args.hidden or cfg.widths), batch_size=args.batch or cfg.batch_size)
    hidden, rows = list(cfg.widths), cfg.batch_size

    nets = td3.make_nets(ACT, cfg)
    key = jax.random.PRNGKey(0)
    agent = td3.init_agent(key, nets, OBS, ACT)
    ks = jax.random.split(key, 5)
    shapes = [(rows, OBS), (rows, ACT), (rows,), (rows,), (rows, OBS)]
    batch = Transition(*(jax.random.normal(k, s) for k, s in zip(ks, shapes)),
                       *[jnp.zeros((rows,))] * (len(Transition._fields) - len(shapes)))

    critics, actor = work(rows, hidden)
    average = critics + actor / cfg.policy_delay
    counted = jax.jit(lambda a: td3.td3_update(nets, a, batch, key, cfg)).lower(agent).compile().cost_analysis()
    counted = (counted[0] if isinstance(counted, list) else counted)["flops"]

    def updates(agent):
        def one(a, k):
            a, m = td3.td3_update(nets, a, batch, k, cfg)
            return a, m["losses/qf"]
        return jax.lax.scan(one, agent, jax.random.split(key, args.updates))

    ms = best(jax.jit(updates), agent, args.repeats) / args.updates * 1e3
    rate = average / (ms * 1e-3) / 1e9
    same_size = chain_rate(rows, max(hidden), 2000, args.repeats)
    wide = chain_rate(rows, 512, 500, args.repeats)

    print(f"TD3 update, {'-'.join(map(str, hidden))}, batch {rows}, policy delay {cfg.policy_delay}")
    print(f"work: critics' step {critics / 1e6:.1f} MFLOP, actor's step {actor / 1e6:.1f} MFLOP "
          f"(XLA counts {counted / 1e6:.1f} for both); {average / 1e6:.1f} MFLOP per update on average")
    print(f"rate: {ms:.3f} ms per update, {rate:.0f} GFLOP/s")
    print(f"this machine: {same_size:.0f} GFLOP/s for {rows}x{max(hidden)}x{max(hidden)} products, "
          f"{wide:.0f} GFLOP/s for {rows}x512x512 (both cores); the update runs at "
          f"{rate / same_size:.0%} of the first")
    print(json.dumps({"critics_mflop": round(critics / 1e6, 2), "actor_mflop": round(actor / 1e6, 2),
                      "xla_mflop_both_branches": round(counted / 1e6, 2), "ms_per_update": round(ms, 4),
                      "gflops": round(rate, 1), "chain_gflops": round(same_size, 1),
                      "wide_chain_gflops": round(wide, 1)}))


if __name__ == "__main__":
    main()
