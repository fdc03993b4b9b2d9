"""The persistent XLA compilation cache every ``d2spo`` command uses.

A program XLA compiled once (a learner's chunk, an evaluation's rollout, a certification's grid)
is kept on disk and loaded instead of compiled when a later command builds the same program: a
second ``d2spo demo``, a second ``d2spo eval`` of a run, or a new seed of a config already trained.
The entry's key is JAX's: a hash of the program itself, the jax/jaxlib versions, the XLA flags and
the device, so a changed program or another version is a new entry, never a wrong hit.

Where it lives (``cache_dir``):

* ``$D2SPO_COMPILE_CACHE`` if set: a directory, or ``off`` (also ``0``, ``false``, ``no``) to disable;
* else ``$XDG_CACHE_HOME/d2spo/jax``, else ``~/.cache/d2spo/jax``.

A cache JAX was already told to use (``JAX_COMPILATION_CACHE_DIR``, or ``jax.config`` before the
command) is kept. The cache is capped at ``MAX_BYTES`` (least recently used entries go first). A
damaged entry is a miss: JAX warns and compiles afresh (``tests/test_compile_cache.py``; an entry that
cannot be read for another reason, a missing package, is named so, not called damaged), and the
damaged file is deleted so that the fresh compilation's entry takes its place (``_heal_reads``:
JAX never writes over an existing entry, so it would otherwise be a miss and a warning in every
later command); an entry without its access-time file gets one (``keep_access_times``: else no
later program could be written); a cache directory that cannot be made turns the cache off with one warning. The
keys hold no path of the cache's on a CPU-only install (``portable_keys``): a cache moved or copied
elsewhere still serves every program.

Entries live in a folder of the cache per number of CPUs the process may run on (``cpus-2``, ...:
``entries_dir``). XLA:CPU splits a program's large operations into as many parallel parts as it
sees CPUs (``outer_dimension_partitions``), which can change results in the last bits, and JAX's key
does not hold that number: without the folders a program compiled under ``taskset -c 0`` served
later 2-CPU runs of the same seed, whose course then depended on what the cache had seen
(tests/test_compile_cache.py; bench/RESULTS.md, "2026-12-01, night").
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import jax

from d2spo.errors import D2SPOWarning

ENV_VAR = "D2SPO_COMPILE_CACHE"
"""The environment variable that moves (a directory) or disables (``off``) the cache."""
OFF = frozenset({"off", "0", "false", "no", "none"})
MAX_BYTES = 4 * 1024**3
"""Size cap of each ``cpus-N`` folder of the cache: the least recently used entries are deleted beyond it."""
MIN_COMPILE_SECONDS = 0.5
"""Programs that compile faster than this are not worth a disk entry."""


_SAVED_EVENT = "/jax/compilation_cache/compile_time_saved_sec"
_saved = [0.0]


def _count_saved(event: str, duration: float, **_) -> None:
    if event == _SAVED_EVENT:
        _saved[0] += duration


jax.monitoring.register_event_duration_secs_listener(_count_saved)


def seconds_saved() -> float:
    """Compile time the persistent cache has saved this process so far, by JAX's own reckoning
    (each entry read: the compile time it recorded, less the time reading it took). ``train`` reports
    the part of it its compilation phase saved (``compile_seconds_saved`` in summary.json)."""
    return _saved[0]


def cache_dir(environ: dict | None = None) -> Path | None:
    """The directory the commands' cache uses, or None when ``$D2SPO_COMPILE_CACHE`` turns it off."""
    env = os.environ if environ is None else environ
    value = env.get(ENV_VAR)
    if value is not None and value.strip():
        return None if value.strip().lower() in OFF else Path(value).expanduser()
    base = env.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "d2spo" / "jax"


def usable_cpus() -> int:
    """The number of CPUs this process may run on (its affinity mask): what XLA:CPU compiles for."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def entries_dir(root: Path) -> Path:
    """The folder of ``root`` that holds the entries compiled for this process's CPUs."""
    return root / f"cpus-{usable_cpus()}"


