"""`d2spo export` and `d2spo.deploy`: the exported policy acts as the JAX policy does (π_rl, π_Ω, the
runtime filter), builds the env's observation from the robot's readings, keeps the automaton state
as the env does, loads without JAX, fits in 1 MB for the default networks, and bad input gets one
line and exit status 2."""

from __future__ import annotations

import dataclasses
import json
import runpy
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _tiny import tiny_cfg, write_run

from d2spo import cli
from d2spo.algos import make_learner
from d2spo.config import TrainConfig
from d2spo.deploy import Policy
from d2spo.envs import EnvConfig, dynamics, sensors
from d2spo.errors import ArtefactError
from d2spo.export import ExportConfig, export_run, write_export
from d2spo.ltl.labelling import next_state
from d2spo.run import build
from d2spo.safety.filter import cbf_condition
from d2spo.train import learner_program

ROOT = Path(__file__).resolve().parent.parent






def _has(module: str) -> bool:
    try:
        __import__(module)
    except ImportError:
        return False
    return True


OFFICE = {"name": "office", "arena": [5.0, 4.0], "start": [0.6, 0.6, 0.0],
          "obstacles": [{"center": [2.5, 2.0], "radius": 0.4}, {"center": [2.5, 0.5], "half_extents": [0.25, 0.25]},
                        {"center": [1.7, 2.6], "radius": 0.3}],
          "areas": [{"name": "desk-1", "label": "desk", "center": [4.2, 0.9], "radius": 0.35},
                    {"name": "desk-2", "label": "desk", "center": [0.8, 3.3], "radius": 0.35},
                    {"name": "kitchen", "center": [4.2, 3.2], "radius": 0.35}]}
"""A layout with disk obstacles, a non-square arena and two areas sharing a label (docs/layouts.md)."""


def _tiny_run(root: Path, cfg: TrainConfig):
    """(run dir, export dir, cfg, learner, policy): an untrained tiny D²SPO run whose h is set by hand to
    tanh(4 min(x)/H - 1), a barrier that crosses zero 0.3 m from obstacles (so the filter acts at part
    of the arena), and its export (with ONNX where the onnx package is here)."""
    _, _, learner = build(cfg)
    carry = learner_program(learner, "init")(jax.random.PRNGKey(0))
    p = jax.tree_util.tree_map(np.zeros_like, carry.safety.cbf)
    p["params"]["Dense_0"]["kernel"][-1, 0] = 4.0  # the input's last entry is min(x)/H
    p["params"]["Dense_0"]["bias"][0] = -1.0
    p["params"]["Dense_1"]["kernel"][0, 0] = 1.0
    carry = carry.replace(safety=carry.safety.replace(cbf=jax.tree_util.tree_map(jnp.asarray, p)))
    write_run(root / "run", cfg, carry)
    export_run(root / "run", root / "out", ExportConfig(onnx=_has("onnx")))
    return root / "run", root / "out", cfg, learner, learner.policy(carry)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """``_tiny_run`` of ϕ1 on ``paper``."""
    return _tiny_run(tmp_path_factory.mktemp("export"), tiny_cfg())


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
    return _tiny_run(root, dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, reverse=False),
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
    assert np.abs(built - obs).max() < 1e-5
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
    assert np.abs(from_obs - want).max() < 1e-5 and np.abs(from_sensors - want).max() < 1e-5
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
    assert np.abs(got - want).max() < 1e-5
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


@pytest.mark.skipif(not (_has("onnx") and _has("onnxruntime")), reason="needs the extra d2spo[onnx]")
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
    m = write_export(tmp_path / "out", cfg, built, policy, {"run": None}, ExportConfig(onnx=_has("onnx")))
    total = sum(m["sizes"].values())
    print(f"default-sized export: {m['sizes']}, {total / 1024:.0f} KiB")
    assert total <= 1_000_000
    assert [layer["kernel"] for layer in m["networks"]["actor"]["layers"]] == ["actor.0.kernel", "actor.1.kernel",
                                                                               "actor.2.kernel"]
    assert np.load(tmp_path / "out" / "weights.npz")["actor.1.kernel"].shape == (128, 128)


def test_the_example_drives_the_export_from_a_gymnasium_loop(tiny, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["deploy_gym_loop.py", str(tiny[1]), "--episodes", "2", "--filter", "on"])
    runpy.run_path(str(ROOT / "examples" / "deploy_gym_loop.py"), run_name="__main__")
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3 and not any("differed" in ln for ln in lines)  # the tracker kept the env's state
    assert json.loads(lines[-1])["episodes"] == 2 and json.loads(lines[-1])["runtime_filter"] == "on"


