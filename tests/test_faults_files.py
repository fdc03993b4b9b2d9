"""Faults of issue #35 around the files a user names or a run directory holds, and sizes beyond the
machine: a planted `.lock` symlink, a FIFO or `/dev/zero` as a JSON input, evaluation files of two
layouts sharing a name, a layout file edited under a run, a damaged reproduce.json, sizes that
fail only after compiling, and Gymnasium's async vector env. Nothing here trains or compiles a
learner: where a command would go on to build one, ``build`` is replaced by a function that raises."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from importlib import resources
from pathlib import Path

import pytest

from d2spo.cli import main
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.errors import ConfigError, RunDirError


class Built(Exception):
    """Raised by the stand-in for ``build``: the command got past every check."""


class Hung(Exception):
    """Raised by the alarm: the command blocked."""


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


@pytest.fixture
def no_build(monkeypatch):
    """Training and evaluation stop with ``Built`` where they would build a learner."""

    def built(*a, **kw):
        raise Built

    monkeypatch.setattr("d2spo.train.build", built)
    monkeypatch.setattr("d2spo.evaluate.load_policy", built)


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


def started_run(out: Path, layout: str) -> Path:
    """A run directory as `d2spo train` leaves it before its first chunk (config.json and what
    goes with it), on ``layout``."""
    from d2spo.run import prepare_dir

    out.mkdir(parents=True)
    prepare_dir(out, TrainConfig(env=EnvConfig(layout=layout)), resume=False)
    return out


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


# ------------------------------------------------------------------------ 3. eval file names


@pytest.fixture
def fake_rollouts(monkeypatch):
    """``d2spo eval`` without a policy or a rollout: every layout gets the same rates."""
    rates = {"episodes": 1, "safety_rate": 1.0, "completion_rate": 0.0, "mean_return": 0.0, "mean_length": 1.0,
             "mean_distance": 0.0, "max_steps": 2}
    monkeypatch.setattr("d2spo.evaluate.load_policy",
                        lambda run_dir, which, **kw: (None, None, None, {"policy": "last (after 0 episodes)"}))
    monkeypatch.setattr("d2spo.evaluate._specialist_rollouts", lambda cfg, learner, policy, ecfg, *a, **kw:
                        [dict(rates) for _ in ecfg.layouts()])


def test_two_layouts_never_share_an_evaluation_file(tmp_path, capsys, fake_rollouts):
    run = started_run(tmp_path / "run", "paper")
    a, b = layout_file(tmp_path / "a" / "lab.json", "relaxed"), layout_file(tmp_path / "b" / "lab.json", "open")
    for layout in (a, b, "random:55", "random5:5"):
        assert cli(capsys, "eval", run, "--layout", layout)[0] == 0
    names = sorted(p.name for p in run.glob("eval-*.json"))
    assert len(names) == 4, names
    for p in run.glob("eval-*.json"):
        res = json.loads(p.read_text())
        assert p.name.startswith("eval-lab-") == res["layout"].endswith("lab.json")
    by_layout = {json.loads(p.read_text())["layout"]: p.name for p in run.glob("eval-*.json")}
    assert by_layout[str(a)] != by_layout[str(b)]
    assert by_layout["random:55"] != by_layout["random5:5"]


def test_evaluation_file_names_of_built_in_and_random_layouts_are_kept():
    from d2spo.evaluate import evaluation_path, layout_sha256, layout_tag

    one = {"layout": "paper", "per_layout": [{}], "dynamics": "default", "runtime_filter": None}
    assert evaluation_path(Path("r"), one) == Path("r") / "eval-paper-default.json"
    assert layout_tag("random:11") == "random11" and layout_tag("random") == "random0"
    assert layout_tag("random5:5") == "random5-5" != layout_tag("random:55")
    assert layout_sha256("paper") is None and layout_sha256("random:3") is None


def test_a_run_trained_under_its_own_dynamics_is_evaluated_as_trained_not_as_its_preset(tmp_path, capsys,
                                                                                        fake_rollouts):
    """A run trained with a dynamics file or per-field flags wrote its evaluations as `-default`, the
    preset it started from, though it ran under its own values."""
    from d2spo.evaluate import trained_dynamics
    from d2spo.run import prepare_dir

    assert trained_dynamics(TrainConfig()) == "default"
    assert trained_dynamics(TrainConfig(env=EnvConfig(preset="turtlebot"))) == "turtlebot"
    assert trained_dynamics(TrainConfig(env=EnvConfig(slip=0.05))) == "default"  # the preset's own value
    run = tmp_path / "run"
    run.mkdir()
    prepare_dir(run, TrainConfig(env=EnvConfig(layout="relaxed", v_gain=0.85)), resume=False)
    assert cli(capsys, "eval", run)[0] == 0
    res = json.loads((run / "eval-relaxed-trained.json").read_text())
    assert res["dynamics"] == "trained" and res["dynamics_values"]["v_gain"] == 0.85
    assert cli(capsys, "eval", run, "--slip", "0.2")[0] == 0 and (run / "eval-relaxed-trained-slip0.2-filter-a3-i3.json").exists()


# ------------------------------------------------------------------ 4. the layout's content


def test_a_layout_file_edited_since_the_run_started_is_refused(tmp_path, capsys, no_build, monkeypatch):
    lab = layout_file(tmp_path / "lab.json")
    run = started_run(tmp_path / "run", str(lab))
    def built(*a, **kw):
        raise Built

    for module in ("d2spo.export", "d2spo.certify"):  # as if it had a checkpoint; stop where they would build
        monkeypatch.setattr(f"{module}.has_checkpoint", lambda run_dir: True)
        monkeypatch.setattr(f"{module}.build", built)
    for command in (["train", "--resume", str(run), "--no-progress"], ["export", str(run), "--out", str(tmp_path / "x")],
                    ["certify", str(run)]):
        with pytest.raises(Built):  # unchanged: the checks pass
            main(command)
    lab.write_text(lab.read_text().replace('"name"', ' "name"', 1))  # one byte more
    line = one_error(capsys, "train", "--resume", run, "--no-progress")
    assert f"{run}: its layout file {lab} changed since the run started" in line
    line = one_error(capsys, "eval", run)
    assert f"its layout file {lab} changed since the run started" in line
    assert f"to evaluate on it as it is now, pass --layout {lab}" in line
    # export and certify read the map too: an export's filter, a certificate, of another map than learnt
    # (they once went on with the edited file)
    line = one_error(capsys, "export", run, "--out", tmp_path / "y")
    assert f"its layout file {lab} changed since the run started" in line and "export's map" in line
    assert not (tmp_path / "y").exists()
    line = one_error(capsys, "certify", run)
    assert f"its layout file {lab} changed since the run started" in line and "checked against another map" in line
    recorded = json.loads((run / "inputs.json").read_text())["layout"]
    assert recorded["file"] == str(lab) and len(recorded["sha256"]) == 64


def test_the_training_layout_file_is_known_by_its_content_not_its_spelling(tmp_path, monkeypatch):
    """`d2spo eval RUN --layout in/lab.json` ran with the filter as trained and `--layout /abs/in/lab.json`
    (the same file) with it on, as if elsewhere. Now a file is the training layout when it holds the
    bytes the run started with, and an edited file is another layout (the filter on)."""
    from d2spo.evaluate import filter_choice
    from d2spo.run import is_training_layout, load_run_config

    monkeypatch.chdir(tmp_path)
    lab = layout_file(tmp_path / "in" / "lab.json")
    run = started_run(tmp_path / "run", "in/lab.json")
    cfg = load_run_config(run)
    assert cfg.algo == "d2spo"
    for spelling in ("in/lab.json", "./in/lab.json", str(lab), "in/../in/lab.json"):
        same = is_training_layout(run, cfg, spelling)
        assert same and filter_choice(cfg, spelling, None, None, None, same) is None, spelling
    (tmp_path / "copy.json").write_bytes(lab.read_bytes())
    assert is_training_layout(run, cfg, "copy.json")  # the same bytes: the same layout
    assert not is_training_layout(run, cfg, "relaxed") and not is_training_layout(run, cfg, "missing.json")
    lab.write_text(lab.read_text().replace('"name"', ' "name"', 1))  # one byte more
    same = is_training_layout(run, cfg, "in/lab.json")
    assert not same and filter_choice(cfg, "in/lab.json", None, None, None, same) is True
    assert filter_choice(cfg, "in/lab.json", None, None) is None  # by name alone, as before


def test_a_run_on_a_relative_layout_path_is_found_from_another_directory(tmp_path, capsys, no_build, monkeypatch):
    """config.json keeps the layout's path as given (``lab.json``); from another directory the run's
    file is found where inputs.json recorded it, or at the --layout given, if it holds the same bytes."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    monkeypatch.chdir(tmp_path / "a")
    layout_file(tmp_path / "a" / "lab.json")
    run = started_run(tmp_path / "a" / "run", "lab.json")
    monkeypatch.chdir(tmp_path / "b")
    for command in (["train", "--resume", str(run), "--no-progress"], ["eval", str(run)]):
        with pytest.raises(Built):  # found through inputs.json's absolute path
            main(command)
    (tmp_path / "a" / "lab.json").rename(tmp_path / "b" / "moved.json")
    line = one_error(capsys, "eval", run)
    assert f"its layout file lab.json (at {tmp_path / 'a' / 'lab.json'} when it started) is not found from" in line
    assert "pass --layout PATH" in line
    with pytest.raises(Built):  # the same bytes elsewhere, named by --layout
        main(["eval", str(run), "--layout", "moved.json"])
    layout_file(tmp_path / "b" / "other.json", "open")
    assert "is not found from" in one_error(capsys, "eval", run, "--layout", "other.json")  # other bytes


