"""TD3-Lagrangian: the episode-cost window, the multiplier's response to synthetic episode costs,
the cost critic's target, and a short training on `relaxed` that must raise the return."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _learning import assert_trains_without_nans_and_improves

from d2spo.algos.offpolicy import empty_window, mean_episode_cost, record_episodes
from d2spo.algos.td3 import TD3Config
from d2spo.algos.td3_lag import TD3LagConfig
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.errors import ConfigError
from d2spo.replay import Transition
from d2spo.run import build

TINY = TD3Config(hidden=(32, 32), batch_size=64, learning_starts=500, buffer_size=50_000, updates_per_step=4)


def test_cost_window_keeps_the_last_episodes_in_order():
    w = empty_window(4)
    assert np.isnan(float(mean_episode_cost(w)))
    w = record_episodes(w, jnp.array([True, False, True]), jnp.array([1.0, 9.0, 0.0]))
    assert float(mean_episode_cost(w)) == pytest.approx(0.5)  # 9.0 belongs to no finished episode
    w = record_episodes(w, jnp.array([False, False, False]), jnp.array([5.0, 5.0, 5.0]))
    assert int(w.count) == 2 and float(mean_episode_cost(w)) == pytest.approx(0.5)
    # Six episodes end at once in a window of four: only the last four count.
    w = record_episodes(w, jnp.ones(6, bool), jnp.array([7.0, 7.0, 1.0, 1.0, 0.0, 0.0]))
    assert int(w.count) == 8 and float(mean_episode_cost(w)) == pytest.approx(0.5)
    w = record_episodes(w, jnp.array([True, False]), jnp.array([4.0, 0.0]))
    assert float(mean_episode_cost(w)) == pytest.approx((1.0 + 0.0 + 0.0 + 4.0) / 4)


def _learner(**lag):
    cfg = TrainConfig(algo="td3-lag", task="relaxed", num_envs=4, env=EnvConfig(layout="relaxed"),
                      td3_lag=TD3LagConfig(td3=TINY, **lag))
    return build(cfg)[2]


def test_multiplier_rises_above_the_limit_and_falls_below():
    learner = _learner()
    agent = jax.jit(learner.init)(jax.random.PRNGKey(0)).agent
    on_step = jax.jit(learner.on_step)
    lam0 = float(agent.lag.multiplier)
    # A constructed chunk: 4 envs, every one of them collides (cost 1 > d = 0.05) at step 3.
    done = jnp.zeros((6, 4), bool).at[3].set(True)
    ep_cost = jnp.zeros((6, 4)).at[3].set(1.0)
    window, trace = empty_window(10), []
    for t in range(6):
        window = record_episodes(window, done[t], ep_cost[t])
        agent, m = on_step(agent, mean_episode_cost(window))
        trace.append(float(m["charts/lambda"]))
    assert trace[:3] == [lam0] * 3  # no finished episode yet: J_c unknown, lambda untouched
    assert trace[3] > lam0 and np.all(np.diff(trace[3:]) > 0)
    peak = trace[-1]
    safe = record_episodes(empty_window(10), jnp.ones(10, bool), jnp.zeros(10))  # J_c = 0 < d
    for _ in range(50):
        agent, m = on_step(agent, mean_episode_cost(safe))
    assert 0.0 <= float(m["charts/lambda"]) < peak


def test_cost_critic_learns_the_collision_cost():
    learner = _learner(cost_reduce="max")
    agent = jax.jit(learner.init)(jax.random.PRNGKey(1)).agent
    n = 64
    obs = jax.random.uniform(jax.random.PRNGKey(2), (n, learner.env.observation_size))
    act = jax.random.uniform(jax.random.PRNGKey(3), (n, 2), minval=-1, maxval=1)
    # Every transition collides and terminates: y_c = c = 1 exactly, whatever the bootstrap.
    batch = Transition(obs, act, jnp.zeros(n), jnp.ones(n), obs, jnp.ones(n))

    @jax.jit
    def fit(agent, key):
        return jax.lax.scan(lambda a, k: learner.update(a, batch, k), agent, jax.random.split(key, 300))

    agent, m = fit(agent, jax.random.PRNGKey(4))
    assert float(m["values/qc"][-1]) == pytest.approx(1.0, abs=0.05)
    assert float(m["values/q"][-1]) == pytest.approx(0.0, abs=0.05)
    assert np.isnan(np.asarray(m["losses/actor"][1::2])).all()  # policy_delay 2: actor every other update


def test_config_errors():
    with pytest.raises(ConfigError, match="cost_reduce"):
        TD3LagConfig(cost_reduce="median")
    with pytest.raises(ConfigError, match="cost_window"):
        TD3LagConfig(cost_window=0)


def test_td3_lag_trains_on_relaxed_without_nans_and_improves(tmp_path):
    # Seed 1: seed 0's untrained policy collides in only 12% of the first 75 episodes, too little to
    # show learning against; under the suite's compiler flags of 2026-11-27 (tests/conftest.py) it
    # ended at 28%. Seeds 1, 2, 3 fell from 79%, 100%, 100% to 0% under the same flags.
    cfg = TrainConfig(algo="td3-lag", task="relaxed", episodes=300, num_envs=16, chunk_steps=50, eval_episodes=32, seed=1,
                      window=100, env=EnvConfig(layout="relaxed", max_steps=200), td3_lag=TD3LagConfig(td3=TINY)).check()
    assert_trains_without_nans_and_improves(cfg, tmp_path / "run")
