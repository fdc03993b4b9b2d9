"""Faults a run directory survives: a kill at any moment (inside checkpoint writes too), damaged
checkpoints, run state that does not match, bad files and the machine's faults. Each ends in an
exact resume, a fallback with one warning, or one line on stderr with the right exit status.

The kill moments are drawn at random: set D2SPO_FAULT_SEED to draw others (failures print it).
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import pytest

from d2spo.algos.td3 import TD3Config
from d2spo.cli import main
from d2spo.config import TrainConfig, config_to_dict
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


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run, and its images at every moment a kill could land."""
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


def assert_same_run(run: Path, ref: Path, why: str) -> None:
    """Byte-identical episodes and final state; equal counters and rates; nothing left over."""
    assert (run / "episodes.csv").read_bytes() == (ref / "episodes.csv").read_bytes(), why
    assert state_file(run).read_bytes() == state_file(ref).read_bytes(), why
    meta, ref_meta = counters(run), counters(ref)
    clocks = {k: 0 for k in ("wall_seconds", "setup_seconds", "compile_seconds")}  # times, not state
    assert {**meta, **clocks} == {**ref_meta, **clocks}, why
    summary, ref_summary = (json.loads((d / "summary.json").read_bytes()) for d in (run, ref))
    timing = ("wall_seconds", "env_steps_per_second", "wall_seconds_total", "compile_seconds")
    assert {k: v for k, v in summary.items() if k not in timing} == \
        {k: v for k, v in ref_summary.items() if k not in timing}, why
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


def mid_run(reference, rng: random.Random, tmp_path: Path) -> Path:
    """A copy of the run killed at a random moment between two checkpoints after the third."""
    _, _, images = reference
    third = [i for i, (lab, _) in enumerate(images.taken) if lab == "write checkpoint.json"][2]
    _, d = images.pick(rng, lambda i, lab: i > third and lab == "append")
    shutil.copytree(d, tmp_path / "run")
    return tmp_path / "run"


# ------------------------------------------------------------------------------- kills
def _first_commit(images: Images) -> int:
    return next(i for i, (lab, _) in enumerate(images.taken) if lab == "write checkpoint.json")


KILLS = {
    "mid-append": lambda imgs: lambda i, lab: lab == "append",
    "before-first-checkpoint": lambda imgs: lambda i, lab: i <= _first_commit(imgs),
    "writing-state": lambda imgs: lambda i, lab: i > _first_commit(imgs) and lab.startswith("write checkpoint-"),
    "committing": lambda imgs: lambda i, lab: i > _first_commit(imgs) and lab == "write checkpoint.json",
    "after-commit": lambda imgs: lambda i, lab: lab == "write checkpoint.prev.json" or lab.startswith("delete"),
    "before-summary": lambda imgs: lambda i, lab: lab == "write summary.json",
}


@pytest.mark.parametrize("when", list(KILLS))
def test_killed_at_any_moment_resumes_byte_identical(reference, tmp_path, when):
    ref, _, images = reference
    rng = random.Random(f"{SEED}-{when}")
    moment, image = images.pick(rng, KILLS[when](images))
    why = f"killed at {moment}, D2SPO_FAULT_SEED={SEED}"
    run = tmp_path / "run"
    shutil.copytree(image, run)
    if not (run / "config.json").is_file():  # killed before it wrote anything: started again in place
        train(CFG, run)
    elif not (run / "checkpoint.json").is_file():
        with pytest.warns(RunDirWarning, match="no checkpoint was written"):
            train(CFG, run, resume=True)
    else:
        resume_quietly(run)
    assert_same_run(run, ref, why)


