"""The commands' persistent compilation cache (d2spo/compile_cache.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from d2spo import compile_cache


def test_the_cache_directory_follows_the_environment(tmp_path):
    home_default = compile_cache.cache_dir({})
    assert home_default == Path.home() / ".cache" / "d2spo" / "jax"
    assert compile_cache.cache_dir({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "d2spo" / "jax"
    moved = tmp_path / "elsewhere"
    assert compile_cache.cache_dir({compile_cache.ENV_VAR: str(moved), "XDG_CACHE_HOME": "/x"}) == moved
    for off in ("off", "OFF", "0", "false", " no "):
        assert compile_cache.cache_dir({compile_cache.ENV_VAR: off}) is None
    assert compile_cache.cache_dir({compile_cache.ENV_VAR: ""}) == home_default  # empty: unset


def test_a_cache_jax_already_uses_is_kept():
    import jax

    before = jax.config.jax_compilation_cache_dir
    assert before  # tests/conftest.py sets the tests' own cache
    assert compile_cache.enable({compile_cache.ENV_VAR: "/nonexistent/elsewhere"}) == Path(before)
    assert jax.config.jax_compilation_cache_dir == before


# A fresh interpreter: enable the cache from the environment, compile two programs, print results.
_PROGRAM = r"""
import os, sys, warnings
import jax, jax.numpy as jnp
from d2spo import compile_cache
from d2spo.console import show_warning
warnings.showwarning = show_warning
path = compile_cache.enable()
print("dir", path)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # cache even these small programs
scale = float(os.environ.get("D2SPO_TEST_SCALE", "3.0"))  # another scale: another program, a new entry
f = jax.jit(lambda x: jnp.sin(x) * scale + jnp.cumsum(x))
g = jax.jit(lambda x: jnp.cos(x) - 2.0)
x = jnp.arange(8.0)
values = f"f {float(jnp.sum(f(x)))} g {float(jnp.sum(g(x)))}"
print("saved", compile_cache.seconds_saved())  # the compile time the cache's hits saved
print(values)
"""


def _run(env_dir: str, scale: float = 3.0) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env[compile_cache.ENV_VAR] = env_dir
    env["D2SPO_TEST_SCALE"] = str(scale)
    return subprocess.run([sys.executable, "-c", _PROGRAM], env=env, capture_output=True, text=True, timeout=120)


def _entries(d: Path) -> list[Path]:
    return sorted(p for p in d.rglob("*-cache") if p.is_file())


@pytest.mark.parametrize("damage", ["truncate", "garbage", "flip"])
def test_a_damaged_entry_is_a_warning_and_a_fresh_compilation(tmp_path, damage):
    first = _run(str(tmp_path))
    assert first.returncode == 0, first.stderr
    entries = _entries(tmp_path)
    assert len(entries) >= 2  # two programs, two entries (a changed program is a new entry)
    expected = first.stdout.splitlines()[-1]
    for e in entries:
        data = e.read_bytes()
        if damage == "truncate":
            e.write_bytes(data[: len(data) // 3])
        elif damage == "garbage":
            e.write_bytes(b"not a cache entry" * 7)
        else:
            mid = len(data) // 2
            e.write_bytes(data[:mid] + bytes([data[mid] ^ 0xFF]) + data[mid + 1:])
    second = _run(str(tmp_path))
    assert second.returncode == 0, second.stderr
    assert second.stdout.splitlines()[-1] == expected
    assert "d2spo: warning: a damaged compilation cache entry was ignored" in second.stderr
    assert "Traceback" not in second.stderr
    # the damaged entries were replaced by the fresh compilations': the next command reads them
    # (JAX alone never writes over an entry, so each later command warned and compiled again)
    third = _run(str(tmp_path))
    assert third.returncode == 0 and third.stdout.splitlines()[-1] == expected
    assert "warning" not in third.stderr, third.stderr
    assert len(_entries(tmp_path)) == len(entries)


def _access_time(entry: Path) -> Path:
    """An entry's access-time file (JAX's names: KEY-cache, KEY-atime)."""
    return entry.with_name(entry.name.removesuffix("-cache") + "-atime")


def test_an_entry_without_its_access_time_does_not_stop_new_entries(tmp_path):
    """JAX's size-capped cache reads every entry's access-time file before it writes one; an entry
    without it (a command killed between the two writes) made every later write fail with a warning,
    so no new program was kept. The cache gives such an entry an access time as it opens."""
    first = _run(str(tmp_path))
    assert first.returncode == 0, first.stderr
    old = _entries(tmp_path)
    for e in old:
        _access_time(e).unlink()
    second = _run(str(tmp_path), scale=5.0)  # f is a new program; g's entry is read
    assert second.returncode == 0, second.stderr
    assert "warning" not in second.stderr.lower(), second.stderr
    assert len(_entries(tmp_path)) == len(old) + 1  # f at the new scale was written
    assert all(_access_time(e).is_file() for e in _entries(tmp_path))


def test_an_entry_left_without_its_access_time_mid_session_is_mended_before_the_next_write(tmp_path):
    """The same within one process: an entry another process left without its access time after this
    one opened the cache (tests/conftest.py keeps the access times, as the commands do)."""
    from jax._src.lru_cache import LRUCache

    cache = LRUCache(str(tmp_path), max_size=1 << 20)
    cache.put("a", b"first")
    (tmp_path / "a-atime").unlink()
    cache.put("b", b"second")  # JAX's eviction scan alone: FileNotFoundError for a-atime
    assert cache.get("a") == b"first" and cache.get("b") == b"second"
    assert (tmp_path / "a-atime").is_file()


def test_a_cache_copied_or_moved_elsewhere_still_hits(tmp_path):
    """An entry's key holds no path of the cache's (JAX's GPU autotuning cache folder was in it): a
    copy under another path serves every program, so the run there writes no entry of its own."""
    if compile_cache._accelerator_plugins():
        pytest.skip("a GPU plugin is installed: JAX keeps its autotuning cache, whose folder is in the keys")
    import shutil

    first = _run(str(tmp_path / "a"))
    assert first.returncode == 0, first.stderr
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    names = [p.name for p in _entries(tmp_path / "b")]
    assert len(names) >= 2
    second = _run(str(tmp_path / "b"))
    assert second.returncode == 0 and second.stdout.splitlines()[-1] == first.stdout.splitlines()[-1]
    assert [p.name for p in _entries(tmp_path / "b")] == names  # all hits: nothing compiled, nothing new
    # what train's compile_seconds_saved reads: no hit the first time; the second, the hits' recorded
    # compile times less the reads' (below zero for programs as small as these)
    saved = [float(r.stdout.splitlines()[-2].split()[1]) for r in (first, second)]
    assert saved[0] == 0.0 and saved[1] != 0.0


def test_entries_are_kept_per_number_of_usable_cpus(monkeypatch, tmp_path):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    assert compile_cache.entries_dir(tmp_path) == tmp_path / "cpus-1"
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 5})
    assert compile_cache.entries_dir(tmp_path) == tmp_path / "cpus-3"


# Prints the folder the cache uses, then a hash of what XLA compiled for a large elementwise op.
_PARTITIONS = r"""
import hashlib, jax, jax.numpy as jnp
from d2spo import compile_cache
print(compile_cache.enable())
text = jax.jit(lambda x: jnp.tanh(x) * 2.0).lower(jnp.ones((4096, 256))).compile().as_text()
print("outer_dimension_partitions" in text, hashlib.sha256(text.encode()).hexdigest())
"""


def test_a_process_on_fewer_cpus_compiles_another_program_and_uses_its_own_entries(tmp_path):
    """XLA:CPU splits large operations into one part per usable CPU, and JAX's key does not hold
    that number: a process confined to one CPU (``taskset -c 0``) compiles another program, so its
    entries go to another folder instead of serving processes that may use every CPU."""
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    if len(cpus) < 2:
        pytest.skip("needs a process that may run on two CPUs or more")
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env[compile_cache.ENV_VAR] = str(tmp_path)
    env["JAX_PLATFORMS"] = "cpu"  # XLA:CPU's partitioning, also where a GPU is installed

    def run(one_cpu: bool) -> list[str]:  # confined before JAX starts, as `taskset -c N` would
        pin = f"import os; os.sched_setaffinity(0, {{{cpus[0]}}})\n" if one_cpu else ""
        done = subprocess.run([sys.executable, "-c", pin + _PARTITIONS], env=env, capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 0, done.stderr
        return done.stdout.split()

    one, every = run(True), run(False)
    assert one[0] == str(tmp_path / "cpus-1") and every[0] == str(tmp_path / f"cpus-{len(cpus)}")
    assert one[1] == "False" and every[1] == "True"  # the premise: XLA partitions for the CPUs it sees
    assert one[2] != every[2]


def test_the_cache_can_be_turned_off(tmp_path):
    off = _run("off")
    assert off.returncode == 0, off.stderr
    assert "dir None" in off.stdout


def test_an_unwritable_cache_directory_is_one_warning(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache directory would go")
    res = _run(str(blocker / "cache"))
    assert res.returncode == 0, res.stderr
    assert "dir None" in res.stdout
    assert "d2spo: warning: the compilation cache is off" in res.stderr


@pytest.mark.parametrize(("detail", "said"), [
    ("'jit_f': RuntimeError: Please install the `filelock` package to set `jax_compilation_cache_max_size`",
     "the compilation cache could not be used"),
    ("'jit_f': XlaRuntimeError: INVALID_ARGUMENT: could not deserialize executable",
     "a damaged compilation cache entry was ignored"),
])
def test_a_cache_that_cannot_be_used_is_not_called_damaged(capsys, detail, said):
    from d2spo.console import _CACHE_READ_ERROR, show_warning

    show_warning(UserWarning(f"{_CACHE_READ_ERROR} {detail}"), UserWarning, "x.py", 1)
    err = capsys.readouterr().err
    assert err.startswith(f"d2spo: warning: {said} and the program compiled afresh (")
    assert detail in err and err.count("\n") == 1
