"""Faults of issue #35 around the files a user names or a run directory holds, and sizes beyond the
machine: a planted `.lock` symlink, a FIFO or `/dev/zero` as a JSON input, a damaged
reproduce.json, sizes that fail only after compiling, and Gymnasium's async vector env (the
layout a run was trained on: tests/test_faults_layouts.py). Nothing here trains or compiles a
learner: where a command would go on to build one it stops with ``Built`` (the ``no_build``
fixture)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from _faults import Hung, cli, one_error

from d2spo.config import TrainConfig
from d2spo.errors import ConfigError, RunDirError


@pytest.fixture
def alarm():
    """``alarm(seconds)``: a blocking call (opening a FIFO, waiting on a pipe) raises ``Hung`` after
    that long instead of hanging the test run."""

    def ring(signum, frame):
        raise Hung("blocked")

    old = signal.signal(signal.SIGALRM, ring)
    yield signal.alarm
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


@pytest.fixture
def machine_of(monkeypatch):
    """``machine_of(n)``: this machine reports ``n`` bytes of physical memory."""
    real = os.sysconf

    def set_memory(n: int) -> None:
        fake = {"SC_PAGE_SIZE": 4096, "SC_PHYS_PAGES": n // 4096}
        monkeypatch.setattr(os, "sysconf", lambda name: fake[name] if name in fake else real(name))

    return set_memory


# ------------------------------------------------------------------------------------ 1. .lock


@pytest.mark.parametrize("target_exists", [True, False])
def test_a_planted_lock_symlink_is_refused_and_its_target_untouched(tmp_path, capsys, monkeypatch, target_exists):
    monkeypatch.setattr("d2spo.train.build", lambda cfg: (None, None, None))
    monkeypatch.setattr("d2spo.train.preflight_checks", lambda *a: None)
    monkeypatch.setattr("d2spo.train._train_locked", lambda *a: pytest.fail("the lock was taken"))
    target = tmp_path / "outside" / "precious.txt"
    target.parent.mkdir()
    if target_exists:
        target.write_text("precious\n")
    run = tmp_path / "run"
    run.mkdir()
    (run / ".lock").symlink_to(target)
    line = one_error(capsys, "train", "--out", run, "--no-progress")
    assert f"{run / '.lock'}: a symbolic link" in line
    if target_exists:
        assert target.read_text() == "precious\n"
    else:
        assert not target.exists(), "a dangling link's target was created"
    assert sorted(p.name for p in run.iterdir()) == [".lock"], "nothing written"


def test_a_lock_that_is_a_fifo_or_directory_is_refused(tmp_path, alarm):
    from d2spo.runio import RunLock, run_holder

    for make in (os.mkfifo, os.mkdir):
        run = tmp_path / make.__name__
        run.mkdir()
        make(run / ".lock")
        alarm(20)
        with pytest.raises(RunDirError, match=r"\.lock: not a plain file"):
            RunLock(run).__enter__()
        with pytest.raises(RunDirError, match=r"\.lock: not a plain file"):
            run_holder(run)
        alarm(0)


# ----------------------------------------------------------------------- 2. non-regular inputs


def test_a_fifo_or_device_as_a_json_input_is_one_line(tmp_path, capsys, alarm, no_build):
    """Checked before the file is opened for reading (which blocks on a FIFO, and never ends on
    /dev/zero): a layout, a --dynamics file and a run's config.json."""
    fifo = tmp_path / "lab.json"
    os.mkfifo(fifo)
    alarm(20)
    assert f"{fifo}: not a regular file (a FIFO)" in one_error(capsys, "env", "check", "--layout", fifo)
    line = one_error(capsys, "train", "--dynamics", fifo, "--out", tmp_path / "run", "--no-progress")
    assert "dynamics: " in line and "not a regular file (a FIFO)" in line
    assert not (tmp_path / "run").exists()
    run = tmp_path / "fiforun"
    run.mkdir()
    os.mkfifo(run / "config.json")
    assert f"{run / 'config.json'}: not a regular file (a FIFO)" in one_error(capsys, "eval", run)
    assert "not a regular file (a FIFO)" in one_error(capsys, "train", "--resume", run, "--no-progress")
    alarm(0)
    line = one_error(capsys, "env", "check", "--layout", "/dev/zero")
    assert "/dev/zero: not a regular file (a character device)" in line
    assert "not a regular file (a directory)" in one_error(capsys, "env", "show", "--layout", tmp_path)
    big = tmp_path / "big.json"
    big.write_bytes(b" " * (16 * 2**20 + 1))
    assert "more than the 16 MiB" in one_error(capsys, "ltl", "phi1", "--layout", big)


