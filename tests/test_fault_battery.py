"""Faults a hostile user can cause, each of which once ended in a wrong result with exit 0 or in a
traceback: an interrupted `reproduce`, hyper-parameters out of range, bad `eval` counts, a rejected
`train` writing to --out, unbounded work (long ordered tasks, huge arenas, deep formulas)."""

from __future__ import annotations

import csv
import dataclasses
import re

import pytest
from _reproduce import TINY_EPISODES, small_config, use_small_configs

from d2spo import record as record_mod
from d2spo import reproduce as rp
from d2spo import run as run_mod


def _exit_code(args: list[str]) -> int:
    """``d2spo ARGS``'s exit status (a usage error found while parsing leaves by SystemExit)."""
    from d2spo.cli import main

    try:
        return main(args)
    except SystemExit as e:
        return e.code


def _table(path) -> str:
    """A table without its wall-time column (the only thing that may differ between two runs)."""
    text = path.read_text()
    if path.suffix == ".csv":
        rows = list(csv.DictReader(text.splitlines()))
        return "\n".join(str({k: v for k, v in r.items() if k != "wall_seconds_mean"}) for r in rows)
    return re.sub(r"\| [^|]* \|\n", "|\n", text)  # the last column of every row


def test_interrupted_reproduce_resumes_its_seed_group_exactly(tmp_path, monkeypatch):
    """Two seeds trained as one vmapped group, stopped in their third chunk after the group and each
    seed had checkpointed: the rerun resumes the group (not each seed alone from its own checkpoint),
    so the tables are those of an uninterrupted run, and the group directory is removed."""
    use_small_configs(monkeypatch)  # checkpoints every 10 episodes: the group and each seed checkpoint mid-run
    kw = {"seeds": 2, "episodes": TINY_EPISODES, "methods": ["ppo-lag"], "progress": False, "log": lambda s: None}
    rp.reproduce(["table3"], tmp_path / "a", **kw)

    record, calls = record_mod.RunRecord.record, []

    def killed_in_chunk_3(run, log, progress):
        calls.append(run)
        if len(calls) == 5:  # the third chunk
            raise KeyboardInterrupt
        record(run, log, progress)

    monkeypatch.setattr(record_mod.RunRecord, "record", killed_in_chunk_3)
    with pytest.raises(KeyboardInterrupt):
        rp.reproduce(["table3"], tmp_path / "b", **kw)
    monkeypatch.setattr(record_mod.RunRecord, "record", record)
    runs = tmp_path / "b" / "runs"
    assert len(list(runs.glob(".group-*/checkpoint.json"))) == 1
    assert list(runs.glob("ppo-lag-*/checkpoint.json"))  # what made a seed resume alone, the other restart
    # `d2spo train --resume` of one seed would go on alone (a solo run): refused, the group untouched
    from d2spo.errors import RunDirError
    from d2spo.run import load_run_config
    from d2spo.train import train

    seed0 = rp.run_dir(tmp_path / "b", rp.runs_for("table3", 2, TINY_EPISODES, ["ppo-lag"])[0])
    before = (seed0 / "episodes.csv").read_bytes()
    with pytest.raises(RunDirError, match="one of the seeds trained together in .group-"):
        train(load_run_config(seed0), seed0, resume=True)
    assert (seed0 / "episodes.csv").read_bytes() == before
    rp.reproduce(["table3"], tmp_path / "b", **kw)
    for name in ("table3.md", "table3.csv"):
        assert _table(tmp_path / "b" / name) == _table(tmp_path / "a" / name), name
    for spec in rp.runs_for("table3", 2, TINY_EPISODES, ["ppo-lag"]):
        a, b = rp.run_dir(tmp_path / "a", spec), rp.run_dir(tmp_path / "b", spec)
        assert (a / "episodes.csv").read_bytes() == (b / "episodes.csv").read_bytes()
    assert not list(runs.glob(".group-*")), "the group directory is removed"


