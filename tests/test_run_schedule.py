"""What a run's length sets reaches the training programs as an argument (``algos.base.RunSchedule``),
not as constants: runs that differ only in ``--episodes`` are one program."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from _tiny import tiny_cfg

from d2spo.algos.base import schedule_values, with_schedule
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.run import build
from d2spo.train import learner_program


def test_runs_that_differ_only_in_their_episode_count_are_one_program():
    """What a run's length sets (the anneal rate k2, one episode's share of the run for the noise
    decay: ``algos.base.RunSchedule``) reaches the programs as an argument, so that runs differing
    only in ``--episodes`` lower to the same StableHLO and the second finds the first's compilation
    in the cache. D²SPO on a patrol (both numbers read), the baselines' off- and on-policy loops (the
    anneal); the numbers the argument carries give the bits the constants gave."""
    def learner(episodes, algo="d2spo"):
        if algo != "d2spo":  # the defaults, on the task and layout `relaxed`
            return build(TrainConfig(algo=algo, task="relaxed", episodes=episodes, env=EnvConfig(layout="relaxed")).check())[2]
        cfg = dataclasses.replace(tiny_cfg(), task="patrol2", episodes=episodes, env=EnvConfig(layout="paper"))
        return build(cfg.check())[2]

    short, long = learner(40), learner(400)
    assert short.cfg.exploration_noise_final is not None and short.schedule.cfg.enabled
    assert all(a != b for a, b in zip(schedule_values(short), schedule_values(long)))
    key = jax.random.PRNGKey(0)
    for name, arg in (("init", key), ("chunk", jax.eval_shape(short.init, key))):
        assert learner_program(short, name).lower(arg).as_text() == learner_program(long, name).lower(arg).as_text()
    for algo in ("td3-lag", "ppo-lag"):  # their schedules sit in the loop they share with other baselines
        a, b = learner(40, algo), learner(400, algo)
        assert schedule_values(a) != schedule_values(b)
        assert learner_program(a, "init").lower(key).as_text() == learner_program(b, "init").lower(key).as_text()

    episodes = jnp.arange(60, dtype=jnp.int32)  # past the 40 of `short`: its anneal and noise end

    def numbers(schedule, episodes):  # the episode counts an argument, as in a chunk (not folded by XLA)
        return jax.vmap(lambda e: (schedule.env_params(short.params, e).label_radius,
                                   short.cfg.noise_at(e, schedule.per_episode)))(episodes)

    as_argument = jax.jit(lambda v, e: numbers(with_schedule(short, v).schedule, e))(schedule_values(short), episodes)
    as_constants = jax.jit(lambda e: numbers(short.schedule, e))(episodes)
    for x, y in zip(as_argument, as_constants):
        assert jnp.array_equal(x, y) and len(jnp.unique(x)) > 10
