"""Zero-shot use of a generalist (d2spo/zero_shot.py, ``d2spo eval RUN --task F --layout L``) and its
runtime filter (algos/generalist.py)."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _counting import count_calls

from d2spo.algos.d2spo import D2SPOConfig
from d2spo.algos.generalist import build_generalist
from d2spo.algos.td3 import TD3Config
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig, generator, layouts
from d2spo.envs.generalist import view
from d2spo.envs.task_plan import slot_max_steps
from d2spo.errors import ConfigError
from d2spo.safety.cbf import CBFConfig
from d2spo.zero_shot import generalist_layout, task_tag

SMALL = {"td3": TD3Config(buffer_size=1024),
         "cbf": CBFConfig(transitions_capacity=1024, p_exp_capacity=1024, unsafe_capacity=1024)}
"""Small replay buffer and safety datasets: the runs here are never trained, and a checkpoint of the
default ones is 232 MB of zeros, written, copied and read by several tests (about 1 MB so)."""


def _cfg(**d2spo) -> TrainConfig:
    return TrainConfig(algo="d2spo", task="phi1", generalist=True, generalist_layouts=1, num_envs=4,
                       env=EnvConfig(preset="ideal"), d2spo=D2SPOConfig(pretrain=False, **d2spo), **SMALL)


@pytest.fixture(scope="module")
def gen_run(tmp_path_factory):
    """A generalist run directory with a checkpoint of zeros: as good as any policy for the plumbing."""
    from d2spo.checkpoint import Checkpoints, run_fingerprint
    from d2spo.config import config_to_dict

    cfg = _cfg()
    out = tmp_path_factory.mktemp("gen") / "run"
    out.mkdir()
    (out / "config.json").write_text(json.dumps(config_to_dict(cfg)))
    _, _, learner = build_generalist(cfg, [generator.generate(3)], 400)
    shapes = jax.eval_shape(learner.init, jax.random.PRNGKey(0))  # zeros: a robot that stands still
    Checkpoints(out, run_fingerprint(out)).save(jax.tree_util.tree_map(lambda t: jnp.zeros(t.shape, t.dtype), shapes),
                                                {"episodes": 0, "env_steps": 0, "chunks": 0, "wall_seconds": 0.0})
    return out


def _main(args: list[str]) -> int:
    from d2spo.cli import main

    try:
        return main(args)
    except SystemExit as e:
        return e.code


def _layout_file(tmp_path, **changes) -> str:
    data = layouts.load("paper").to_json()
    data.update(changes)
    path = tmp_path / "lay.json"
    path.write_text(json.dumps(data))
    return str(path)


def test_eval_runs_a_generalist_on_another_task_and_unseen_layouts_with_one_limit(gen_run, capsys, tmp_path):
    assert _main(["eval", str(gen_run), "--task", "phi2", "--layout", "random:11", "--layout-seeds", "2",
                  "--episodes", "4", "--runtime-filter", "False", "--plot", str(tmp_path / "ev.png"),
                  "--plot-episodes", "2"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "task 'phi2' (zero-shot)" in out and f"wrote {tmp_path / 'ev.png'}" in out
    assert (tmp_path / "ev.png").read_bytes()[:4] == b"\x89PNG"
    res = json.loads((gen_run / "eval-random11x2-ideal-phi2.json").read_text())
    assert "paths" not in res  # the trajectories go to the picture only
    assert res["task"] == "phi2" and res["layouts"] == ["random:11", "random:12"] and not res["runtime_filter"]
    assert [r["episodes"] for r in res["per_layout"]] == [4, 4]
    needs = [generalist_layout(EnvConfig(preset="ideal"), n, "phi2")[1] for n in res["layouts"]]
    assert res["max_steps"] == max([400] + needs)
    assert all(r["mean_length"] <= res["max_steps"] for r in res["per_layout"])


@pytest.mark.parametrize("args,match", [
    (["--task", "F B7", "--layout", "paper"], "propositions with no area"),
    (["--task", "phi2"], "give --layout"),
])
def test_eval_refuses_a_generalist_case_in_one_line(gen_run, capsys, args, match):
    assert _main(["eval", str(gen_run), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0], err


TWELVE = "tests/data/layouts/twelve-areas.json"


def test_a_generalist_runs_zero_shot_on_twelve_named_areas_with_shared_labels_and_a_pillar(gen_run, capsys):
    """12 areas with names of their own (three docks labelled dock, four desks labelled desk), a
    12 m x 8 m arena and a round pillar: the generalist trained on A1..A4 in square rooms of boxes
    is evaluated there on a task over those labels."""
    lay, _ = generalist_layout(EnvConfig(preset="ideal"), TWELVE, "F (desk & F (kitchen & F dock))")
    assert len(lay.areas) == 12 and len(lay.disks) == 1 and lay.arena == (12.0, 8.0)
    assert _main(["eval", str(gen_run), "--task", "F (desk & F (kitchen & F dock))", "--layout", TWELVE,
                  "--episodes", "2", "--runtime-filter", "False"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "(zero-shot)" in out
    (res,) = [json.loads(f.read_text()) for f in gen_run.glob("eval-twelve-areas-*.json")]
    assert res["per_layout"][0]["episodes"] == 2 and 0.0 <= res["completion_rate"] <= 1.0


@pytest.mark.parametrize("changes,task,match", [
    ({"arena": [21.0, 5.0]}, "phi1", "at most 20 m a side"),
    ({"obstacles": [], "areas": [{"name": f"A{i + 1}", "center": [0.45 + 0.55 * (i % 8), 2.6 + 1.0 * (i // 8)],
                                  "radius": 0.2} for i in range(17)]}, "F A1", "17 areas, more than the 16"),
    ({"areas": [{"name": f"A{i + 1}", "center": c, "radius": 0.35}
                for i, c in enumerate([[4.35, 0.8], [4.35, 1.2], [0.65, 4.35], [2.5, 2.5]])]}, "phi1", "overlap"),
    ({}, "F B7", "propositions with no area"),
    ({}, "F (A1 & A2)", "cannot be completed"),
])
def test_a_layout_or_task_the_generalist_cannot_do_is_refused(tmp_path, changes, task, match):
    with pytest.raises(ConfigError, match=match):
        generalist_layout(EnvConfig(), _layout_file(tmp_path, **changes), task)


def test_a_walled_off_area_is_refused(tmp_path):
    ring = [{"center": [4.35 + dx, 0.8 + dy], "half_extents": [hx, hy]}
            for dx, dy, hx, hy in [(0, 0.6, 0.65, 0.1), (0, -0.6, 0.65, 0.1), (-0.6, 0, 0.1, 0.65)]]
    obstacles = layouts.load("paper").to_json()["obstacles"][:1] + ring
    with pytest.raises(ConfigError, match="A1"):
        generalist_layout(EnvConfig(), _layout_file(tmp_path, obstacles=obstacles), "phi1")


def test_task_tags_name_tasks_and_hash_formulas():
    assert task_tag("phi2") == "phi2"
    tag = task_tag("F A1 & F A2")
    assert tag.startswith("f-") and tag == task_tag("F A1 & F A2") and tag != task_tag("F A2 & F A1")


def test_the_runtime_filter_keeps_clear_of_each_environments_own_layout():
    lays = [generator.generate(3), generator.generate(4)]
    _, params, learner = build_generalist(_cfg(runtime_filter=True), lays, 400, tasks_of=[0, 0])
    state, _ = jax.jit(learner.env.reset_batch, static_argnums=2)(jax.random.PRNGKey(1), params, 8)
    ctx = jax.jit(learner.filter_context)(state)
    for k in range(8):
        g = view(params, state.layout[k]).geom
        np.testing.assert_array_equal(np.asarray(ctx.box_lo[k]), np.asarray(g.box_lo))
        assert bool(jnp.all(ctx.mask[k]))
    assert len(set(np.asarray(state.layout).tolist())) == 2  # both layouts drawn: the contexts differ


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


def test_the_validation_layouts_are_held_out():
    from d2spo.config import VALIDATION_SEED
    from d2spo.envs import generator
    from d2spo.validation import Validation

    # a mixture of two tasks (phi1 and one random): 4 slots to solve, not 2 x 17 (12 s of the test)
    cfg = dataclasses.replace(_cfg(), validation_layouts=2, validation_episodes=4, generalist_tasks=1)
    env, params, learner = build_generalist(cfg, [generator.generate(0)], 400)
    v = Validation(cfg, env, params, learner)
    assert v.layouts == f"world:{VALIDATION_SEED}..{VALIDATION_SEED + 1}"  # the default training world
    want = [layouts.load(f"world:{VALIDATION_SEED + i}").arena[0] for i in range(2)]
    tasks = len(env.plan.names)  # every held-out layout with every task of the mixture
    np.testing.assert_allclose(np.asarray(v.params.bank.arena)[::tasks, 0], want, rtol=1e-6)
    assert np.asarray(v.params.bank.task).tolist() == list(range(tasks)) * 2


def test_a_zero_shot_eval_of_n_layouts_builds_one_generalist_and_n_envs(gen_run, monkeypatch):
    """``d2spo eval GENERALIST --layout random:S --layout-seeds N`` checks each of the N layouts once
    (one ``make_env`` each), builds the generalist once, and builds nothing else."""
    from d2spo import run as run_mod
    from d2spo import zero_shot
    from d2spo.evaluate import EvalConfig, evaluate_run

    calls = count_calls(monkeypatch, {"make_env": (zero_shot, "make_env"),
                                      "build_generalist": (zero_shot, "build_generalist"),
                                      "run.build": (run_mod, "build")})
    # the evaluation of the first test here (the same program: its compilation is shared)
    ecfg = EvalConfig(episodes=4, task="phi2", layout="random:11", layout_seeds=2, runtime_filter=False)
    res = evaluate_run(gen_run, ecfg)
    assert res["layouts"] == ["random:11", "random:12"]
    assert calls == {"make_env": 2, "build_generalist": 1, "run.build": 0}


def test_a_zero_shot_patrol_is_scored_against_each_layouts_route_optimal_visits(gen_run, capsys):
    """A recurrence evaluated zero-shot: per layout its route-optimal visits in the evaluation's step
    limit, and the visits as a fraction of them (0 for the standing-still policy of zeros)."""
    assert _main(["eval", str(gen_run), "--task", "patrol2", "--layout", "random:11", "--episodes", "2",
                  "--runtime-filter", "False"]) == 0
    out = capsys.readouterr().out
    assert "accepting visits per episode: 0.00 (0.0% of the route-optimal count)" in out
    res = json.loads((gen_run / "eval-random11-ideal-patrol2.json").read_text())
    (lay,) = res["per_layout"]
    env_cfg = EnvConfig(preset="ideal").resolved()
    checked = generalist_layout(EnvConfig(preset="ideal"), "random:11", "patrol2")
    from d2spo.envs.compiled_task import compile_task
    from d2spo.ltl import task_automaton, task_formula

    task = compile_task(task_automaton(task_formula("patrol2")), checked[0], "event", env_cfg.robot_radius)
    best = task.optimal_visits(res["max_steps"], env_cfg.dt, env_cfg.v_max * env_cfg.v_gain)
    assert lay["route_optimal_visits"] == best >= 2 and lay["visit_fraction"] == 0.0 == res["visit_fraction"]
    # the episodes of a recurrence are at least --recurrence-max-steps long, as a specialist's are
    assert res["max_steps"] == max(slot_max_steps(checked[0]), EnvConfig().recurrence_max_steps) == 1000
    # the table's row gives the visits against the layout's optimum, not a completion rate of 0
    assert "visits / optimum" in out and f"0.00 of {best} (0.0%)" in out and "completion_rate" not in out


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


def test_the_validation_scores_a_patrol_by_its_visits_against_the_slots_optimum():
    """With patrols in the mixture (``--generalist-patrols``) a validation episode of a patrol scores
    its visits over its slot's route-optimal count (at most 1, 0 with a collision); one of a task that
    completes scores 1 when it completes safely."""
    from d2spo.envs.compiled_task import compile_task
    from d2spo.envs.layouts import load
    from d2spo.ltl import task_automaton
    from d2spo.ltl.tasks import patrol_tasks
    from d2spo.validation import Validation

    cfg = dataclasses.replace(_cfg(), generalist_tasks=0, generalist_patrols=1, validation_layouts=1,
                              validation_episodes=4, generalist_world="random")
    env, params, learner = build_generalist(cfg, [generator.generate(3)], None)
    assert env.plan.recurrent == (False, True)
    val = Validation(cfg, env, params, learner)
    lay = load("random:50000")
    limit = int(np.asarray(val.params.bank.max_steps)[1])
    own = compile_task(task_automaton(patrol_tasks(1)[0]), lay, env.config.label_mode, env.config.robot_radius)
    best = own.optimal_visits(limit, env.config.dt, env.config.v_max * env.config.v_gain)
    assert best > 0 and val.optimum.tolist() == [0, best]
    # slots 0 (phi1) and 1 (the patrol): completed safely, collided, a patrol at half and at twice its optimum
    collided = np.array([False, True, False, False])
    completed = np.array([True, True, False, False])
    visits = np.array([0, 0, best // 2, 2 * best])
    slot = np.array([0, 0, 1, 1])
    val.rollout = lambda *_: (collided, completed, np.zeros(4), np.array([100, 50, 400, 400]), np.zeros((4, 2, 3)),
                              visits, slot)
    out = val(None)
    assert out["success_rate"] == pytest.approx((1 + 0 + (best // 2) / best + 1) / 4)
    assert out["mean_steps_success"] == 100.0


def test_a_generalist_trained_with_pairings_evaluates_zero_shot(tmp_path, capsys):
    """``--generalist-pairings`` sizes only the training bank: ``d2spo eval`` of such a run builds
    its one-task generalist as for any other (the pairing is not checked against a mixture of one)."""
    from d2spo.checkpoint import Checkpoints, run_fingerprint
    from d2spo.config import config_to_dict

    cfg = dataclasses.replace(_cfg(), generalist_tasks=1, generalist_pairings=2)
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text(json.dumps(config_to_dict(cfg)))
    _, _, learner = build_generalist(cfg, [generator.generate(3)], 400)
    shapes = jax.eval_shape(learner.init, jax.random.PRNGKey(0))
    Checkpoints(out, run_fingerprint(out)).save(jax.tree_util.tree_map(lambda t: jnp.zeros(t.shape, t.dtype), shapes),
                                                {"episodes": 0, "env_steps": 0, "chunks": 0, "wall_seconds": 0.0})
    assert _main(["eval", str(out), "--task", "phi2", "--layout", "random:11", "--episodes", "2",
                  "--runtime-filter", "False"]) == 0
    assert "completed" in capsys.readouterr().out  # the table's column


def test_eval_forbidden_range_hides_a_far_forbidden_area_in_its_own_file(gen_run, capsys, monkeypatch, tmp_path):
    """``d2spo eval GEN --forbidden-range R``: the generalist built for the evaluation sees a forbidden
    area only within R m (``EnvConfig.forbidden_range``), the result records R in its JSON, title and
    file name (``-rR``; ``-rinf`` for ``inf``, always seen); 0, nan or a specialist: one line, exit 2."""
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
    for run, asked in ((trained, None), (trained, float("inf")), (gen_run, float("inf"))):
        with pytest.raises(Seen):
            evaluate_run(run, EvalConfig(2, "random:11", task="phi2", forbidden_range=asked))
    assert seen[1:] == [1.2, None, None]
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
