"""Tasks no finite run completes (issue #34): a "never" part ends the episode at its completed
state; a recurrence is scored by its accepting visits (docs/ltl.md, "Tasks no finite run completes")."""

from __future__ import annotations

import json
from functools import cache

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.envs import EnvConfig, make_env
from d2spo.ltl import Automaton, BuchiTask, NoDeterministicBuchi, task_automaton
from d2spo.ltl.reward import RewardConfig
from d2spo.record import visits_per_episode
from d2spo.runio import read_episodes

NEVER = "G !A4 & F A1"
PATROL = "G F A1 & G F A3 & G !A4"
STOP = jnp.zeros(2)


@cache
def scripted(task: str, shaping: float = 0.0):
    """Layout paper, no unmodelled effects, no start jitter, straight-line shaping (or none)."""
    cfg = EnvConfig(preset="ideal", start_jitter_xy=0.0, start_jitter_theta=0.0, max_steps=300,
                    reward=RewardConfig(shaping=shaping, shaping_metric="euclidean"))
    env, params = make_env(cfg, task)
    return env, params, jax.jit(env.step)


def visit_areas(task: str, names: list[str], shaping: float = 0.0):
    """Teleport the robot into each named area of `paper` in turn; one step each."""
    env, params, step = scripted(task, shaping)
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    centre = {a.name: a.center for a in env.layout.areas}
    out = []
    for name in names:
        state = state.replace(pose=state.pose.at[:2].set(jnp.asarray(centre[name], jnp.float32)))
        state, _, reward, _, done, info = step(jax.random.key(0), state, STOP, params)
        out.append((float(reward), bool(done), info))
    return params, out


def test_the_monitor_stays_for_tasks_with_a_good_prefix_and_the_dba_serves_the_others():
    assert type(task_automaton("F (A1 & F A2)")) is Automaton
    never, patrol = task_automaton(NEVER), task_automaton(PATROL)
    assert isinstance(never, BuchiTask) and len(never.accepting) == 1  # A1 reached, A4 never entered
    assert isinstance(patrol, BuchiTask) and not patrol.accepting and any(map(any, patrol.visits))
    with pytest.raises(NoDeterministicBuchi):
        task_automaton("F G A1")


def test_a_never_part_completes_when_its_target_is_reached_and_is_rejected_by_the_forbidden_area():
    params, [(reward, done, info)] = visit_areas(NEVER, ["A1"])
    assert done and bool(info["terminated"]) and bool(info["completed"])
    assert reward == pytest.approx(params.reward.r_goal) and "accepting_visit" not in info  # a never part has none
    params, [(reward, done, info)] = visit_areas(NEVER, ["A4"])
    assert done and bool(params.aut.rejecting[info["q_next"]]) and not bool(info["completed"])
    assert reward == pytest.approx(-params.reward.r_reject)


def test_a_patrol_counts_its_accepting_visits_and_runs_on():
    params, steps = visit_areas(PATROL, ["A1", "A3", "A1", "A3"])
    cfg, dist = params.reward, params.aut.distance
    assert [r for r, _, _ in steps] == pytest.approx([cfg.c_p, cfg.r_goal, cfg.c_p, cfg.r_goal])
    assert [bool(i["accepting_visit"]) for _, _, i in steps] == [False, True, False, True]
    assert not any(done for _, done, _ in steps) and not any(bool(i["completed"]) for _, _, i in steps)
    # after each visit the distance to the next one restarts: waiting for A1 again, 2 areas away
    assert [int(dist[i["q_next"]]) for _, _, i in steps] == [1, 2, 1, 2]


def test_the_visit_is_rewarded_with_shaping_on_although_the_distance_jumps_back_up():
    _, steps = visit_areas(PATROL, ["A1", "A3"], shaping=10.0)
    assert all(r > 0 for r, _, _ in steps)
    _, [(entering_a4, done, _)] = visit_areas(PATROL, ["A4"], shaping=10.0)
    assert entering_a4 < 0 and done