def test_kill_9_during_a_checkpoint_write_then_resume_is_exact(reference, tmp_path):
    """A real SIGKILL in a child process, at a random rename of a checkpoint file."""
    ref, _, images = reference
    writes = [lab for lab, _ in images.taken if lab.startswith("write checkpoint")]
    k = random.Random(f"{SEED}-kill9").randrange(1, len(writes))
    run = tmp_path / "run"
    script = f"""
import json, os, signal, sys
from pathlib import Path
import jax
jax.config.update("jax_compilation_cache_dir", {jax.config.jax_compilation_cache_dir!r})
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
from d2spo.config import config_from_dict
from d2spo.train import train
run, n, real = Path(sys.argv[1]), [0], os.replace
def replace(src, dst, *a, **kw):
    if Path(dst).parent == run and Path(dst).name.startswith("checkpoint"):
        n[0] += 1
        if n[0] == {k}:
            os.kill(os.getpid(), signal.SIGKILL)
    return real(src, dst, *a, **kw)
os.replace = replace
train(config_from_dict(json.loads(sys.argv[2])), run)
"""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[1] / "src"),
                                                        os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", script, str(run), json.dumps(config_to_dict(CFG))], env=env,
                          check=False, capture_output=True, text=True, timeout=300)
    why = f"SIGKILL at checkpoint write {k} ({writes[k - 1]}), D2SPO_FAULT_SEED={SEED}"
    assert proc.returncode == -signal.SIGKILL, (why, proc.stderr[-2000:])
    assert [p for p in run.iterdir() if p.name.endswith(".tmp")], "the kill left a temporary file"
    assert (run / ".lock").read_text().startswith("pid ") and str(os.getpid()) not in (run / ".lock").read_text()
    if (run / "checkpoint.json").is_file():  # the dead process's lock is taken over
        resume_quietly(run)
    else:
        with pytest.warns(RunDirWarning):
            train(CFG, run, resume=True)
    assert_same_run(run, ref, why)


# ---------------------------------------------------------------------- damaged checkpoints
@pytest.mark.parametrize("damaged", ["state", "manifest"])
def test_a_damaged_newest_checkpoint_falls_back_to_the_previous_one(reference, tmp_path, damaged):
    ref = reference[0]
    rng = random.Random(f"{SEED}-flip-{damaged}")
    run = mid_run(reference, rng, tmp_path)
    target = run / "checkpoint.json" if damaged == "manifest" else state_file(run)
    flip_byte(target, rng, text=damaged == "manifest")
    with pytest.warns(RunDirWarning, match="resuming from the previous checkpoint") as caught:
        train(CFG, run, resume=True)
    assert len([w for w in caught if issubclass(w.category, RunDirWarning)]) == 1
    assert_same_run(run, ref, f"{target.name} damaged, D2SPO_FAULT_SEED={SEED}")


def test_an_edited_counter_is_caught_by_the_manifest_checksum(reference, tmp_path, capsys):
    rng = random.Random(f"{SEED}-edit")
    run = mid_run(reference, rng, tmp_path)
    m = json.loads((run / "checkpoint.json").read_bytes())
    m.get("meta", m)["episodes"] = "forty"
    (run / "checkpoint.json").write_text(json.dumps(m))
    shutil.copy(run / "checkpoint.json", run / "checkpoint.prev.json")
    line = one_error(capsys, 2, *resume(run))
    assert "no usable checkpoint" in line and "own SHA-256" in line


@pytest.mark.parametrize("damaged", ["state", "manifest"])
def test_both_checkpoints_damaged_is_refused_in_one_line(reference, tmp_path, capsys, damaged):
    rng = random.Random(f"{SEED}-flip2-{damaged}")
    run = mid_run(reference, rng, tmp_path)
    for name in ("checkpoint.json", "checkpoint.prev.json"):
        target = run / name if damaged == "manifest" else state_file(run, name)
        flip_byte(target, rng, text=damaged == "manifest")
    csv_before = (run / "episodes.csv").read_bytes()
    line = one_error(capsys, 2, *resume(run))
    assert "no usable checkpoint" in line and "checkpoint.prev.json" in line
    assert (run / "episodes.csv").read_bytes() == csv_before, "nothing is changed by a refused resume"


# ------------------------------------------------------------------- run state that does not match
def test_a_config_changed_after_the_run_started_is_refused(reference, tmp_path, capsys):
    run = mid_run(reference, random.Random(f"{SEED}-cfg"), tmp_path)
    cfg = json.loads((run / "config.json").read_bytes())
    cfg["num_envs"] = 4
    (run / "config.json").write_text(json.dumps(cfg))
    line = one_error(capsys, 2, *resume(run))
    assert "another config.json" in line


