"""The test suite's own set-up (tests/conftest.py), checked where it runs."""

from __future__ import annotations

import pytest


def test_each_file_is_one_xdist_group(request):
    """Under `make test` (pytest-xdist, ``--dist loadgroup``) every test carries its file's group in
    its id, so a file's module fixtures are built once, on one worker. The conftest's marker must be
    in place before xdist reads it: added after, the groups were silently ignored and the files
    split across both workers (the suite 532.65 s against 444.74 s of pytest once they applied,
    slow Intel, 2026-11-29)."""
    if not getattr(request.config.option, "loadgroup", False):
        pytest.skip("not under pytest-xdist's --dist loadgroup")
    assert request.node.nodeid.endswith("@test_suite_setup.py"), request.node.nodeid