def test_a_new_export_removes_the_files_only_the_one_it_replaces_had(tiny, tmp_path):
    """An earlier export with --onnx left policy.onnx & co.; exporting again without --onnx must not
    leave them beside the new manifest, where a robot stack reading policy.onnx would run the old run."""
    import shutil

    out = tmp_path / "again"
    shutil.copytree(tiny[1], out)
    manifest = json.loads((out / "manifest.json").read_text())
    if not manifest["onnx"]:  # where the onnx package is missing, as an export with --onnx lists them
        manifest["onnx"] = {"policy": {"file": "policy.onnx", "sha256": "0"}, "cbf": {"file": "cbf.onnx", "sha256": "0"}}
        (out / "manifest.json").write_text(json.dumps(manifest))
        for name in ("policy.onnx", "cbf.onnx"):
            (out / name).write_bytes(b"old")
    assert any(f.suffix == ".onnx" for f in out.iterdir())
    (out / "notes.txt").write_text("mine")  # not listed by the export: left alone
    export_run(tiny[0], out, ExportConfig(onnx=False))
    assert sorted(f.name for f in out.iterdir()) == ["manifest.json", "notes.txt", "weights.npz"]


def test_the_example_refuses_a_path_that_is_not_a_policy_in_one_line(tiny, tmp_path, capsys, monkeypatch):
    for path in (tmp_path / "nope", tiny[1] / "manifest.json"):
        monkeypatch.setattr(sys, "argv", ["deploy_gym_loop.py", str(path)])
        with pytest.raises(SystemExit) as e:
            runpy.run_path(str(ROOT / "examples" / "deploy_gym_loop.py"), run_name="__main__")
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and len(err) == 1 and "error:" in err[0], err


def test_an_export_given_where_a_run_is_asked_for_is_named_as_an_export(tiny, capsys):
    for command in (["eval", str(tiny[1])], ["export", str(tiny[1]), "--out", str(tiny[1].parent / "x")]):
        assert cli.main(command) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "is an exported policy (`d2spo export`), not a run directory" in err[0], err


def _one_error_line(capsys, args) -> str:
    assert cli.main(args) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("d2spo: error: "), err
    return err[0]


def test_export_command_and_bad_input(tiny, tmp_path, capsys):
    run = tiny[0]
    assert cli.main(["export", str(run), "--out", str(tmp_path / "cli"), "--runtime-filter", "True",
                     "--filter-iters", "5"]) == 0
    assert "runtime filter on by default" in capsys.readouterr().out
    assert Policy.load(tmp_path / "cli").filter_on and Policy.load(tmp_path / "cli").runtime_filter.iters == 5
    assert cli.main(["export", str(run), "--out", str(tmp_path / "cli")]) == 0  # an earlier export is replaced
    assert not Policy.load(tmp_path / "cli").filter_on
    assert "no such run directory" in _one_error_line(capsys, ["export", str(tmp_path / "nothing"), "--out",
                                                               str(tmp_path / "o")])
    write_run(tmp_path / "nockpt", tiny_cfg())
    assert "no checkpoint" in _one_error_line(capsys, ["export", str(tmp_path / "nockpt"), "--out", str(tmp_path / "o")])
    (tmp_path / "file").write_text("x")
    assert "exists and is not a directory" in _one_error_line(capsys, ["export", str(run), "--out",
                                                                       str(tmp_path / "file")])
    assert "holds no exported policy" in _one_error_line(capsys, ["export", str(run), "--out", str(run)])
    # a filter of no iterations would return the action as it is: refused, as eval and training refuse it
    assert "filter_iters: must be a positive integer, got 0" in _one_error_line(
        capsys, ["export", str(run), "--out", str(tmp_path / "o"), "--filter-iters", "0"])
    write_run(tmp_path / "ppo", tiny_cfg("ppo-lag"))
    assert "ppo-lag is not exported" in _one_error_line(capsys, ["export", str(tmp_path / "ppo"), "--out",
                                                                 str(tmp_path / "o")])
    write_run(tmp_path / "td3", tiny_cfg("td3"))
    assert "only D²SPO has a runtime filter" in _one_error_line(capsys, ["export", str(tmp_path / "td3"), "--out",
                                                                         str(tmp_path / "o"), "--filter-iters", "2"])
    assert not (tmp_path / "o").exists()


