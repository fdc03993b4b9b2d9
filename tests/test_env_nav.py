"""The functional environment: batching, jit, determinism, autoreset, collisions, labelling."""

from __future__ import annotations

import math
from functools import cache, partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.envs import EnvConfig, dynamics, geometry, make_env, sensors
from d2spo.ltl.automaton import UNREACHABLE, AutomatonArrays
from d2spo.ltl.reward import RewardConfig

NO_SHAPING = RewardConfig(shaping=0.0, shaping_metric="euclidean")  # no fields, no task-on-layout check


@cache
def build(task="phi1", **cfg):
    """(env, params, jitted step, jitted step_batch) for a config, built once per test session."""
    env, params = make_env(EnvConfig(**cfg), task)
    return env, params, jax.jit(env.step), jax.jit(env.step_batch)


@partial(jax.jit, static_argnums=2)
def keys_and_actions(key, t, n):
    """The per-step env key and the [n, 2] actions (some out of range) of the random rollouts."""
    k_act, k_env = jax.random.split(jax.random.fold_in(key, t))
    return k_env, jax.random.split(k_env, n), jax.random.uniform(k_act, (n, 2), minval=-1.5, maxval=1.5)


def scripted():
    """Paper layout, no unmodelled effects, no start jitter, Eq. (8) without shaping."""
    return build("phi1", preset="ideal", start_jitter_xy=0.0, start_jitter_theta=0.0, reward=NO_SHAPING)


def teleport(state, xy):
    return state.replace(pose=state.pose.at[:2].set(jnp.asarray(xy, jnp.float32)))


STOP = jnp.zeros(2)

# --------------------------------------------------------------------------- batch / jit / keys


def rollout_batch(step_batch, env, params, key, n, steps):
    state, obs = jax.jit(env.reset_batch, static_argnums=2)(key, params, n)
    out = []
    for t in range(steps):
        k_env, _, action = keys_and_actions(key, t, n)
        state, obs, reward, cost, done, info = step_batch(k_env, state, action, params)
        out.append(jax.tree.map(np.asarray, (state, obs, reward, cost, done, info)))
    return out


def test_batch_equals_envs_stepped_one_by_one_with_autoreset():
    env, params, step, step_batch = build("phi1", max_steps=6)
    n, steps, key = 3, 14, jax.random.key(3)
    batch = rollout_batch(step_batch, env, params, key, n, steps)
    reset = jax.jit(env.reset)
    for i in range(n):
        state, _ = reset(jax.random.split(key, n)[i], params)
        for t in range(steps):
            _, keys, actions = keys_and_actions(key, t, n)
            state, obs, reward, cost, done, info = step(keys[i], state, actions[i], params)
            got = jax.tree.map(lambda a: a[i], batch[t])
            # 1e-5: the path direction divides a difference of two field lookups by its norm, which
            # brings float32 rounding (vmapped or not) to ~2e-6
            for a, b in zip(jax.tree.leaves((state, obs, reward, cost, done, info)), jax.tree.leaves(got)):
                np.testing.assert_allclose(np.asarray(a), b, rtol=1e-5, atol=1e-5)
    dones = np.array([np.asarray(b[4]) for b in batch])
    assert dones[5].all() and not dones[:5].any()  # truncation after max_steps = 6, then a new episode


def test_fixed_key_is_deterministic_and_keys_matter():
    env, params, _, step_batch = build("phi1", max_steps=6)
    a = rollout_batch(step_batch, env, params, jax.random.key(0), 3, 4)[-1]  # n = 3: reuses the
    b = rollout_batch(step_batch, env, params, jax.random.key(0), 3, 4)[-1]  # compiled functions
    c = rollout_batch(step_batch, env, params, jax.random.key(1), 3, 4)[-1]
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert not np.allclose(np.asarray(a[0].pose), np.asarray(c[0].pose))