def enable(environ: dict | None = None) -> Path | None:
    """Point JAX's persistent compilation cache at ``entries_dir(cache_dir())``; returns that folder
    (None: off). A directory JAX was already given is kept. Call before the first compilation."""
    current = jax.config.jax_compilation_cache_dir
    if current:
        return Path(current)
    root = cache_dir(environ)
    if root is None:
        return None
    path = entries_dir(root)
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK | os.X_OK):
            raise PermissionError(f"{path}: not writable")
    except OSError as e:
        warnings.warn(f"the compilation cache is off: {e} (set {ENV_VAR} to another directory, or to 'off')",
                      D2SPOWarning, stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    keep_access_times()
    portable_keys()
    _heal_reads()
    return path


def keep_access_times() -> None:
    """Give an entry without its access-time file one before JAX evicts. With a size cap
    (``MAX_BYTES``) JAX writes an entry, then its ``-atime`` file, and before every later write
    reads the access time of every entry of the folder to find the least recently used; one entry
    without it (a process killed or interrupted between the two writes, or an entry written by a
    JAX without the cap) made every later write in that folder fail, each with JAX's warning, so no
    new program was kept again. Wraps JAX's eviction scan (``jax._src.lru_cache.LRUCache.
    _evict_if_needed``, jax 0.10's; it runs under the cache's file lock) so that the missing files
    are written first, with the entry's last change as its access time; where a JAX lacks it,
    nothing is wrapped. The test suite calls it too."""
    from jax._src import lru_cache

    evict = getattr(getattr(lru_cache, "LRUCache", None), "_evict_if_needed", None)
    if evict is None or getattr(evict, "_d2spo_mends", False):
        return

    def mending_evict(self, *args, **kwargs):
        where = str(self.path)
        if getattr(self, "eviction_enabled", False) and "://" not in where:  # a local folder
            _mend_access_times(Path(where))
        return evict(self, *args, **kwargs)

    mending_evict._d2spo_mends = True
    lru_cache.LRUCache._evict_if_needed = mending_evict


def _mend_access_times(path: Path) -> None:
    """Write the missing ``-atime`` file of each entry of ``path`` (jax._src.lru_cache's file names)."""
    for entry in path.glob("*-cache"):
        atime = entry.with_name(entry.name.removesuffix("-cache") + "-atime")
        try:
            if not atime.exists():
                atime.write_bytes(entry.stat().st_mtime_ns.to_bytes(8, "little"))
        except OSError:  # the entry deleted meanwhile by another process's eviction: it needs none
            pass


def portable_keys() -> None:
    """Entries whose keys hold no path, where no GPU plugin is installed. JAX also turns on XLA's
    GPU autotuning cache in a folder of the cache directory, and that folder's path is part of
    every entry's key: a cache moved or copied elsewhere (another ``$D2SPO_COMPILE_CACHE``, a CI
    cache restored under another home) would miss on every program. Without a GPU there is nothing
    to autotune, so that cache goes off (``jax_persistent_cache_enable_xla_caches``); with one, JAX's
    default stands. The test suite calls it too, so that its programs and its child commands' share
    their entries."""
    if not _accelerator_plugins():
        jax.config.update("jax_persistent_cache_enable_xla_caches", "")


def _accelerator_plugins() -> list[str]:
    """The JAX plugins installed (``jax-cuda13-plugin`` and the like register under the entry-point
    group ``jax_plugins``); empty on a CPU-only install."""
    from importlib.metadata import entry_points

    return [e.name for e in entry_points(group="jax_plugins")]


_SETUP_TROUBLE = re.compile(r"[Pp]lease install|No module named")
"""An entry that cannot be read for want of a package is not damaged: it is left alone."""


def _heal_reads() -> None:
    """Delete an entry JAX fails to read (cut short, not a compressed executable, a flipped byte), so
    the compilation that follows writes a good one under its key. Wraps JAX's read of an entry
    (``jax._src.compilation_cache.get_executable_and_time``, jax 0.10's; where a JAX lacks it, nothing
    is wrapped and a damaged entry stays a miss); the exception still reaches JAX, which warns."""
    from jax._src import compilation_cache as jax_cache

    read = getattr(jax_cache, "get_executable_and_time", None)
    if read is None or getattr(read, "_d2spo_heals", False):
        return

    def healing_read(cache_key, *args, **kwargs):
        try:
            return read(cache_key, *args, **kwargs)
        except Exception as e:
            if not _SETUP_TROUBLE.search(str(e)) and jax.config.jax_compilation_cache_dir:
                for suffix in ("-cache", "-atime"):  # jax._src.lru_cache's file names
                    (Path(jax.config.jax_compilation_cache_dir) / f"{cache_key}{suffix}").unlink(missing_ok=True)
            raise

    healing_read._d2spo_heals = True
    jax_cache.get_executable_and_time = healing_read