def test_a_recurrence_trains_with_the_per_state_fields_toward_its_next_visit():
    env, params = make_env(EnvConfig(), PATROL)  # the default shaping: one field per automaton state
    task, aut = env.task, env.task.automaton
    assert task.recurrence and np.isfinite(task.route_length)
    waiting_a3 = aut.delta[aut.initial][aut.letter(["A1"])]  # A1 entered: A3 is the next visit
    assert aut.visits[waiting_a3][aut.letter(["A3"])] and task.fields.targets[waiting_a3] == ("A3",)
    # the visit's area counts as progress: annealed early in training, the 'geodesic' metric's target
    assert np.asarray(params.advance)[waiting_a3].tolist() == [a.name == "A3" for a in env.layout.areas]
    a3 = next(a for a in env.layout.areas if a.name == "A3")
    # in the state that waits for A3 the field leads to A3 (the visit), and is 0 at its rim
    iy, ix = (int(round(c / 0.05)) for c in (a3.center[1], a3.center[0] + a3.radius + 0.1))
    far = task.fields.field[waiting_a3]
    assert task.fields.target_cells[waiting_a3][int(a3.center[1] / 0.05), int(a3.center[0] / 0.05)]
    assert 0.0 < far[iy, ix] < 0.3 < far[int(0.6 / 0.05), int(0.6 / 0.05)]


def test_the_route_optimal_visits_follow_the_lap_between_two_areas(tmp_path):
    """On an open 6 m arena with A1 at x=1 and A2 at x=5 (radius 0.4, the robot's 0.15 m aside), a lap
    A1 -> A2 -> A1 is twice the gap between the areas' rims, about 2 * (4 - 0.8) = 6.4 m."""
    from d2spo.envs import routes
    from d2spo.envs.workspace import Area, Layout

    layout = Layout("lap", (6.0, 2.0), (1.0, 1.0, 0.0), (), (Area("A1", (1.0, 1.0), 0.4), Area("A2", (5.0, 1.0), 0.4)))
    aut = task_automaton("GF A1 & GF A2")
    lengths = routes.visit_lengths(aut, layout, "event", 0.15, 40.0)
    laps = np.diff(lengths)
    assert len(lengths) >= 6 and np.all(laps > 0)
    assert laps[1:] == pytest.approx(2 * 3.2, abs=0.15)
    assert lengths[0] == pytest.approx(4.6 - 1.0, abs=0.15)  # A1 is read at the start: from its centre to A2
    assert routes.visit_lengths(aut, layout, "event", 0.15, lengths[2] - 0.01) == lengths[:2]


def test_a_gap_the_barriers_margin_closes_gives_no_visits_keeping_it():
    """A wall across a 6 m x 3 m arena with a 0.45 m gap between A1 and A2: a robot of radius 0.15
    fits through (the route-optimal count is the laps), one that keeps the barrier's 0.3 m does not
    (``route_optimal_visits_margin`` 0), which ``d2spo eval`` then names; on the open arena the two
    counts agree."""
    from types import SimpleNamespace

    from d2spo.envs.compiled_task import compile_task
    from d2spo.envs.workspace import Area, Layout, Obstacle
    from d2spo.rollout import visit_optimum

    areas = (Area("A1", (1.0, 1.5), 0.4), Area("A2", (5.0, 1.5), 0.4))
    gap = 0.45  # the wall spans y in [0, 1.275] and [1.725, 3]
    wall = (Obstacle((3.0, (1.5 - gap / 2) / 2), (0.1, (1.5 - gap / 2) / 2)),
            Obstacle((3.0, 3.0 - (1.5 - gap / 2) / 2), (0.1, (1.5 - gap / 2) / 2)))
    cfg = SimpleNamespace(dt=0.1, v_max=0.95, v_gain=1.0)
    aut = task_automaton("GF A1 & GF A2")
    walled = compile_task(aut, Layout("gap", (6.0, 3.0), (1.0, 1.5, 0.0), wall, areas), "event", 0.15)
    out = visit_optimum(walled, 600, cfg, 2.0, margin=0.3)
    assert out["route_optimal_visits"] >= 5 and out["route_optimal_visits_margin"] == 0 and out["margin"] == 0.3
    assert out["visit_fraction"] == pytest.approx(2.0 / out["route_optimal_visits"])
    open_ = compile_task(aut, Layout("open", (6.0, 3.0), (1.0, 1.5, 0.0), (), areas), "event", 0.15)
    both = visit_optimum(open_, 600, cfg, 2.0, margin=0.3)
    assert both["route_optimal_visits_margin"] == both["route_optimal_visits"] >= 5
    assert "route_optimal_visits_margin" not in visit_optimum(open_, 600, cfg, 2.0)  # no barrier, no margin


