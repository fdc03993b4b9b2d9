"""The run loop: outputs, determinism, atomic checkpoints and exact resume, NaN detection."""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json

import numpy as np
import pytest

from d2spo.algos.td3 import TD3Config
from d2spo.config import TrainConfig, config_from_dict, config_to_dict
from d2spo.envs import EnvConfig
from d2spo.errors import ConfigError, NaNError, RunDirError
from d2spo.ltl.reward import RewardConfig
from d2spo.train import train


def tiny(**kw) -> TrainConfig:
    base = TrainConfig(
        algo="tlgrl", task="relaxed", episodes=60, num_envs=8, chunk_steps=25, checkpoint_every=20,
        window=50, eval_episodes=8,
        # 40-step episodes: the default per-state metric would warn that the task cannot fit in them
        env=EnvConfig(layout="relaxed", max_steps=40, reward=RewardConfig(shaping_metric="geodesic")),
        td3=TD3Config(hidden=(16, 16), batch_size=32, learning_starts=64, buffer_size=4096),
    )
    return dataclasses.replace(base, **kw).check()


def rows(path):
    with open(path) as f:
        return list(csv.reader(f))


def test_outputs_and_summary(tmp_path, capsys):
    from _learning import untrained_eval

    events = []
    summary = train(tiny(eval_untrained=True), tmp_path / "run", progress=events.append)
    run = tmp_path / "run"
    # the initial policy on the final evaluation's episodes, as an independent build evaluates it
    assert summary["eval_untrained"] == pytest.approx(untrained_eval(tiny(), 8), rel=1e-6)
    assert summary["eval_untrained"] != summary["eval"]  # training changed the policy
    with pytest.raises(ConfigError, match="eval_untrained: the initial policy of a resumed run"):
        train(tiny(eval_untrained=True), run, resume=True)
    for name in ("config.json", "episodes.csv", "summary.json", "checkpoint.json"):
        assert (run / name).is_file(), name
    table = rows(run / "episodes.csv")
    assert table[0] == ["episode", "return", "cost", "collided", "completed", "completed_relaxed", "length",
                        "end_x", "end_y"]
    assert len(table) == 1 + 60
    assert [int(r[0]) for r in table[1:]] == list(range(60))
    collided = np.array([int(r[3]) for r in table[1:]])
    end = np.array([[float(r[7]), float(r[8])] for r in table[1:]])
    assert np.all((end >= 0.0) & (end <= 5.0)) and len(np.unique(end, axis=0)) > 1  # where each episode ended
    assert summary["safety_rate"] == pytest.approx(1.0 - collided[-50:].mean())
    assert summary["collisions_all"] == collided.sum() >= collided[-50:].sum()  # every episode, not the window's
    # rejected: ended before the 40-step limit, neither collided nor done under training's (relaxed) labelling
    relaxed, length = (np.array([int(r[i]) for r in table[1:]]) for i in (5, 6))
    assert summary["rejection_rate"] == pytest.approx(((length < 40) & (collided == 0) & (relaxed == 0))[-50:].mean())
    assert summary["episodes"] == 60 and summary["window"] == 50
    assert 0.0 <= summary["eval"]["safety_rate"] <= 1.0
    assert json.loads((run / "summary.json").read_text()) == summary
    # wall time without compilation (the training loop), the compilation, and everything together
    assert summary["compile_seconds"] > 0 and summary["wall_seconds"] > 0
    assert summary["wall_seconds_total"] >= summary["wall_seconds"] + summary["compile_seconds"]
    # the progress callback hears of the compilation before the first chunk and of the final evaluation
    phases = [e.get("phase", "chunk") for e in events]
    assert phases[:2] == ["compiling", "compiled"] and phases[-1] == "evaluating"
    assert set(phases[2:-1]) == {"chunk"} and events[-2]["episodes"] == 60
    assert list((run / "tb").iterdir()), "TensorBoard events written"
    # `d2spo eval` on it: prints and writes the rates, with the distance driven
    from d2spo.cli import main

    capsys.readouterr()  # from here on stderr is the CLI's alone (train() above may warn the plain way)
    assert main(["eval", str(run), "--episodes", "4", "--plot", str(tmp_path / "ev.png")]) == 0
    assert (tmp_path / "ev.png").read_bytes()[:4] == b"\x89PNG"
    # its progress, plain lines off a terminal on stderr (as train's; stdout holds the table alone):
    # the first layout (which compiles), then all done
    seen = capsys.readouterr()
    assert "layouts evaluated" not in seen.out
    shown = [ln for ln in seen.err.splitlines() if "layouts evaluated" in ln]
    assert shown == [f"eval run: 0/1 layouts evaluated, {shown[0].split(', ')[1].split(';')[0]}; layout 'relaxed' "
                     "(compiling the rollout first)", shown[1]] and shown[1].startswith("eval run: 1/1 layouts evaluated")
    ev = json.loads((run / "eval-relaxed-default.json").read_text())
    assert ev["episodes"] == 4 and [p["layout"] for p in ev["per_layout"]] == ["relaxed"]
    assert ev["mean_distance"] > 0.0 and ev["runtime_filter"] is None  # tlgrl has no filter
    # the limit its episodes ran to: the run's own (its config's, as training built its env)
    from d2spo.run import build, load_run_config
    own = int(build(load_run_config(run))[1].max_steps)
    assert ev["max_steps"] == ev["per_layout"][0]["max_steps"] == own and not ev["max_steps_given"]
    # another episode limit (a specialist; tests/test_zero_shot.py checks what it does to a patrol)
    assert main(["eval", str(run), "--episodes", "4", "--max-steps", "60", "--no-progress"]) == 0
    longer = json.loads((run / "eval-relaxed-default-T60.json").read_text())
    assert longer["max_steps"] == 60 and longer["max_steps_given"]
    # training's final evaluation again: its key (the run's seed + 10000) and its episode count; another
    # seed is another evaluation, in a file of its own
    assert main(["eval", str(run), "--episodes", "8", "--seed", "10000", "--no-progress"]) == 0
    again = json.loads((run / "eval-relaxed-default-s10000.json").read_text())
    keys = ("safety_rate", "completion_rate", "mean_return", "mean_length", "mean_distance")
    assert {k: again["per_layout"][0][k] for k in keys} == pytest.approx({k: summary["eval"][k] for k in keys},
                                                                          rel=1e-6)
    assert again["seed"] == 10000 and ev["seed"] == 0
    # under custom dynamics: a JSON file with every field, and a per-field flag on top of it
    robot = {"dt": 0.1, "v_max": 0.5, "omega_max": 1.0, "actuator_tau": 0.0, "v_gain": 1.0, "omega_gain": 1.0,
             "slip": 0.0, "noise_xy": 0.0, "noise_theta": 0.0}
    (tmp_path / "slow.json").write_text(json.dumps(robot))
    assert main(["eval", str(run), "--episodes", "4", "--dynamics", str(tmp_path / "slow.json"), "--slip", "0.2",
                 "--no-progress"]) == 0
    quiet = capsys.readouterr()
    assert "layouts evaluated" not in quiet.out + quiet.err
    tag = "slow-" + hashlib.sha256((tmp_path / "slow.json").read_bytes()).hexdigest()[:12]  # two slow.json never meet
    ev = json.loads((run / f"eval-relaxed-{tag}-slip0.2.json").read_text())
    assert ev["dynamics"] == f"{tag}-slip0.2" and ev["dynamics_values"] == {**robot, "slip": 0.2}
    (tmp_path / "bad.json").write_text(json.dumps({**robot, "v_gain": -1}))
    assert main(["eval", str(run), "--dynamics", str(tmp_path / "bad.json")]) == 2
    assert main(["eval", str(run), "--noise-xy", "-1"]) == 2
    assert main(["eval", str(run), "--plot", str(tmp_path / "no" / "ev.png")]) == 2
    err = (seen.err + quiet.err + capsys.readouterr().err).strip().splitlines()
    # evaluation runs training's pre-flight check: these 40-step episodes are too short for the task
    assert any(ln.startswith("d2spo: warning:") and "cannot be completed" in ln for ln in err)
    err = [ln for ln in err if not ln.startswith("d2spo: warning:") and "layouts evaluated" not in ln]
    assert err == [f"d2spo: error: dynamics.v_gain: must be positive, got -1 (in {tmp_path / 'bad.json'})",
                   "d2spo: error: --noise-xy: must be non-negative, got -1.0",
                   f"d2spo: error: --plot: {tmp_path / 'no' / 'ev.png'}: the folder {tmp_path / 'no'} does not exist"]
    # a layout that does not load is the one line on stderr: refused before the progress starts
    assert main(["eval", str(run), "--layout", "nosuch", "--episodes", "2"]) == 2
    seen = capsys.readouterr()
    assert seen.out == "" and seen.err.startswith("d2spo: error: --layout: unknown layout 'nosuch'")
    assert seen.err.count("\n") == 1, seen.err