@pytest.mark.parametrize("content, kind", [("[1, 2]", "array"), ('"x"', "string"), ("3", "number"), ("null", "null")])
def test_a_config_json_that_is_not_an_object_is_one_line(tmp_path, capsys, no_build, content, kind):
    """Valid JSON of another kind than an object once went on to ``dict(...)`` and a traceback."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(content)
    line = one_error(capsys, "eval", run)
    assert f"{run / 'config.json'}: holds a JSON {kind} where the run's config is an object" in line
    (run / "config.json").write_text('{"td3": 5}')  # an object, with a section that is not
    assert one_error(capsys, "eval", run) == f"d2spo: error: {run / 'config.json'}: td3: expected an object, got int"
    (run / "config.json").write_text('{"episodes": "abc"}')  # the file's value, not a flag: named so
    assert one_error(capsys, "eval", run).startswith(f"d2spo: error: {run / 'config.json'}: episodes: ")
    assert one_error(capsys, "eval", run / "config.json").endswith("config.json: is a file, not a run directory")


def test_a_folder_that_holds_runs_names_them(tmp_path, capsys, no_build):
    """`d2spo eval demo_out` (make demo's folder, whose run is demo_out/d2spo-relaxed) or a reproduce
    OUT: the refusal names the runs inside to give instead; an empty folder gets no such clause."""
    empty = tmp_path / "empty"
    empty.mkdir()
    assert one_error(capsys, "eval", empty).endswith("is this a d2spo run directory?")
    demo = tmp_path / "demo_out"
    (demo / "d2spo-relaxed").mkdir(parents=True)
    (demo / "d2spo-relaxed" / "config.json").write_text("{}")
    line = one_error(capsys, "eval", demo)
    assert line.endswith(f"It holds a run: give it instead ({demo / 'd2spo-relaxed'})"), line
    out = tmp_path / "repro"
    for name in ("d2spo-phi1-paper-s0", "d2spo-phi1-paper-s1", "cpo-phi1-paper-s0", "rcrl-phi1-paper-s0"):
        (out / "runs" / name).mkdir(parents=True)
        (out / "runs" / name / "config.json").write_text("{}")
    (out / "runs" / "not-a-run").mkdir()
    line = one_error(capsys, "certify", out)
    assert f"It holds runs: give one instead ({out / 'runs' / 'cpo-phi1-paper-s0'}, " in line, line
    assert line.endswith(" and 1 more)") and "not-a-run" not in line, line


# -------------------------------------------------------------- 5. report on reproduce.json


@pytest.mark.parametrize("content", [
    b'{"targets": ["table2"], "seeds": 3, "epis',  # cut short
    b'[1, 2, 3]', b'42', b'{}', b'{"seeds": 3}',
    b'{"targets": ["table2"], "seeds": 3, "episodes": 10, "runs": [], "rendered": {"table2": 5}}',
    b'{"targets": 7, "seeds": 3, "episodes": 10, "runs": []}',
    b'{"targets": ["\xff\xfe"], "seeds": 3, "episodes": 10, "runs": []}',  # not UTF-8
], ids=["truncated", "list", "number", "empty", "missing-keys", "rendered-number", "targets-number", "not-utf8"])
def test_report_on_a_damaged_reproduce_json_is_one_line(tmp_path, capsys, content):
    (tmp_path / "table2.md").write_text("| a |\n")
    (tmp_path / "reproduce.json").write_bytes(content)
    line = one_error(capsys, "report", tmp_path)
    assert f"{tmp_path / 'reproduce.json'}: damaged (" in line
    assert not (tmp_path / "report.md").exists()


def test_report_on_a_sound_reproduce_json_is_written(tmp_path, capsys):
    (tmp_path / "table2.md").write_text("| a |\n")
    meta = {"targets": ["table2"], "seeds": 3, "episodes": 10, "runs": [], "finished": 0, "train": False,
            "backend": "local", "rendered": {"table2": {"seeds": 3, "episodes": 10, "methods": None}}}
    (tmp_path / "reproduce.json").write_text(json.dumps(meta))
    rc, lines = cli(capsys, "report", tmp_path)
    assert rc == 0 and lines == []
    assert "Rendered" in (tmp_path / "report.md").read_text()


def test_report_given_a_training_run_says_what_it_reads(tmp_path, capsys):
    """It suggested `d2spo reproduce all --out RUN`: reproducing into a training's run directory."""
    (tmp_path / "config.json").write_text("{}")
    line = one_error(capsys, "report", tmp_path)
    assert "a run directory of `d2spo train`" in line and "reproduce all --out" not in line
    assert not (tmp_path / "report.md").exists()


# ------------------------------------------------------------------ 6. sizes beyond the machine


@pytest.mark.parametrize("flags, flag", [  # the refusal names the flag typed
    (["--td3.buffer-size", "100000000000"], "--td3.buffer-size"),
    (["--td3.hidden", "10000000", "10000000"], "--td3.hidden"),
    (["--eval-episodes", "100000000"], "--eval-episodes"),
    (["--num-envs", "50000000"], "--num-envs"),
    (["--algo", "ppo-lag", "--ppo-lag.rollout-steps", "100000000"], "--ppo-lag.rollout-steps"),
    (["--cbf.transitions-capacity", "2000000000"], "--cbf.transitions-capacity"),
])
def test_a_size_beyond_the_machine_is_refused_before_anything_is_built(tmp_path, capsys, machine_of, no_build,
                                                                      flags, flag):
    machine_of(64 * 2**30)
    line = one_error(capsys, "train", *flags, "--out", tmp_path / "run", "--no-progress")  # no_build: never built
    assert line.startswith(f"d2spo: error: {flag}: a run of this config needs at least ")
    assert "more than this machine's 64.0 GiB" in line
    assert not (tmp_path / "run").exists()


def test_a_buffer_past_its_32_bit_index_is_refused_whatever_the_memory(tmp_path, capsys, machine_of, no_build):
    machine_of(2**60)
    line = one_error(capsys, "train", "--td3.buffer-size", "3000000000", "--out", tmp_path / "run")
    assert "--td3.buffer-size: at most 2147483647" in line


def test_every_learner_s_defaults_fit_this_machine():
    from d2spo.algos import known_algos

    for algo in known_algos():
        TrainConfig(algo=algo).check()
    TrainConfig(generalist=True).check(seeds=3)


def test_a_huge_buffer_from_the_shell_exits_2_at_once(tmp_path):
    """The real command and this machine's memory: 1e11 transitions need terabytes. "At once" as what
    it did, not a clock: refused by the memory check (its message) before anything was built or
    compiled (its own, empty, compilation cache stays without an entry)."""
    d2spo = Path(sys.executable).with_name("d2spo")
    cache = tmp_path / "cache"
    env = {**os.environ, "D2SPO_COMPILE_CACHE": str(cache)}
    p = subprocess.run([str(d2spo), "train", "--td3.buffer-size", "100000000000", "--out", str(tmp_path / "run"),
                        "--no-progress"], capture_output=True, text=True, timeout=120, env=env)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("d2spo: error: --td3.buffer-size: a run of this config needs at "
                                                   "least "), lines
    assert "more than this machine's" in lines[0]
    assert not (tmp_path / "run").exists()
    assert not [f for f in cache.rglob("*") if f.is_file()]  # nothing compiled


# ------------------------------------------------------------------ 7. async vector envs


@pytest.mark.parametrize("vector_kwargs", [{}, {"context": "fork"}])
def test_async_vector_env_with_fork_is_refused_before_forking(vector_kwargs, alarm):
    gym = pytest.importorskip("gymnasium")
    import multiprocessing

    if vector_kwargs == {} and multiprocessing.get_context().get_start_method() != "fork":
        pytest.skip("the default start method here is not fork")
    alarm(60)
    with pytest.raises(ConfigError, match=r"vector_kwargs=\{'context': 'spawn'\}"):
        gym.make_vec("d2spo/Nav-v0", num_envs=2, vectorization_mode="async", vector_kwargs=vector_kwargs,
                     layout="paper", task="phi1")
    alarm(0)
    assert not multiprocessing.active_children()


def test_async_vector_env_with_spawn_steps(alarm):
    gym = pytest.importorskip("gymnasium")
    alarm(120)
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=2, vectorization_mode="async", vector_kwargs={"context": "spawn"},
                        layout="paper", task="phi1")
    try:
        obs, _ = envs.reset(seed=0)
        assert obs.shape == (2, envs.single_observation_space.shape[0])
        obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
        assert obs.shape[0] == 2 and reward.shape == (2,) and info["cost"].shape == (2,)
    finally:
        envs.close()
        alarm(0)