def test_a_tiny_training_on_a_never_part_writes_no_visits(tmp_path, capsys):
    from d2spo.cli import main

    out = tmp_path / "run"  # small networks: what is asserted is the bookkeeping, not the learning
    status = main(["train", "--algo", "tlgrl", "--task", NEVER, "--layout", "paper", "--episodes", "8",
                   "--num-envs", "2", "--eval-episodes", "2", "--td3.hidden", "16", "16", "--td3.batch-size", "32",
                   "--no-progress", "--out", str(out)])
    assert status == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["episodes"] == 8 and "accepting_visits_per_episode" not in summary  # a never part has none
    assert "accepting_visits_per_episode" not in summary["eval"]


def test_visits_are_counted_per_episode_across_chunks():
    # two envs; env 0 ends at step 1, env 1 at step 2; env 0 carries 2 visits from the chunk before
    visit = [[1, 0], [0, 1], [1, 0]]
    done = [[0, 0], [1, 0], [0, 1]]
    assert visits_per_episode(visit, done, None)[0] == [1, 1]
    counts, running = visits_per_episode(visit, done, np.array([2, 0]))
    assert counts == [3, 1] and running.tolist() == [1, 0]


def _visit_log(done: np.ndarray, visit: np.ndarray):
    from d2spo.algos.base import ChunkLog

    z = np.zeros(done.shape)
    return ChunkLog(done=done, ep_return=z, ep_cost=z, ep_length=z + 5, ep_collided=z > 0, ep_completed=z > 0,
                    ep_completed_relaxed=z > 0, ep_end_xy=np.zeros(done.shape + (2,)), metrics={},
                    nonfinite=np.array(False), accepting_visit=visit)


def test_accepting_visits_survive_a_resume_and_reach_tensorboard(tmp_path):
    """The visits of an episode that spans a checkpoint are counted on after a resume (the counts
    travel in the checkpoint's meta), and every finished episode's count is a TensorBoard scalar."""
    from d2spo.config import TrainConfig
    from d2spo.record import RunRecord

    cfg = TrainConfig(algo="tlgrl", task="G F A1 & G F A3", episodes=10, num_envs=2, chunk_steps=4,
                      env=EnvConfig(layout="paper", reward=RewardConfig(shaping_metric="geodesic")))
    done = np.array([[False, False], [True, False], [False, False], [False, True]])
    visit = np.array([[True, True], [True, False], [False, True], [True, True]])
    logs = [_visit_log(done, visit), _visit_log(done, visit[::-1])]
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    whole = RunRecord(cfg, tmp_path / "a", None, checkpoints=None, visits=True)
    for log in logs:
        whole.record(log, None)
    first = RunRecord(cfg, tmp_path / "b", None, checkpoints=None, visits=True)
    first.record(logs[0], None)
    meta = json.loads(json.dumps(first.meta))  # as a checkpoint keeps it
    resumed = RunRecord(cfg, tmp_path / "b", meta, checkpoints=None, visits=True)
    resumed.record(logs[1], None)
    # first chunk: env 0 ends at step 1 after 2 visits, env 1 at step 3 after 3, env 0 has 1 more
    # in its unfinished episode; second chunk: env 0 ends at step 1 after that 1 + 1, env 1 at step 3
    # after 3 (without the carried count the resumed run would say 1 for episode 2)
    assert whole.visits == resumed.visits == [2, 3, 2, 3]
    # ... and episodes.csv ends each row with them, the resumed file byte for byte the whole one's
    csv_a, csv_b = (tmp_path / d / "episodes.csv" for d in "ab")
    assert csv_a.read_bytes() == csv_b.read_bytes()
    assert csv_a.read_text().splitlines()[0].endswith(",end_y,accepting_visits")
    assert [r[-1] for r in read_episodes(csv_a)] == [2, 3, 2, 3]
    whole.tb.close()
    from _tb import tb_scalars

    values = tb_scalars(tmp_path / "a" / "tb")["episode/accepting_visits"]
    assert values == [(0, 2.0), (1, 3.0), (2, 2.0), (3, 3.0)]


