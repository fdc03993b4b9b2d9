"""A pytest plugin: every XLA compilation (``jax_log_compiles``) attributed to the test running it.

    PYTHONPATH=bench D2SPO_TEST_JAX_CACHE=/tmp/cold pytest -p compile_count tests/FILE.py

prints, per test, how many programs XLA compiled and the seconds it took, slowest first; with a cold
cache directory every compilation is counted. bench/RESULTS.md's counts per test come from it.
"""

from __future__ import annotations

import collections
import logging
import re

import jax

_FINISHED = re.compile(r"Finished XLA compilation of (.*?) in ([0-9.e-]+) sec")
_current: dict[str, str | None] = {"test": None}
_count: collections.Counter = collections.Counter()
_seconds: collections.defaultdict = collections.defaultdict(float)


class _Handler(logging.Handler):
    def emit(self, record: logging.LogRecord) -> None:
        match = _FINISHED.search(record.getMessage())
        if match and _current["test"] is not None:
            _count[_current["test"]] += 1
            _seconds[_current["test"]] += float(match.group(2))


def pytest_configure(config) -> None:
    jax.config.update("jax_log_compiles", True)
    logging.getLogger("jax").addHandler(_Handler())


def pytest_runtest_setup(item) -> None:
    _current["test"] = item.nodeid


def pytest_terminal_summary(terminalreporter) -> None:
    terminalreporter.section("XLA compilations per test")
    for test in sorted(_count, key=lambda t: -_seconds[t]):
        terminalreporter.write_line(f"{_count[test]:5d} {_seconds[test]:7.1f} s  {test}")
    terminalreporter.write_line(f"{sum(_count.values()):5d} {sum(_seconds.values()):7.1f} s  in all")
