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


LONG_RUNNING_LEVEL = "D2SPO_XLA_LONG_RUNNING_LEVEL"
"""Environment variable: XLA's backend optimisation level for the programs that run long once
compiled, whatever level ``XLA_FLAGS`` sets for the rest."""


def long_running_options() -> dict | None:
    """Compiler options for a program that runs far longer than it compiles: D²SPO's ``init``,
    whose cautious start pre-trains the barrier and π_Ω for thousands of steps.

    None (XLA's flags as they are) unless ``$D2SPO_XLA_LONG_RUNNING_LEVEL`` names a level. The test
    suite compiles at level 0 to compile fast (tests/conftest.py), and sets this to 2 so that its
    inits still run fast: phi1's init compiled in 8.6 s and ran in 16.3 s at level 0, and in 12.8 s
    and 3.0 s at level 3, XLA's default (2-core AMD); level 2 balanced the two best there. The
    commands leave it unset: they compile everything at XLA's default level already.
    """
    return _level_options(LONG_RUNNING_LEVEL)


CHUNK_LEVEL = "D2SPO_XLA_CHUNK_LEVEL"
"""Environment variable: XLA's backend optimisation level for the learners' chunks, whatever level
``XLA_FLAGS`` sets for the rest."""


def chunk_options() -> dict | None:
    """Compiler options for a learner's chunk: None (XLA's flags as they are) unless
    ``$D2SPO_XLA_CHUNK_LEVEL`` names a level. The commands leave it unset. The test suite's learning
    checks of the off-policy baselines (tests/_learning.py) set 2 while they train for 300
    episodes: their chunks run 10-20 times each, and at the suite's level 0 running, not compiling,
    was most of their time (RCRL's check 19.8 s at level 0, 11.4 s at level 2; cold cache, 2-core
    AMD EPYC family 25, 2026-12-01)."""
    return _level_options(CHUNK_LEVEL)


def _level_options(variable: str) -> dict | None:
    level = os.environ.get(variable, "").strip()
    if not level:
        return None
    if level not in ("0", "1", "2", "3"):
        from d2spo.errors import ConfigError

        raise ConfigError(f"${variable}", f"expected an XLA optimisation level 0-3, got {level!r}")
    return {"xla_backend_optimization_level": int(level)}