def test_same_seed_same_run_and_resume_is_exact(tmp_path):
    cfg = tiny()
    train(cfg, tmp_path / "a")
    # Interrupted after two chunks, then resumed: identical episodes.
    assert train(cfg, tmp_path / "b", stop_after_chunks=2) is None
    n_before = len(rows(tmp_path / "b" / "episodes.csv"))
    assert 1 < n_before < 61
    # on disk with the checkpoint, as a kill leaves it: every episode's scalars (record.durable_tensorboard)
    from _tb import tb_scalars

    assert [step for step, _ in tb_scalars(tmp_path / "b" / "tb")["episode/return"]] == list(range(n_before - 1))  # rows(): the header too
    train(cfg, tmp_path / "b", resume=True)
    assert rows(tmp_path / "a" / "episodes.csv") == rows(tmp_path / "b" / "episodes.csv")
    a = json.loads((tmp_path / "a" / "summary.json").read_text())
    b = json.loads((tmp_path / "b" / "summary.json").read_text())
    for k in ("safety_rate", "completion_rate", "mean_return", "eval", "env_steps"):
        assert a[k] == b[k], k
    # resuming a finished run trains and evaluates nothing: its summary.json stands, byte for byte
    # (it once compiled, evaluated again and added the time to compile_seconds and wall_seconds_total)
    from d2spo.errors import RunDirWarning

    before = (tmp_path / "b" / "summary.json").read_bytes()
    with pytest.warns(RunDirWarning, match="the run finished .*nothing was trained or evaluated again"):
        assert train(cfg, tmp_path / "b", resume=True) == b
    assert (tmp_path / "b" / "summary.json").read_bytes() == before
    # a damaged summary.json is written again (the final evaluation again), not a warning and an error
    (tmp_path / "b" / "summary.json").write_bytes(before[:100])
    with pytest.warns(RunDirWarning, match="not valid JSON.*evaluating it again"):
        again = train(cfg, tmp_path / "b", resume=True)
    assert again["eval"] == b["eval"] and json.loads((tmp_path / "b" / "summary.json").read_text()) == again