def test_jit_and_no_jit_agree():
    env, params, step, _ = build("phi1", max_steps=6)
    key = jax.random.key(5)
    s1, _ = jax.jit(env.reset)(key, params)
    s2 = s1
    for t in range(1):
        k = jax.random.fold_in(key, t)
        action = jnp.array([0.8, -0.3])
        s1, o1, r1, c1, d1, i1 = step(k, s1, action, params)
        with jax.disable_jit():
            s2, o2, r2, c2, d2, i2 = env.step(k, s2, action, params)
        for a, b in zip(jax.tree.leaves((s1, o1, r1, c1, d1, i1)), jax.tree.leaves((s2, o2, r2, c2, d2, i2))):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5)


def test_an_eager_call_is_one_program_kept_and_a_traced_call_is_the_method_itself():
    """``env.step`` on concrete arrays compiles once and keeps the program (``compiled_when_eager``),
    with jit's results bit for bit; under ``jit`` the step is traced inline (no nested program), so
    training's programs are what they were."""
    env, params = make_env(EnvConfig(max_steps=6), "phi1")
    key = jax.random.key(3)
    state, _ = env.reset(key, params)
    action = jnp.array([0.8, -0.3])
    out = env.step(key, state, action, params)
    programs = env.__dict__["_eager_programs"]
    assert len(programs) == 2  # reset's and step's
    step_program = next(p for f, p in programs.items() if f.__name__ == "step")
    assert step_program._cache_size() == 1
    again = env.step(jax.random.key(4), out[0], jnp.array([0.1, 0.2]), params)
    assert step_program._cache_size() == 1 and len(programs) == 2  # the same shapes: no new program
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(jax.jit(env.step)(key, state, action, params))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    jaxpr = jax.make_jaxpr(env.step)(key, state, action, params)
    assert "pjit" not in {e.primitive.name for e in jaxpr.eqns}
    assert np.asarray(again[1]).shape == (env.observation_size,)


def test_reset_jitter_is_bounded_and_random():
    env, params, _, _ = build("phi1", max_steps=6)
    state, obs = jax.jit(env.reset_batch, static_argnums=2)(jax.random.key(0), params, 64)
    start = np.array(env.layout.start)
    dev = np.asarray(state.pose) - start
    assert np.all(np.abs(dev[:, :2]) <= 0.05 + 1e-6) and np.all(np.abs(dev[:, 2]) <= 0.1 + 1e-6)
    assert dev[:, 0].std() > 0.01
    assert obs.shape == (64, env.observation_size) and obs.dtype == jnp.float32


def test_autoreset_returns_new_episode_and_keeps_final_observation():
    env, params, step, _ = build("phi1", max_steps=6)
    state, _ = jax.jit(env.reset)(jax.random.key(1), params)
    for t in range(6):
        prev = state
        state, obs, reward, cost, done, info = step(jax.random.key(10 + t), state, jnp.array([1.0, 0.2]), params)
    assert bool(done) and bool(info["truncated"]) and not bool(info["terminated"])
    assert int(info["ep_length"]) == 6 and int(state.t) == 0
    np.testing.assert_allclose(info["pose"], prev.pose)
    np.testing.assert_allclose(obs, jax.jit(env.observe)(state, params), atol=1e-6)  # the new episode
    assert np.linalg.norm(np.asarray(state.pose[:2]) - env.layout.start[:2]) < 0.08
    moved = state.replace(pose=info["next_pose"], q=info["q_next"])
    np.testing.assert_allclose(info["next_obs"], jax.jit(env.observe)(moved, params), atol=1e-6)


# --------------------------------------------------------------------------------- collisions