def test_a_patrol_file_without_the_visits_column_resumes_without_it(tmp_path):
    """A patrol trained before episodes.csv had the column keeps its columns when it resumes; a
    co-safe task's file never has it."""
    from d2spo.runio import EPISODE_FIELDS, EpisodeWriter

    path = tmp_path / "episodes.csv"
    old = EpisodeWriter(path)  # the columns before
    old.append([(0, 1.0, 0.0, 0, 0, 0, 5, 0.0, 0.0)])
    resumed = EpisodeWriter(path, keep_rows=1, visits=True)
    assert not resumed.visits and path.read_text().splitlines()[0] == ",".join(EPISODE_FIELDS)
    new = EpisodeWriter(tmp_path / "new.csv", visits=True)
    new.append([(0, 1.0, 0.0, 0, 0, 0, 5, 0.0, 0.0, 4)])
    assert EpisodeWriter(tmp_path / "new.csv", keep_rows=1).visits  # the file's columns, not the caller's
    assert read_episodes(tmp_path / "new.csv") == [(0, 1.0, 0.0, 0, 0, 0, 5, 0.0, 0.0, 4)]


def test_the_printed_automaton_names_the_accepting_visits():
    text = task_automaton("GF A1 & GF A3 & G !A4").pretty()
    assert text.splitlines()[-3:] == ["accepting visits:", "  in 0: A1 & A3 & !A4", "  in 1: A3 & !A4"]
    never = task_automaton("G !A4 & F A1").pretty().splitlines()
    assert never[-2] == "accepting visits: none"
    # its completed state is no good prefix of the formula (A4 may still come): it says what it is
    assert "1      completed  0         G !A4" in never and never[-1].startswith("completed: the goal is met")
    assert "accepting_means" in task_automaton("G !A4 & F A1").to_json()
    assert "accepting_means" not in task_automaton("GF A1 & GF A3").to_json()


def test_the_summary_table_scores_a_recurrence_by_its_visits_not_completion():
    from rich.console import Console

    from d2spo.progress import summary_table

    base = {"episodes": 10, "env_steps": 3000, "wall_seconds": 1.0, "env_steps_per_second": 3000.0,
            "window_episodes": 10, "safety_rate": 1.0, "completion_rate": 0.0, "completion_rate_relaxed": 0.0,
            "accepting_visits_per_episode": 2.5, "eval": {"episodes": 5, "safety_rate": 1.0, "completion_rate": 0.0,
                                                         "accepting_visits_per_episode": 3.0}}
    console = Console(width=200, record=True)
    console.print(summary_table({**base, "route_optimal_visits": 5, "visit_fraction": 0.5}, "patrol"))
    text = console.export_text()
    assert "completion" not in text and "2.50 of 5 (50.0%)" in text and "3.00" in text
    console.print(summary_table(base, "a Büchi task on a bank of layouts: no optimum, completion shown"))
    assert "completion rate (last 10)" in console.export_text()


