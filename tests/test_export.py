"""`d2spo export` and `d2spo.deploy`: the exported policy acts as the JAX policy does (π_rl, π_Ω, the
runtime filter), builds the env's observation from the robot's readings, keeps the automaton state
as the env does, loads without JAX, fits in 1 MB for the default networks, and bad input gets one
line and exit status 2."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _export_runs import OFFICE, has_module, tiny_run
from _tiny import tiny_cfg, write_run

from d2spo.algos import make_learner
from d2spo.config import TrainConfig
from d2spo.deploy import Policy
from d2spo.envs import EnvConfig, dynamics, sensors
from d2spo.export import ExportConfig, export_run, write_export
from d2spo.ltl.labelling import next_state
from d2spo.run import build
from d2spo.safety.filter import cbf_condition
from d2spo.train import learner_program

ROOT = Path(__file__).resolve().parent.parent
OBSERVATION_TOLERANCE = 1e-5
"""docs/deploy.md's bound on |deploy's observation - the env's|: measured up to 2.9e-6 (the path part)
along a trained ϕ1 run's trajectories (bench/deploy_match.py), 1.2e-7 at these random states."""
ACTION_TOLERANCE = 1e-4
"""docs/deploy.md's bound on |deploy's action - JAX's| without the filter: a trained network amplifies
the observation's float32 differences (up to 3.1e-5 along a trained ϕ1 run's trajectories,
bench/deploy_match.py; the 2e-6 documented before held at random states only); these tiny untrained
networks stay near 2e-7."""


@pytest.fixture(scope="module")
def tiny(tiny_export):
    """``tiny_run`` of ϕ1 on ``paper``: tests/conftest.py's ``tiny_export``, built once per worker."""
    return tiny_export


@pytest.fixture(scope="module", params=["paper", "office"])
def case(request, tmp_path_factory):
    """``tiny``, and a tiny run of "F desk & F kitchen" on ``OFFICE`` (disks, a shared label) by a robot
    that cannot reverse (``--no-reverse``) with an actor that proposes forward motion only
    (``--td3.forward-only``: its export ends with a linear layer)."""
    if request.param == "paper":
        return request.getfixturevalue("tiny")
    root = tmp_path_factory.mktemp("office")
    (root / "office.json").write_text(json.dumps(OFFICE))
    cfg = tiny_cfg(layout=str(root / "office.json"), task="F desk & F kitchen")
    return tiny_run(root, dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, reverse=False),
                                               td3=dataclasses.replace(cfg.td3, forward_only=True)).check())


@pytest.fixture(scope="module")
def states(case):
    """256 random poses in the arena with random automaton states: the env's states, observations and
    lidar scans (every obstacle sensed)."""
    _, _, _, learner, _ = case
    env, params = learner.env, learner.params

    @jax.jit  # eagerly: one program per op
    def draw(key, params):
        k1, k2, k3 = jax.random.split(key, 3)
        n = 256
        xy = jax.random.uniform(k1, (n, 2), minval=0.05, maxval=params.geom.arena_hi - 0.05)
        theta = jax.random.uniform(k2, (n,), minval=-np.pi, maxval=np.pi)
        q = jax.random.randint(k3, (n,), 0, env.n_states)
        start = env.reset_state(jnp.zeros(3), params)
        s = jax.vmap(lambda a, b, c: start.replace(pose=jnp.concatenate([a, b[None]]), q=c))(xy, theta, q)
        obs = jax.vmap(lambda one: env.observe(one, params))(s)
        everything = jnp.ones((params.geom.n_obstacles,), bool)
        scans = jax.vmap(lambda p: sensors.lidar(p, params.geom, everything, env.n_rays, params.sensing_radius))(s.pose)
        return s, obs, scans

    s, obs, scans = draw(jax.random.PRNGKey(7), params)
    return s, np.asarray(obs), np.asarray(s.pose), np.asarray(s.q), np.asarray(scans)


def _jax_actions(case, states, runtime_filter: bool) -> np.ndarray:
    _, _, cfg, learner, policy = case
    s, obs, *_ = states
    cfg = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, runtime_filter=runtime_filter))
    lrn = make_learner(cfg, learner.env, learner.params)
    key = jax.random.PRNGKey(0)
    return np.asarray(jax.jit(jax.vmap(lambda o, st: lrn.act(policy, o, st, key)))(jnp.asarray(obs), s))


def test_the_documented_tolerances_are_the_tested_ones():
    """docs/deploy.md promised 2e-6 (measured at random states) while this file asserted 1e-5 and a
    trial measured 1.6e-5 along trajectories: the page states the bounds asserted here."""
    page = (ROOT / "docs" / "deploy.md").read_text()
    short = lambda x: f"{x:.0e}".replace("e-0", "e-")  # noqa: E731  1e-05 -> 1e-5
    assert (f"the observation within {short(OBSERVATION_TOLERANCE)} and an action\nwithout the filter within "
            f"{short(ACTION_TOLERANCE)} of JAX's") in page