def test_a_new_run_refuses_a_folder_of_other_files_and_leaves_them(tmp_path):
    """`train --out proj` deleted proj's hidden .*.tmp and policy-*.msgpack files and wrote config.json
    over proj's own."""
    from d2spo.errors import RunDirError

    proj = tmp_path / "proj"
    proj.mkdir()
    files = {"config.json": '{"my": "project settings"}', ".draft.tmp": "d", "policy-final.msgpack": "m"}
    for name, text in files.items():
        (proj / name).write_text(text)
    with pytest.raises(RunDirError, match="not empty and holds no d2spo run"):
        train(tiny(), proj)
    assert {p.name: p.read_text() for p in proj.iterdir()} == files  # no .lock either


def test_a_checkpoint_taken_before_an_interrupt_is_written_and_resumes_exactly(tmp_path, monkeypatch):
    """Interrupted (Ctrl-C) in the fourth chunk, a run has the checkpoint taken after the third, and
    resumes from it to the episodes of an uninterrupted run."""
    import d2spo.record as record_mod

    cfg = tiny(checkpoint_every=1, chunk_steps=40)  # episodes end in every chunk: a checkpoint after each
    train(cfg, tmp_path / "a")
    record, calls = record_mod.RunRecord.record, []

    def interrupted_in_chunk_4(run, log, progress):  # as tests/test_fault_battery.py interrupts a group
        calls.append(run)
        if len(calls) == 4:
            raise KeyboardInterrupt
        record(run, log, progress)

    monkeypatch.setattr(record_mod.RunRecord, "record", interrupted_in_chunk_4)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, tmp_path / "b")
    monkeypatch.setattr(record_mod.RunRecord, "record", record)
    manifest = json.loads((tmp_path / "b" / "checkpoint.json").read_text())
    written = rows(tmp_path / "b" / "episodes.csv")
    assert manifest["meta"]["chunks"] == 3 and manifest["meta"]["episodes"] == len(written) - 1 > 0
    train(cfg, tmp_path / "b", resume=True)
    assert rows(tmp_path / "a" / "episodes.csv") == rows(tmp_path / "b" / "episodes.csv")


