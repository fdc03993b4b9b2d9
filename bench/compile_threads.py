"""Do two XLA compilations in two threads of one process run side by side? (bench/RESULTS.md)

    python bench/compile_threads.py

Lowers four independent jitted functions (60 chained matmul/tanh/sin/cos layers each), compiles one
alone, then two at once from two threads, and prints both wall times. Side by side, two would take
about as long as one; one after the other, twice as long.
"""

from __future__ import annotations

import threading
import time

import jax
import jax.numpy as jnp


def program(k: int):
    def f(x):
        for i in range(60):
            x = jnp.tanh(x @ x.T * (i + k)) + jnp.sin(x) * jnp.cos(x + i)
        return x

    return jax.jit(f).lower(jnp.ones((64, 64)))


def main() -> None:
    a, b, c = program(1), program(2), program(3)
    t = time.perf_counter()
    a.compile()
    one = time.perf_counter() - t
    t = time.perf_counter()
    other = threading.Thread(target=b.compile)
    other.start()
    c.compile()
    other.join()
    print(f"one compilation {one:.2f} s; two in two threads {time.perf_counter() - t:.2f} s")


if __name__ == "__main__":
    main()
