"""Shared test set-up: a persistent XLA compilation cache so repeated jits are cheap."""

from __future__ import annotations

import os
import sys
from pathlib import Path

# Bytecode caches on, for the suite and the commands it starts as child processes, where the
# environment turned them off (PYTHONDONTWRITEBYTECODE: these machines set it): else every child
# compiles d2spo from source again (`import d2spo.cli`: 1.75 s against 1.48 s with the cache).
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False

# The suite compiles far more than it runs: most tests train a few chunks of a program XLA takes
# 10-40 s to compile. XLA's backend optimisation level 0 compiles those programs about 3x faster
# (bench/compile_times.py: the --fast D²SPO chunk 72.7 s -> 24.1 s on a loaded 2-core machine) and
# computes the same functions; only the machine code is less tuned. XLA's CPU fusion emitters off
# halves backend compiling again (the relaxed D²SPO chunk at level 0: 5.8 s -> 3.2 s; the suite's
# backend compiling 367 s -> 192 s, its tests 851 s -> 621 s, 2-core AMD family 26, 2026-11-27);
# the commands keep them, as they run 37% slower without (bench/profile_chunk.py, default level:
# 1.31 -> 1.79 ms per vectorised step). Set before the backend starts
# (the first computation); the commands the tests start as child processes inherit it. The
# product's commands keep XLA's default level. D2SPO_TEST_XLA_OPT=default runs the suite without it.
if os.environ.get("D2SPO_TEST_XLA_OPT", "0") != "default" and "xla_backend_optimization_level" not in os.environ.get(
        "XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false".strip()
    # ... except D²SPO's init, which pre-trains for thousands of steps: at level 0 phi1's ran 5x
    # slower (16.3 s against 3.0 s) for 4 s less compiling (d2spo/_xla.py, long_running_options).
    # Level 2 balances the two best: the cautious-start test took 13.8-14.1 s against 16.3-16.8 s
    # at level 3 (cold cache, 2-core AMD family 26, 2026-11-27).
    os.environ.setdefault("D2SPO_XLA_LONG_RUNNING_LEVEL", "2")

import jax  # noqa: E402
import pytest  # noqa: E402

import d2spo  # noqa: E402, F401  (sets XLA flags before the first computation starts the backend: d2spo/_xla.py)
from d2spo import compile_cache, memo  # noqa: E402

_CACHE = Path(os.environ.get("D2SPO_TEST_JAX_CACHE", Path(__file__).resolve().parent.parent / ".pytest_cache" / "jax"))
# its folder for this process's CPUs, as the commands' (d2spo/compile_cache.py, entries_dir)
jax.config.update("jax_compilation_cache_dir", str(compile_cache.entries_dir(_CACHE)))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
# the commands' size cap, so that each entry gets the access-time file the child commands' JAX
# reads, and their mending of an entry left without one (a child killed or interrupted mid-write)
jax.config.update("jax_compilation_cache_max_size", compile_cache.MAX_BYTES)
compile_cache.keep_access_times()
compile_cache.portable_keys()  # the keys the commands use, so that child commands share the entries
# `d2spo` commands the tests start in child processes (tests/test_reproduce.py's Ray backend, the
# command-line checks) use the same cache (d2spo/compile_cache.py), not the user's ~/.cache/d2spo.
os.environ["D2SPO_COMPILE_CACHE"] = str(_CACHE)

# Property tests draw the same examples on every run (CI included), so a green tree stays green;
# `HYPOTHESIS_PROFILE=explore pytest ...` draws fresh ones to hunt for new counterexamples.
from hypothesis import settings  # noqa: E402

settings.register_profile("ci", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


# `make test` runs two pytest workers (pytest-xdist, `--dist loadgroup`): XLA compiles a program on
# one core, and compiling is most of the suite. A test file is one group, so its module fixtures
# are built once; files whose tests share compiled programs through the persistent cache (the same
# config) are one group, so the second finds the first's program instead of compiling it again.
_SHARED_PROGRAMS = {
    "test_plots.py": "fig5-run",  # the session fixture short_d2spo_run, below
    "test_d2spo.py": "fig5-run",
    "test_run_faults.py": "tiny-run",  # the shapes of test_train.tiny()
    "test_run_kills.py": "tiny-run",  # tests/_run_faults.py: its reference run, a session fixture
    "test_train.py": "tiny-run",
    "test_wandb.py": "tiny-run",  # test_train.tiny() with --wandb
    "test_memo.py": "tiny-run",
    "test_reproduce.py": "small-reproduce",  # _reproduce.small_config
    "test_fault_battery.py": "small-reproduce",
    "test_certify_run.py": "tiny-d2spo",  # _tiny.tiny_cfg
    "test_export.py": "tiny-d2spo",
    "test_export_cli.py": "tiny-d2spo",  # the session fixture tiny_export, below
    "test_deploy_runtime.py": "tiny-d2spo",  # the same export, split from test_export_cli.py
    "test_zero_shot.py": "zero-shot",  # tests/_generalist_run.py: one generalist program, its eval's
    "test_eval_options.py": "zero-shot",
}


@pytest.hookimpl(tryfirst=True)  # before xdist's hook reads the group into each test's id
def pytest_collection_modifyitems(config, items):
    for item in items:
        name = Path(str(item.fspath)).name
        item.add_marker(pytest.mark.xdist_group(_SHARED_PROGRAMS.get(name, name)))


@pytest.fixture(autouse=True)
def _memo_fresh_around_patches(request):
    """A test that patches (``monkeypatch``) neither reuses an earlier test's builds and programs
    (``d2spo.memo``: they would not see its patches) nor leaves its own, built under its patches,
    to a later test."""
    patches = "monkeypatch" in request.fixturenames
    if patches:
        memo.clear()
    yield
    if patches:
        memo.clear()


@pytest.fixture(scope="session")
def run_reference(tmp_path_factory):
    """The fault tests' uninterrupted tiny run and its images at every moment a kill could land
    (tests/_run_faults.py): built once per worker for tests/test_run_kills.py and
    tests/test_run_faults.py, which are one xdist group."""
    from _run_faults import reference_run

    return reference_run(tmp_path_factory)


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory):
    """The tiny ϕ1 run on ``paper`` and its export that tests/test_export.py, test_export_cli.py and
    test_deploy_runtime.py share (tests/_export_runs.py): one per worker, as the files are one xdist group."""
    from _export_runs import tiny_run
    from _tiny import tiny_cfg

    return tiny_run(tmp_path_factory.mktemp("export"), tiny_cfg())


SHORT_RUN_CALLS = {"distances": ("d2spo.ltl.automaton", "Automaton", "distances"),
                   "route_length": ("d2spo.envs.routes", None, "route_length"),
                   "reachable_states": ("d2spo.envs.routes", None, "reachable_states"),
                   "state_fields": ("d2spo.envs.compiled_task", None, "state_fields")}
"""What the short D²SPO run counts while it trains: how often it computes its task's distances,
route and fields (tests/test_d2spo.py checks each is done once per run)."""


@pytest.fixture(scope="session")
def short_d2spo_run(tmp_path_factory):
    """250 episodes of D²SPO on the `relaxed` layout, task F A1, with Fig. 5's policy snapshots:
    tests/test_d2spo.py checks what it learnt, tests/test_plots.py draws Figs. 4-5 from it (the two
    files are one xdist group, so it trains once). Returns the run directory, its summary and the
    calls of ``SHORT_RUN_CALLS`` counted while it trained."""
    import importlib

    from _counting import count_calls
    from _reproduce import short_run_config

    from d2spo.train import train

    # max_steps unset: the step limit follows the route; D²SPO: its barrier's margin is checked too
    cfg = short_run_config()
    out = tmp_path_factory.mktemp("short-d2spo") / "run"
    with pytest.MonkeyPatch.context() as mp:
        targets = {}
        for name, (module, owner, attr) in SHORT_RUN_CALLS.items():
            mod = importlib.import_module(module)
            targets[name] = (getattr(mod, owner) if owner else mod, attr)
        calls = count_calls(mp, targets)  # forgets this process's builds (d2spo.memo), so they are counted
        summary = train(cfg, out)
    # its builds and programs stay (d2spo.memo): the wrappers only counted, and the tests that read
    # the run evaluate it with the same rollout program
    return out, summary, dict(calls)


@pytest.fixture
def no_build(monkeypatch):
    """Training and evaluation stop with ``_faults.Built`` where they would build a learner (the fault
    tests around files and run directories: nothing there compiles)."""
    from _faults import Built

    def built(*a, **kw):
        raise Built

    monkeypatch.setattr("d2spo.train.build", built)
    monkeypatch.setattr("d2spo.evaluate.load_policy", built)