def _to_earlier_format(run: Path) -> None:
    """checkpoint.json holding only the counters and the state in checkpoint.msgpack."""
    m = json.loads((run / "checkpoint.json").read_bytes())
    if "format" not in m:
        return
    shutil.copy(run / m["state"], run / "checkpoint.msgpack")
    for p in [*run.glob("checkpoint-*.msgpack"), run / "checkpoint.prev.json"]:
        p.unlink()
    (run / "checkpoint.json").write_text(json.dumps(m["meta"], indent=2))


def test_a_run_directory_of_the_earlier_format_still_resumes_exactly(reference, tmp_path):
    run = mid_run(reference, random.Random(f"{SEED}-legacy"), tmp_path)
    _to_earlier_format(run)
    resume_quietly(run)
    assert_same_run(run, reference[0], f"earlier format, D2SPO_FAULT_SEED={SEED}")
    prev = json.loads((run / "checkpoint.prev.json").read_bytes())
    assert prev["format"] == 2  # the next checkpoint is in the new format, the old state checksummed
    assert prev["state"] == "checkpoint.msgpack" or not (run / "checkpoint.msgpack").exists()


def test_earlier_format_with_bad_counters_or_another_config_is_refused(reference, tmp_path, capsys):
    run = mid_run(reference, random.Random(f"{SEED}-legacy-bad"), tmp_path)
    _to_earlier_format(run)
    good = (run / "checkpoint.json").read_text()
    (run / "checkpoint.json").write_text(json.dumps({**json.loads(good), "episodes": "forty"}))
    assert "'episodes' must be a non-negative integer" in one_error(capsys, 2, *resume(run))
    (run / "checkpoint.json").write_text(good)
    cfg = json.loads((run / "config.json").read_bytes())
    cfg["num_envs"] = 4  # the earlier format recorded no fingerprint: the state's shapes tell
    (run / "config.json").write_text(json.dumps(cfg))
    assert "written with another config" in one_error(capsys, 2, *resume(run))


