"""``d2spo eval``'s options on a generalist run (d2spo/evaluate.py, d2spo/evalfiles.py): which policy
runs (``--policy``), the episode limit (``--max-steps``), the layouts drawn (``--layout-seeds``) and
what the robot sees of a far forbidden area (``--forbidden-range``). The run is never trained
(tests/_generalist_run.py); tests/test_zero_shot.py checks the zero-shot evaluation itself."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from _generalist_run import main as _main
from _generalist_run import zeros_generalist_run

from d2spo.envs import EnvConfig
from d2spo.errors import ConfigError
from d2spo.zero_shot import generalist_layout


@pytest.fixture(scope="module")
def gen_run(tmp_path_factory):
    return zeros_generalist_run(tmp_path_factory.mktemp("gen") / "run")


def test_eval_runs_the_validated_policy_unless_the_last_is_asked_for(gen_run, tmp_path):
    import shutil

    from flax import serialization

    from d2spo.checkpoint import Checkpoints, load_checkpoint, run_fingerprint
    from d2spo.run import best_policy_path, load_policy

    run = tmp_path / "run"
    shutil.copytree(gen_run, run)
    cfg, learner, last, meta = load_policy(run)
    assert meta["policy"].startswith("last")  # no validation in this run
    ones = jax.tree_util.tree_map(lambda t: np.ones(t.shape, t.dtype), last)
    best_policy_path(run).write_bytes(serialization.to_bytes(ones))
    carry, meta = load_checkpoint(run, jax.eval_shape(learner.init, jax.random.PRNGKey(0)), run_fingerprint(run))
    Checkpoints(run, run_fingerprint(run)).save(carry, dict(meta, best={"episodes": 7, "success_rate": 0.5}))
    _, _, best, meta = load_policy(run)
    assert meta["policy"] == "best on validation (after 7 episodes)"
    assert all(np.all(x == 1) for x in jax.tree_util.tree_leaves(best))
    _, _, again, meta = load_policy(run, "last")
    assert meta["policy"].startswith("last") and all(np.all(x == 0) for x in jax.tree_util.tree_leaves(again))
    with pytest.raises(ConfigError, match="best, last"):
        load_policy(run, "first")
    # shared without its checkpoints (the replay buffer makes them hundreds of MB): config.json,
    # summary.json and the validated policy are enough for "best"; "last" needs a checkpoint
    from d2spo.errors import RunDirError

    shared = tmp_path / "shared"
    shared.mkdir()
    for name in ("config.json", best_policy_path(run).name):
        shutil.copy(run / name, shared / name)
    with pytest.raises(RunDirError):  # no summary.json: nothing says which policy this is
        load_policy(shared)
    (shared / "summary.json").write_text(json.dumps({"episodes": 10, "validation": {"best": {"episodes": 7}}}))
    _, _, best, meta = load_policy(shared)
    assert meta["policy"] == "best on validation (after 7 episodes)" and meta["episodes"] == 10
    assert all(np.all(x == 1) for x in jax.tree_util.tree_leaves(best))
    with pytest.raises(RunDirError, match="a shared run without its checkpoints: its kept policy"):
        load_policy(shared, "last")  # the message says why there is none and what runs instead
    # ... or with the checkpoints' manifests but not their state files: the same, with a warning
    from d2spo.errors import RunDirWarning

    for name in ("checkpoint.json", "checkpoint.prev.json"):
        if (run / name).exists():
            shutil.copy(run / name, shared / name)
    with pytest.warns(RunDirWarning, match="no usable checkpoint.*the validated policy and summary.json"):
        _, _, best, meta = load_policy(shared)
    assert meta["policy"] == "best on validation (after 7 episodes)"
    with pytest.raises(RunDirError, match="no usable checkpoint"):
        load_policy(shared, "last")
    # a damaged validated policy, or one of other shapes, is one RunDirError line, not a traceback
    # from flax (or a policy of the wrong shapes handed on); the last checkpoint's is still there
    good = best_policy_path(run).read_bytes()
    best_policy_path(run).write_bytes(good[:100])
    with pytest.raises(RunDirError, match=r"policy-best.msgpack cannot be restored .*--policy last"):
        load_policy(run)
    assert load_policy(run, "last")[3]["policy"].startswith("last")
    best_policy_path(shared).write_bytes(good[:100])  # and where no checkpoint is left to fall back on
    with pytest.warns(RunDirWarning), pytest.raises(RunDirError, match="cannot be restored"):
        load_policy(shared)
    wide = jax.tree_util.tree_map(lambda t: np.ones((*t.shape, 2), t.dtype), last)
    best_policy_path(run).write_bytes(serialization.to_bytes(wide))
    with pytest.raises(RunDirError, match="where this config builds .*another config"):
        load_policy(run)


def test_eval_max_steps_sets_the_episode_limit_and_the_optimum_with_it(gen_run, capsys):
    """``d2spo eval --max-steps N``: episodes of N steps, the route-optimal count of N steps, its own
    file beside the run's-limit evaluation, the limit in the table's title; a limit too short for one
    accepting visit is one line and exit 2 before anything is built."""
    base = gen_run / "eval-random11-ideal-patrol2.json"
    if not base.is_file():  # the test above writes it; alone, this one does
        assert _main(["eval", str(gen_run), "--task", "patrol2", "--layout", "random:11", "--episodes", "2",
                      "--runtime-filter", "False"]) == 0
    default = json.loads(base.read_text())
    limit = 2 * default["max_steps"]
    capsys.readouterr()
    assert _main(["eval", str(gen_run), "--task", "patrol2", "--layout", "random:11", "--episodes", "2",
                  "--runtime-filter", "False", "--max-steps", str(limit)]) == 0
    assert f"of {limit} steps" in " ".join(capsys.readouterr().out.split())  # the title, however rich wraps it
    res = json.loads((gen_run / f"eval-random11-ideal-patrol2-T{limit}.json").read_text())
    assert res["max_steps"] == limit and res["max_steps_given"] and not default["max_steps_given"]
    env_cfg = EnvConfig(preset="ideal").resolved()
    from d2spo.envs.compiled_task import compile_task
    from d2spo.ltl import task_automaton, task_formula

    checked = generalist_layout(EnvConfig(preset="ideal"), "random:11", "patrol2")
    task = compile_task(task_automaton(task_formula("patrol2")), checked[0], "event", env_cfg.robot_radius)
    best = task.optimal_visits(limit, env_cfg.dt, env_cfg.v_max * env_cfg.v_gain)
    assert res["per_layout"][0]["route_optimal_visits"] == best > default["per_layout"][0]["route_optimal_visits"]
    assert _main(["eval", str(gen_run), "--task", "patrol2", "--layout", "random:11", "--max-steps", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "too short for one accepting visit" in err[0], err
    assert _main(["eval", str(gen_run), "--max-steps", "0"]) == 2
    assert "--max-steps: " in capsys.readouterr().err


def test_layout_seeds_walks_every_drawn_family_and_is_refused_elsewhere():
    """``--layout-seeds N`` names N layouts of any drawn family (docs/layouts.md promises it for
    ``zones``); on a fixed layout it is one line, not a silent single layout."""
    from d2spo.errors import ConfigError
    from d2spo.evaluate import EvalConfig

    assert EvalConfig(layout="world:50000", layout_seeds=3).layouts() == ["world:50000", "world:50001", "world:50002"]
    assert EvalConfig(layout="zones:7", layout_seeds=2).layouts() == ["zones:7", "zones:8"]
    assert EvalConfig(layout="random5", layout_seeds=2).layouts() == ["random5:0", "random5:1"]
    assert EvalConfig(layout="paper").layouts() == ["paper"]
    for layout in ("paper", None, "worlds:3", "tests/data/layouts/handmade/corridor-5.json"):
        with pytest.raises(ConfigError, match="layout_seeds: only applies with a drawn layout"):
            EvalConfig(layout=layout, layout_seeds=2)


def test_eval_forbidden_range_hides_a_far_forbidden_area_in_its_own_file(gen_run, capsys, monkeypatch, tmp_path):
    """``d2spo eval GEN --forbidden-range R``: the generalist built for the evaluation sees a forbidden
    area only within R m (``EnvConfig.forbidden_range``), the result records R in its JSON, title and
    file name (``-rR``; ``-rinf`` for ``inf``, always seen); without it, the range the run trained with,
    else the robot's lidar range (``zero_shot.seen_forbidden_range``); 0, nan or a specialist: one line,
    exit 2."""
    from d2spo import plots, zero_shot
    from d2spo.console import forbidden_note
    from d2spo.evalfiles import evaluation_path
    from d2spo.evaluate import EvalConfig, evaluate_run

    seen, titles = [], []
    build = zero_shot.generalist_on
    monkeypatch.setattr(zero_shot, "generalist_on", lambda cfg, env_cfg, *a: seen.append(env_cfg.forbidden_range)
                        or build(cfg, env_cfg, *a))
    monkeypatch.setattr(plots, "evaluation_figure", lambda path, paths, per, title: titles.append(title))
    assert _main(["eval", str(gen_run), "--task", "phi2", "--layout", "random:11", "--episodes", "2",
                  "--runtime-filter", "False", "--forbidden-range", "1.2", "--plot", str(tmp_path / "p.png")]) == 0
    assert seen == [1.2] and "forbidden area seen within 1.2 m" in " ".join(capsys.readouterr().out.split())
    assert titles[0].endswith(", forbidden area seen within 1.2 m"), titles  # the picture says it too
    res = json.loads((gen_run / "eval-random11-ideal-phi2-r1.2.json").read_text())
    assert res["forbidden_range"] == 1.2 and res["forbidden_range_given"]
    assert forbidden_note({**res, "forbidden_range": None}) == ", forbidden area always seen"  # inf asked

    class Seen(Exception):
        pass

    def stop(cfg, env_cfg, *a):  # what the evaluation would build; nothing is compiled
        seen.append(env_cfg.forbidden_range)
        raise Seen

    monkeypatch.setattr(zero_shot, "generalist_on", stop)
    trained = tmp_path / "trained-r"  # a generalist trained with R = 1.2, evaluated as trained and with inf
    trained.mkdir()
    cfg = json.loads((gen_run / "config.json").read_text())
    cfg["env"]["forbidden_range"] = 1.2
    (trained / "config.json").write_text(json.dumps(cfg))
    cfg["env"]["forbidden_range"], cfg["env"]["sensing_radius"] = None, 2.0
    wide = tmp_path / "lidar-2m"  # trained without a range, by a robot whose lidar sees 2 m
    wide.mkdir()
    (wide / "config.json").write_text(json.dumps(cfg))
    for run, asked in ((trained, None), (trained, float("inf")), (gen_run, float("inf")), (gen_run, None),
                       (wide, None), (wide, 0.5)):
        with pytest.raises(Seen):
            evaluate_run(run, EvalConfig(2, "random:11", task="phi2", forbidden_range=asked))
    # as trained with R; inf: always; trained without R: the lidar's range unless asked
    assert seen[1:] == [1.2, None, None, 1.2, 2.0, 0.5]
    assert forbidden_note({**res, "forbidden_range": None, "forbidden_range_given": False}) == ""
    assert evaluation_path(gen_run, {**res, "forbidden_range": None}).name == "eval-random11-ideal-phi2-rinf.json"
    assert evaluation_path(gen_run, {**res, "forbidden_range_given": False}).name == "eval-random11-ideal-phi2.json"
    spec = tmp_path / "spec"
    spec.mkdir()
    (spec / "config.json").write_text((gen_run / "config.json").read_text().replace('"generalist": true',
                                                                                    '"generalist": false'))
    for args, match in ((["--forbidden-range", "0"], "--forbidden-range: must be a number > 0 (inf: always seen)"),
                        (["--forbidden-range", "nan"], "--forbidden-range: must be a number > 0 (inf: always seen)"),
                        (["--layout", "paper", "--forbidden-range", "1.2"], "this run is a specialist")):
        assert _main(["eval", str(gen_run if "paper" not in args else spec), *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0], err
