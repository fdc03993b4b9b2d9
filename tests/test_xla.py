"""The XLA CPU scheduler flag set by ``import d2spo`` (d2spo/_xla.py) and the hang it prevents."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from d2spo import _xla

# Three orthogonally initialised networks, initialised for two seeds at once: the program that
# never finished on a 2-core machine under XLA's concurrency-optimized CPU scheduler.
_VMAPPED_INIT = textwrap.dedent("""
    import d2spo
    import jax, jax.numpy as jnp
    from d2spo.algos.common.networks import GaussianPolicy, ValueNetwork, init_params
    obs = jnp.zeros((1, 28))
    P, V = GaussianPolicy(2, (64, 64)), ValueNetwork((64, 64))
    def init(key):
        a, b, c = jax.random.split(key, 3)
        return init_params(P, a, obs), init_params(V, b, obs), init_params(V, c, obs)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1)])
    jax.block_until_ready(jax.jit(jax.vmap(init))(keys))
    print("finished")
""")


def test_import_sets_the_scheduler_flag_and_keeps_a_users_choice(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    _xla.apply()
    assert os.environ["XLA_FLAGS"] == "--xla_dump_to=/tmp/x --xla_cpu_enable_concurrency_optimized_scheduler=false"
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_concurrency_optimized_scheduler=true")
    _xla.apply()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_enable_concurrency_optimized_scheduler=true"
    monkeypatch.delenv("XLA_FLAGS")
    _xla.apply()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_enable_concurrency_optimized_scheduler=false"


def test_vmapped_orthogonal_init_finishes_in_a_fresh_process():
    """Runs in a child with no compilation cache, so the program is compiled under the flag; a
    hang fails the test at the timeout instead of blocking the suite."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_COMPILATION_CACHE_DIR", "D2SPO_COMPILE_CACHE")}
    try:
        r = subprocess.run([sys.executable, "-c", _VMAPPED_INIT], env=env, capture_output=True, text=True, timeout=180)
    except subprocess.TimeoutExpired:
        pytest.fail("the vmapped initialisation did not finish in 180 s (XLA scheduler deadlock?)")
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "finished"


def test_long_running_programs_get_the_level_the_environment_names(monkeypatch):
    """``$D2SPO_XLA_LONG_RUNNING_LEVEL`` (the suite sets 3) becomes D²SPO's init's compiler option;
    unset, the commands' programs keep XLA's flags; a bad value is a ConfigError (one line)."""
    from d2spo.errors import ConfigError

    monkeypatch.setenv(_xla.LONG_RUNNING_LEVEL, "3")
    assert _xla.long_running_options() == {"xla_backend_optimization_level": 3}
    monkeypatch.delenv(_xla.LONG_RUNNING_LEVEL)
    assert _xla.long_running_options() is None
    monkeypatch.setenv(_xla.LONG_RUNNING_LEVEL, "fast")
    with pytest.raises(ConfigError, match="expected an XLA optimisation level 0-3, got 'fast'"):
        _xla.long_running_options()