def test_a_group_killed_between_its_seeds_summaries_before_any_checkpoint_resumes(tmp_path, monkeypatch):
    """Runs shorter than the checkpoint period: killed after one seed wrote summary.json and before
    the other did, the group never checkpointed. The rerun trains the group again from its start
    (the finished seed is kept as it was) instead of refusing the finished seed's directory for
    good and wiping the other's; the tables are those of an uninterrupted run."""
    monkeypatch.setattr(rp.RunSpec, "config", lambda spec: dataclasses.replace(small_config(spec), checkpoint_every=1000))
    kw = {"seeds": 2, "episodes": TINY_EPISODES, "methods": ["ppo-lag"], "progress": False, "log": lambda s: None}
    rp.reproduce(["table3"], tmp_path / "a", **kw)
    finish, calls = record_mod.RunRecord.finish, []

    def killed_after_one_summary(run, *args):
        calls.append(run)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return finish(run, *args)

    monkeypatch.setattr(record_mod.RunRecord, "finish", killed_after_one_summary)
    with pytest.raises(KeyboardInterrupt):
        rp.reproduce(["table3"], tmp_path / "b", **kw)
    monkeypatch.setattr(record_mod.RunRecord, "finish", finish)
    specs = rp.runs_for("table3", 2, TINY_EPISODES, ["ppo-lag"])
    assert [rp.is_finished(tmp_path / "b", s) for s in specs] == [True, False]
    rp.reproduce(["table3"], tmp_path / "b", **kw)
    for name in ("table3.md", "table3.csv"):
        assert _table(tmp_path / "b" / name) == _table(tmp_path / "a" / name), name
    for spec in specs:
        a, b = rp.run_dir(tmp_path / "a", spec), rp.run_dir(tmp_path / "b", spec)
        assert (a / "episodes.csv").read_bytes() == (b / "episodes.csv").read_bytes()


def test_a_finished_groups_leftover_directory_is_removed(tmp_path):
    (spec0, spec1) = rp.runs_for("table3", 2, TINY_EPISODES, ["ppo-lag"])
    for s in (spec0, spec1):
        rp.run_dir(tmp_path, s).mkdir(parents=True)
        (rp.run_dir(tmp_path, s) / "summary.json").write_text("{}")
    group = run_mod.group_dir([rp.run_dir(tmp_path, spec0), rp.run_dir(tmp_path, spec1)])
    group.mkdir()
    (group / "checkpoint.msgpack").write_bytes(b"x" * 1000)
    assert rp.started_groups(tmp_path, [spec0, spec1]) == [] and not group.exists()


# ---- every hyper-parameter checked where it is defined, one line, exit 2, nothing written --------
BAD_FLAGS = [
    ["--td3.gamma", "-1"], ["--td3.actor-lr", "-0.001"], ["--td3.policy-delay", "0"],
    ["--td3.learning-starts", "-100"], ["--r-goal", "inf"], ["--c-n", "nan"], ["--td3.batch-size", "0"],
    ["--td3.hidden", "0"], ["--td3.buffer-size", "0"], ["--d2spo.update-every", "0"], ["--seed", str(2**64)],
    ["--cbf.cbf-lr", "1e6"], ["--sac-lag.sac.tau", "0"], ["--ppo-lag.gamma", "1.5"], ["--anneal.k1", "0"],
    ["--rcrl.multiplier-lr", "nan"], ["--cpo.cg-damping", "-1"], ["--dt", "nan"],
]