def test_drive_into_obstacle_costs_one_and_ends_the_episode():
    env, params, step, _ = scripted()
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)  # (0.6, 0.6) facing +x; obstacle 0 ahead
    clearance = jax.jit(lambda p: geometry.clearance(p[:2], params.geom) - params.robot_radius)
    rewards = []
    for t in range(40):
        state, obs, reward, cost, done, info = step(jax.random.key(t), state, jnp.array([1.0, 0.0]), params)
        rewards.append(float(reward))
        if bool(done):
            break
        assert float(cost) == 0.0 and float(clearance(info["next_pose"])) > 0
    assert float(cost) == 1.0 and bool(info["collided"]) and bool(info["terminated"])
    assert float(clearance(info["next_pose"])) <= 0
    assert float(info["next_pose"][0]) == pytest.approx(0.6 + 0.1 * (t + 1), abs=1e-4)  # 0.1 m per step
    assert int(info["ep_length"]) == t + 1
    assert float(info["ep_cost"]) == 1.0 and bool(info["ep_collided"]) and not bool(info["ep_completed"])
    cfg = params.reward
    assert rewards[:-1] == pytest.approx([-cfg.c_n] * t)
    assert rewards[-1] == pytest.approx(-cfg.c_n - cfg.c_collision)
    assert float(info["ep_return"]) == pytest.approx(sum(rewards), abs=1e-5)
    assert int(state.t) == 0 and not bool(state.ep_collided)  # reset


def test_collision_without_termination_blocks_the_robot():
    env, params, step, _ = build("phi1", preset="ideal", start_jitter_xy=0.0, start_jitter_theta=0.0,
                                 collision_terminates=False, max_steps=30)
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    costs, xs = [], []
    for t in range(25):
        state, obs, reward, cost, done, info = step(jax.random.key(t), state, jnp.array([1.0, 0.0]), params)
        costs.append(float(cost))
        xs.append(float(state.pose[0]))
        assert not bool(done)
    first = costs.index(1.0)
    assert all(c == 1.0 for c in costs[first:])  # pushing into the obstacle keeps costing
    assert max(xs) < 2.25 - 0.15 and xs[-1] == xs[first - 1]  # held at its last free position
    assert float(state.ep_cost) == 25 - first and bool(state.ep_collided)


def test_a_nan_action_is_a_collision():
    """The JAX env cannot raise: a position that is not a number counts as a collision (it once
    counted as safe, and the NaN pose went on unnoticed)."""
    env, params, step, _ = scripted()
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    state, _, _, cost, done, info = step(jax.random.key(1), state, jnp.array([jnp.nan, 0.0]), params)
    assert float(cost) == 1.0 and bool(info["collided"]) and bool(done)
    assert bool(geometry.collides(jnp.array([jnp.nan, 0.6]), params.geom, params.robot_radius))
    assert not bool(geometry.collides(jnp.array([0.6, 0.6]), params.geom, params.robot_radius))


def test_actions_are_clipped():
    env, params, step, _ = scripted()
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    a = step(jax.random.key(1), state, jnp.array([5.0, -7.0]), params)
    b = step(jax.random.key(1), state, jnp.array([1.0, -1.0]), params)
    np.testing.assert_array_equal(np.asarray(a[0].pose), np.asarray(b[0].pose))
    dt, w = float(params.dyn.dt), float(params.dyn.omega_max)
    assert float(a[0].pose[2]) == pytest.approx(-w * dt, abs=1e-6)


def test_a_robot_that_cannot_reverse_spans_zero_to_v_max():
    """``reverse=False``: a₀ = −1 stands still, 0 drives at v_max / 2, 1 at v_max, and random actions
    never move the robot backwards; the default (reverse) commands a₀ · v_max exactly."""
    kw = dict(preset="ideal", start_jitter_xy=0.0, start_jitter_theta=0.0, reward=NO_SHAPING)
    env, params, step, _ = build("phi1", reverse=False, **kw)
    v_max = float(params.dyn.v_max)
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    for a0, v in ((-1.0, 0.0), (0.0, 0.5 * v_max), (1.0, v_max), (-3.0, 0.0)):
        moved = step(jax.random.key(1), state, jnp.array([a0, 0.0]), params)[0].pose - state.pose
        assert float(jnp.hypot(moved[0], moved[1])) == pytest.approx(v * float(params.dyn.dt), abs=1e-6)
    key, s, moved = jax.random.key(3), state, 0.0
    for t in range(40):
        k_env, _, action = keys_and_actions(key, t, 1)
        nxt, _, _, _, done, _ = step(k_env, s, action[0], params)
        if not done:  # an episode's end resets the pose
            heading = s.pose[2] + dynamics.wrap_angle(nxt.pose[2] - s.pose[2]) / 2  # midpoint integration
            forward = (nxt.pose[0] - s.pose[0]) * jnp.cos(heading) + (nxt.pose[1] - s.pose[1]) * jnp.sin(heading)
            assert float(forward) >= -1e-6, t
            moved += float(forward)
        s = nxt
    assert moved > 0.5
    _, reversing, *_ = build("phi1", **kw)
    a = jnp.linspace(-1.0, 1.0, 9)
    got = jax.vmap(lambda x: dynamics.command(jnp.stack([x, x]), reversing.dyn))(a)
    np.testing.assert_array_equal(np.asarray(got[:, 0]), np.asarray(a * reversing.dyn.v_max))


