"""XLA settings d2spo needs, applied before JAX starts its CPU backend.

XLA's CPU *concurrency-optimized scheduler* deadlocks on some vmapped programs on a 2-core
machine: the program never finishes and every thread sits idle. d2spo hit it with the seeds of
``ppo-lag`` / ``cpo`` initialised together (``jax.vmap`` over three orthogonally initialised
networks, i.e. several batched QR decompositions in one program): on jax/jaxlib 0.10.2 it hung every
time without the flag below and finished every time with it (``tests/test_xla.py``). The flag only
changes how XLA orders independent operations, not what they compute.

``XLA_FLAGS`` is read when the backend starts (the first computation), so this must run before
that; ``import d2spo`` does it. A user who sets the flag themselves keeps their own value.
"""

from __future__ import annotations

import os

SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"


def apply() -> None:
    flags = os.environ.get("XLA_FLAGS", "")
    if SCHEDULER_FLAG not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {SCHEDULER_FLAG}=false".strip()