@pytest.mark.parametrize("flag", BAD_FLAGS, ids=lambda f: f[0])
def test_bad_hyper_parameter_is_one_line_exit_2_and_writes_nothing(flag, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text("mine")  # the user's own file must survive a rejected train
    section = flag[0][2:].split(".")[0]
    algo = ["--algo", section] if section in ("td3-lag", "sac-lag", "rcrl", "ppo-lag", "cpo") else []  # its flags
    assert _exit_code(["train", *algo, "--episodes", "1", "--out", str(out), "--no-progress", *flag]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("d2spo: error:") and flag[0].split(".")[-1].lstrip("-") in err[0], err
    assert sorted(p.name for p in out.iterdir()) == ["config.json"] and (out / "config.json").read_text() == "mine"


def test_defaults_validate_and_configs_check_every_section():
    from d2spo.config import TrainConfig, config_from_dict, config_to_dict
    from d2spo.errors import ConfigError

    data = config_to_dict(TrainConfig())
    assert config_from_dict(data) == TrainConfig()
    data["sac_lag"]["sac"]["gamma"] = 0.0
    with pytest.raises(ConfigError, match=r"sac.gamma: must be in \(0, 1\]"):
        config_from_dict(data)  # a hand-edited config.json is refused like a flag


def test_rejected_layout_leaves_the_users_config_json(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text("mine")
    assert _exit_code(["train", "--episodes", "1", "--out", str(out), "--layout", "nope", "--no-progress"]) == 2
    assert (out / "config.json").read_text() == "mine"


# ---- the NaN guard ------------------------------------------------------------------------------
def _log(chunk_steps=4, num_envs=2, ret=1.0, metrics=None):
    import numpy as np

    from d2spo.algos.base import ChunkLog

    z = np.zeros((chunk_steps, num_envs))
    done = z.astype(bool)
    done[-1, 0] = True
    return ChunkLog(done, z + ret, z, z.astype(int), z.astype(int), z.astype(int), z.astype(int) + 3,
                    np.zeros((chunk_steps, num_envs, 2)), metrics or {}, np.bool_(False))


def test_params_finite_flags_a_nan_or_inf_in_any_floating_leaf():
    """The parameters' half of ``ChunkLog.nonfinite``: one flat check over the floating leaves of a
    tree that also holds integer leaves (an optimiser's step count), eager and jitted."""
    import jax
    import jax.numpy as jnp

    from d2spo.algos.base import params_finite

    tree = {"w": jnp.ones((3, 2)), "b": jnp.zeros(2, jnp.float32), "count": jnp.asarray(7, jnp.int32),
            "opt": (jnp.full((4,), 0.5, jnp.bfloat16), jnp.asarray(2.0))}
    for check in (params_finite, jax.jit(params_finite)):
        assert bool(check(tree))
        for bad in (jnp.nan, jnp.inf, -jnp.inf):
            assert not bool(check({**tree, "b": tree["b"].at[1].set(bad)}))
            assert not bool(check({**tree, "opt": (tree["opt"][0].at[3].set(bad), tree["opt"][1])}))
        assert bool(check({"count": jnp.asarray(1, jnp.int32)}))  # nothing floating: finite


def test_nan_guard_watches_returns_metrics_and_losses_before_writing(tmp_path):
    import numpy as np

    from d2spo.config import TrainConfig
    from d2spo.errors import NaNError

    cfg = TrainConfig(episodes=100, chunk_steps=4, num_envs=2)
    from d2spo.checkpoint import Checkpoints

    run = record_mod.RunRecord(cfg, tmp_path, None, Checkpoints(tmp_path, None))
    nan = np.nan
    run.record(_log(metrics={"losses/qf": np.array([1.0, nan, 1.0, nan])}), None)
    assert len(run.writer) == 1
    for bad in (_log(ret=nan), _log(metrics={"charts/lambda": np.array([np.inf] * 4)})):
        with pytest.raises(NaNError, match="no checkpoint was written"):
            run.record(bad, None)
    assert len(run.writer) == 1 and len((tmp_path / "episodes.csv").read_text().splitlines()) == 2
    run.record(_log(metrics={"losses/qf": np.full(4, nan)}), None)  # no update this chunk: no value yet
    with pytest.raises(NaNError, match="losses/qf has been NaN"):
        for _ in range(3):
            run.record(_log(metrics={"losses/qf": np.full(4, nan)}), None)
    run.tb and run.tb.close()


# ---- eval ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    import json

    import jax

    from d2spo.algos.td3 import TD3Config
    from d2spo.checkpoint import Checkpoints, run_fingerprint
    from d2spo.config import TrainConfig, config_to_dict
    from d2spo.envs import EnvConfig

    cfg = TrainConfig(algo="tlgrl", task="relaxed", episodes=2, num_envs=2, chunk_steps=20, eval_episodes=0,
                      env=EnvConfig(layout="relaxed", max_steps=20),
                      td3=TD3Config(hidden=(8,), batch_size=8, learning_starts=8, buffer_size=256))
    out = tmp_path_factory.mktemp("eval") / "run"
    out.mkdir()
    (out / "config.json").write_text(json.dumps(config_to_dict(cfg)))
    _, _, learner = run_mod.build(cfg)  # an untrained policy is as good as any for a refusal
    Checkpoints(out, run_fingerprint(out)).save(jax.jit(learner.init)(jax.random.PRNGKey(0)),
                                                {"episodes": 0, "env_steps": 0, "chunks": 0, "wall_seconds": 0.0})
    return out


@pytest.mark.parametrize("args", [["--episodes", "0"], ["--episodes", "-1"], ["--layout-seeds", "0"],
                                  ["--layout-seeds", "-1"], ["--layout-seeds", "3"], ["--seed", str(2**64)],
                                  ["--task", "phi2"],
                                  ["--episodes", str(10**10)]])  # terabytes in parallel: once a hang
def test_eval_refuses_bad_counts_and_keeps_the_earlier_result(args, tiny_run, capsys):
    earlier = tiny_run / "eval-relaxed-default.json"
    earlier.write_text("earlier")
    assert _exit_code(["eval", str(tiny_run), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("d2spo: error:"), err
    assert earlier.read_text() == "earlier"


# ---- unbounded work ---------------------------------------------------------------------------
def _ordered_visits(n: int) -> str:
    f = "F A1"
    for i in range(1, n):
        f = f"F(A{i % 3 + 1} & X {f})"
    return f


@pytest.mark.parametrize("formula", ["X " * 3000 + "a", " | ".join(f"a{i % 10}" for i in range(3000)),
                                     "(" * 400 + "a" + ")" * 400, " U ".join(["a"] * 150)],
                         ids=["next-3000", "or-3000", "parens-400", "until-150"])
def test_deep_or_long_formulas_are_refused_in_one_line(formula, capsys):
    assert _exit_code(["ltl", formula]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ("MAX_DEPTH" in err[0] or "MAX_SIZE" in err[0]), err


def test_a_long_ordered_task_is_refused_naming_the_limit(monkeypatch):
    import importlib

    from d2spo.ltl import AutomatonTooLarge, translate

    tr_mod = importlib.import_module("d2spo.ltl.translate")  # d2spo.ltl.translate is also the function

    assert len(translate(_ordered_visits(6)).delta) == 7  # short ones still translate
    monkeypatch.setattr(tr_mod, "MAX_TABLEAU_STEPS", 300_000)  # the same refusal, sooner
    # the work is bounded by the step count the refusal names (no wall-clock threshold)
    with pytest.raises(AutomatonTooLarge, match="MAX_TABLEAU_STEPS=300000"):
        translate(_ordered_visits(30))


def test_huge_arena_is_refused_up_front_or_stays_fast(monkeypatch):
    """A 40x `relaxed` (200 m a side): the geodesic shaping is refused up front (MAX_NODES); the
    euclidean one is built, and stays fast as a bound on the work, not a clock: every grid it builds
    is capped before it is built, the reachability check's at 1000 cells a side
    (``workspace.check_robot_fits``) and the task searches' at 400 (``routes._task_grid``), where a
    5 cm grid is 4000 a side (minutes and > 6 GB before)."""
    import math
    import sys

    from d2spo.envs import EnvConfig, layouts, make_env, workspace
    from d2spo.errors import ConfigError
    from d2spo.ltl.reward import RewardConfig

    with pytest.raises(ConfigError, match=r"MAX_NODES.*; is the layout in metres\?$"):  # a lab in centimetres
        make_env(EnvConfig(layout="relaxed", layout_scale=40.0), task="F A1")
    arena = tuple(40.0 * x for x in layouts.load("relaxed").arena)
    assert max(arena) / 0.05 >= 4000  # the premise: uncapped, a 5 cm grid would be this large
    caps, built, real = {"reachable_grid": 1000, "_task_grid": 400}, [], workspace.free_grid

    def capped(layout, robot_radius, resolution):
        caller, side = sys._getframe(1).f_code.co_name, max(math.ceil(x / resolution) for x in layout.arena)
        built.append(caller)
        assert tuple(layout.arena) == pytest.approx(arena) and side <= caps[caller], (caller, side)
        return real(layout, robot_radius, resolution)

    monkeypatch.setattr(workspace, "free_grid", capped)
    make_env(EnvConfig(layout="relaxed", layout_scale=40.0, reward=RewardConfig(shaping_metric="euclidean")),
             task="F A1")
    assert set(built) == set(caps)  # both searches ran, each on its capped grid


@pytest.mark.parametrize("word", ["phi3", "tuor3"])
def test_a_typo_of_a_task_name_is_one_warning_line(word, capsys):
    """`d2spo ltl phi3` once printed phi3's automaton as a proposition without a word; now one
    warning line names the tasks meant (the automaton is still printed: a proposition may be meant)."""
    import warnings

    from d2spo.console import show_warning

    with warnings.catch_warnings():
        warnings.showwarning = show_warning  # as d2spo's main installs it
        assert _exit_code(["ltl", word]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"d2spo: warning: {word!r} is not a task name"), err
    for quiet in ("phi1", "A1", "a", "(!A2 U A1) & F A2"):
        assert _exit_code(["ltl", quiet]) == 0
        assert not capsys.readouterr().err, quiet
