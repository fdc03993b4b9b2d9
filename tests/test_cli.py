"""The command line: bad input gets one line on stderr and exit status 2, never a traceback."""

from __future__ import annotations

import subprocess
import sys

import pytest

from d2spo import cli


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "d2spo.cli", *args], capture_output=True, text=True, timeout=300
    )


def test_tyro_box_condenses_to_one_line():
    box = (
        "╭─ Value error ─────────╮\n"
        "│ Error parsing --n: bad │\n"
        "│ ────────────────────── │\n"
        "│ Argument helptext:     │\n"
        "╰────────────────────────╯\n"
    )
    assert cli._tyro_error_line(box) == "Value error: Error parsing --n: bad"


@pytest.mark.parametrize(
    "args",
    [
        ["no-such-command"],
        ["env", "show", "--rollout-steps", "many"],
        ["ltl"],
    ],
)
def test_usage_errors_exit_2_with_one_line(args):
    res = run_cli(*args)
    assert res.returncode == 2, res
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("d2spo: error: ")
    assert "Traceback" not in res.stderr
