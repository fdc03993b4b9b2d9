"""The speed settings None stands for, per learner (config.LEARNER_DEFAULTS, README "Departures")."""

from __future__ import annotations

import pytest

from d2spo.algos.td3 import TD3Config, make_nets
from d2spo.config import FORMER_SPEED_SETTINGS, LEARNER_DEFAULTS, TrainConfig, config_from_dict, config_to_dict
from d2spo.errors import ConfigError


def _speed(cfg: TrainConfig) -> dict:
    return {"num_envs": cfg.num_envs, "td3.hidden": cfg.td3.hidden}


@pytest.mark.parametrize("algo", ["d2spo", "sl"])
def test_the_cbf_learners_on_one_layout_get_the_fast_settings(algo):
    assert _speed(TrainConfig(algo=algo)) == LEARNER_DEFAULTS
    assert LEARNER_DEFAULTS != FORMER_SPEED_SETTINGS


@pytest.mark.parametrize("algo", ["td3", "tlgrl", "td3-lag", "sac-lag", "rcrl", "ppo-lag", "cpo"])
def test_every_other_learner_keeps_its_former_settings(algo):
    assert _speed(TrainConfig(algo=algo)) == FORMER_SPEED_SETTINGS


def test_the_generalist_keeps_its_former_settings():
    assert _speed(TrainConfig(algo="d2spo", generalist=True)) == FORMER_SPEED_SETTINGS


def test_values_given_are_kept_and_config_json_records_the_resolved_ones():
    cfg = TrainConfig(algo="d2spo", num_envs=8, td3=TD3Config(hidden=(32,)))
    assert _speed(cfg) == {"num_envs": 8, "td3.hidden": (32,)}
    d = config_to_dict(TrainConfig(algo="d2spo"))
    assert (d["num_envs"], d["td3"]["hidden"]) == (32, [64, 64])
    # a run trained before the change recorded its own values, and keeps them
    d.update(num_envs=16)
    d["td3"]["hidden"] = [128, 128]
    assert _speed(config_from_dict(d)) == FORMER_SPEED_SETTINGS


def test_none_alone_means_the_former_widths():
    assert TD3Config().widths == (128, 128)
    nets = make_nets(2, TD3Config())
    assert nets.actor.hidden == (128, 128) and nets.critic.hidden == (128, 128)
    with pytest.raises(ConfigError, match="td3.hidden"):
        TD3Config(hidden=(0,))
