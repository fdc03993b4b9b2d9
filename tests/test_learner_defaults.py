"""``--fast`` (config.FAST_SETTINGS) and what None stands for otherwise (README "Departures")."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.algos.td3 import TD3Config, make_nets
from d2spo.cli import main
from d2spo.config import (
    DEFAULT_SETTINGS,
    FAST_SETTINGS,
    GENERALIST_SETTINGS,
    TrainConfig,
    config_from_dict,
    config_to_dict,
)
from d2spo.envs import EnvConfig
from d2spo.errors import ConfigError
from d2spo.safety.cbf import CBFConfig


def _speed(cfg: TrainConfig) -> dict:
    return {"num_envs": cfg.num_envs, "td3.hidden": cfg.td3.hidden}


@pytest.mark.parametrize("algo", ["d2spo", "sl", "td3", "tlgrl", "td3-lag", "sac-lag", "rcrl", "ppo-lag", "cpo"])
def test_every_learner_keeps_the_default_settings_without_fast(algo):
    assert _speed(TrainConfig(algo=algo)) == DEFAULT_SETTINGS


def test_the_generalist_gets_256_256_networks_unless_told_and_an_old_run_reads_back_as_it_ran():
    gen = TrainConfig(algo="d2spo", generalist=True)
    assert _speed(gen) == GENERALIST_SETTINGS and gen.td3.hidden == (256, 256) != DEFAULT_SETTINGS["td3.hidden"]
    assert config_to_dict(gen)["td3"]["hidden"] == [256, 256]  # recorded in config.json
    told = TrainConfig(algo="d2spo", generalist=True, td3=TD3Config(hidden=(128, 128)))
    assert told.td3.hidden == (128, 128)
    old = config_to_dict(told)  # a generalist trained before 256 256 became its default
    assert config_from_dict(old).td3.hidden == (128, 128)


@pytest.mark.parametrize("algo", ["d2spo", "sl"])
def test_fast_gives_the_cbf_learners_32_envs_and_64_64_networks(algo):
    assert _speed(TrainConfig(algo=algo, fast=True)) == FAST_SETTINGS != DEFAULT_SETTINGS


@pytest.mark.parametrize("kw", [{"algo": "tlgrl"}, {"algo": "td3-lag"}, {"algo": "d2spo", "generalist": True}])
def test_fast_is_refused_where_it_was_not_measured(kw):
    with pytest.raises(ConfigError, match="fast"):
        TrainConfig(fast=True, **kw)


def test_values_given_are_kept_and_config_json_records_the_resolved_ones():
    cfg = TrainConfig(algo="d2spo", fast=True, num_envs=8, td3=TD3Config(hidden=(32,)))
    assert _speed(cfg) == {"num_envs": 8, "td3.hidden": (32,)}
    d = config_to_dict(TrainConfig(algo="d2spo", fast=True))
    assert (d["num_envs"], d["td3"]["hidden"], d["fast"]) == (32, [64, 64], True)
    assert _speed(config_from_dict(d)) == FAST_SETTINGS
    # a config.json written before the flag existed has its values, and no "fast"
    del d["fast"]
    assert _speed(config_from_dict(d)) == FAST_SETTINGS and not config_from_dict(d).fast


def test_none_alone_means_the_default_widths():
    assert TD3Config().widths == (128, 128)
    nets = make_nets(2, TD3Config())
    assert nets.actor.hidden == (128, 128) and nets.critic.hidden == (128, 128)
    with pytest.raises(ConfigError, match="td3.hidden"):
        TD3Config(hidden=(0,))


def test_fast_on_the_command_line_for_another_learner_is_one_line(capsys):
    assert main(["train", "--algo", "tlgrl", "--fast", "--episodes", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("d2spo: error: --fast:")


def test_the_generalists_actor_proposes_forward_motion_and_old_runs_keep_theirs():
    """``td3.forward_only`` None: on for the generalist, off on one layout; a config.json written
    before the field existed (a generalist whose actor could propose reverse) reads back off."""
    gen = TrainConfig(algo="d2spo", generalist=True)
    assert gen.td3.forward_only is True and TrainConfig(algo="d2spo").td3.forward_only is False
    assert TrainConfig(algo="d2spo", generalist=True, td3=TD3Config(forward_only=False)).td3.forward_only is False
    d = config_to_dict(gen)
    assert d["td3"]["forward_only"] is True and config_from_dict(d).td3.forward_only is True
    del d["td3"]["forward_only"]
    assert config_from_dict(d).td3.forward_only is False


def test_the_exploration_noise_is_constant_unless_a_final_value_is_given():
    """``td3.exploration_noise_final``: None keeps TD3's constant noise (the same Python float, so the
    default program is traced as before); set, the noise falls on a straight line to it over the
    run's episodes and stays there (``RunSchedule.per_episode``: one episode's share of the run)."""
    import jax.numpy as jnp

    from d2spo.algos.base import RunSchedule
    from d2spo.ltl.anneal import AnnealConfig

    per_episode = RunSchedule.for_run(AnnealConfig(), 20000).per_episode
    assert TD3Config().noise_at(jnp.int32(5000), per_episode) == 0.2
    cfg = TD3Config(exploration_noise=0.2, exploration_noise_final=0.05)
    at = [float(cfg.noise_at(jnp.int32(e), per_episode)) for e in (0, 10000, 20000, 25000)]
    assert at == pytest.approx([0.2, 0.125, 0.05, 0.05])
    with pytest.raises(ConfigError, match="exploration_noise_final"):
        TD3Config(exploration_noise_final=-0.1)


def test_a_patrol_on_one_layout_anneals_its_exploration_noise_unless_told_otherwise():
    """``td3.recurrence_noise_final``: a recurrence trained on one layout (td3, tlgrl, d2spo, sl) takes
    it as its ``exploration_noise_final`` when that is None; a task that completes keeps the constant
    noise (its learner's config is the very object, so its program is traced as before); an explicit
    final value, or None, wins; a config.json written before the field keeps the constant noise."""
    from d2spo.run import build

    assert TD3Config().recurrence_noise_final == 0.05
    assert TD3Config().for_task(False) == TD3Config() and TD3Config().for_task(True).exploration_noise_final == 0.05
    assert TD3Config(exploration_noise_final=0.1).for_task(True).exploration_noise_final == 0.1
    assert TD3Config(recurrence_noise_final=None).for_task(True).exploration_noise_final is None
    small = dict(episodes=8, num_envs=2, td3=TD3Config(hidden=(8, 8), batch_size=8))
    for algo in ("tlgrl", "d2spo"):
        patrol = TrainConfig(algo=algo, task="G F A1 & G F A3 & G !A4", **small).check()
        assert build(patrol)[2].cfg.exploration_noise_final == 0.05, algo
        phi1 = TrainConfig(algo=algo, task="phi1", **small).check()
        assert build(phi1)[2].cfg is phi1.td3, algo
    d = config_to_dict(patrol)
    del d["td3"]["recurrence_noise_final"]
    assert config_from_dict(d).td3.recurrence_noise_final is None
    old = config_to_dict(TrainConfig(algo="td3-lag"))
    del old["td3_lag"]["td3"]["recurrence_noise_final"]
    assert config_from_dict(old).td3_lag.td3.recurrence_noise_final is None


def test_td3_lag_anneals_a_patrols_exploration_noise_as_d2spo_does():
    """td3-lag explored a patrol with its constant noise (its loop's behaviour hook saw no episode
    count) while D²SPO's fell from 0.2 to 0.05: a patrol comparison favoured D²SPO. Its exploration now
    follows the same schedule, and a task that completes keeps the constant noise."""
    from d2spo.algos.td3_lag import TD3LagConfig
    from d2spo.run import build

    lag = TD3LagConfig(td3=TD3Config(hidden=(8, 8), batch_size=8))
    small = dict(episodes=100, num_envs=2, td3_lag=lag)
    for task, final in (("G F A1 & G F A3 & G !A4", 0.05), ("phi1", None)):
        cfg = TrainConfig(algo="td3-lag", task=task, **small).check()
        learner = build(cfg)[2]
        assert learner.cfg.td3.exploration_noise_final == final, task
        carry = jax.jit(learner.init)(jax.random.PRNGKey(0))
        key, obs = jax.random.PRNGKey(1), carry.obs
        first, last = (learner.behaviour(carry.agent, obs, key, jnp.int32(e)) for e in (0, 100))
        assert (np.abs(np.asarray(first) - np.asarray(last)).max() > 1e-3) == (final is not None), task
    given = TrainConfig(algo="td3-lag", td3_lag=TD3LagConfig(td3=TD3Config(exploration_noise_final=0.1))).check()
    assert build(dataclasses.replace(given, num_envs=2))[2].cfg.td3.exploration_noise_final == 0.1


@pytest.mark.parametrize("term", ["smoothness", "saturation", "speed-search"])
def test_td3_lag_refuses_the_actor_terms_its_loss_lacks(capsys, term):
    with pytest.raises(SystemExit) as e:
        main(["train", "--algo", "td3-lag", f"--td3-lag.td3.{term}", "1", "--out", "/nonexistent/x"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"d2spo: error: --td3-lag.td3.{term}: "), err


def test_the_actor_terms_check_their_values():
    with pytest.raises(ConfigError, match="smoothness"):
        TD3Config(smoothness=-1.0)
    for dims in ((2,), (), (1, 1)):
        with pytest.raises(ConfigError, match="smoothness_dims"):
            TD3Config(smoothness_dims=dims)
    assert TD3Config(smoothness_dims=(1,)).smoothness_dims == (1,)
    with pytest.raises(ConfigError, match="saturation"):
        TD3Config(saturation=-1.0)
    with pytest.raises(ConfigError, match="saturation_bound"):
        TD3Config(saturation_bound=0.0)
    assert TD3Config().saturation == 0.0  # off by default: the actor's loss as before
    with pytest.raises(ConfigError, match="speed_search"):
        TD3Config(speed_search=-1.0)
    assert TD3Config().speed_search == 0.0


def _update_steps(cfg: TrainConfig) -> tuple:
    return cfg.cbf.nominal_updates_per_iter, cfg.cbf.updates_per_iter


PATROL = "G F A1 & G F A3 & G !A4"


@pytest.mark.parametrize(("kw", "steps"), [
    ({}, (10, 10)),  # ϕ1 with 5 and 5: vmapped seeds 0-5 completed 98.70-99.95%, four under Table II's 99.5%
    ({"task": "relaxed"}, (10, 10)),
    ({"task": "G !A4 & F A3"}, (10, 10)),  # a never part, but finite
    ({"task": PATROL}, (5, 5)),
    ({"task": "patrol3"}, (5, 5)),
    ({"task": PATROL, "algo": "sl"}, (5, 5)),
    ({"task": "G F (A1 & F A2"}, (10, 10)),  # no formula: refused where it is built, not here
    ({"task": PATROL, "generalist": True}, (10, 10)),
    ({"task": PATROL, "fast": True}, (10, 10)),  # --fast's ϕ1 seed 0 with 5 and 5: 85.20% against 99.70%
    ({"task": PATROL, "env": EnvConfig(preset="turtlebot")}, (10, 10)),
    ({"task": PATROL, "env": EnvConfig(v_gain=0.9)}, (10, 10)),  # the default preset, but not its robot
    ({"task": PATROL, "env": EnvConfig(robot_radius=0.1)}, (10, 10)),
])
def test_update_omega_theta_is_halved_for_a_patrol_on_one_layout_with_the_default_robot_only(kw, steps):
    """UPDATE(Ω, Θ)'s steps None: 5 and 5 for a recurrence on one layout with the default robot
    (not --fast), where half the count made more accepting visits; 10 and 10 everywhere else; a
    value given is kept, and config.json records the resolved counts."""
    cfg = TrainConfig(**kw)
    assert _update_steps(cfg) == steps
    assert _update_steps(config_from_dict(config_to_dict(cfg))) == steps
    given = TrainConfig(**kw, cbf=CBFConfig(updates_per_iter=7))
    assert _update_steps(given) == (steps[0], 7)


@pytest.mark.parametrize(("kw", "batch"), [
    ({}, 128),  # ϕ1 on paper: 3 minutes with Tables II-III held (bench/RESULTS.md, "2026-12-04, afternoon")
    ({"task": "relaxed"}, 128),
    ({"task": "G !A4 & F A3"}, 128),  # a never part, but finite
    ({"algo": "sl"}, 128),
    ({"env": EnvConfig(preset="turtlebot")}, 256),  # Fig. 4's robot: measured at 256
    ({"env": EnvConfig(v_gain=0.9)}, 256),  # the default preset, but not its robot
    ({"task": PATROL}, 256),  # measured with 5 and 5 steps at 256
    ({"task": "G F (A1 & F A2"}, 256),  # no formula: refused where it is built, not here
    ({"generalist": True}, 256),
    ({"fast": True}, 256),
])
def test_the_safety_minibatch_is_128_for_a_finite_task_on_one_layout_only(kw, batch):
    """``cbf.batch_size`` None: 128 for a task that is not a recurrence, on one layout, with the
    default robot, without --fast; 256 everywhere else; a value given is kept, and config.json
    records the resolved one."""
    cfg = TrainConfig(**kw)
    assert cfg.cbf.batch_size == batch == cfg.cbf.minibatch
    assert config_from_dict(config_to_dict(cfg)).cbf.batch_size == batch
    assert TrainConfig(**kw, cbf=CBFConfig(batch_size=64)).cbf.minibatch == 64


def test_a_config_json_of_before_the_minibatch_default_reads_back_256():
    d = config_to_dict(TrainConfig())
    d["cbf"]["batch_size"] = 256  # what every run recorded before 2026-12-04 (afternoon)
    assert config_from_dict(d).cbf.minibatch == 256
    assert CBFConfig().minibatch == 256  # a CBFConfig on its own
    with pytest.raises(ConfigError, match="batch_size"):
        CBFConfig(batch_size=0)


def test_a_config_json_without_the_update_steps_reads_back_the_former_ten():
    d = config_to_dict(TrainConfig())
    del d["cbf"]["updates_per_iter"], d["cbf"]["nominal_updates_per_iter"]
    assert _update_steps(config_from_dict(d)) == (10, 10)


def test_a_cbf_config_on_its_own_takes_ten_and_ten():
    assert (CBFConfig().nominal_steps, CBFConfig().eq9_steps) == (10, 10)
    assert (CBFConfig(nominal_updates_per_iter=0, updates_per_iter=3).nominal_steps,
            CBFConfig(updates_per_iter=3).eq9_steps) == (0, 3)
    with pytest.raises(ConfigError, match="updates_per_iter"):
        CBFConfig(updates_per_iter=0)


@pytest.mark.parametrize("algo, extra, kept", [("td3-lag", [], {}), ("d2spo", [], {}),
                                               ("d2spo", ["--num-envs", "32"], {"num_envs": 32}),
                                               ("td3-lag", ["--td3-lag.td3.hidden", "64", "64"], {"td3.hidden": (64, 64)})])
def test_no_fast_over_a_fast_runs_config_json_gives_the_learners_own_defaults(algo, extra, kept, tmp_path, recwarn):
    """A user trial (2026-12-03): `train --config FAST/config.json --algo td3-lag --no-fast` kept the
    32 envs and 64-64 networks --fast had recorded, and the baseline trained at half its own update
    rate without a word. Now the values --fast gave go back to the learner's defaults unless a flag
    sets them again, with a warning naming each; --fast itself over another learner says --no-fast."""
    from d2spo import cli
    from d2spo.errors import D2SPOWarning

    path = tmp_path / "config.json"
    path.write_text(__import__("json").dumps(config_to_dict(TrainConfig(algo="d2spo", fast=True))))
    cfg = cli.parse(["train", "--config", str(path), "--algo", algo, "--no-fast", *extra]).config()
    assert not cfg.fast and _speed(cfg) == {**DEFAULT_SETTINGS, **kept}
    assert (cfg.cbf.updates_per_iter, cfg.cbf.nominal_updates_per_iter) == (10, 10)  # ϕ1's, with or without --fast
    assert cfg.cbf.batch_size == 128  # --fast's 256 gives way to ϕ1's own
    said = [str(w.message) for w in recwarn if issubclass(w.category, D2SPOWarning)]
    assert len(said) == 1 and ("num_envs 32 -> 16" in said[0]) == ("num_envs" not in kept), said
    assert "cbf.updates_per_iter" not in said[0], said
    assert ("cbf.batch_size 256 -> 128" in said[0]) == (algo == "d2spo"), said
    assert cli.parse(["train", "--config", str(path)]).config() == TrainConfig(algo="d2spo", fast=True)
    with pytest.raises(ConfigError, match="over the --config file of a --fast run: --no-fast"):
        cli.parse(["train", "--config", str(path), "--algo", "td3-lag"])


def test_no_fast_over_a_fast_patrols_config_json_gives_back_the_patrols_halved_steps(tmp_path, recwarn):
    """--fast records 10 and 10 steps of UPDATE(Ω, Θ); `--no-fast` over its config.json gives a patrol
    on one layout its own 5 and 5 again, and the warning names the change."""
    from d2spo import cli
    from d2spo.errors import D2SPOWarning

    path = tmp_path / "config.json"
    path.write_text(__import__("json").dumps(config_to_dict(TrainConfig(algo="d2spo", task=PATROL, fast=True))))
    cfg = cli.parse(["train", "--config", str(path), "--no-fast"]).config()
    assert (cfg.cbf.updates_per_iter, cfg.cbf.nominal_updates_per_iter) == (5, 5)
    said = [str(w.message) for w in recwarn if issubclass(w.category, D2SPOWarning)]
    assert len(said) == 1 and "cbf.updates_per_iter 10 -> 5" in said[0], said