@pytest.mark.parametrize("how", ["garbled", "shorter"])
def test_a_damaged_or_shortened_episodes_csv_is_refused(reference, tmp_path, capsys, how):
    run = mid_run(reference, random.Random(f"{SEED}-csv-{how}"), tmp_path)
    lines = (run / "episodes.csv").read_bytes().splitlines(keepends=True)
    kept = counters(run)["episodes"]
    if how == "garbled":
        lines[kept // 2] = b"7,\xff\xfe,zz\r\n"
        (run / "episodes.csv").write_bytes(b"".join(lines))
        assert f"line {kept // 2 + 1}: not a valid row" in one_error(capsys, 2, *resume(run))
    else:
        (run / "episodes.csv").write_bytes(b"".join(lines[:kept - 3]))
        assert "the checkpoint was taken after" in one_error(capsys, 2, *resume(run))


# ------------------------------------------------------------------------------ the directory
def test_a_second_training_on_one_directory_is_refused_naming_the_holder(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    fd = os.open(run / ".lock", os.O_RDWR | os.O_CREAT)
    try:
        os.write(fd, b"pid 4242 on elsewhere, since today\n")
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        line = one_error(capsys, 2, "train", *FLAGS, "--out", run)
        assert "in use by another training (pid 4242 on elsewhere" in line
        assert sorted(p.name for p in run.iterdir()) == [".lock"], "nothing written"
    finally:
        os.close(fd)


def test_a_file_shaped_or_read_only_out_is_one_line(tmp_path, capsys, monkeypatch):
    (tmp_path / "file").write_text("x")
    assert "not a directory" in one_error(capsys, 2, "train", *FLAGS, "--out", tmp_path / "file")
    assert "a file is in the way" in one_error(capsys, 2, "train", *FLAGS, "--out", tmp_path / "file" / "run")
    ro = tmp_path / "ro"
    ro.mkdir()
    real_open, real_mkdir = os.open, os.mkdir

    def refuse(real):
        def call(path, *a, **kw):
            if str(path).startswith(str(ro)):
                raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
            return real(path, *a, **kw)
        return call

    monkeypatch.setattr(os, "open", refuse(real_open))
    monkeypatch.setattr(os, "mkdir", refuse(real_mkdir))
    assert "Read-only file system" in one_error(capsys, 1, "train", *FLAGS, "--out", ro)
    assert "Read-only file system" in one_error(capsys, 1, "train", *FLAGS, "--out", ro / "sub")


def test_a_full_disk_is_one_line_and_leaves_the_run_resumable(reference, tmp_path, capsys, monkeypatch):
    """ENOSPC while the third checkpoint's state is written: exit 1, one line, no temporary file,
    and the run resumes from the second checkpoint to the same result."""
    run = tmp_path / "run"
    real_fsync = os.fsync
    seen = []

    def fsync(fd):
        st = os.fstat(fd)
        names = [p.name for p in run.iterdir() if p.stat().st_ino == st.st_ino] if run.is_dir() else []
        if any(n.startswith(".checkpoint") and ".msgpack." in n for n in names):  # a state file's
            seen.append(names[0])
            if len(seen) == 3:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    line = one_error(capsys, 1, "train", *FLAGS, "--out", run)
    monkeypatch.undo()
    assert "No space left on device" in line and "checkpoint-3.msgpack" in line
    assert not [p for p in run.iterdir() if p.name.endswith(".tmp")]
    assert json.loads((run / "checkpoint.json").read_bytes())["state"] == "checkpoint-2.msgpack"
    rc, lines = cli(capsys, *resume(run))
    assert rc == 0 and lines == [], lines
    assert_same_run(run, reference[0], "ENOSPC at the third checkpoint")


def test_a_layout_or_config_that_is_not_utf8_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_bytes(b'{"name": "\xff\xfe"}')
    assert "not UTF-8" in one_error(capsys, 2, "env", "check", "--layout", bad)
    line = one_error(capsys, 2, "train", "--layout", bad, "--out", tmp_path / "run", "--no-progress")
    assert "not UTF-8" in line and not (tmp_path / "run").exists(), "nothing written for a bad layout"
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "config.json").write_bytes(b'{"algo": "\xff"}')
    assert "not UTF-8" in one_error(capsys, 2, *resume(tmp_path / "r"))


def test_the_nan_message_names_a_checkpoint_that_exists(tmp_path):
    """Before any checkpoint it says there is none; after one, it names checkpoint.json and its episode."""
    import numpy as np

    from d2spo.algos.base import ChunkLog
    from d2spo.checkpoint import Checkpoints
    from d2spo.errors import NaNError
    from d2spo.record import RunRecord

    z = np.zeros((2, 3))
    log = ChunkLog(z.astype(bool), z, z, z, z, z, z, np.zeros((2, 3, 2)), {}, np.bool_(True))
    (tmp_path / "config.json").write_text("{}")
    run = RunRecord(CFG, tmp_path, None, Checkpoints(tmp_path, "fingerprint"))
    with pytest.raises(NaNError, match="no checkpoint was written"):
        run.record(log, None)
    run.checkpoints.save({"w": np.ones(3)}, {"episodes": 7, "env_steps": 9, "chunks": 1, "wall_seconds": 1.0})
    with pytest.raises(NaNError, match="after episode 7, is .*checkpoint.json") as e:
        run.record(log, None)
    assert Path(str(e.value).rsplit(" is ", 1)[1]).is_file()
    run.tb.close()


def test_run_files_get_the_permissions_the_umask_allows(tmp_path):
    from d2spo.runio import RunLock, atomic_write_bytes

    old = os.umask(0o022)
    try:
        atomic_write_bytes(tmp_path / "a", b"x")
        EpisodeWriter(tmp_path / "episodes.csv")
        with RunLock(tmp_path / "run"):
            assert (tmp_path / "run" / ".lock").stat().st_mode & 0o777 == 0o644
        os.umask(0o077)
        atomic_write_bytes(tmp_path / "b", b"x")
    finally:
        os.umask(old)
    assert [(tmp_path / n).stat().st_mode & 0o777 for n in ("a", "episodes.csv", "b")] == [0o644, 0o644, 0o600]
    assert not (tmp_path / "run" / ".lock").exists(), "the lock is removed when released"
