"""Custom dynamics: a JSON file with every dynamics field (`--dynamics FILE.json` for `d2spo train` and
`d2spo eval`), validated like a layout: one line naming the field, exit status 2."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import pytest

from d2spo import cli
from d2spo.envs import EnvConfig, make_env
from d2spo.envs.dynamics import DYNAMICS_FIELDS, load_dynamics
from d2spo.errors import ConfigError

SLOW_ROBOT = {"name": "slow-bot", "dt": 0.1, "v_max": 0.5, "omega_max": 1.0, "actuator_tau": 0.0, "v_gain": 1.0,
              "omega_gain": 1.0, "slip": 0.0, "noise_xy": 0.0, "noise_theta": 0.0}


def write(tmp_path, data, name="robot.json"):
    path = tmp_path / name
    if isinstance(data, bytes):
        path.write_bytes(data)
    else:
        path.write_text(data if isinstance(data, str) else json.dumps(data))
    return path


def test_a_dynamics_file_changes_the_env(tmp_path):
    values = load_dynamics(write(tmp_path, SLOW_ROBOT))
    assert set(values) == set(DYNAMICS_FIELDS) and values["v_max"] == 0.5
    env_cfg = EnvConfig(layout="open", start_jitter_xy=0.0, start_jitter_theta=0.0)
    env, params = make_env(env_cfg, task="F A1")
    _, custom = make_env(EnvConfig(**{**env_cfg.__dict__, **values}), task="F A1")

    @jax.jit
    def distance(params):  # 5 steps full speed ahead; the dynamics live in params.dyn
        state, _ = env.reset(jax.random.PRNGKey(0), params)
        step = lambda s, k: (env.step(k, s, jnp.array([1.0, 0.0]), params)[0], None)
        state, _ = jax.lax.scan(step, state, jax.random.split(jax.random.PRNGKey(1), 5))
        return jnp.linalg.norm(state.pose[:2] - params.start[:2])

    moved = {"preset": float(distance(params)), "file": float(distance(custom))}
    # no lag, gain 1, no slip or noise: 5 steps of 0.1 s at 0.5 m/s
    assert moved["file"] == pytest.approx(0.25, abs=1e-5)
    assert moved["preset"] > 0.35  # the default preset's 1 m/s (with its lag, gain and slip)


def test_train_reads_the_file_and_flags_override_it(tmp_path):
    path = write(tmp_path, SLOW_ROBOT)
    cmd = cli.parse(["train", "--dynamics", str(path), "--v-gain", "0.7", "--episodes", "10"])
    cfg = cmd.config()
    assert cfg.env.v_max == 0.5 and cfg.env.omega_max == 1.0 and cfg.env.slip == 0.0
    assert cfg.env.v_gain == 0.7  # the flag wins over the file
    assert cli.parse(["train"]).config().env.v_max is None  # no file: the preset's
    # UPDATE(Ω, Θ)'s steps: a patrol's halved only for the default robot; a file's robot takes 10
    # unless a flag says otherwise (config.TrainConfig._resolve_cbf_fields)
    steps = lambda c: (c.cbf.nominal_updates_per_iter, c.cbf.updates_per_iter)  # noqa: E731
    assert steps(cli.parse(["train", "--task", "patrol2"]).config()) == (5, 5)
    assert steps(cli.parse(["train", "--task", "patrol2", "--dynamics", str(path)]).config()) == (10, 10)
    assert steps(cli.parse(["train", "--task", "patrol2", "--dynamics", str(path), "--cbf.updates-per-iter",
                            "5"]).config()) == (10, 5)
    # and the minibatch: 128 for ϕ1 with the default robot, 256 for a file's (cbf.ONE_LAYOUT_BATCH_SIZE)
    assert cli.parse(["train"]).config().cbf.batch_size == 128
    assert cli.parse(["train", "--dynamics", str(path)]).config().cbf.batch_size == 256
    assert cli.parse(["train", "--dynamics", str(path), "--cbf.batch-size", "64"]).config().cbf.batch_size == 64



def test_a_file_beside_config_replaces_the_robot_the_config_recorded(tmp_path):
    """`train --config RUN/config.json --dynamics NEW.json` kept the config's recorded dynamics (every
    value of a robot given before is in it) and its UPDATE(Ω, Θ) steps; flags still win over the file."""
    from d2spo.config import config_to_dict

    first = cli.parse(["train", "--dynamics", str(write(tmp_path, SLOW_ROBOT)), "--episodes", "10"]).config()
    (tmp_path / "config.json").write_text(json.dumps(config_to_dict(first)))
    fast = write(tmp_path, {**SLOW_ROBOT, "v_max": 1.5, "omega_max": 3.0}, "fast.json")
    cfg = cli.parse(["train", "--config", str(tmp_path / "config.json"), "--dynamics", str(fast)]).config()
    assert (cfg.env.v_max, cfg.env.omega_max) == (1.5, 3.0)
    cfg = cli.parse(["train", "--config", str(tmp_path / "config.json"), "--dynamics", str(fast),
                     "--v-max", "0.9"]).config()
    assert (cfg.env.v_max, cfg.env.omega_max) == (0.9, 3.0)
    # a flag typed again with the config's own value wins too (it was taken for unset, the file's 1.5 won)
    cfg = cli.parse(["train", "--config", str(tmp_path / "config.json"), "--dynamics", str(fast),
                     "--v-max", "0.5"]).config()
    assert (cfg.env.v_max, cfg.env.omega_max) == (0.5, 3.0)
    cfg = cli.parse(["train", "--config", str(tmp_path / "config.json"), "--dynamics", str(fast),
                     "--v_max", "0.5"]).config()  # tyro's other spelling of the flag
    assert (cfg.env.v_max, cfg.env.omega_max) == (0.5, 3.0)
    # a patrol's config of the default robot (5 and 5 steps) with a file: the file's robot's 10 and 10
    default = cli.parse(["train", "--task", "patrol2", "--episodes", "10"]).config()
    (tmp_path / "default.json").write_text(json.dumps(config_to_dict(default)))
    cfg = cli.parse(["train", "--config", str(tmp_path / "default.json"), "--dynamics", str(fast)]).config()
    assert (cfg.cbf.nominal_updates_per_iter, cfg.cbf.updates_per_iter) == (10, 10)


@pytest.mark.parametrize("content, field, words", [
    ({k: v for k, v in SLOW_ROBOT.items() if k != "slip"}, "dynamics.slip", "missing"),
    ({**SLOW_ROBOT, "v_max": "fast"}, "dynamics.v_max", "expected a finite number, got 'fast'"),
    ({**SLOW_ROBOT, "noise_xy": -0.01}, "dynamics.noise_xy", "must be non-negative, got -0.01"),
    ({**SLOW_ROBOT, "dt": 0}, "dynamics.dt", "must be positive"),
    ({**SLOW_ROBOT, "slip": 1.0}, "dynamics.slip", "must be in [0, 1)"),
    ({**SLOW_ROBOT, "wheel_base": 0.2}, "dynamics", "unknown keys ['wheel_base']"),
    ({**SLOW_ROBOT, "robot_radius": 0.2}, "dynamics", "robot_radius is not dynamics: the robot's size is --robot-radius"),
    ([1, 2], "dynamics", "expected a JSON object"),
    ('{"dt": 0.1,', "dynamics", "malformed JSON"),
    ('{"name": "r\xe9"}'.encode("latin-1"), "dynamics", "not UTF-8"),
])
def test_bad_files_give_one_line_and_exit_2(tmp_path, capsys, content, field, words):
    path = write(tmp_path, content)
    with pytest.raises(ConfigError) as e:
        load_dynamics(path)
    assert e.value.field == field and words in str(e.value)
    assert cli.main(["train", "--dynamics", str(path), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    shown = "--dynamics" if field == "dynamics" else field  # the flag typed, or the file's own field
    assert len(err) == 1 and err[0].startswith(f"d2spo: error: {shown}: ") and words in err[0], err
    assert not (tmp_path / "run").exists()  # nothing written


def test_a_file_that_starts_with_a_byte_order_mark_loads(tmp_path):
    """Windows editors write UTF-8 with a BOM: the file is read as the same JSON."""
    import json

    plain = load_dynamics(write(tmp_path, SLOW_ROBOT))
    path = tmp_path / "bom.json"
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(SLOW_ROBOT).encode())
    assert load_dynamics(path) == plain


def test_missing_file(tmp_path, capsys):
    assert cli.main(["train", "--dynamics", str(tmp_path / "nope.json")]) == 2
    assert "dynamics: cannot read" in capsys.readouterr().err


def test_the_example_in_the_docs_loads(tmp_path):
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "env.md").read_text()
    example = text.split("### Custom dynamics", 1)[1].split("```json\n", 1)[1].split("```", 1)[0]
    values = load_dynamics(write(tmp_path, example))
    assert values["actuator_tau"] == 0.12 and EnvConfig(**values).resolved().v_max == 0.5


@pytest.mark.parametrize("flags, words", [
    (["--dt", "1e-9"], "episode limit: relaxed's shortest route needs over 100,000 steps"),  # was an OverflowError
    (["--dt", "1e-300"], "episode limit: "),
    (["--v-max", "0.0001"], "episode limit: "),  # was a silent hang: an episode limit of millions of steps
    (["--v-max", "1e39"], "--v-max: must be at most 1e+06"),  # overflowed float32 and stopped as "non-finite"
])
def test_dynamics_that_no_episode_could_run_are_refused_in_one_line(tmp_path, capsys, flags, words):
    try:  # a flag's value is refused while parsing (SystemExit 2), the derived limit when the env is built
        rc = cli.main(["train", "--task", "relaxed", "--layout", "relaxed", *flags, "--episodes", "4",
                       "--out", str(tmp_path / "run")])
    except SystemExit as e:
        rc = e.code
    assert rc == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and words in err[0], err
    with pytest.raises(ConfigError, match="must be at most"):
        load_dynamics(write(tmp_path, {**SLOW_ROBOT, "noise_xy": 1e300}))
