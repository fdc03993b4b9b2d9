"""Helpers of the fault tests around files and run directories (tests/test_faults_files.py,
tests/test_faults_layouts.py): the CLI's status and stderr lines, a layout file, a started run.
The ``no_build`` fixture (tests/conftest.py) makes commands stop with ``Built`` where they would
build a learner."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

from d2spo.cli import main
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig


class Built(Exception):
    """Raised by the stand-in for ``build``: the command got past every check."""


class Hung(Exception):
    """Raised by the alarm: the command blocked."""



def cli(capsys, *args) -> tuple[int, list[str]]:
    """The CLI's exit status and the lines it wrote on stderr (never a traceback)."""
    capsys.readouterr()
    rc = main([str(a) for a in args])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return rc, [ln for ln in err.splitlines() if ln.strip()]


def one_error(capsys, *args) -> str:
    """The one line of a command refused with exit status 2."""
    rc, lines = cli(capsys, *args)
    assert rc == 2, (rc, lines)
    assert len(lines) == 1 and lines[0].startswith("d2spo: error: "), lines
    return lines[0]


def layout_file(path: Path, builtin: str = "relaxed") -> Path:
    """A copy of a built-in layout at ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(resources.files("d2spo.envs").joinpath("layouts", f"{builtin}.json").read_text())
    return path


def paper_starting_in(path: Path, label: str) -> Path:
    """The `paper` layout at ``path``, its start moved to the centre of the area labelled ``label``."""
    data = json.loads(resources.files("d2spo.envs").joinpath("layouts", "paper.json").read_text())
    area = next(a for a in data["areas"] if a.get("label", a["name"]) == label)
    path.write_text(json.dumps({**data, "start": [*area["center"], 0.0]}))
    return path


def started_run(out: Path, layout: str) -> Path:
    """A run directory as `d2spo train` leaves it before its first chunk (config.json and what
    goes with it), on ``layout``."""
    from d2spo.run import prepare_dir

    out.mkdir(parents=True)
    prepare_dir(out, TrainConfig(env=EnvConfig(layout=layout)), resume=False)
    return out