def test_a_run_without_a_recorded_layout_hash_still_resumes_and_evaluates(tmp_path, no_build):
    lab = layout_file(tmp_path / "lab.json")
    run = started_run(tmp_path / "run", str(lab))
    (run / "inputs.json").unlink(missing_ok=True)  # a run of an earlier d2spo
    lab.write_text(lab.read_text() + "\n")
    with pytest.raises(Built):
        main(["train", "--resume", str(run), "--no-progress"])
    with pytest.raises(Built):
        main(["eval", str(run)])


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


# ------------------------------------------------------------------ 6. sizes beyond the machine


@pytest.mark.parametrize("flags, field", [
    (["--td3.buffer-size", "100000000000"], "td3.buffer_size"),
    (["--td3.hidden", "10000000", "10000000"], "td3.hidden"),
    (["--eval-episodes", "100000000"], "eval_episodes"),
    (["--num-envs", "50000000"], "num_envs"),
    (["--algo", "ppo-lag", "--ppo-lag.rollout-steps", "100000000"], "ppo_lag.rollout_steps"),
    (["--cbf.transitions-capacity", "2000000000"], "cbf.transitions_capacity"),
])
def test_a_size_beyond_the_machine_is_refused_before_anything_is_built(tmp_path, capsys, machine_of, no_build,
                                                                      flags, field):
    machine_of(64 * 2**30)
    t0 = time.perf_counter()
    line = one_error(capsys, "train", *flags, "--out", tmp_path / "run", "--no-progress")
    assert time.perf_counter() - t0 < 20
    assert line.startswith(f"d2spo: error: {field}: a run of this config needs at least ")
    assert "more than this machine's 64.0 GiB" in line
    assert not (tmp_path / "run").exists()


def test_a_buffer_past_its_32_bit_index_is_refused_whatever_the_memory(tmp_path, capsys, machine_of, no_build):
    machine_of(2**60)
    line = one_error(capsys, "train", "--td3.buffer-size", "3000000000", "--out", tmp_path / "run")
    assert "td3.buffer_size: at most 2147483647" in line


def test_every_learner_s_defaults_fit_this_machine():
    from d2spo.algos import known_algos

    for algo in known_algos():
        TrainConfig(algo=algo).check()
    TrainConfig(generalist=True).check(seeds=3)


def test_a_huge_buffer_from_the_shell_exits_2_at_once(tmp_path):
    """The real command and this machine's memory: 1e11 transitions need terabytes."""
    d2spo = Path(sys.executable).with_name("d2spo")
    t0 = time.perf_counter()
    p = subprocess.run([str(d2spo), "train", "--td3.buffer-size", "100000000000", "--out", str(tmp_path / "run"),
                        "--no-progress"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert time.perf_counter() - t0 < 20
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("d2spo: error: td3.buffer_size: "), lines
    assert not (tmp_path / "run").exists()


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
