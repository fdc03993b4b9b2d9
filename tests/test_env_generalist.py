"""The generalist's environment (envs/generalist.py): a slot (layout and task) per episode from a bank, the
subgoal observation; shared labels, disks and rectangular arenas."""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.envs import EnvConfig, generator, layouts, make_env, sensors
from d2spo.envs.generalist import GeneralistEnv, make_generalist_env, subgoal, view
from d2spo.envs.sensors import Sensed
from d2spo.errors import ConfigError
from d2spo.ltl.reward import RewardConfig

SEEDS = (3, 4, 5)
OFFICE = "tests/data/layouts/office.json"


@pytest.fixture(scope="module")
def built():
    lays = [generator.generate(s) for s in SEEDS]
    env, params = make_generalist_env(EnvConfig(preset="ideal"), "phi1", lays)
    return lays, env, params


def sensed_all(info_or_ctx, mask=None):
    """Every obstacle of a step's info (or a learner's context) as sensed: boxes, walls and disks."""
    get = (lambda k: info_or_ctx[k]) if isinstance(info_or_ctx, dict) else (
        lambda k: getattr(info_or_ctx, {"sensed": "mask"}.get(k, k)))
    m = get("sensed") if mask is None else mask
    return Sensed(get("box_lo"), get("box_hi"), jnp.ones_like(m), get("disk_center"), get("disk_radius"))


def test_view_holds_the_drawn_layouts_geometry(built):
    bank, env, params = built
    for b, seed in enumerate(SEEDS):
        lay = generator.generate(seed)
        v = view(params, jnp.int32(b))
        assert np.allclose(np.asarray(v.geom.arena_hi), lay.arena)
        assert np.allclose(np.asarray(v.area_center)[:4], [a.center for a in lay.areas], atol=1e-5)
        assert np.all(np.asarray(v.area_center)[4:] < -100) and not np.any(np.asarray(v.area_radius)[4:])
        o = lay.obstacles[0]
        from d2spo.envs import geometry
        assert bool(geometry.collides(jnp.asarray(o.center, jnp.float32), v.geom, v.robot_radius))
        # unused slots are far away: a free point of the layout does not collide
        free = np.asarray(lay.start[:2], np.float32)
        assert not bool(geometry.collides(jnp.asarray(free), v.geom, v.robot_radius))


def test_resets_draw_every_layout_and_observations_are_finite(built):
    bank, env, params = built
    assert isinstance(env, GeneralistEnv) and env.observation_size == env.n_rays + 10
    states, obs = jax.jit(lambda k: env.reset_batch(k, params, 64))(jax.random.PRNGKey(0))
    assert set(np.asarray(states.layout).tolist()) == {0, 1, 2}
    assert obs.shape == (64, env.observation_size) and bool(jnp.all(jnp.isfinite(obs)))
    starts = np.asarray(params.bank.start)[np.asarray(states.layout), :2]
    assert np.allclose(np.asarray(states.pose)[:, :2], starts, atol=1e-5)
    sl = env.observation_slices
    # phi1's initial state has a target (A1) and forbidden areas (A2, A3)
    assert np.all(np.asarray(obs[:, sl["target"]])[:, 3] == 1.0)
    assert np.all(np.asarray(obs[:, sl["forbidden"]])[:, 3] == 1.0)
    # the target's distance is the subgoal's path length d, observed as d / (d + 10 m)
    one = jax.tree.map(lambda a: a[0], states)
    d = float(subgoal(view(params, one.layout), one.q, one.pose[:2])[0])
    assert abs(float(obs[0, sl["target"]][0]) - d / (d + 10.0)) < 1e-5


