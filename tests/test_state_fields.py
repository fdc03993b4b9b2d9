"""The shaping distance per automaton state (envs/state_fields.py), the task compiled on a layout
(envs/compiled_task.py), its routes (envs/routes.py) and the pre-flight checks (envs/preflight.py)."""

from __future__ import annotations

import hashlib
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.envs import EnvConfig, geodesic, layouts, make_env, preflight, routes, state_fields
from d2spo.envs.compiled_task import compile_task
from d2spo.errors import ConfigError, TaskWarning
from d2spo.ltl import task_formula, translate
from d2spo.ltl.reward import RewardConfig
from d2spo.ltl.tasks import SUITE

PAPER = layouts.load("paper")


def _split(task: str, layout=PAPER) -> dict[int, tuple[tuple[str, ...], tuple[str, ...]]]:
    compiled = compile_task(translate(task_formula(task)), layout, "event", 0.15)
    targets, forbidden = (state_fields.named_areas(compiled.automaton, layout, compiled.roles, role)
                          for role in (state_fields.TARGET, state_fields.FORBIDDEN))
    return {q: (t, f) for q, (t, f) in enumerate(zip(targets, forbidden, strict=True))}


def _fields(aut, layout, costs: dict | None = None) -> state_fields.StateFields:
    """The per-state fields of ``aut`` on ``layout`` (default: clearance 0.3 m, no collision tier)."""
    return compile_task(aut, layout, "event", 0.15, costs or {"clearance": 0.3}).fields


def _check(aut, layout, name: str) -> None:
    preflight.check_feasible(compile_task(aut, layout, "event", 0.15), name)


def test_phi1_targets_and_forbidden_areas():
    # docs/ltl.md's table: 0 start, 1 A1 visited, 3 A1 and A2 visited, 2 rejecting, 4 accepting
    assert _split("phi1") == {
        0: (("A1",), ("A2", "A3")),  # A2 or A3 first rejects
        1: (("A2",), ("A3",)),  # A1 again changes nothing; A3 before A2 rejects
        2: ((), ()),
        3: (("A3",), ()),
        4: ((), ()),
    }


def test_phi2_targets_and_forbidden_areas_under_event_labelling():
    # 0 start; 2 A1 read (A3 must be the next letter); 3 A3 read (A1 next); 4 both at once;
    # 5 F (A4 & X F A2); 6 F A2; 1 rejecting; 7 accepting. The first letter must hold A1 or A3,
    # the second the other one: every other area entered then rejects, A1 again included.
    assert _split("phi2") == {
        0: (("A1", "A3"), ("A2", "A4")),
        1: ((), ()),
        2: (("A3",), ("A1", "A2", "A4")),
        3: (("A1",), ("A2", "A3", "A4")),
        4: (("A1", "A3"), ("A2", "A4")),
        5: (("A4",), ()),  # A1, A2, A3 leave F (A4 & X F A2) as it is
        6: (("A2",), ()),
        7: ((), ()),
    }


def test_avoid_until_targets_and_forbidden_areas():
    # !A4 U (A2 & F A3): 0 start (A4 rejects, A1 and A3 change nothing), 1 = F A3
    split = _split("avoid-until")
    assert split[0] == (("A2",), ("A4",))
    assert split[1] == (("A3",), ())


def test_a_letter_that_moves_farther_from_acceptance_is_forbidden():
    # next-chain F (A3 & X (A4 & X A1)): after A3, entering A1 instead of A4 starts over
    split = _split("next-chain")
    assert split[1] == (("A4",), ("A1",))


CORRIDOR = layouts.from_json({
    "name": "corridor", "arena": [4.0, 2.0], "start": [0.5, 1.0, 0.0], "obstacles": [],
    "areas": [{"name": "A1", "center": [3.5, 1.0], "radius": 0.3},
              {"name": "A2", "center": [2.0, 1.0], "radius": 0.5}],
})


