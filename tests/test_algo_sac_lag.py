"""SAC-Lagrangian: the multiplier's response to synthetic episode costs, the critics and the
temperature on a fixed batch, and a short training on `relaxed` that must raise the return."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _learning import assert_trains_without_nans_and_improves

from d2spo.algos.offpolicy import empty_window, mean_episode_cost, record_episodes
from d2spo.algos.sac import SACConfig
from d2spo.algos.sac_lag import SACLagConfig
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.errors import ConfigError
from d2spo.replay import Transition
from d2spo.run import build

TINY = SACConfig(hidden=(32, 32), batch_size=64, learning_starts=500, buffer_size=50_000, updates_per_step=4)


def _learner(**kw):
    cfg = TrainConfig(algo="sac-lag", task="relaxed", num_envs=4, env=EnvConfig(layout="relaxed"),
                      sac_lag=SACLagConfig(sac=TINY, **kw))
    return build(cfg)[2]


def test_multiplier_rises_above_the_limit_and_falls_below():
    learner = _learner()
    agent = jax.jit(learner.init)(jax.random.PRNGKey(0)).agent
    on_step = jax.jit(learner.on_step)
    lam0 = float(agent.lag.multiplier)
    # A constructed chunk: half of 8 envs collide (episode cost 1) at step 2: J_c = 0.5 > d = 0.05.
    done = jnp.zeros((5, 8), bool).at[2].set(True)
    ep_cost = jnp.zeros((5, 8)).at[2, :4].set(1.0)
    window, trace = empty_window(10), []
    for t in range(5):
        window = record_episodes(window, done[t], ep_cost[t])
        agent, m = on_step(agent, mean_episode_cost(window))
        trace.append(float(m["charts/lambda"]))
    assert float(mean_episode_cost(window)) == pytest.approx(0.5)
    assert trace[:2] == [lam0] * 2 and trace[2] > lam0 and np.all(np.diff(trace[2:]) > 0)
    peak = trace[-1]
    # A looser limit (d = 0.6 > J_c = 0.5): the same episodes now push lambda down, never below 0.
    agent = agent.replace(lag=agent.lag.replace(cost_limit=jnp.float32(0.6)))
    for _ in range(40):
        agent, m = on_step(agent, mean_episode_cost(window))
    assert 0.0 <= float(m["charts/lambda"]) < peak


def test_critics_and_temperature_on_a_fixed_batch():
    learner = _learner()
    assert learner.nets.target_entropy == -2.0  # -|A|
    agent = jax.jit(learner.init)(jax.random.PRNGKey(1)).agent
    n = 64
    obs = jax.random.uniform(jax.random.PRNGKey(2), (n, learner.env.observation_size))
    act = jax.random.uniform(jax.random.PRNGKey(3), (n, 2), minval=-1, maxval=1)
    # Terminal transitions with r = 0.5, c = 1: the targets are exactly 0.5 and 1.
    batch = Transition(obs, act, jnp.full(n, 0.5), jnp.ones(n), obs, jnp.ones(n))

    @jax.jit
    def fit(agent, key):
        return jax.lax.scan(lambda a, k: learner.update(a, batch, k), agent, jax.random.split(key, 300))

    agent, m = fit(agent, jax.random.PRNGKey(4))
    assert float(m["values/qc"][-1]) == pytest.approx(1.0, abs=0.05)
    assert float(m["values/q"][-1]) == pytest.approx(0.5, abs=0.05)
    alpha = np.asarray(m["charts/alpha"][::2])  # actor and temperature every other update
    assert np.isnan(np.asarray(m["charts/alpha"][1::2])).all()
    assert alpha[0] == pytest.approx(TINY.init_alpha) and alpha[-1] != pytest.approx(TINY.init_alpha)


def test_config_errors():
    with pytest.raises(ConfigError, match="cost_critics"):
        SACLagConfig(cost_critics=0)
    with pytest.raises(ConfigError, match="init_alpha"):
        SACConfig(init_alpha=0.0)


def test_sac_lag_trains_on_relaxed_without_nans_and_improves(tmp_path):
    cfg = TrainConfig(algo="sac-lag", task="relaxed", episodes=300, num_envs=16, chunk_steps=50, eval_episodes=32,
                      window=100, env=EnvConfig(layout="relaxed", max_steps=200), sac_lag=SACLagConfig(sac=TINY)).check()
    assert_trains_without_nans_and_improves(cfg, tmp_path / "run")
