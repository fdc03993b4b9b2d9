"""The helpers of the run-directory fault tests (tests/test_run_kills.py, tests/test_run_faults.py):
the tiny config they train, the reference run with its images at every moment a kill could land, and
the checks of an exact resume and of a one-line refusal.

The kill moments are drawn at random: set D2SPO_FAULT_SEED to draw others (failures print it).
"""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import warnings
from pathlib import Path

import pytest

from d2spo.algos.td3 import TD3Config
from d2spo.cli import main
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.errors import RunDirWarning
from d2spo.ltl.reward import RewardConfig
from d2spo.runio import EpisodeWriter
from d2spo.train import train

SEED = int(os.environ.get("D2SPO_FAULT_SEED", "0"))

CFG = TrainConfig(  # the shapes of test_train.tiny(): its compiled chunk is reused
    algo="tlgrl", task="relaxed", episodes=60, num_envs=8, chunk_steps=25, checkpoint_every=10, window=50,
    eval_episodes=0, env=EnvConfig(layout="relaxed", max_steps=40, reward=RewardConfig(shaping_metric="geodesic")),
    td3=TD3Config(hidden=(16, 16), batch_size=32, learning_starts=64, buffer_size=4096),
).check()
FLAGS = ["--algo", "tlgrl", "--task", "relaxed", "--episodes", "60", "--num-envs", "8", "--chunk-steps", "25",
         "--checkpoint-every", "10", "--window", "50", "--eval-episodes", "0", "--layout", "relaxed",
         "--max-steps", "40", "--shaping-metric", "geodesic", "--td3.hidden", "16", "16", "--td3.batch-size", "32", "--td3.learning-starts", "64",
         "--td3.buffer-size", "4096", "--no-progress"]


# ------------------------------------------------------------------------------------ helpers
class Images:
    """Copies of a run directory as a kill -9 would leave it at each moment training changes it:
    before each rename into it (its temporary file cut in half), before each deletion, and in the
    middle of each append to episodes.csv."""

    def __init__(self, run: Path, root: Path):
        self.run, self.root, self.taken = run, root, []

    def take(self, label: str, cut: tuple[str, int] | None = None, half_tmp: str | None = None) -> None:
        dst = self.root / f"{len(self.taken):03d}"
        shutil.copytree(self.run, dst)
        if cut is not None:
            os.truncate(dst / cut[0], cut[1])
        if half_tmp is not None:
            os.truncate(dst / half_tmp, (dst / half_tmp).stat().st_size // 2)
        self.taken.append((label, dst))

    def pick(self, rng: random.Random, pred) -> tuple[str, Path]:
        found = [(i, lab, d) for i, (lab, d) in enumerate(self.taken) if pred(i, lab)]
        assert found, "no such moment"
        i, lab, d = rng.choice(found)
        return f"moment {i} ({lab})", d


def reference_run(tmp_path_factory):
    """An uninterrupted run, and its images at every moment a kill could land (the session fixture
    ``run_reference`` of tests/conftest.py: tests/test_run_kills.py and tests/test_run_faults.py share it)."""
    root = tmp_path_factory.mktemp("faults")
    run = root / "reference"
    images = Images(run, root / "images")
    real_replace, real_unlink, real_append = os.replace, os.unlink, EpisodeWriter.append

    def replace(src, dst, *a, **kw):
        if Path(dst).parent == run:
            images.take(f"write {Path(dst).name}", half_tmp=Path(src).name)
        return real_replace(src, dst, *a, **kw)

    def unlink(path, *a, **kw):
        if Path(path).parent == run and not Path(path).name.startswith("."):
            images.take(f"delete {Path(path).name}")
        return real_unlink(path, *a, **kw)

    def append(self, rows):
        size = self.path.stat().st_size
        real_append(self, rows)
        if rows:
            images.take("append", cut=("episodes.csv", (size + self.path.stat().st_size) // 2))

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "replace", replace)
        mp.setattr(os, "unlink", unlink)
        mp.setattr(EpisodeWriter, "append", append)
        summary = train(CFG, run)
    return run, summary, images


def state_file(run: Path, manifest: str = "checkpoint.json") -> Path:
    """The state file a manifest names (the earlier format: always checkpoint.msgpack)."""
    return run / json.loads((run / manifest).read_bytes()).get("state", "checkpoint.msgpack")


def counters(run: Path) -> dict:
    m = json.loads((run / "checkpoint.json").read_bytes())
    return m.get("meta", m)


def _state(record: dict) -> dict:
    """A run's counters or summary without its clocks: every key naming seconds (wall, setup and
    compile times, what the compile cache saved, steps per second) is a time, not state."""
    return {k: v for k, v in record.items() if "second" not in k}


def assert_same_run(run: Path, ref: Path, why: str) -> None:
    """Byte-identical episodes and final state; equal counters and rates; nothing left over."""
    assert (run / "episodes.csv").read_bytes() == (ref / "episodes.csv").read_bytes(), why
    assert state_file(run).read_bytes() == state_file(ref).read_bytes(), why
    meta, ref_meta = counters(run), counters(ref)
    assert _state(meta) == _state(ref_meta), why
    summary, ref_summary = (json.loads((d / "summary.json").read_bytes()) for d in (run, ref))
    assert _state(summary) == _state(ref_summary), why
    left = sorted(p.name for p in run.iterdir() if p.name.endswith(".tmp") or p.name == ".lock")
    assert left == [], (why, left)
    states = sorted(p.name for p in run.glob("checkpoint*.msgpack"))
    assert len(states) == 2, (why, states)  # the newest and the previous one


def resume_quietly(run: Path) -> None:
    """Resume, asserting that nothing was repaired (no RunDirWarning)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        train(CFG, run, resume=True)
    assert not [w for w in caught if issubclass(w.category, RunDirWarning)], [str(w.message) for w in caught]


def cli(capsys, *args) -> tuple[int, list[str]]:
    """The CLI's exit status and the lines it wrote on stderr (never a traceback)."""
    capsys.readouterr()
    rc = main([str(a) for a in args])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    # the 40-step episodes draw the episode-time warning (preflight.check_time) at every training
    # start: it is not what these tests are about
    time_warning = re.compile(r"^d2spo: warning: 'relaxed' (cannot be completed|: the shortest route) on layout")
    return rc, [ln for ln in err.splitlines() if ln.strip() and not time_warning.match(ln)]


def resume(run: Path) -> list:
    return ["train", "--resume", run, "--no-progress"]


def one_error(capsys, status: int, *args) -> str:
    """The one line of a refused command, which must exit with ``status``."""
    rc, lines = cli(capsys, *args)
    assert rc == status, (rc, lines)
    assert len(lines) == 1 and lines[0].startswith("d2spo: error: "), lines
    return lines[0]


def flip_byte(path: Path, rng: random.Random, text: bool = False) -> None:
    """XOR one byte with a random non-zero mask (in a JSON file, a byte that is not whitespace)."""
    data = bytearray(path.read_bytes())
    where = [i for i, b in enumerate(data) if not (text and chr(b).isspace())]
    i = rng.choice(where)
    data[i] ^= rng.randrange(1, 256)
    path.write_bytes(bytes(data))


def mid_run(run_reference, rng: random.Random, tmp_path: Path) -> Path:
    """A copy of the run killed at a random moment between two checkpoints after the third."""
    _, _, images = run_reference
    third = [i for i, (lab, _) in enumerate(images.taken) if lab == "write checkpoint.json"][2]
    _, d = images.pick(rng, lambda i, lab: i > third and lab == "append")
    shutil.copytree(d, tmp_path / "run")
    return tmp_path / "run"
