"""Run configs: config.json round trips, an old config keeps the defaults it was trained with, the
differences a resume or a comparison reports ignore what the learner does not read, and the
learners' table (reward, annealing, sections, filter)."""

from __future__ import annotations

import dataclasses
import json

import pytest
from test_train import tiny

from d2spo.config import TrainConfig, config_from_dict, config_to_dict
from d2spo.errors import ConfigError


def test_config_round_trip_and_errors():
    cfg = tiny()
    assert config_from_dict(json.loads(json.dumps(config_to_dict(cfg)))) == cfg
    with pytest.raises(ConfigError, match="algo"):
        dataclasses.replace(cfg, algo="nope").check()
    with pytest.raises(ConfigError, match="episodes"):
        dataclasses.replace(cfg, episodes=0).check()
    bad = config_to_dict(cfg)
    bad["td3"]["no_such_field"] = 1
    with pytest.raises(ConfigError, match="td3.no_such_field"):
        config_from_dict(bad)


def test_old_config_keeps_the_default_it_was_trained_with():
    """A config.json written before shaping_clearance existed was trained with None (the robot
    radius), not with today's default 0.3: reading it back (e.g. to resume) must say so. A missing
    key whose default never changed takes today's default."""
    old = config_to_dict(TrainConfig())
    del old["env"]["reward"]["shaping_clearance"]
    del old["cbf"]["filter_alpha_coef"]
    cfg = config_from_dict(old)
    assert cfg.env.reward.shaping_clearance is None and TrainConfig().env.reward.shaping_clearance == 0.3
    assert cfg.cbf.filter_alpha_coef == TrainConfig().cbf.filter_alpha_coef
    # the episode limit of an unset max_steps: 200 steps before base_max_steps existed
    del old["env"]["base_max_steps"]
    assert config_from_dict(old).env.base_max_steps == 200 and TrainConfig().env.base_max_steps == 300


def test_effective_differences_ignore_what_the_learner_does_not_read():
    from d2spo.config_diff import config_differences
    from d2spo.ltl.reward import RewardConfig

    base = TrainConfig()
    other_reward = dataclasses.replace(base, env=dataclasses.replace(base.env, reward=RewardConfig(shaping_clearance=None)))
    assert config_differences(other_reward, base) == ["env.reward.shaping_clearance: None -> 0.3"]
    # the sparse-reward learners never use the shaping, nor D²SPO a baseline's section
    for algo in ("td3", "sl"):
        assert config_differences(dataclasses.replace(other_reward, algo=algo), dataclasses.replace(base, algo=algo)) == []
    cpo_changed = dataclasses.replace(base, cpo=dataclasses.replace(base.cpo, target_kl=0.02))
    assert config_differences(cpo_changed, base) == []
    assert len(config_differences(dataclasses.replace(cpo_changed, algo="cpo"), dataclasses.replace(base, algo="cpo"))) == 1
    assert config_differences(dataclasses.replace(base, seed=1), base) == ["seed: 1 -> 0"]


def test_effective_differences_ignore_the_generalists_and_the_patrols_settings_where_they_cannot_act():
    """One layout reads no generalist setting, and a task that is no recurrence reads no patrol
    setting; where they act (a generalist, a patrol) a change is a difference."""
    from d2spo.algos.td3 import TD3Config
    from d2spo.config_diff import config_differences
    from d2spo.envs import EnvConfig

    def changed(**kw):
        return TrainConfig(**kw, generalist_world="random", validation_layouts=3, patrol_validation=0,
                           env=EnvConfig(distance_obs="capped", recurrence_max_steps=0),
                           td3=TD3Config(recurrence_noise_final=None))

    assert config_differences(changed(), TrainConfig()) == []
    assert config_differences(changed(algo="td3-lag"), TrainConfig(algo="td3-lag")) == []
    patrol = config_differences(changed(task="patrol2"), TrainConfig(task="patrol2"))
    assert patrol == ["env.recurrence_max_steps: 0 -> 1000", "patrol_validation: 0 -> 32",
                      "td3.recurrence_noise_final: None -> 0.05"]
    generalist = config_differences(changed(generalist=True), TrainConfig(generalist=True))
    assert "generalist_world: 'random' -> 'world'" in generalist and "env.distance_obs: 'capped' -> 'ratio'" in generalist
    # a task that does not translate keeps every setting (nothing is assumed about it)
    assert config_differences(changed(task="F ("), TrainConfig(task="F (")) != []



def test_the_learner_table_says_reward_annealing_sections_and_filter():
    from d2spo.algos import LEARNERS, config_sections, has_runtime_filter
    from d2spo.run import build

    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    for algo, spec in LEARNERS.items():
        assert set(config_sections(algo)) <= fields
        assert ("anneal" in config_sections(algo)) == spec.anneal == (spec.reward == "progress")
        assert TrainConfig(algo=algo).env_config().reward.mode == spec.reward
    assert {a for a in LEARNERS if LEARNERS[a].reward == "sparse"} == {"td3", "sl"}
    assert {a for a in LEARNERS if has_runtime_filter(a)} == {"d2spo", "sl"}
    # the registry, not the learner, switches the annealing off (td3 and tlgrl are one class)
    assert not build(TrainConfig(algo="td3", num_envs=2))[2].schedule.cfg.enabled
    assert build(TrainConfig(algo="tlgrl", num_envs=2))[2].schedule.cfg.enabled


def test_a_formula_s_default_run_directory_names_the_formula_not_its_spelling():
    """Every formula once trained into runs/d2spo-custom-paper-s0, so a second one was refused there."""
    from d2spo.run import default_out

    def out(task):
        return default_out(TrainConfig(task=task)).name

    assert out("phi1") == "d2spo-phi1-paper-s0"
    patrol = out("GF A1 & GF A3 & G !A4")
    assert patrol.startswith("d2spo-custom-") and patrol.endswith("-paper-s0") and len(patrol) == len("d2spo-custom--paper-s0") + 8
    assert out("□◇A1 ∧ □◇A3 ∧ □¬A4") == out("G F A1&G F A3&G !A4") == patrol
    assert out("GF A1 & GF A2") != patrol


def test_snapshots_from_python_and_past_the_run():
    """`TrainConfig(snapshots=[50])` was refused as "must be a list of positive integers, got [50]";
    a snapshot past the run's episodes was accepted, never written, and failed the figure at the end."""
    assert TrainConfig(episodes=100, snapshots=[50, 100]).check().snapshots == (50, 100)
    with pytest.raises(ConfigError, match="snapshots: 500 is past the run's 100 episodes"):
        TrainConfig(episodes=100, snapshots=(50, 500)).check()
    with pytest.raises(ConfigError, match="snapshots: must be a list of positive integers, got \\(0,\\)"):
        TrainConfig(episodes=100, snapshots=[0]).check()


def test_a_layout_given_to_the_generalist_is_refused_not_recorded():
    """`train --generalist --layout lab.json` trained on world:0.. without a word and wrote the lab
    into config.json, so its owner believed the lab was part of training."""
    from d2spo.envs import EnvConfig

    with pytest.raises(ConfigError, match=r"env.layout: has no effect with --generalist: it trains on generated "
                                          r"layouts \(world:0..255\); to run it on your layout"):
        TrainConfig(generalist=True, env=EnvConfig(layout="relaxed")).check()
    assert TrainConfig(generalist=True).check().generalist