def test_a_patrol_on_one_layout_keeps_the_policy_that_visits_most(tmp_path, capsys):
    """A patrol's last policy can visit far less often than its training did, so a run on one layout
    validates its policy every ``--validate-every`` episodes and keeps the best (``--patrol-validation``
    episodes on the training layout); ``d2spo eval`` and summary.json's eval_best use it."""
    from d2spo.cli import main

    out = tmp_path / "run"  # small networks: what is asserted is the bookkeeping, not the learning
    status = main(["train", "--algo", "tlgrl", "--task", PATROL, "--layout", "paper", "--episodes", "8",
                   "--num-envs", "2", "--max-steps", "300", "--eval-episodes", "2", "--td3.hidden", "16", "16",
                   "--td3.batch-size", "32", "--validate-every", "2", "--patrol-validation", "3",
                   "--no-progress", "--out", str(out)])
    seen = capsys.readouterr()
    assert status == 0, seen.err
    summary = json.loads((out / "summary.json").read_text())
    val = summary["validation"]
    assert val["layouts"] == "paper" and val["episodes"] == 3
    history = val["history"]
    assert len(history) >= 3 and [h["episodes"] for h in history] == sorted({h["episodes"] for h in history})
    top = max(h["success_rate"] for h in history)  # the best score; of equals, the latest
    assert val["best"] == [h for h in history if h["success_rate"] == top][-1]
    assert (out / "policy-best.msgpack").is_file() and "eval_best" in summary
    assert "kept policy (episode" in seen.out
    assert main(["eval", str(out), "--episodes", "2"]) == 0
    res = json.loads(next(out.glob("eval-paper-*-best.json")).read_text())
    assert res["policy"] == f"best on validation (after {val['best']['episodes']} episodes)"
    # interrupted and resumed, the run validates the same policies and keeps the same one
    from d2spo.run import load_run_config
    from d2spo.train import train

    cut = tmp_path / "cut"
    assert train(load_run_config(out), cut, stop_after_chunks=2) is None
    before = json.loads((cut / "checkpoint.json").read_text())["meta"]["validation"]
    assert 0 < len(before) < len(history)  # validated before the cut, and after it
    events = []
    resumed = train(load_run_config(out), cut, resume=True, progress=events.append)
    assert resumed["validation"] == {**val, "seconds": resumed["validation"]["seconds"]}
    chunks = [e for e in events if "phase" not in e]  # a patrol's progress line shows no completion
    assert chunks and all(e.get("recurrence") is True and "accepting_visits" in e for e in chunks)
    assert (cut / "policy-best.msgpack").read_bytes() == (out / "policy-best.msgpack").read_bytes()
    # a co-safe task keeps its last policy, as does a patrol with --patrol-validation 0
    from d2spo.config import TrainConfig
    from d2spo.run import build
    from d2spo.validation import PatrolValidation, validation_for

    for task, n, kind in ((PATROL, 3, PatrolValidation), (NEVER, 3, type(None)), (PATROL, 0, type(None))):
        cfg = TrainConfig(algo="tlgrl", task=task, patrol_validation=n, env=EnvConfig(layout="paper", max_steps=300))
        assert isinstance(validation_for(cfg, *build(cfg)), kind), (task, n)


def test_a_patrols_validation_scores_visits_against_the_layouts_optimum():
    """An episode scores its visits over the layout's route-optimal count, at most 1, and 0 when it
    collided."""
    from d2spo.config import TrainConfig
    from d2spo.run import build
    from d2spo.validation import PatrolValidation

    cfg = TrainConfig(algo="tlgrl", task=PATROL, patrol_validation=4, env=EnvConfig(layout="paper", max_steps=600))
    env, params, learner = build(cfg)
    val = PatrolValidation(cfg, env, params, learner)
    best = env.task.optimal_visits(600, env.config.dt, env.config.v_max * env.config.v_gain)
    assert val.optimum == best > 2
    visits = np.array([best // 2, 2 * best, best, 1])
    collided = np.array([False, False, True, False])
    val.rollout = lambda *_: (collided, np.zeros(4, bool), np.zeros(4), np.full(4, 600), None, visits)
    out = val(None)
    assert out["success_rate"] == pytest.approx(((best // 2) / best + 1 + 0 + 1 / best) / 4)
    assert out["mean_steps_success"] is None and out["accepting_visits_per_episode"] == visits.mean()
    assert out["safety_rate"] == 0.75
