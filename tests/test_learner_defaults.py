"""``--fast`` (config.FAST_SETTINGS) and what None stands for otherwise (README "Departures")."""

from __future__ import annotations

import pytest

from d2spo.algos.td3 import TD3Config, make_nets
from d2spo.cli import main
from d2spo.config import DEFAULT_SETTINGS, FAST_SETTINGS, TrainConfig, config_from_dict, config_to_dict
from d2spo.errors import ConfigError


def _speed(cfg: TrainConfig) -> dict:
    return {"num_envs": cfg.num_envs, "td3.hidden": cfg.td3.hidden}


@pytest.mark.parametrize("algo", ["d2spo", "sl", "td3", "tlgrl", "td3-lag", "sac-lag", "rcrl", "ppo-lag", "cpo"])
def test_every_learner_keeps_the_default_settings_without_fast(algo):
    assert _speed(TrainConfig(algo=algo)) == DEFAULT_SETTINGS
    assert _speed(TrainConfig(algo="d2spo", generalist=True)) == DEFAULT_SETTINGS


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
    assert len(err) == 1 and err[0].startswith("d2spo: error: fast:")


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