def test_the_field_goes_round_a_forbidden_area_and_not_round_a_neutral_one():
    lay = CORRIDOR
    start = jnp.array(lay.start[:2], jnp.float32)
    straight = 3.0 - 0.3  # to A1's disk along the corridor's axis, through A2; no obstacles
    avoid = _fields(translate("!A2 U A1"), lay)
    plain = _fields(translate("F A1"), lay)  # A2 is no proposition
    assert avoid.forbidden[0] == ("A2",) and plain.forbidden[0] == ()
    around = float(geodesic.lookup(jnp.asarray(avoid.field), start, index=0))
    through = float(geodesic.lookup(jnp.asarray(plain.field), start, index=0))
    assert through == pytest.approx(straight, abs=0.05)
    # round A2 with 0.3 m to spare: at least the arc of radius 0.8 instead of its chord 1.6
    assert around > straight + 0.8 * (math.pi - 2) - 0.1


def test_a_robot_inside_a_forbidden_area_it_just_entered_may_leave_it():
    # phi2 state 2 (A1 read): A1 is forbidden (entering it again rejects), but leaving costs nothing
    fields = jnp.asarray(_fields(translate(task_formula("phi2")), PAPER).field)
    centre = float(geodesic.lookup(fields, jnp.array([4.35, 0.8]), index=2))
    rim = float(geodesic.lookup(fields, jnp.array([4.05, 0.95]), index=2))
    assert centre < rim + 0.4  # no penalty for crossing A1 from inside
    # from A1 the path to A3 goes round A4: longer than the obstacle-only path through A4 (5.5 m)
    assert centre > 5.9


def test_suite_tasks_pass_the_check_on_paper_and_the_impossible_one_does_not():
    for name in SUITE:
        aut = translate(task_formula(name))
        if name == "a1-and-a2":
            with pytest.raises(ConfigError, match="cannot be completed"):
                _check(aut, PAPER, name)
        else:
            _check(aut, PAPER, name)
    assert len(SUITE) >= 10


def test_check_rejects_a_forbidden_area_that_cuts_every_path_and_an_unknown_proposition():
    cut = layouts.from_json({
        "name": "cut", "arena": [4.0, 1.0], "start": [0.5, 0.5, 0.0], "obstacles": [],
        "areas": [{"name": "A1", "center": [3.5, 0.5], "radius": 0.3},
                  {"name": "A2", "center": [2.0, 0.5], "radius": 0.45}],
    })
    with pytest.raises(ConfigError, match=r"state 0 .*cannot reach A1 without entering A2"):
        _check(translate("!A2 U A1"), cut, "t")
    _check(translate("F A2 & F A1"), cut, "t")  # crossing A2 is fine here
    with pytest.raises(ConfigError, match="'A9' names no area"):
        make_env(EnvConfig(layout="paper", reward=RewardConfig(shaping_metric="geodesic-per-state")),
                 task="!A9 U A1")


def test_geodesic_reward_is_bit_identical_to_before_the_per_state_option():
    """Rewards of a fixed rollout (phi2 on paper, relaxed labelling radius 1 m, the geodesic metric,
    the default until 2026-11-23) as computed by commit f20c02d, before envs/state_fields.py existed."""
    env, params = make_env(EnvConfig(layout="paper", label_radius=1.0,
                                     reward=RewardConfig(shaping_metric="geodesic")), task="phi2")
    n = 2
    state, _ = jax.jit(env.reset_batch, static_argnums=2)(jax.random.PRNGKey(3), params, n)
    # XLA's default optimisation level (3) and fusion emitters, as the commands compile: the
    # suite's level 0 without fusion emitters (tests/conftest.py) computes the same function with
    # other roundings
    a0 = jnp.zeros((n, 2), jnp.float32)
    step = jax.jit(env.step_batch).lower(jax.random.PRNGKey(0), state, a0, params).compile(
        compiler_options={"xla_backend_optimization_level": 3, "xla_cpu_use_fusion_emitters": True})
    out = []
    for t in range(40):
        a = jnp.stack([jnp.full((n,), 0.8), jnp.sin(0.13 * t + jnp.arange(n, dtype=jnp.float32))], -1)
        state, _, r, _, _, _ = step(jax.random.PRNGKey(100 + t), state, a, params)
        out.append(np.asarray(r))
    r = np.stack(out).astype(np.float32)
    assert float(r.sum()) == -47.613834381103516
    assert hashlib.sha256(r.tobytes()).hexdigest()[:16] == "623a5c6d62e700dd"


