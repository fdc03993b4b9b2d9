"""Does XLA:CPU keep both cores busy? One program's independent updates, and two programs at once.

    python bench/concurrency.py [--hidden 128] [--batch 128] [--steps 2000]

Two gradient steps of two independent MLPs (35 inputs, two tanh layers of ``--hidden``, 2 outputs,
batch ``--batch``: about the size of one TD3 critic's step in D²SPO), run ``--steps`` times in a
``lax.scan``, timed four ways, best of three:

1. each MLP's step alone in its program, then both in the same scan step (independent of each
   other): if XLA ran independent operations of one program on different cores, "both" would take
   about as long as the slower one alone, not their sum;
2. the one-MLP program twice from one Python thread (dispatched asynchronously), then twice at once
   from two Python threads: if two programs execute side by side, the two threads take about as
   long as one run.

D²SPO's step holds TD3's update and UPDATE(Ω, Θ) in one program (bench/RESULTS.md, "2026-12-01, morning"),
so case 1 says whether the second core can help a single run. Prints one line per case.
"""

from __future__ import annotations

import argparse
import threading
import time

import jax
import jax.numpy as jnp

import d2spo  # noqa: F401  (the XLA flags d2spo's commands run with: d2spo/_xla.py)


def init(key, hidden: int):
    k1, k2, k3 = jax.random.split(key, 3)
    return [jax.random.normal(k1, (35, hidden)) * 0.1, jax.random.normal(k2, (hidden, hidden)) * 0.1,
            jax.random.normal(k3, (hidden, 2)) * 0.1]


def sgd_step(w, x):
    def loss(w):
        h = jnp.tanh(jnp.tanh(x @ w[0]) @ w[1])
        return jnp.mean((h @ w[2]) ** 2)

    return [a - 1e-3 * g for a, g in zip(w, jax.grad(loss)(w))]


def best_of_three(fn) -> float:
    fn()  # compile and warm up
    times = []
    for _ in range(3):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hidden", type=int, default=128)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--steps", type=int, default=2000)
    args = ap.parse_args()
    x = jax.random.normal(jax.random.PRNGKey(1), (args.batch, 35))
    a, b = init(jax.random.PRNGKey(0), args.hidden), init(jax.random.PRNGKey(2), args.hidden)

    def program(which: str):
        def body(carry, _):
            wa, wb = carry
            if which in ("a", "both"):
                wa = sgd_step(wa, x)
            if which in ("b", "both"):
                wb = sgd_step(wb, x)
            return (wa, wb), None

        run = jax.jit(lambda carry: jax.lax.scan(body, carry, None, length=args.steps)[0])
        return lambda: jax.block_until_ready(run((a, b)))

    per_step = {k: best_of_three(program(k)) / args.steps * 1e3 for k in ("a", "b", "both")}
    print(f"one program, per scan step: MLP a alone {per_step['a']:.3f} ms, b alone {per_step['b']:.3f} ms, "
          f"both (independent) {per_step['both']:.3f} ms: {per_step['both'] / max(per_step['a'], per_step['b']):.2f}x "
          f"the slower alone (1.0: side by side; 2.0: one after the other)")

    one = jax.jit(lambda w: jax.lax.scan(lambda w, _: (sgd_step(w, x), None), w, None, length=args.steps)[0])
    alone = best_of_three(lambda: jax.block_until_ready(one(a)))
    serial = best_of_three(lambda: jax.block_until_ready((one(a), one(b))))

    def two_threads():
        threads = [threading.Thread(target=lambda w=w: jax.block_until_ready(one(w))) for w in (a, b)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()

    side = best_of_three(two_threads)
    print(f"two programs: one run {alone:.3f} s; two from one thread {serial:.3f} s ({serial / alone:.2f}x); "
          f"two from two threads {side:.3f} s ({side / alone:.2f}x)")


if __name__ == "__main__":
    main()