def test_a_forbidden_area_beyond_the_forbidden_range_is_observed_as_none(built):
    """``EnvConfig.forbidden_range`` R: the nearest forbidden area's part is what it was within R m of
    its edge and all zeros beyond, as for a task that forbids nothing; unset, it is seen at any
    distance. On narrow-gap-15 the default generalist stopped short of a gap whenever its task had a
    never part, the forbidden area 10 m away (bench/RESULTS.md, "2026-12-03, later")."""
    lays, _, _ = built
    sl = None
    parts = {}
    for r in (None, 0.5, 100.0):
        env, params = make_generalist_env(EnvConfig(preset="ideal", forbidden_range=r), "phi1", lays)
        _, obs = jax.jit(lambda k, env=env, params=params: env.reset_batch(k, params, 16))(jax.random.PRNGKey(0))
        sl = env.observation_slices
        parts[r] = np.asarray(obs)
    edge = []  # each start's distance to the nearest forbidden area's edge, read back off the ratio
    for row in parts[None]:
        f = row[sl["forbidden"]][0]
        edge.append(10.0 * f / (1.0 - f))
    far = np.asarray(edge) > 0.5
    assert far.any() and np.all(parts[None][:, sl["forbidden"]][:, 3] == 1.0)
    assert np.all(parts[0.5][far][:, sl["forbidden"]] == 0.0)
    close = lambda a, b: np.allclose(a, b, atol=1e-6)  # noqa: E731  another program, the same values
    assert close(parts[0.5][~far], parts[None][~far])
    assert close(parts[100.0], parts[None])
    others = np.ones(parts[None].shape[1], bool)
    others[sl["forbidden"]] = False
    assert close(parts[0.5][:, others], parts[None][:, others])  # only that part changes
    with pytest.raises(ConfigError, match="forbidden_range"):
        EnvConfig(forbidden_range=0.0)
    from d2spo.config import TrainConfig

    with pytest.raises(ConfigError, match="without --generalist it has no effect"):
        TrainConfig(env=EnvConfig(forbidden_range=1.2)).check()
    TrainConfig(generalist=True, env=EnvConfig(forbidden_range=1.2)).check()


def test_observed_distances_beyond_twenty_metres_stay_apart():
    """A 20 m world's routes run past 40 m. Capped at 20 m (the encoding of runs before 2026-11-27,
    still read from their config.json), 25 m and 40 m looked alike and a robot stalled there; the
    ratio keeps every two distances apart, increasing and below 1."""
    from d2spo.config import TrainConfig, config_from_dict, config_to_dict
    from d2spo.envs.generalist import observed_distance

    d = jnp.array([0.0, 1.0, 10.0, 20.0, 25.0, 40.0, 80.0])
    ratio, capped = np.asarray(observed_distance(d)), np.asarray(observed_distance(d, "capped"))
    assert ratio[0] == 0.0 and np.all(np.diff(ratio) > 0.01) and ratio[-1] < 1.0
    assert capped[3] == capped[4] == capped[5] == 2.0
    gen = config_to_dict(TrainConfig(algo="d2spo", generalist=True))
    assert gen["env"]["distance_obs"] == "ratio"
    del gen["env"]["distance_obs"]
    assert config_from_dict(gen).env.distance_obs == "capped"
    with pytest.raises(ConfigError, match="distance_obs"):
        EnvConfig(distance_obs="log")