# --------------------------------------------------------------------------------- labelling


def test_visiting_areas_in_order_completes_the_task():
    env, params, step, _ = scripted()
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    centre = {a.name: a.center for a in env.layout.areas}
    cfg = params.reward
    rewards = []
    for name in ("A1", "A2", "A3"):
        state, obs, reward, cost, done, info = step(jax.random.key(0), teleport(state, centre[name]), STOP, params)
        rewards.append(float(reward))
    assert rewards == pytest.approx([cfg.c_p, cfg.c_p, cfg.r_goal])
    assert bool(done) and bool(info["terminated"]) and bool(info["completed"]) and bool(info["ep_completed"])
    assert int(state.q) == int(params.aut.initial)  # the next episode has started


def test_visiting_in_the_wrong_order_rejects():
    env, params, step, _ = scripted()
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    a2 = env.layout.areas[1].center
    state, obs, reward, cost, done, info = step(jax.random.key(0), teleport(state, a2), STOP, params)
    assert bool(params.aut.rejecting[info["q_next"]]) and bool(done) and bool(info["terminated"])
    assert float(reward) == pytest.approx(-params.reward.r_reject)
    assert not bool(info["completed"])


def test_relaxed_radius_drives_q_and_true_radius_drives_completed():
    env, params, step, _ = build("relaxed", layout="open", preset="ideal", label_radius=0.6, reward=NO_SHAPING)
    assert np.allclose(params.label_radius, 0.6) and np.allclose(params.area_radius, 0.35)
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    (a1, a2) = (env.layout.areas[0].center, env.layout.areas[1].center)
    near = lambda c: (c[0] - 0.5, c[1])
    state, _, _, _, done, info = step(jax.random.key(0), teleport(state, near(a1)), STOP, params)
    assert int(info["q_next"]) != int(info["q"]) and int(info["q_true_next"]) == int(info["q_true"])
    state, _, _, _, done, info = step(jax.random.key(0), teleport(state, near(a2)), STOP, params)
    assert bool(done) and bool(info["completed_relaxed"]) and not bool(info["completed"])
    assert bool(info["ep_completed_relaxed"]) and not bool(info["ep_completed"])
    # annealing: the trainer shrinks params.label_radius; then only the true radius counts
    tight = params.replace(label_radius=params.area_radius)
    state, _ = jax.jit(env.reset)(jax.random.key(0), tight)
    state, _, _, _, _, info = step(jax.random.key(0), teleport(state, near(a1)), STOP, tight)
    assert int(info["q_next"]) == int(info["q"])


def test_event_labelling_lets_the_robot_linger_step_labelling_does_not():
    # phi2 starts with "A1 and next A3": under step labelling, staying in A1 for a second step
    # reads A1 twice and the task is lost; under event labelling it reads one letter.
    for mode, rejected in (("event", False), ("step", True)):
        env, params, step, _ = build("phi2", preset="ideal", label_mode=mode, reward=NO_SHAPING)
        state, _ = jax.jit(env.reset)(jax.random.key(0), params)
        state = teleport(state, env.layout.areas[0].center)
        for _ in range(2):
            state, _, _, _, done, info = step(jax.random.key(0), state, STOP, params)
        assert bool(params.aut.rejecting[info["q_next"]]) == rejected and bool(done) == rejected


