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
from _generalist_run import gen_cfg, zeros_generalist_run
from _generalist_run import main as _main

from d2spo.algos.generalist import build_generalist
from d2spo.envs import EnvConfig, generator, layouts
from d2spo.envs.generalist import view
from d2spo.envs.task_plan import slot_max_steps
from d2spo.errors import ConfigError
from d2spo.evalfiles import task_tag
from d2spo.zero_shot import generalist_layout


@pytest.fixture(scope="module")
def gen_run(tmp_path_factory):
    """A generalist run directory with a checkpoint of zeros: as good as any policy for the plumbing."""
    return zeros_generalist_run(tmp_path_factory.mktemp("gen") / "run")


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
    _, params, learner = build_generalist(gen_cfg(runtime_filter=True), lays, 400, tasks_of=[0, 0])
    state, _ = jax.jit(learner.env.reset_batch, static_argnums=2)(jax.random.PRNGKey(1), params, 8)
    ctx = jax.jit(learner.filter_context)(state)
    for k in range(8):
        g = view(params, state.layout[k]).geom
        np.testing.assert_array_equal(np.asarray(ctx.box_lo[k]), np.asarray(g.box_lo))
        assert bool(jnp.all(ctx.mask[k]))
    assert len(set(np.asarray(state.layout).tolist())) == 2  # both layouts drawn: the contexts differ


def test_the_validation_layouts_are_held_out():
    from d2spo.config import VALIDATION_SEED
    from d2spo.envs import generator
    from d2spo.validation import Validation

    # a mixture of two tasks (phi1 and one random): 4 slots to solve, not 2 x 17 (12 s of the test)
    cfg = dataclasses.replace(gen_cfg(), validation_layouts=2, validation_episodes=4, generalist_tasks=1)
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


def test_the_validation_scores_a_patrol_by_its_visits_against_the_slots_optimum():
    """With patrols in the mixture (``--generalist-patrols``) a validation episode of a patrol scores
    its visits over its slot's route-optimal count (at most 1, 0 with a collision); one of a task that
    completes scores 1 when it completes safely."""
    from d2spo.envs.compiled_task import compile_task
    from d2spo.envs.layouts import load
    from d2spo.ltl import task_automaton
    from d2spo.ltl.tasks import patrol_tasks
    from d2spo.validation import Validation

    cfg = dataclasses.replace(gen_cfg(), generalist_tasks=0, generalist_patrols=1, validation_layouts=1,
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
    out = zeros_generalist_run(tmp_path / "run", dataclasses.replace(gen_cfg(), generalist_tasks=1, generalist_pairings=2))
    assert _main(["eval", str(out), "--task", "phi2", "--layout", "random:11", "--episodes", "2",
                  "--runtime-filter", "False"]) == 0
    assert "completed" in capsys.readouterr().out  # the table's column