def test_a_damaged_or_foreign_export_is_refused(tiny, tmp_path):
    with pytest.raises(ArtefactError, match="is a run directory, not an export; `d2spo export"):
        Policy.load(tiny[0])
    with pytest.raises(ArtefactError, match="no such directory"):
        Policy.load(tmp_path / "nope")
    with pytest.raises(ArtefactError, match=r"is a file; give the directory `d2spo export` wrote \("):
        Policy.load(tiny[1] / "manifest.json")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ArtefactError, match="no manifest.json"):
        Policy.load(tmp_path / "empty")
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(tiny[1], copy)
    weights = copy / "weights.npz"
    weights.write_bytes(weights.read_bytes()[:-10])
    with pytest.raises(ArtefactError, match="damaged"):
        Policy.load(copy)
    manifest = json.loads((tiny[1] / "manifest.json").read_text())
    (copy / "manifest.json").write_text(json.dumps({**manifest, "format_version": 99}))
    with pytest.raises(ArtefactError, match="format version 99"):
        Policy.load(copy)
    shutil.copy(tiny[1] / "weights.npz", weights)
    (copy / "manifest.json").write_text(json.dumps({k: v for k, v in manifest.items() if k != "automaton"}))
    with pytest.raises(ArtefactError, match="damaged .KeyError"):
        Policy.load(copy)


@pytest.mark.parametrize("call, match", [
    (lambda p, r, pose: p.act(r, (0.6, 0.6, float("nan")), 0), r"pose must be .*entries \[2\] are not finite"),
    (lambda p, r, pose: p.act(r, (0.6, float("inf"), 0.0), 0), r"pose must be .*not finite"),
    (lambda p, r, pose: p.act(r, (0.6, 0.6), 0), "pose must be .*got 2 values"),
    (lambda p, r, pose: p.act(r, (50.0, 0.6, 0.0), 0), "outside the arena.*layout's frame, in metres"),
    (lambda p, r, pose: p.act(r[:3], pose, 0), "ranges must be 16 lidar ranges.*got 3 values"),
    (lambda p, r, pose: p.act(r.reshape(2, 8), pose, 0), "ranges must be 16 lidar ranges"),
    (lambda p, r, pose: p.act(["1.0"] * 16, pose, 0), "ranges must be 16 lidar ranges"),
    (lambda p, r, pose: p.act(None, pose, 0), "ranges must be 16 lidar ranges"),
    (lambda p, r, pose: p.act(np.where(np.arange(16) == 3, -0.5, r), pose, 0), r"lidar ranges \[3\] are negative"),
    (lambda p, r, pose: p.act(r, pose, 1.5), "q must be an integer automaton state"),
    (lambda p, r, pose: p.act(r, pose, True), "q must be an integer automaton state"),
    (lambda p, r, pose: p.act(r, pose, None), "q must be an integer automaton state"),
    (lambda p, r, pose: p.act(r, pose, 0, filter="yes"), "filter must be True, False or None"),
    (lambda p, r, pose: p.act_observation(np.full(p.observation_size, np.nan)), "obs must be .*not finite"),
    (lambda p, r, pose: p.act_observation(np.zeros(10)), "obs must be an observation of .*got 10 values"),
    (lambda p, r, pose: p.command([float("nan"), 0.0]), "action must be .*not finite"),
    (lambda p, r, pose: p.command(0.5), "action must be .*got 1 value$"),
    (lambda p, r, pose: p.filter(pose, [float("nan"), 0.0]), "u0 must be .*not finite"),
    (lambda p, r, pose: p.filter(pose, [0.1]), "u0 must be .*got 1 value"),
    (lambda p, r, pose: p.scan((float("nan"), 0.6, 0.0)), "pose must be"),
    (lambda p, r, pose: p.task_tracker().update(0.6, 0.6), "update before reset"),
    (lambda p, r, pose: p.task_tracker().reset(float("nan"), 0.6), "x must be a finite number"),
    (lambda p, r, pose: p.task_tracker().reset(0.6, None), "y must be a finite number"),
])
def test_every_runtime_call_refuses_malformed_input_in_one_value_error(tiny, call, match):
    """A robot's driver may hand the runtime a NaN pose, a scan of the wrong size or a float state:
    each is one ValueError naming the argument, never a NaN action (the first case returned
    [nan, nan] before) nor numpy's own message."""
    policy = Policy.load(tiny[1])
    pose = (0.6, 0.6, 0.0)
    with pytest.raises(ValueError, match=match):
        call(policy, policy.scan(pose), pose)


def test_a_policy_without_a_filter_says_so_when_asked_to_filter(tiny):
    """``policy.filter`` of an export without one (not D²SPO) is a ValueError, not 'NoneType' is not callable."""
    from d2spo.deploy.policy import Policy as P

    policy = P.load(tiny[1])
    policy.runtime_filter = None
    with pytest.raises(ValueError, match="no runtime filter"):
        policy.filter((0.6, 0.6, 0.0), [0.1, 0.0])