def letter_from_membership(inside: jnp.ndarray, ap_area: jnp.ndarray) -> jnp.ndarray:
    """Reference for the env's letters, written per proposition (the env works per area): the
    letter (bit i <=> AP i holds) from membership ``inside`` [N_areas] and ``ap_area`` [n_aps], the
    area index of AP i or -1 when no area carries its name (the AP is then always false)."""
    valid = ap_area >= 0
    held = jnp.where(valid, inside[jnp.clip(ap_area, 0, None)], False)
    bits = jnp.left_shift(jnp.int32(1), jnp.arange(ap_area.shape[0], dtype=jnp.int32))
    return jnp.sum(jnp.where(held, bits, 0)).astype(jnp.int32)


def test_letter_from_membership():
    inside = jnp.array([True, False, True])
    # AP 0 -> area 0, AP 1 -> area 2, AP 2 -> no such area (always false), AP 3 -> area 1.
    ap_area = jnp.array([0, 2, -1, 1], dtype=jnp.int32)
    assert int(letter_from_membership(inside, ap_area)) == 0b0011
    assert int(letter_from_membership(jnp.array([False, True, False]), ap_area)) == 0b1000
    assert int(letter_from_membership(jnp.array([True, True, True]), ap_area)) == 0b1011


def test_letters_match_letter_from_membership():
    env, params, _, _ = build("phi2", preset="ideal", label_mode="event", reward=NO_SHAPING)
    ap_area = jnp.asarray([env.layout.area_names.index(ap) if ap in env.layout.area_names else -1 for ap in env.aps])
    xy = jax.random.uniform(jax.random.key(0), (500, 2), maxval=5.0)
    xy = jnp.concatenate([xy, jnp.asarray([a.center for a in env.layout.areas])])
    ours = jax.vmap(lambda p: env._letters(p, params.aut.initial, params)[1])(xy)
    inside = jnp.linalg.norm(xy[:, None, :] - params.area_center[None], axis=-1) <= params.area_radius
    ref = jax.vmap(letter_from_membership, in_axes=(0, None))(inside, ap_area)
    np.testing.assert_array_equal(np.asarray(ours), np.asarray(ref))
    assert len(set(np.asarray(ours).tolist())) == 1 + len(env.layout.areas)


class VisitInOrder:
    """A hand-built automaton for '(!A2 U A1) & F A2' (independent of the translator)."""

    aps = ("A1", "A2")
    delta = np.array([[0, 1, 3, 2], [1, 1, 2, 2], [2, 2, 2, 2], [3, 3, 3, 3]], np.int32)  # letters {},{A1},{A2},both

    def arrays(self, feasible_letters):
        dist = np.array([UNREACHABLE, UNREACHABLE, 0, UNREACHABLE])
        for _ in range(4):
            for q in (0, 1):
                dist[q] = min(dist[q], 1 + min(dist[self.delta[q, x]] for x in feasible_letters))
        return AutomatonArrays(jnp.asarray(self.delta), jnp.array([False, False, True, False]),
                               jnp.array([False, False, False, True]), jnp.asarray(dist, jnp.int32),
                               jnp.asarray(0, jnp.int32))


def test_make_env_accepts_an_automaton_object():
    env, params = make_env(EnvConfig(layout="relaxed", preset="ideal", reward=NO_SHAPING), VisitInOrder())
    assert env.aps == ("A1", "A2") and env.n_states == 4
    assert np.asarray(params.aut.distance).tolist() == [2, 1, 0, UNREACHABLE]  # only {A1}, {A2} feasible
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    step = jax.jit(env.step)
    for area, want in ((0, 1), (1, 2)):
        state, _, _, _, done, info = step(jax.random.key(0), teleport(state, env.layout.areas[area].center), STOP,
                                          params)
        assert int(info["q_next"]) == want
    assert bool(info["completed"]) and bool(done)