def test_subgoal_descends_the_path_rewards_along_it_and_an_ending_episode_draws_a_new_layout(built):
    bank, env, params = built
    # jitted, each a program of its own: eagerly, every operation inside compiles one of its own
    states, _ = jax.jit(lambda k: env.reset_batch(k, params, 16))(jax.random.PRNGKey(3))
    state = jax.tree.map(lambda a: a[0], states)
    v = jax.jit(view)(params, state.layout)
    subgoal_at = jax.jit(subgoal)
    dist, direction, found = subgoal_at(v, state.q, state.pose[:2])
    assert bool(found) and float(dist) > 0.5 and abs(float(jnp.linalg.norm(direction)) - 1.0) < 1e-4
    ahead = subgoal_at(v, state.q, state.pose[:2] + 0.05 * direction)[0]
    assert float(ahead) < float(dist) - 0.03  # a step along it shortens the path
    # env 0 faces the direction and drives: the shaping term is positive; the others are on their
    # last step: they end and restart in drawn layouts
    heading = jnp.arctan2(direction[1], direction[0])
    states = states.replace(pose=states.pose.at[0, 2].set(heading), t=states.t.at[1:].set(399))
    step = jax.jit(env.step_batch)
    new, obs, r, cost, done, info = step(jax.random.PRNGKey(4), states, jnp.tile(jnp.array([[1.0, 0.0]]), (16, 1)),
                                         params)
    assert int(info["q_next"][0]) == int(state.q) and float(r[0]) > 0.0 and not bool(done[0])
    assert bool(jnp.all(done[1:])) and bool(jnp.all(new.t[1:] == 0)) and bool(jnp.all(jnp.isfinite(obs)))
    assert len(set(np.asarray(new.layout[1:]).tolist())) > 1
    # the CBF input read off the observation is what the sensed boxes alone give (walls are boxes):
    # the learner's data and its acting see the same x, with no arena
    x_obs = jax.jit(env.cbf_input)(info["next_obs"], params)
    ctx = sensed_all(info)
    big = jnp.array([-100.0, -100.0]), jnp.array([100.0, 100.0])
    x_ctx = jax.jit(jax.vmap(lambda p, c: sensors.cbf_input(p, c, *big, env.n_rays, params.sensing_radius)))(
        info["next_pose"], ctx)
    np.testing.assert_allclose(np.asarray(x_obs), np.asarray(x_ctx), atol=1e-4)


def test_a_task_over_other_areas_is_refused(built):
    bank, _, _ = built
    with pytest.raises(ConfigError, match="F A5 & F A1 names A5, which no area of layout 'random:3' carries"):
        make_generalist_env(EnvConfig(), "F A5 & F A1", bank)
    with pytest.raises(ConfigError, match="one area at a time"):  # the bank's areas never overlap
        make_generalist_env(EnvConfig(), "F (A1 & A2)", bank)
    with pytest.raises(ConfigError, match="robot_radius: .* at most 0.25 m"):
        make_generalist_env(EnvConfig(robot_radius=0.3), "phi1", bank)