def test_per_state_potential_in_the_env_reads_the_state_field():
    cfg = EnvConfig(layout="paper", preset="ideal", start_jitter_xy=0.0, start_jitter_theta=0.0,
                    reward=RewardConfig(shaping_metric="geodesic-per-state"))
    env, params = make_env(cfg, task="avoid-until")
    assert params.state_field.shape == (4, 101, 101)
    state, _ = jax.jit(env.reset)(jax.random.PRNGKey(0), params)  # eagerly: one program per op
    state, _, r, _, _, info = jax.jit(env.step)(jax.random.PRNGKey(1), state, jnp.array([1.0, 0.0]), params)
    f = params.state_field
    before = float(geodesic.lookup(f, info["pose"][:2], index=0))
    after = float(geodesic.lookup(f, info["next_pose"][:2], index=0))
    diag = math.hypot(5.0, 5.0)
    # no automaton move: -c_n plus the shaping of the field of state 0
    assert float(r) == pytest.approx(-0.01 + 10.0 * (before - after) / diag, abs=1e-4)


def test_cli_plots_the_fields_and_refuses_a_bad_task_before_training(tmp_path, capsys):
    from d2spo import cli

    png = tmp_path / "fields.png"
    assert cli.main(["ltl", "never-a4", "--layout", "paper", "--plot", str(png)]) == 0
    assert png.stat().st_size > 10_000
    capsys.readouterr()
    rc = cli.main(["train", "--task", "!A9 U A1", "--shaping-metric", "geodesic-per-state",
                   "--out", str(tmp_path / "run"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "'A9' names no area of layout 'paper'" in err[0]
    assert not (tmp_path / "run" / "episodes.csv").exists()


def test_route_length_is_the_shortest_drive_and_goes_round_what_rejects():
    lay = CORRIDOR
    # "F A1" (A2 is no proposition): straight along the axis to A1's disk; the grid's cells are
    # 5 cm and the route starts from the start cell's centre
    straight = routes.route_length(translate("F A1"), lay, "event", 0.15)
    assert straight == pytest.approx(3.0 - 0.3, abs=0.1)
    # "!A2 U A1" must keep its centre out of A2's disk (radius 0.5 m): tangent, arc, tangent to
    # A1's disk, 2.89 m on the continuous plane (at most 8.2% more on the grid)
    around = routes.route_length(translate("!A2 U A1"), lay, "event", 0.15)
    arc = math.sqrt(1.5**2 - 0.25) + math.sqrt(1.2**2 - 0.25) + 0.5 * (math.pi - math.acos(0.5 / 1.5)
                                                                       - math.acos(0.5 / 1.2))
    assert arc - 0.05 < around < arc * routes.OCTILE_EXCESS
    # A1, then A2, then A1 again: to A1's disk (through A2, neutral then), back to A2's rim (2.5 m)
    # and on to A1's rim (3.2 m) again: 2.7 + 0.7 + 0.7 m
    back = routes.route_length(translate("F (A1 & X F (A2 & X F A1))"), lay, "event", 0.15)
    assert 4.1 - 0.05 < back < 4.1 + 0.15
    assert routes.route_length(translate(task_formula("a1-and-a2")), PAPER, "event", 0.15) == math.inf


def test_check_time_warns_when_a_task_cannot_fit_in_an_episode_and_when_tight():
    task = compile_task(translate(task_formula("phi2")), PAPER, "event", 0.15)
    assert task.route_length == routes.route_length(task.automaton, PAPER, "event", 0.15)
    steps = task.route_length / (0.1 * 1.0)
    with pytest.warns(TaskWarning, match=r"'phi2' cannot be completed .* within .* every episode will time out"):
        preflight.check_time(task, int(steps / routes.OCTILE_EXCESS) - 1, 0.1, 1.0,
                                "'phi2'")
    with pytest.warns(TaskWarning, match="may run out of time"):  # the grid's route may exceed the continuous one
        preflight.check_time(task, int(steps / routes.OCTILE_EXCESS) + 1, 0.1, 1.0,
                                "'phi2'")
    with pytest.warns(TaskWarning, match="shortest route"):
        preflight.check_time(task, int(steps / preflight.TIGHT_FRACTION) - 1, 0.1, 1.0,
                                "'phi2'")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        preflight.check_time(task, int(steps / preflight.TIGHT_FRACTION) + 1, 0.1, 1.0,
                                "'phi2'")


def test_default_step_limit_gives_a_long_task_room_and_a_short_one_the_base():
    phi1, phi2 = (compile_task(translate(task_formula(t)), PAPER, "event", 0.15) for t in ("phi1", "phi2"))
    need = {t: a.route_length / 0.1 for t, a in (("phi1", phi1), ("phi2", phi2))}
    # the former base, 200 steps (old config.json files): phi1 fits, phi2 is tight and gets twice its route
    assert need["phi1"] <= preflight.TIGHT_FRACTION * 200 < need["phi2"]
    assert preflight.default_max_steps(phi1, 0.1, 1.0, 200) == 200
    auto = preflight.default_max_steps(phi2, 0.1, 1.0, 200)
    assert auto % 50 == 0 and preflight.ROOM * need["phi2"] <= auto < preflight.ROOM * need["phi2"] + 50
    # today's base, 300: both fit; at half the speed phi2 needs twice the steps and gets twice its route
    assert EnvConfig().base_max_steps == 300
    assert need["phi2"] <= preflight.TIGHT_FRACTION * 300 < 2 * need["phi2"]
    for task in (phi1, phi2):
        assert preflight.default_max_steps(task, 0.1, 1.0, 300) == 300
    slow = preflight.default_max_steps(phi2, 0.1, 0.5, 300)
    assert slow % 50 == 0 and 2 * preflight.ROOM * need["phi2"] <= slow < 2 * preflight.ROOM * need["phi2"] + 50
    with warnings.catch_warnings():  # the automatic limit is never tight
        warnings.simplefilter("error")
        preflight.check_time(phi2, auto, 0.1, 1.0, "'phi2'")
        preflight.check_time(phi2, slow, 0.1, 0.5, "'phi2'")
    # the env takes it when max_steps is unset, and an explicit limit wins
    assert int(make_env(EnvConfig(layout="paper", preset="ideal", base_max_steps=200), "phi2")[1].max_steps) == auto
    env, explicit = make_env(EnvConfig(layout="paper", preset="ideal", max_steps=200), "phi2")
    assert int(explicit.max_steps) == 200
    with pytest.warns(TaskWarning, match="may run out of time"):  # what training checks: tight
        preflight.preflight(env, explicit, "'phi2'")
    assert int(make_env(EnvConfig(layout="paper", preset="ideal", base_max_steps=200), "phi1")[1].max_steps) == 200
    assert int(make_env(EnvConfig(layout="paper", preset="ideal"), "phi1")[1].max_steps) == 300


def test_barrier_margin_warns_when_every_route_passes_closer_than_d():
    """random:100012: phi2's only routes squeeze between A4 (forbidden on the way to A1) and a box, at
    a clearance of about 0.27 m; the barrier's d = 0.3 m is more, 0.25 m less. paper's 0.75 m
    passages leave every route 0.3 m."""
    env, _ = make_env(EnvConfig(layout="random:100012"), "phi2")
    with pytest.warns(TaskWarning, match=r"without entering A2, A3, A4 .* keeping 0.3 m .*--cbf.d"):
        preflight.preflight(env, None, "'phi2'", margin=0.3, episode_time=False)
    paper, _ = make_env(EnvConfig(layout="paper"), "phi2")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        preflight.preflight(env, None, "'phi2'", margin=0.25, episode_time=False)
        preflight.preflight(paper, None, "'phi2'", margin=0.3, episode_time=False)


def _steepest(sf: state_fields.StateFields, q: int, layout, robot_radius: float) -> float:
    """Largest |field difference| / distance between 4-neighbour grid nodes where the robot fits."""
    f = sf.field[q]
    ny, nx = f.shape
    xs, ys = np.linspace(0.0, layout.arena[0], nx), np.linspace(0.0, layout.arena[1], ny)
    lo = np.array([o.lo for o in layout.obstacles]).reshape(-1, 2)
    hi = np.array([o.hi for o in layout.obstacles]).reshape(-1, 2)
    fits = geodesic.clearance(xs, ys, lo, hi, layout.arena) >= robot_radius
    spacing = xs[1] - xs[0]
    across = np.abs(np.diff(f, axis=1))[fits[:, 1:] & fits[:, :-1]]
    along = np.abs(np.diff(f, axis=0))[fits[1:] & fits[:-1]]
    return float(max(across.max(), along.max()) / spacing)


def test_the_field_rises_at_most_clearance_cost_per_metre_where_the_robot_fits():
    # phi2 state 6 (A2 next, nothing forbidden): between two nodes where the robot fits, the field
    # differs by at most the dearer way from one to the other, 2x the distance in the clearance band.
    # At 10x (until 2026-11-25) it rose 10 m per metre sideways across the mouth of the 0.79 m
    # openings round A4, where D²SPO's policy dithered.
    aut = translate(task_formula("phi2"))
    mild = _fields(aut, PAPER, RewardConfig().field_costs(0.15))
    steep = _fields(aut, PAPER, dict(clearance=0.3, robot_radius=0.15, clearance_cost=10.0, collide_cost=10.0))
    assert mild.targets[6] == ("A2",) and mild.forbidden[6] == ()
    assert _steepest(mild, 6, PAPER, 0.15) <= geodesic.CLEARANCE_COST + 1e-3
    assert _steepest(steep, 6, PAPER, 0.15) > 8.0
    # the env trains on the fields of its reward config
    _, params = make_env(EnvConfig(layout="paper"), task="phi2")
    np.testing.assert_array_equal(np.asarray(params.state_field), mild.field)


def test_reward_defaults_are_the_field_banks_costs_and_old_configs_keep_theirs():
    from d2spo.config import TrainConfig, config_from_dict, config_to_dict

    assert RewardConfig().shaping_clearance_cost == geodesic.CLEARANCE_COST
    assert RewardConfig().shaping_collide_cost == geodesic.COLLIDE_COST
    data = config_to_dict(TrainConfig())
    for key in ("shaping_clearance_cost", "shaping_collide_cost"):
        del data["env"]["reward"][key]  # a config.json written before the fields existed
    old = config_from_dict(data).env.reward
    assert (old.shaping_clearance_cost, old.shaping_collide_cost) == (10.0, 10.0)
    with pytest.raises(ConfigError, match="shaping_clearance_cost"):
        RewardConfig(shaping_clearance_cost=0.5)


def test_sixteen_neighbours_bring_the_field_within_3_percent_of_the_straight_distance():
    # An open 4 m x 4 m arena, A1 of radius 0.2 m in a corner: at 22.5 degrees off the grid's axes the
    # 8-neighbour path is 8.2% longer than the segment; with knight moves 2.7% at most (there: 1.9%).
    lay = layouts.from_json({"name": "open4", "arena": [4.0, 4.0], "start": [0.5, 0.5, 0.0], "obstacles": [],
                             "areas": [{"name": "A1", "center": [0.5, 0.5], "radius": 0.2}]})
    aut = translate("F A1")
    costs = dict(clearance=0.0, robot_radius=0.0)
    eight, sixteen = (_fields(aut, lay, {**costs, "neighbours": n}).field[0] for n in (8, 16))
    for angle in (0.0, math.pi / 8, math.pi / 4, 3 * math.pi / 8):
        p = jnp.array([0.5 + 3.0 * math.cos(angle), 0.5 + 3.0 * math.sin(angle)], jnp.float32)
        straight = 3.0 - 0.2
        e8 = float(geodesic.lookup(jnp.asarray(eight)[None], p, index=0)) / straight - 1
        e16 = float(geodesic.lookup(jnp.asarray(sixteen)[None], p, index=0)) / straight - 1
        assert -0.01 < e16 < 0.03, (angle, e16)
        assert e16 <= e8 + 1e-3, (angle, e8, e16)
        if angle in (math.pi / 8, 3 * math.pi / 8):
            assert e8 > 0.06, (angle, e8)
    with pytest.raises(ConfigError, match="shaping_neighbours"):
        RewardConfig(shaping_neighbours=12)
    # the reward's option reaches the env's fields; the default is the 8-neighbourhood of before
    assert RewardConfig().field_costs(0.15)["neighbours"] == 8
    _, params = make_env(EnvConfig(layout="paper", reward=RewardConfig(shaping_neighbours=16)), task="phi2")
    np.testing.assert_array_equal(np.asarray(params.state_field),
                                  _fields(translate(task_formula("phi2")), PAPER,
                                          RewardConfig(shaping_neighbours=16).field_costs(0.15)).field)
