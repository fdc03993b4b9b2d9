"""Where the test suite's time goes: per test, its wall time and JAX's compile-pipeline durations
(tracing, lowering to MLIR, XLA's backend compile, time the persistent cache saved).

As a pytest plugin, one JSON line per test into ``$D2SPO_SUITE_PROFILE/<worker pid>.jsonl``::

    D2SPO_SUITE_PROFILE=/tmp/sp PYTHONPATH=bench python -m pytest -p suite_profile -n 2 --dist loadgroup tests

then the summary by test file, the slowest tests and the suite's totals::

    python bench/suite_profile.py /tmp/sp [--top 30]

The durations are those of ``jax.monitoring``'s events in the test's process (a child process a
test starts is not counted); tracing nested in another trace is counted in both. Each backend
compile is also listed by the compiled module's name (``jit_chunk``, ...), so that programs
compiled many times under one name stand out: ``--programs N`` prints the N costliest names.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import time
from pathlib import Path

import pytest

EVENTS = {
    "trace": "/jax/core/compile/jaxpr_trace_duration",
    "lower": "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "backend": "/jax/core/compile/backend_compile_duration",
    "cache_saved": "/jax/compilation_cache/compile_time_saved_sec",
}

_durations: dict[str, float] = collections.defaultdict(float)
_current: list[str | None] = [None]
_compiles: list[tuple[str, float]] = []


def _listen(event: str, duration: float, **_) -> None:
    if _current[0] is not None:
        _durations[event] += duration


def pytest_configure(config) -> None:
    import jax

    jax.monitoring.register_event_duration_secs_listener(_listen)
    from jax._src import compiler  # private: the one place that sees the module's name and its backend time

    compile_and_load = compiler.backend_compile_and_load

    def timed(backend, module, *args, **kwargs):
        t = time.perf_counter()
        try:
            return compile_and_load(backend, module, *args, **kwargs)
        finally:
            name = str(module.operation.attributes["sym_name"]).strip('"')
            _compiles.append((name, time.perf_counter() - t))

    compiler.backend_compile_and_load = timed


def _record(nodeid: str, wall: float) -> None:
    out = Path(os.environ.get("D2SPO_SUITE_PROFILE", ".suite_profile"))
    out.mkdir(parents=True, exist_ok=True)
    row = {"id": nodeid, "wall": round(wall, 3), **{k: round(_durations.get(e, 0.0), 3) for k, e in EVENTS.items()},
           "compiles": [[n, round(d, 3)] for n, d in _compiles]}
    with open(out / f"{os.getpid()}.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _durations.clear()
    _compiles.clear()
    _current[0] = item.nodeid
    t = time.perf_counter()
    yield
    _current[0] = None
    _record(item.nodeid, time.perf_counter() - t)


def summarise(directory: Path, top: int, programs: int = 0) -> str:
    rows = [json.loads(line) for f in sorted(directory.glob("*.jsonl")) for line in f.read_text().splitlines()]
    if not rows:
        raise SystemExit(f"suite_profile: no rows in {directory}")
    keys = ["wall", *EVENTS]
    lines = [f"{len(rows)} tests in {len(list(directory.glob('*.jsonl')))} workers; totals (s): "
             + ", ".join(f"{k} {sum(r[k] for r in rows):.1f}" for k in keys), "",
             "| file | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    by_file: dict[str, dict[str, float]] = collections.defaultdict(lambda: collections.defaultdict(float))
    for r in rows:
        for k in keys:
            by_file[r["id"].split("::")[0]][k] += r[k]
    for name, v in sorted(by_file.items(), key=lambda kv: -kv[1]["wall"])[:top]:
        lines.append(f"| {name} | " + " | ".join(f"{v[k]:.1f}" for k in keys) + " |")
    lines += ["", "| test | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    for r in sorted(rows, key=lambda r: -r["wall"])[:top]:
        lines.append(f"| {r['id']} | " + " | ".join(f"{r[k]:.1f}" for k in keys) + " |")
    if programs:
        by_name: dict[str, list[float]] = collections.defaultdict(list)
        files: dict[str, set[str]] = collections.defaultdict(set)
        for r in rows:
            for name, d in r.get("compiles", []):
                by_name[name].append(d)
                files[name].add(r["id"].split("::")[0].removeprefix("tests/"))
        lines += ["", "| compiled module | compiles | backend s | test files |", "|---|---:|---:|---|"]
        for name, ds in sorted(by_name.items(), key=lambda kv: -sum(kv[1]))[:programs]:
            lines.append(f"| {name} | {len(ds)} | {sum(ds):.1f} | {', '.join(sorted(files[name]))} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("directory", type=Path)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--programs", type=int, default=0, help="also the N compiled modules with the most backend time")
    args = ap.parse_args()
    print(summarise(args.directory, args.top, args.programs))


if __name__ == "__main__":
    main()
