"""Faults a run directory survives besides kills (tests/test_run_kills.py): damaged checkpoints,
run state that does not match, bad files and the machine's faults. Each ends in an exact resume, a
fallback with one warning, or one line on stderr with the right exit status."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import random
import shutil
from pathlib import Path

import pytest
from _run_faults import (
    CFG,
    FLAGS,
    SEED,
    assert_same_run,
    cli,
    counters,
    flip_byte,
    mid_run,
    one_error,
    resume,
    resume_quietly,
    state_file,
)

from d2spo.errors import RunDirWarning
from d2spo.runio import EpisodeWriter
from d2spo.train import train


# ---------------------------------------------------------------------- damaged checkpoints
@pytest.mark.parametrize("damaged", ["state", "manifest"])
def test_a_damaged_newest_checkpoint_falls_back_to_the_previous_one(run_reference, tmp_path, damaged):
    ref = run_reference[0]
    rng = random.Random(f"{SEED}-flip-{damaged}")
    run = mid_run(run_reference, rng, tmp_path)
    target = run / "checkpoint.json" if damaged == "manifest" else state_file(run)
    flip_byte(target, rng, text=damaged == "manifest")
    with pytest.warns(RunDirWarning, match="using the previous checkpoint") as caught:
        train(CFG, run, resume=True)
    assert len([w for w in caught if issubclass(w.category, RunDirWarning)]) == 1
    assert_same_run(run, ref, f"{target.name} damaged, D2SPO_FAULT_SEED={SEED}")


def test_an_edited_counter_is_caught_by_the_manifest_checksum(run_reference, tmp_path, capsys):
    rng = random.Random(f"{SEED}-edit")
    run = mid_run(run_reference, rng, tmp_path)
    m = json.loads((run / "checkpoint.json").read_bytes())
    m.get("meta", m)["episodes"] = "forty"
    (run / "checkpoint.json").write_text(json.dumps(m))
    shutil.copy(run / "checkpoint.json", run / "checkpoint.prev.json")
    line = one_error(capsys, 2, *resume(run))
    assert "no usable checkpoint" in line and "own SHA-256" in line


@pytest.mark.parametrize("damaged", ["state", "manifest"])
def test_both_checkpoints_damaged_is_refused_in_one_line(run_reference, tmp_path, capsys, damaged):
    rng = random.Random(f"{SEED}-flip2-{damaged}")
    run = mid_run(run_reference, rng, tmp_path)
    for name in ("checkpoint.json", "checkpoint.prev.json"):
        target = run / name if damaged == "manifest" else state_file(run, name)
        flip_byte(target, rng, text=damaged == "manifest")
    csv_before = (run / "episodes.csv").read_bytes()
    line = one_error(capsys, 2, *resume(run))
    assert "no usable checkpoint" in line and "checkpoint.prev.json" in line
    assert (run / "episodes.csv").read_bytes() == csv_before, "nothing is changed by a refused resume"


# ------------------------------------------------------------------- run state that does not match
def test_a_config_changed_after_the_run_started_is_refused(run_reference, tmp_path, capsys):
    run = mid_run(run_reference, random.Random(f"{SEED}-cfg"), tmp_path)
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


def test_a_run_directory_of_the_earlier_format_still_resumes_exactly(run_reference, tmp_path):
    run = mid_run(run_reference, random.Random(f"{SEED}-legacy"), tmp_path)
    _to_earlier_format(run)
    resume_quietly(run)
    assert_same_run(run, run_reference[0], f"earlier format, D2SPO_FAULT_SEED={SEED}")
    prev = json.loads((run / "checkpoint.prev.json").read_bytes())
    assert prev["format"] == 2  # the next checkpoint is in the new format, the old state checksummed
    assert prev["state"] == "checkpoint.msgpack" or not (run / "checkpoint.msgpack").exists()


def test_earlier_format_with_bad_counters_or_another_config_is_refused(run_reference, tmp_path, capsys):
    run = mid_run(run_reference, random.Random(f"{SEED}-legacy-bad"), tmp_path)
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
def test_a_damaged_or_shortened_episodes_csv_is_refused(run_reference, tmp_path, capsys, how):
    run = mid_run(run_reference, random.Random(f"{SEED}-csv-{how}"), tmp_path)
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


def test_a_full_disk_is_one_line_and_leaves_the_run_resumable(run_reference, tmp_path, capsys, monkeypatch):
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
    assert_same_run(run, run_reference[0], "ENOSPC at the third checkpoint")


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


def test_a_dead_tensorboard_writer_stops_the_run_instead_of_hanging_it(tmp_path):
    """tensorboardX's writer thread dies on a write error (a full disk) and its 10-event queue then
    blocked every later scalar forever: the run hung with the error printed once."""
    import pytest

    from d2spo.record import TB_QUEUE, _tensorboard, check_tensorboard

    writer = _tensorboard(tmp_path / "tb")
    assert writer.file_writer.event_writer._event_queue._maxsize == TB_QUEUE  # puts never wait on a live thread
    check_tensorboard(writer, tmp_path / "tb")  # alive: nothing
    writer.file_writer.event_writer._event_queue.put(writer.file_writer.event_writer._worker._shutdown_signal)
    writer.file_writer.event_writer._worker.join(timeout=10)  # the thread has ended, as after its OSError
    with pytest.raises(OSError, match="TensorBoard's event writer stopped"):
        check_tensorboard(writer, tmp_path / "tb")