def test_the_dynamics_robot_and_reward_are_the_configs(built):
    bank, _, _ = built
    cfg = EnvConfig(preset="turtlebot", max_steps=123, reward=RewardConfig(c_n=0.02))
    env, params = make_generalist_env(cfg, "phi1", bank, max_steps=77)
    _, nav = make_env(dataclasses.replace(cfg, layout="paper"), "phi1")
    assert env.config == dataclasses.replace(cfg, max_steps=77).resolved()
    assert int(params.max_steps) == 77 and params.reward == nav.reward
    for name in ("dyn", "robot_radius", "sensing_radius", "start_jitter"):
        for a, b in zip(jax.tree.leaves(getattr(params, name)), jax.tree.leaves(getattr(nav, name)), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_the_generalist_learner_reads_x_and_o_s_per_environment(built):
    from d2spo.algos.d2spo import D2SPOLearner
    from d2spo.algos.generalist import LayoutBank
    from d2spo.algos.td3 import TD3Config
    from d2spo.ltl.anneal import AnnealConfig
    from d2spo.safety.cbf import CBFConfig

    bank, env, params = built
    learner = D2SPOLearner(env, params, TD3Config(), CBFConfig(), AnnealConfig(enabled=False), 4, 10, 100,
                           layouts=LayoutBank)
    states, obs = jax.jit(env.reset_batch, static_argnums=2)(jax.random.PRNGKey(5), params, 16)  # eagerly: 208 one-op programs
    _, _, _, _, _, info = jax.jit(env.step_batch)(jax.random.PRNGKey(6), states, jnp.zeros((16, 2)), params)
    ctx = learner.context(info)
    all_sensed = sensed_all(ctx)
    x_data = jax.vmap(learner.features)(info["next_pose"], all_sensed)
    np.testing.assert_allclose(np.asarray(learner.x_of_obs(info["next_obs"])), np.asarray(x_data), atol=1e-4)
    pose, sensed = learner.synthetic_sample(jax.random.PRNGKey(7))  # walls are its last four boxes
    x = learner.features(pose, sensed)
    assert x.shape == (env.n_rays + 1,) and bool(jnp.all((x >= 0) & (x <= params.sensing_radius)))
    assert float(x[-1]) <= float(jnp.min(jnp.stack([pose[0], pose[1]]))) + 1e-5  # the walls count


def test_the_generalist_flag_is_for_d2spo():
    from d2spo.config import TrainConfig

    with pytest.raises(ConfigError, match="generalist: the generalist is trained with --algo d2spo"):
        TrainConfig(algo="tlgrl", generalist=True)
    with pytest.raises(ConfigError, match="generalist_layouts"):
        TrainConfig(generalist=True, generalist_layouts=0)
    # the annealed radius of Sec. IV-C does not reach the generalist's drawn layouts: refused, not ignored
    from d2spo.ltl.anneal import AnnealConfig

    with pytest.raises(ConfigError, match="anneal: has no effect with --generalist"):
        TrainConfig(generalist=True, anneal=AnnealConfig(enabled=False)).check()
    TrainConfig(generalist=True).check()
    TrainConfig(anneal=AnnealConfig(enabled=False)).check()


def _component_runs(aut, parts, initials, seed: int, length: int, words: int = 200):
    """For random words over the union ``aut``'s letters, per component a: (word, a, its initial state
    q0 in the union, the word as a reads it, a's own run, the union's run from q0)."""
    rng = np.random.default_rng(seed)
    for _ in range(words):
        word = [int(x) for x in rng.integers(0, 1 << len(aut.aps), size=length)]
        for a, q0 in zip(parts, initials):
            mine = [a.letter([p for i, p in enumerate(aut.aps) if w >> i & 1 and p in a.aps]) for w in word]
            yield word, a, q0, mine, a.run(mine), aut.run(word, start=q0)


def test_a_union_runs_each_automaton_from_its_own_initial_state():
    from d2spo.ltl import translate
    from d2spo.ltl.automaton import union

    parts = [translate("(!A2 U A1) & F A2"), translate("F (A3 & X A1)"), translate("!A4 U A2")]
    aut, initials = union(parts)
    assert aut.aps == ("A1", "A2", "A3", "A4") and len(initials) == 3
    for word, a, q0, mine, own, joint in _component_runs(aut, parts, initials, seed=0, length=6):
        assert [a.status(q) for q in own] == [aut.status(q) for q in joint]
        assert [q - q0 + a.initial for q in joint] == own  # component k's states, shifted


def test_random_reach_avoid_tasks_are_distinct_doable_and_reproducible():
    from d2spo.ltl import translate
    from d2spo.ltl.tasks import reach_avoid_tasks

    tasks = reach_avoid_tasks(24, seed=1)
    assert tasks == reach_avoid_tasks(24, seed=1) != reach_avoid_tasks(24, seed=2)
    assert len(set(tasks)) == 24
    for f in tasks:
        a = translate(f)
        singles = [0] + [a.letter([p]) for p in a.aps]
        assert 1 <= a.distances(singles)[a.initial] <= 4, f  # one area at a time: 1 to 4 visits


def test_a_mixture_of_tasks_draws_each_tasks_initial_state(built):
    bank, _, _ = built
    env, params = make_generalist_env(EnvConfig(preset="ideal"), ["phi1", "F A4", "!A4 U (A2 & F A3)"], bank)
    states, obs = jax.jit(env.reset_batch, static_argnums=2)(jax.random.PRNGKey(2), params, 48)
    q = np.asarray(states.q)
    assert set(q.tolist()) == set(np.asarray(params.initials).tolist())
    progress = np.asarray(obs[:, env.observation_slices["progress"]])[:, 0]
    np.testing.assert_allclose(progress, 1.0)  # every task starts at its own largest distance


def test_the_generalists_cbf_input_is_layout_free(built):
    """x = b(z, O_s) depends on the scene around the robot only: moving the robot and every box by
    the same offset (another place, another arena) leaves it unchanged."""
    from d2spo.algos.d2spo import D2SPOLearner
    from d2spo.algos.generalist import LayoutBank
    from d2spo.algos.td3 import TD3Config
    from d2spo.ltl.anneal import AnnealConfig
    from d2spo.safety.cbf import CBFConfig

    bank, env, params = built
    learner = D2SPOLearner(env, params, TD3Config(), CBFConfig(), AnnealConfig(enabled=False), 4, 10, 100,
                           layouts=LayoutBank)
    g = view(params, jnp.int32(1)).geom
    pose = jnp.asarray([*generator.generate(SEEDS[1]).start[:2], 0.7], jnp.float32)
    sensed = Sensed(g.box_lo, g.box_hi, jnp.ones((g.n_obstacles,), bool), g.disk_center, g.disk_radius)
    shift = jnp.asarray([37.5, -12.25], jnp.float32)
    moved = Sensed(g.box_lo + shift, g.box_hi + shift, sensed.mask, g.disk_center + shift, g.disk_radius)
    x = learner.features(pose, sensed)
    np.testing.assert_allclose(np.asarray(learner.features(pose.at[:2].add(shift), moved)), np.asarray(x), atol=1e-4)
    assert float(jnp.min(x)) < params.sensing_radius  # the scene is not empty: something is in range


def test_the_generalist_takes_tasks_no_finite_run_completes(built):
    """A "never" part completes as a monitor does; a recurrence runs with its accepting visits (the
    subgoal after a visit is the next one), alone or in a mixture beside tasks that complete."""
    bank, _, _ = built
    _, never = make_generalist_env(EnvConfig(preset="ideal"), "G !A4 & F A1", bank)
    assert never.aut.visit is None and bool(never.aut.accepting.any())
    env, patrol = make_generalist_env(EnvConfig(preset="ideal"), "patrol2", bank)
    aut = env.automaton
    assert patrol.aut.visit is not None and not bool(patrol.aut.accepting.any())
    waiting_a3 = aut.delta[aut.initial][aut.letter(["A1"])]
    # in each live state the visit's area is the target, A4 forbidden: A1 first, then A3
    local = np.asarray(patrol.local_state)[[aut.initial, waiting_a3]]
    assert np.asarray(patrol.bank.target)[0, local, :4].tolist() == [
        [True, False, False, False], [False, False, True, False]]
    assert np.asarray(patrol.bank.forbidden)[0, local, 3].all()
    mixed_env, mixed = make_generalist_env(EnvConfig(preset="ideal"), ["phi1", "patrol2"], bank)
    assert mixed_env.plan.recurrent == (False, True) and mixed.aut.visit is not None
    lo = mixed_env.plan.offsets[1]  # patrol2's states follow phi1's
    union_aps, own = mixed_env.automaton.aps, env.automaton
    read = [own.letter([p for i, p in enumerate(union_aps) if w >> i & 1 and p in own.aps]) for w in range(16)]
    np.testing.assert_array_equal(np.asarray(mixed.aut.visit)[lo:], np.asarray(patrol.aut.visit)[:, read])
    assert not np.asarray(mixed.aut.visit)[:lo].any()  # phi1 completes: no visits in its states
    assert bool(mixed.aut.accepting[:lo].any()) and not bool(mixed.aut.accepting[lo:].any())


def test_a_union_keeps_each_patrols_accepting_visits():
    """Over random words, each component of a union with patrols visits exactly where it does alone."""
    from d2spo.ltl import task_automaton
    from d2spo.ltl.automaton import union
    from d2spo.ltl.buchi_task import BuchiTask

    parts = [task_automaton(f) for f in ("(!A2 U A1) & F A2", "G F A1 & G F A3 & G !A4", "G (A2 -> F A4) & G F A2")]
    aut, initials = union(parts)
    assert isinstance(aut, BuchiTask) and not isinstance(union(parts[:1])[0], BuchiTask)
    for word, a, q0, mine, own, joint in _component_runs(aut, parts, initials, seed=3, length=8):
        own_visits = [bool(getattr(a, "visits", None) and a.visits[q][b]) for q, b in zip([a.initial, *own], mine)]
        joint_visits = [aut.visits[q][b] for q, b in zip([q0, *joint], word)]
        assert own_visits == joint_visits


def test_random_patrols_are_distinct_recurrences_and_never_the_suites():
    from d2spo.config import TrainConfig
    from d2spo.ltl import task_automaton
    from d2spo.ltl.buchi_task import BuchiTask
    from d2spo.ltl.tasks import MAX_PATROLS, TASKS, patrol_tasks

    tasks = patrol_tasks(MAX_PATROLS, seed=0)
    assert tasks == patrol_tasks(MAX_PATROLS, seed=0) != patrol_tasks(MAX_PATROLS, seed=1)
    assert len(set(tasks)) == MAX_PATROLS == len(patrol_tasks(MAX_PATROLS + 1))  # every distinct one over A1..A4
    suite = {TASKS[t] for t in ("patrol2", "patrol3", "respond")}
    for f in tasks:
        a = task_automaton(f)
        assert isinstance(a, BuchiTask) and not a.accepting and any(map(any, a.visits)), f
        assert f not in suite
        visited = {int(x) for x in re.findall(r"G F A(\d)", f)} | {int(x) for x in re.findall(r"F A(\d)\)", f)}
        never = {int(x) for x in re.findall(r"G !A(\d)", f)}
        assert (visited, never) not in [({1, 3}, {4}), ({1, 2, 3}, {4}), ({1, 2}, set())], f
    with pytest.raises(ConfigError, match="generalist_patrols"):
        TrainConfig(generalist_patrols=2)
    with pytest.raises(ConfigError, match="generalist_patrols"):
        TrainConfig(generalist=True, generalist_patrols=MAX_PATROLS + 1)


def test_every_area_of_a_label_is_a_target_and_either_completes():
    """The office: desk-1 and desk-2 are both labelled desk. Both are targets of "a desk, then the
    kitchen", the field leads to the nearer, and entering either one advances the task."""
    office = layouts.load(OFFICE)
    env, params = make_generalist_env(EnvConfig(preset="ideal"), "F (desk & F kitchen)", [office])
    bank, aut = params.bank, env.automaton
    names = [a.name for a in office.areas]
    desks = [names.index("desk-1"), names.index("desk-2")]
    q0 = int(params.local_state[aut.initial])
    assert np.asarray(bank.target)[0, q0, desks].all() and not np.asarray(bank.target)[0, q0, names.index("kitchen")]
    assert int(bank.area_bits[0, desks[0]]) == int(bank.area_bits[0, desks[1]]) == aut.letter(["desk"])
    step = jax.jit(env.step)
    for d in desks:  # start just outside each desk, drive into it
        state, _ = env.reset(jax.random.PRNGKey(0), params)
        centre, radius = office.areas[d].center, office.areas[d].radius
        pose = jnp.asarray([centre[0] - radius - 0.05, centre[1], 0.0], jnp.float32)
        state = state.replace(pose=pose)
        q = int(state.q)
        for k in range(10):
            state, *_ = step(jax.random.PRNGKey(k), state, jnp.array([1.0, 0.0]), params)
        assert int(state.q) != q and aut.distances([0] + [aut.letter([a]) for a in aut.aps])[int(state.q)] == 1, d
    field = np.asarray(bank.fields[0, q0])
    assert field.max() > 0.5 and np.isfinite(field).all()


def test_disks_are_obstacles_of_the_view_and_of_the_learners_context():
    """A round pillar of the office collides in the view, shows in the lidar and in O_s."""
    office = layouts.load(OFFICE)
    env, params = make_generalist_env(EnvConfig(preset="ideal"), "F (desk & F kitchen)", [office])
    from d2spo.envs import geometry

    pillar = office.disks[0]
    v = view(params, jnp.int32(0))
    assert bool(geometry.collides(jnp.asarray(pillar.center, jnp.float32), v.geom, v.robot_radius))
    beside = jnp.asarray([pillar.center[0] - pillar.radius - 0.4, pillar.center[1]], jnp.float32)
    near = float(sensors.nearest_obstacle(beside, v.geom, jnp.ones((env.n_obstacles,), bool), 5.0))
    assert near == pytest.approx(0.4, abs=1e-4)