def test_other_seed_differs(tmp_path):
    train(tiny(), tmp_path / "a")
    train(tiny(seed=1), tmp_path / "b")
    assert rows(tmp_path / "a" / "episodes.csv") != rows(tmp_path / "b" / "episodes.csv")


def test_refuses_to_overwrite_and_bad_resume(tmp_path):
    # tiny() as the other tests train it, so its programs are compiled already
    train(tiny(), tmp_path / "a")
    with pytest.raises(RunDirError):
        train(tiny(), tmp_path / "a")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunDirError):
        train(tiny(), tmp_path / "empty", resume=True)


def test_nan_is_reported_not_trained_through(tmp_path):
    td3 = TD3Config(hidden=(16, 16), batch_size=32, learning_starts=8, buffer_size=4096)
    object.__setattr__(td3, "critic_lr", float("nan"))  # past the config check (which refuses it): a divergence
    with pytest.raises(NaNError):
        train(tiny(td3=td3), tmp_path / "nan")


def test_seeds_vmapped_together_write_ordinary_runs_and_resume_exactly(tmp_path):
    from d2spo.train import train_seeds

    cfgs = [tiny(seed=s) for s in (0, 1, 2)]
    outs = [tmp_path / "a" / f"s{s}" for s in (0, 1, 2)]
    summaries = train_seeds(cfgs, outs)
    assert [s["seed"] for s in summaries] == [0, 1, 2] and all(s["episodes"] == 60 for s in summaries)
    for out in outs:
        for name in ("config.json", "episodes.csv", "summary.json", "checkpoint.json"):
            assert (out / name).is_file(), name
        assert len(rows(out / "episodes.csv")) == 61
    assert not list((tmp_path / "a").glob(".group-*")), "the group checkpoint is removed at the end"
    tables = [rows(o / "episodes.csv") for o in outs]
    assert tables[0] != tables[1] != tables[2]  # different seeds, different runs
    # interrupted after two chunks, then resumed by calling again: identical to the uninterrupted group
    outs_b = [tmp_path / "b" / f"s{s}" for s in (0, 1, 2)]
    assert train_seeds(cfgs, outs_b, stop_after_chunks=2) is None
    assert 1 < len(rows(outs_b[0] / "episodes.csv")) < 61
    again = train_seeds(cfgs, outs_b)
    for a, b, sa, sb in zip(outs, outs_b, summaries, again):
        assert rows(a / "episodes.csv") == rows(b / "episodes.csv")
        for k in ("safety_rate", "completion_rate", "mean_return", "eval", "env_steps"):
            assert sa[k] == sb[k], k
    # a seed trained in a group is a run like any other: eval reads it
    from d2spo.evaluate import EvalConfig, evaluate_run

    assert 0.0 <= evaluate_run(outs[1], EvalConfig(episodes=4))["safety_rate"] <= 1.0
    with pytest.raises(ConfigError, match="only in their seed"):
        train_seeds([tiny(seed=0), tiny(seed=1, num_envs=4)], [tmp_path / "c0", tmp_path / "c1"])


def test_eval_rates_measure_the_distance_driven():
    """mean_distance sums the steps of each episode until its end (NaN poses after it)."""
    from d2spo.rollout import rates

    nan = float("nan")
    poses = np.array([[[0, 0, 0], [3, 4, 0], [3, 4, 1], [nan, nan, nan]],   # 5 m, then turning on the spot
                      [[1, 1, 0], [1, 1, 0], [1, 2, 0], [1, 3, 0]]], float)  # 2 m
    r = rates(np.array([False, True]), np.array([True, False]), np.array([1.0, 3.0]), np.array([3, 3]), poses)
    assert r["mean_distance"] == pytest.approx(3.5) and r["safety_rate"] == 0.5 and r["completion_rate"] == 0.5
    assert "mean_distance" not in rates(np.array([False]), np.array([True]), np.array([1.0]), np.array([3]))