def test_deploy_imports_and_acts_without_jax(tiny):
    code = ("import sys; from d2spo.deploy import Policy; p = Policy.load(sys.argv[1]); t = p.task_tracker(); "
            "pose = (1.0, 1.0, 0.3); q = t.reset(1.0, 1.0); u = p.act(p.scan(pose), pose, q, filter=True); "
            "assert u.shape == (2,); loaded = [m for m in sys.modules if m.split('.')[0] in ('jax', 'jaxlib', 'flax')]; "
            "assert not loaded, loaded; print('ok')")
    res = subprocess.run([sys.executable, "-c", code, str(tiny[1])], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr


def test_observation_from_the_robots_readings_is_the_envs(case, states):
    policy = Policy.load(case[1])
    _, obs, poses, qs, scans = states
    built = np.stack([policy.observation(scans[i], poses[i], qs[i]) for i in range(len(qs))])
    print(f"observation: max abs difference {np.abs(built - obs).max():.3g}")
    assert np.abs(built - obs).max() < OBSERVATION_TOLERANCE
    mapped = np.stack([policy.scan(p) for p in poses])  # the lidar cast on the exported map
    assert np.abs(mapped - scans).max() < 1e-5
    back = np.stack([policy.pose_of_observation(o) for o in obs])
    assert np.abs(back[:, :2] - poses[:, :2]).max() < 1e-5
    assert np.abs(np.angle(np.exp(1j * (back[:, 2] - poses[:, 2])))).max() < 1e-5
    # a driver's readings that cannot be used, each said for what it is
    with pytest.raises(ValueError, match=f"ranges must be {len(scans[0])} lidar ranges .*got 3 values"):
        policy.observation(scans[0][:3], poses[0], qs[0])
    holes = scans[0].copy()
    holes[[1, 4]] = np.nan
    with pytest.raises(ValueError, match=r"lidar ranges \[1, 4\] are NaN; give \+inf"):
        policy.observation(holes, poses[0], qs[0])


def test_actions_equal_the_jax_policys_without_the_filter(case, states):
    policy = Policy.load(case[1])
    _, obs, poses, qs, scans = states
    want = _jax_actions(case, states, runtime_filter=False)
    from_obs = np.stack([policy.act_observation(o, filter=False) for o in obs])
    from_sensors = np.stack([policy.act(scans[i], poses[i], qs[i], filter=False) for i in range(len(qs))])
    print(f"no filter: max abs difference {np.abs(from_obs - want).max():.3g} (observations), "
          f"{np.abs(from_sensors - want).max():.3g} (readings)")
    assert np.abs(from_obs - want).max() < ACTION_TOLERANCE and np.abs(from_sensors - want).max() < ACTION_TOLERANCE
    u_rl = policy.actor(obs)  # the proposals: forward only where the actor was trained so
    np.testing.assert_allclose(u_rl, np.asarray(case[3].nets.actor.apply(case[4][0], obs)), atol=1e-5)
    assert (u_rl[:, 0] >= 0).all() if case[2].td3.forward_only else (u_rl[:, 0] < 0).any()


def test_actions_equal_the_jax_policys_with_the_filter(case, states):
    """Equal to float tolerance, but where the filter's choice between two of its iterates turns on the
    sign of c at one the projection put on c = 0 (|c| ~ 1e-6): there both actions meet c ≥ 0."""
    _, _, cfg, learner, (_, safety) = case
    policy = Policy.load(case[1])
    _, obs, poses, qs, scans = states
    want = _jax_actions(case, states, runtime_filter=True)
    unfiltered = _jax_actions(case, states, runtime_filter=False)
    acted = np.abs(want - unfiltered).max(axis=1) > 1e-4
    assert 0.1 < acted.mean() < 0.9  # the filter acts at part of the states (not a test of nothing)
    got = np.stack([policy.act_observation(obs[i], poses[i], filter=True) for i in range(len(qs))])
    from_sensors = np.stack([policy.act(scans[i], poses[i], qs[i], filter=True) for i in range(len(qs))])
    diff = np.abs(got - want).max(axis=1)
    sensed = np.abs(from_sensors - want).max(axis=1)
    print(f"filter (acting at {acted.mean():.0%} of the states): abs difference {np.median(diff):.3g} median, "
          f"{diff.max():.3g} max, {(diff > 1e-6).sum()} of {len(diff)} above 1e-6, {(diff > 1e-4).sum()} above 1e-4; from readings "
          f"{(sensed > 1e-4).sum()} above 1e-4")
    assert (diff > 1e-4).mean() <= 0.05 and (sensed > 1e-4).mean() <= 0.05 and np.quantile(diff, 0.9) < 1e-5
    ctx = learner.sensed(jnp.ones((learner.n_obstacles,), bool))
    c = jax.jit(jax.vmap(lambda p, u: cbf_condition(learner.safety_nets, safety.cbf, safety.nominal, p, ctx, u,
                                                    cfg=learner.cbf_cfg, features_fn=learner.features, dt=learner.dt)))
    c_got, c_want = np.asarray(c(poses, got)), np.asarray(c(poses, want))
    assert np.all(c_got >= np.minimum(c_want, 0.0) - 1e-4)  # never less safe, by JAX's own c


@pytest.mark.parametrize("algo", ["td3", "sac-lag"])
def test_other_learners_export_their_actor(algo, case, states, tmp_path):
    """TD3's actor (td3, tlgrl, td3-lag) and SAC's evaluation action tanh(mean) (sac-lag, rcrl)."""
    cfg = dataclasses.replace(case[2], algo=algo)
    _, _, learner = build(cfg)
    carry = learner_program(learner, "init")(jax.random.PRNGKey(1))
    write_run(tmp_path / "run", cfg, carry)
    m = export_run(tmp_path / "run", tmp_path / "out")
    assert m["filter"] is None and "safety_policy" not in m["networks"]
    policy = Policy.load(tmp_path / "out")
    s, obs, *_ = states
    key = jax.random.PRNGKey(0)
    want = np.asarray(jax.jit(jax.vmap(lambda o, st: learner.act(learner.policy(carry), o, st, key)))(obs, s))
    got = np.stack([policy.act_observation(o) for o in obs])
    assert np.abs(got - want).max() < ACTION_TOLERANCE
    with pytest.raises(ValueError, match="no runtime filter"):
        policy.act_observation(obs[0], filter=True)


def test_commands_are_the_envs(case):
    """The exported (v, ω) of an action is the env's, for a robot that reverses and one that cannot."""
    _, out, cfg, learner, _ = case
    policy = Policy.load(out)
    actions = np.array([[a, b] for a in (-1.5, -1.0, -0.3, 0.0, 0.6, 1.0) for b in (-1.0, 0.25)], np.float32)
    want = np.asarray(jax.vmap(lambda a: dynamics.command(a, learner.params.dyn))(jnp.asarray(actions)))
    got = np.array([policy.command(a) for a in actions])
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    slowest = want[:, 0].min()
    assert slowest == (0.0 if not cfg.env.reverse else -want[:, 0].max())


def test_task_tracker_follows_the_envs_automaton(case):
    """Along a path through every area and back (relaxed and true labelling), the tracker's states are
    the env's labelling and transitions (``Env._letters``, ``ltl.labelling.next_state``)."""
    _, _, _, learner, _ = case
    env, params = learner.env, learner.params
    tracker = Policy.load(case[1]).task_tracker()
    stops = [np.asarray(params.start[:2])] + [np.asarray(c) for c in params.area_center] + [np.asarray(params.start[:2])]
    path = np.concatenate([np.linspace(a, b, 40, endpoint=False) for a, b in zip(stops, stops[1:])]).astype(np.float32)

    def step(carry, xy):
        q, letter = carry
        relaxed, _ = env._letters(xy, q, params)
        q = next_state(params.aut, q, relaxed, letter, params.event)
        return (q, relaxed), q

    q0 = jnp.asarray(params.aut.initial, jnp.int32)
    first, _ = env._letters(jnp.asarray(path[0]), q0, params)
    start = next_state(params.aut, q0, first, jnp.int32(0), params.event)
    _, want = jax.lax.scan(step, (start, first), jnp.asarray(path[1:]))
    got = [tracker.reset(*path[0])] + [tracker.update(*xy) for xy in path[1:]]
    assert got[0] == int(start) and got[1:] == np.asarray(want).tolist()
    assert len(set(got)) > 2 and tracker.completed == bool(params.aut.accepting[got[-1]])


@pytest.mark.parametrize("task, label_mode", [("patrol2", "event"), ("GF A1 & GF A2", "step"), ("phi1", "event")])
def test_task_tracker_counts_a_patrols_accepting_visits_as_the_env(task, label_mode):
    """A robot on a patrol never finishes; its laps are the accepting visits the env's info reports
    (``accepting_visit`` under the true labelling). The tracker of the exported automaton counts the
    same along a path that shuttles between the areas; a task with a finite goal counts none."""
    from d2spo.deploy.task import Automaton, TaskTracker
    from d2spo.envs import make_env
    from d2spo.export import _automaton, _layout
    from d2spo.ltl.labelling import accepting_visit

    env, params = make_env(EnvConfig(layout="paper", label_mode=label_mode), task)
    manifest = json.loads(json.dumps({"automaton": _automaton(env, params), "layout": _layout(env, params)}))
    tracker = TaskTracker(Automaton.of_manifest(manifest))
    centres = [np.asarray(c) for c in params.area_center]
    stops = [np.asarray(params.start[:2])] + [centres[i] for i in (0, 1, 2, 1, 0, 1, 2, 1, 0)]  # round A4
    path = np.concatenate([np.linspace(a, b, 30, endpoint=False) for a, b in zip(stops, stops[1:])]).astype(np.float32)

    def step(carry, xy):
        q, letter = carry
        _, true = env._letters(xy, q, params)
        visit = accepting_visit(params.aut, q, true, letter, params.event)
        return (next_state(params.aut, q, true, letter, params.event), true), visit

    q0 = jnp.asarray(params.aut.initial, jnp.int32)
    _, first = env._letters(jnp.asarray(path[0]), q0, params)
    start = next_state(params.aut, q0, first, jnp.int32(0), params.event)
    if params.aut.visit is None:
        assert manifest["automaton"]["visit"] is None
    else:
        _, want = jax.lax.scan(step, (start, first), jnp.asarray(path[1:]))
        want = np.asarray(want).tolist()
    tracker.reset(*path[0])
    got = []
    for xy in path[1:]:
        tracker.update(*xy)
        got.append(tracker.visited)
    if params.aut.visit is None:
        assert tracker.visits == 0 and not any(got)
    else:
        assert got == want and tracker.visits == sum(want) >= 2, (tracker.visits, sum(want))
    tracker.reset(*path[0])
    assert tracker.visits == 0


@pytest.mark.skipif(not (has_module("onnx") and has_module("onnxruntime")), reason="needs the extra d2spo[onnx]")
def test_onnx_graphs_run_as_the_numpy_networks(case, states):
    import onnxruntime

    out = case[1]
    numpy_policy, onnx_policy = Policy.load(out), Policy.load(out, backend="onnxruntime")
    _, obs, poses, *_ = states
    a = np.stack([numpy_policy.act_observation(o, filter=False) for o in obs])
    b = np.stack([onnx_policy.act_observation(o, filter=False) for o in obs])
    assert np.abs(a - b).max() < 1e-5
    x = np.stack([numpy_policy.x_of_observation(o) for o in obs])
    h = onnxruntime.InferenceSession(str(out / "cbf.onnx")).run(["h"], {"x": x})[0][:, 0]
    assert np.abs(h - np.array([numpy_policy.runtime_filter.h(v) for v in x])).max() < 1e-5
    u = np.random.default_rng(0).uniform(-1, 1, (len(obs), 2)).astype(np.float32)
    rate = onnxruntime.InferenceSession(str(out / "nominal.onnx")).run(["rate"], {"s": poses, "u": u})[0]
    mine = np.stack([numpy_policy.runtime_filter.nominal(np.r_[np.cos(p[2]), np.sin(p[2]), v].astype(np.float32))
                     for p, v in zip(poses, u)])
    assert np.abs(rate - mine).max() < 1e-5


def test_default_sized_d2spo_policy_exports_under_1_mb(tmp_path):
    """ϕ1's default networks (TD3 128-128, π_Ω, h and f_n 64-64), random weights (which compress as
    little as trained ones), with ONNX where the onnx package is here."""
    cfg = TrainConfig(algo="d2spo", task="phi1", env=EnvConfig(layout="paper"))
    cfg = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, pretrain=False))  # the same shapes
    built = build(cfg)
    learner = built[2]
    shapes = jax.eval_shape(lambda k: learner.policy(learner.init(k)), jax.random.PRNGKey(0))
    rng = np.random.default_rng(0)
    policy = jax.tree_util.tree_map(lambda t: rng.standard_normal(t.shape).astype(t.dtype), shapes)
    m = write_export(tmp_path / "out", cfg, built, policy, {"run": None}, ExportConfig(onnx=has_module("onnx")))
    total = sum(m["sizes"].values())
    print(f"default-sized export: {m['sizes']}, {total / 1024:.0f} KiB")
    assert total <= 1_000_000
    assert [layer["kernel"] for layer in m["networks"]["actor"]["layers"]] == ["actor.0.kernel", "actor.1.kernel",
                                                                               "actor.2.kernel"]
    assert np.load(tmp_path / "out" / "weights.npz")["actor.1.kernel"].shape == (128, 128)
