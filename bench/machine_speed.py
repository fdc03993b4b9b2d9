"""How fast this machine is right now, at the three things d2spo's timings are made of.

    python bench/machine_speed.py [--repeats 5]

Cloud machines of one CPU type drift from hour to hour, and not evenly: on the AMD EPYC of family 25
model 17, `make test` took 4 min 41 s one hour and 7 min 18 s the next with the same code, while
``bench/concurrency.py``'s MLP step read the same (bench/RESULTS.md, "2026-12-01, a late session").
So a figure in bench/RESULTS.md is best read beside this probe's three numbers, taken the same hour:

- **run**: one gradient step of a 128-128 MLP on a batch of 128 (about a TD3 critic's step), in a
  ``lax.scan`` of 2000, ms per step: what training's speed follows;
- **trace + lower**: tracing and lowering a program of 150 such steps unrolled (Python and MLIR),
  seconds;
- **compile**: XLA compiling that lowered program, at the test suite's flags (level 0, no fusion
  emitters) and at XLA's default, seconds: what a cold `make test` and a cold command follow.

Each is the best of ``--repeats``; every compile is of a program with its own constant, so no
cache (in-process or persistent: none is set here) can serve it. Prints one line per number and a
JSON line last.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp

import d2spo  # noqa: F401  (the XLA flags d2spo's commands run with: d2spo/_xla.py)

HIDDEN, BATCH, INPUTS = 128, 128, 35
SUITE_OPTIONS = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
"""XLA's options for the test suite's programs (tests/conftest.py sets them as XLA_FLAGS)."""


def _weights(key):
    k1, k2, k3 = jax.random.split(key, 3)
    return [jax.random.normal(k1, (INPUTS, HIDDEN)) * 0.1, jax.random.normal(k2, (HIDDEN, HIDDEN)) * 0.1,
            jax.random.normal(k3, (HIDDEN, 2)) * 0.1]


def _step(w, x, lr):
    def loss(w):
        return jnp.mean((jnp.tanh(jnp.tanh(x @ w[0]) @ w[1]) @ w[2]) ** 2)

    return [a - lr * g for a, g in zip(w, jax.grad(loss)(w))]


def _best(fn, repeats: int) -> float:
    best = float("inf")
    for i in range(repeats):
        t = time.perf_counter()
        fn(i)
        best = min(best, time.perf_counter() - t)
    return best


def run_ms(repeats: int, steps: int = 2000) -> float:
    """ms per scanned gradient step, compile excluded."""
    w, x = _weights(jax.random.PRNGKey(0)), jax.random.normal(jax.random.PRNGKey(1), (BATCH, INPUTS))
    scan = jax.jit(lambda w: jax.lax.scan(lambda c, _: (_step(c, x, 1e-3), None), w, None, length=steps)[0])
    jax.block_until_ready(scan(w))
    return _best(lambda _: jax.block_until_ready(scan(w)), repeats) / steps * 1e3


UNROLLED = 150
"""Gradient steps written out in the compiled program (its compile takes seconds, as the suite's do)."""


def _unrolled(lr: float, steps: int = UNROLLED):
    """A jitted program of ``steps`` gradient steps written out one after another; ``lr`` makes it
    a program of its own."""
    def program(w, x):
        for _ in range(steps):
            w = _step(w, x, lr)
        return w

    return jax.jit(program)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    w = _weights(jax.random.PRNGKey(0))
    x = jax.random.normal(jax.random.PRNGKey(1), (BATCH, INPUTS))
    lowered: dict[int, object] = {}

    def trace_lower(i: int) -> None:
        lowered[i] = _unrolled(1e-3 * (1 + i)).lower(w, x)

    figures = {"run_ms": run_ms(args.repeats), "trace_lower_s": _best(trace_lower, args.repeats)}
    for i in range(args.repeats):  # fresh programs for the default level's compiles
        trace_lower(args.repeats + i)
    _unrolled(0.5, 2).lower(w, x).compile()  # XLA's first compile in a process pays its set-up
    suite, default = float("inf"), float("inf")
    for i in range(args.repeats):  # alternated, so a drift within the run touches both alike
        t = time.perf_counter()
        lowered[i].compile(SUITE_OPTIONS)
        suite = min(suite, time.perf_counter() - t)
        t = time.perf_counter()
        lowered[args.repeats + i].compile()
        default = min(default, time.perf_counter() - t)
    figures["compile_suite_s"], figures["compile_default_s"] = suite, default
    print(f"run: {figures['run_ms']:.3f} ms per MLP step")
    print(f"trace + lower: {figures['trace_lower_s']:.2f} s ({UNROLLED} steps unrolled)")
    print(f"compile: {figures['compile_suite_s']:.2f} s at the suite's flags, "
          f"{figures['compile_default_s']:.2f} s at XLA's default")
    print(json.dumps({k: round(v, 4) for k, v in figures.items()}))


if __name__ == "__main__":
    main()