# ------------------------------------------------------------------------------- observation


def test_observation_layout():
    env, params, step, _ = scripted()
    state, obs = jax.jit(env.reset)(jax.random.key(0), params)
    sl = env.observation_slices
    assert env.observation_size == 16 + 4 + 2 * 4 + env.n_states == obs.shape[0]
    H = float(params.sensing_radius)
    pose = jnp.array([2.0, 3.0, math.pi / 2])
    o = np.asarray(jax.jit(env.observe)(state.replace(pose=pose), params))
    want_scan = sensors.lidar(pose, params.geom, jnp.ones(env.n_obstacles, bool), 16, H) / H
    np.testing.assert_allclose(o[sl["lidar"]], want_scan, atol=1e-6)
    np.testing.assert_allclose(o[sl["pose"]], [2 * 2 / 5 - 1, 2 * 3 / 5 - 1, 0.0, 1.0], atol=1e-6)
    # area A4 at (2.5, 2.5): 0.5 m to the robot's right and 0.5 m behind it (robot faces +y)
    a4 = o[sl["areas"]].reshape(4, 2)[3]
    np.testing.assert_allclose(a4 * 5.0, [-0.5, -0.5], atol=1e-5)
    onehot = o[sl["automaton"]]
    assert onehot.sum() == 1 and onehot[int(state.q)] == 1


def test_path_observation_points_along_the_state_field():
    from d2spo.envs import geodesic, spaces
    from d2spo.errors import ConfigError

    env, params, _, _ = build("phi2", preset="ideal", start_jitter_xy=0.0, start_jitter_theta=0.0, observe_path=True)
    state, obs = jax.jit(env.reset)(jax.random.key(0), params)
    sl = env.observation_slices
    assert env.observation_size == obs.shape[0] == sl["path"].stop == 16 + 4 + 8 + env.n_states + 2
    observe = jax.jit(env.observe)
    # phi2 state 6 (A2 next, nothing forbidden) east of A4, facing +y: the path runs north-east
    # through the gap between the boxes at (3.25, 3.25) and (4.5, 2.5); below A2's disk it runs straight at it
    for xy, heading in (((3.9, 2.9), math.pi / 2), ((4.35, 3.2), 0.3)):
        s = state.replace(pose=jnp.array([*xy, heading], jnp.float32), q=jnp.int32(6))
        forward, left = np.asarray(observe(s, params)[sl["path"]])
        assert forward ** 2 + left ** 2 == pytest.approx(1.0, abs=1e-5)
        d = np.asarray(geodesic.descent(params.state_field, jnp.array(xy), 6))
        world = math.atan2(d[1], d[0])
        assert math.atan2(left, forward) == pytest.approx(world - heading, abs=1e-5)
        f = lambda p: float(geodesic.lookup(params.state_field, jnp.array(p), index=6))  # noqa: E731
        assert f(np.add(xy, 0.1 * d)) < f(xy) - 0.08  # a step along it shortens the path by about its length
    assert math.atan2(d[1], d[0]) == pytest.approx(math.pi / 2, abs=math.radians(23))  # below A2: north
    low, high = spaces.observation_bounds(env)
    assert np.all(low[sl["path"]] <= -1) and np.all(high[sl["path"]] >= 1)
    with pytest.raises(ConfigError, match="observe_path"):
        make_env(EnvConfig(layout="paper", observe_path=True, reward=RewardConfig(shaping_metric="geodesic")), "phi2")


def test_info_sensed_is_the_obstacle_set_at_the_current_pose():
    env, params, step, _ = scripted()
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    state = teleport(state, (1.6, 2.5))
    _, _, _, _, _, info = step(jax.random.key(0), state, STOP, params)
    want = geometry.sensed_mask(state.pose[:2], params.geom, params.sensing_radius)
    np.testing.assert_array_equal(np.asarray(info["sensed"]), np.asarray(want))
    assert 0 < int(np.sum(info["sensed"])) < env.n_obstacles