def test_validation_keeps_the_latest_best_policy_and_a_resume_keeps_it(tmp_path):
    """``RunRecord.validate`` (the generalist's model selection) with a stub validation: every
    ``validate_every`` episodes a score is recorded; the kept policy is the last of the highest."""
    from flax import serialization

    from d2spo.checkpoint import Checkpoints
    from d2spo.record import RunRecord
    from d2spo.run import best_policy_path

    scores = iter([0.2, 0.5, 0.5, 0.3])

    class Stub:
        layouts = "random:50000..50001"

        def __call__(self, policy):
            s = next(scores)
            return {"success_rate": s, "completion_rate": s, "safety_rate": 1.0}

    class Learner:
        @staticmethod
        def policy(carry):
            return carry

    cfg = tiny(validate_every=10)
    out = tmp_path / "run"
    out.mkdir()
    run = RunRecord(cfg, out, None, Checkpoints(out, "x"), validation=Stub())
    metas = {}
    for k in range(4):
        run.writer.append([(10 * k + i, 0.0, 0.0, 0, 0, 0, 40, 0.0, 0.0) for i in range(10)])
        run.meta["episodes"] = len(run.writer)
        run.save(Learner, {"w": np.full(2, float(k), np.float32)})
        metas[len(run.writer)] = json.loads(json.dumps(run.meta))
    assert [e["episodes"] for e in run.meta["validation"]] == [10, 20, 30, 40]
    assert [e["success_rate"] for e in run.meta["validation"]] == [0.2, 0.5, 0.5, 0.3]
    assert run.meta["best"]["episodes"] == 30  # the later of the two 0.5s: equals go to the longer-trained
    kept = serialization.from_bytes({"w": np.zeros(2, np.float32)}, best_policy_path(out).read_bytes())
    np.testing.assert_array_equal(kept["w"], [2.0, 2.0])
    again = RunRecord(cfg, out, metas[20], Checkpoints(out, "x"), validation=Stub())
    assert again.next_validation == 30 and again.meta["best"]["episodes"] == 20


def test_validation_prefers_success_then_speed_then_the_later_policy():
    from d2spo.validation import better_validation

    def v(success, steps="absent"):
        return {"success_rate": success} if steps == "absent" else {"success_rate": success, "mean_steps_success": steps}

    assert better_validation(v(0.9, 300.0), v(0.8, 100.0))  # success first, however slow
    assert not better_validation(v(0.8, 100.0), v(0.9, 300.0))
    assert better_validation(v(0.9, 120.0), v(0.9, 150.0))  # of equal success, the faster
    assert not better_validation(v(0.9, 150.0), v(0.9, 120.0))
    assert better_validation(v(0.9, 150.0), v(0.9, 150.0))  # equal in both: the later
    assert better_validation(v(0.9, 150.0), v(0.9))  # a validation of an older run has no steps
    assert better_validation(v(0.9), v(0.9))
    assert not better_validation(v(0.0, None), v(0.0, 10.0))  # None: no success to time
    assert better_validation(v(0.0, None), v(0.0, None))


def test_the_generalists_episodes_default_and_validation_seeds():
    from d2spo.config import GENERALIST_EPISODES, GENERALIST_TASKS, PAPER_EPISODES, VALIDATION_SEED

    assert TrainConfig().episodes == PAPER_EPISODES
    assert TrainConfig(generalist=True).episodes == GENERALIST_EPISODES
    assert TrainConfig(generalist=True, episodes=123).episodes == 123
    assert (TrainConfig().generalist_tasks, TrainConfig(generalist=True).generalist_tasks) == (0, GENERALIST_TASKS)
    assert TrainConfig(generalist=True, generalist_tasks=0).generalist_tasks == 0
    assert config_from_dict(config_to_dict(TrainConfig(generalist=True))).generalist_tasks == GENERALIST_TASKS
    with pytest.raises(ConfigError, match="validation set"):
        TrainConfig(generalist=True, generalist_layouts=VALIDATION_SEED + 1)
    with pytest.raises(ConfigError, match="validate_every"):
        TrainConfig(generalist=True, validate_every=0)
    old = config_to_dict(TrainConfig(generalist=True))
    del old["validation_layouts"]  # a generalist trained before validation kept its last policy
    assert config_from_dict(old).validation_layouts == 0


def test_window_rates_count_an_episode_rejected_only_when_nothing_else_ended_it():
    from d2spo.runio import window_rates

    table = [(0, 0.0, 0.0, 0, 0, 0, 40), (1, 0.0, 0.0, 1, 0, 0, 10),  # out of time; collided
             (2, 0.0, 0.0, 0, 0, 1, 12), (3, 0.0, 0.0, 0, 0, 0, 7),   # relaxed completion; rejected
             (4, 0.0, 0.0, 0, 1, 1, 30)]                             # completed
    assert window_rates(table, 5, max_steps=40)["rejection_rate"] == pytest.approx(0.2)
    assert window_rates(table, 2, max_steps=40)["rejection_rate"] == pytest.approx(0.5)
    assert "rejection_rate" not in window_rates(table, 5)
