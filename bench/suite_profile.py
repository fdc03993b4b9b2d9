"""Where the test suite's time goes: per test, its wall time and JAX's compile-pipeline durations
(tracing, lowering to MLIR, XLA's backend compile, time the persistent cache saved).

As a pytest plugin, one JSON line per test into ``$D2SPO_SUITE_PROFILE/<worker pid>.jsonl``::

    D2SPO_SUITE_PROFILE=/tmp/sp PYTHONPATH=bench python -m pytest -p suite_profile -n 2 --dist loadgroup tests

then the summary by test file, the slowest tests and the suite's totals::

    python bench/suite_profile.py /tmp/sp [--top 30]

The durations are those of ``jax.monitoring``'s events in the test's process (a child process a
test starts is not counted); tracing nested in another trace is counted in both.
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


def _listen(event: str, duration: float, **_) -> None:
    if _current[0] is not None:
        _durations[event] += duration


def pytest_configure(config) -> None:
    import jax

    jax.monitoring.register_event_duration_secs_listener(_listen)


def _record(nodeid: str, wall: float) -> None:
    out = Path(os.environ.get("D2SPO_SUITE_PROFILE", ".suite_profile"))
    out.mkdir(parents=True, exist_ok=True)
    row = {"id": nodeid, "wall": round(wall, 3), **{k: round(_durations.get(e, 0.0), 3) for k, e in EVENTS.items()}}
    with open(out / f"{os.getpid()}.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _durations.clear()
    _current[0] = item.nodeid
    t = time.perf_counter()
    yield
    _current[0] = None
    _record(item.nodeid, time.perf_counter() - t)


def summarise(directory: Path, top: int) -> str:
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
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("directory", type=Path)
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args()
    print(summarise(args.directory, args.top))


if __name__ == "__main__":
    main()
