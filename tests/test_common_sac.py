"""SAC losses: the soft target, the actor objective, and the sign of the temperature update."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from d2spo.algos.common.networks import tanh_gaussian_log_prob
from d2spo.algos.common.sac_losses import (
    alpha_loss,
    default_target_entropy,
    sac_actor_loss,
    sac_cost_critic_loss,
    sac_critic_loss,
)
from d2spo.replay import Transition


def actor_apply(p, s):  # pre-tanh Gaussian with mean p * s and fixed std 0.5
    return p * s, jnp.full(s.shape, jnp.log(0.5))


def critic_apply(p, s, a):  # Q1 = p0 * s + a, Q2 = p1 * s - a  -> [2, B]
    return jnp.stack([p[0] * s[:, 0] + a[:, 0], p[1] * s[:, 0] - a[:, 0]])


def _batch():
    return Transition(
        obs=jnp.array([[1.0], [-1.0], [0.5]]),
        action=jnp.array([[0.3], [-0.2], [0.9]]),
        reward=jnp.array([1.0, 0.0, -1.0]),
        cost=jnp.array([0.0, 1.0, 0.5]),
        next_obs=jnp.array([[0.2], [0.8], [-0.4]]),
        done=jnp.array([0.0, 1.0, 0.0]),
    )


def _next_sample(key, batch, actor_p):
    # Redraw the loss's a' ~ pi(.|s') from the same key, independently of the loss code.
    mean, log_std = actor_apply(actor_p, batch.next_obs)
    u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
    return np.asarray(jnp.tanh(u))[:, 0], np.asarray(tanh_gaussian_log_prob(mean, log_std, u))


def test_sac_critic_soft_target():
    batch, key = _batch(), jax.random.PRNGKey(7)
    online, target, actor_p, alpha, gamma = jnp.array([0.5, 2.0]), jnp.array([1.0, 3.0]), 0.7, 0.2, 0.9
    a2, logp2 = _next_sample(key, batch, actor_p)
    s2, s = np.asarray(batch.next_obs)[:, 0], np.asarray(batch.obs)[:, 0]
    soft_v = np.minimum(1.0 * s2 + a2, 3.0 * s2 - a2) - alpha * logp2
    y = np.asarray(batch.reward) + gamma * (1 - np.asarray(batch.done)) * soft_v
    a = np.asarray(batch.action)[:, 0]
    expected = np.mean((0.5 * s + a - y) ** 2) + np.mean((2.0 * s - a - y) ** 2)
    loss, metrics = sac_critic_loss(online, target, actor_p, alpha, batch, key, gamma, actor_apply, critic_apply)
    assert float(loss) == pytest.approx(expected, rel=1e-5)
    assert float(metrics["values/q_target"]) == pytest.approx(np.mean(y), rel=1e-5)

    # The cost critic uses the cost, no entropy term, and the max over critics by default.
    yc = np.asarray(batch.cost) + gamma * (1 - np.asarray(batch.done)) * np.maximum(1.0 * s2 + a2, 3.0 * s2 - a2)
    _, cm = sac_cost_critic_loss(online, target, actor_p, batch, key, gamma, actor_apply, critic_apply)
    assert float(cm["values/qc_target"]) == pytest.approx(np.mean(yc), rel=1e-5)


def test_sac_actor_loss_and_alpha_is_a_constant():
    obs, key, critic = _batch().obs, jax.random.PRNGKey(3), jnp.array([0.5, 2.0])
    mean, log_std = actor_apply(0.7, obs)
    u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
    a, logp = np.asarray(jnp.tanh(u))[:, 0], np.asarray(tanh_gaussian_log_prob(mean, log_std, u))
    s = np.asarray(obs)[:, 0]
    expected = np.mean(0.2 * logp - np.minimum(0.5 * s + a, 2.0 * s - a))
    loss, metrics = sac_actor_loss(0.7, critic, 0.2, obs, key, actor_apply, critic_apply)
    assert float(loss) == pytest.approx(expected, rel=1e-5)
    assert float(metrics["values/entropy"]) == pytest.approx(-np.mean(logp), rel=1e-5)
    g_alpha = jax.grad(lambda al: sac_actor_loss(0.7, critic, al, obs, key, actor_apply, critic_apply)[0])(0.2)
    assert float(g_alpha) == 0.0
    penalised, _ = sac_actor_loss(0.7, critic, 0.2, obs, key, actor_apply, critic_apply, lambda o, act: 3.0 * act[:, 0])
    assert float(penalised) == pytest.approx(expected + 3.0 * np.mean(a), rel=1e-5)


@pytest.mark.parametrize("mean_log_prob, direction", [(0.0, -1), (5.0, +1)])
def test_alpha_decreases_when_entropy_above_target(mean_log_prob, direction):
    target = default_target_entropy(2)  # -2
    # mean log pi = 0 -> entropy 0 > -2 (alpha must fall); mean log pi = 5 -> entropy -5 < -2 (rise).
    log_alpha = jnp.float32(np.log(0.3))
    log_prob = jnp.full((64,), mean_log_prob)
    assert float(alpha_loss(log_alpha, log_prob, target)) == pytest.approx(-0.3 * (mean_log_prob - 2.0), rel=1e-5)
    tx = optax.sgd(0.1)
    grad = jax.grad(alpha_loss)(log_alpha, log_prob, target)
    updates, _ = tx.update(grad, tx.init(log_alpha))
    new = optax.apply_updates(log_alpha, updates)
    assert np.sign(float(new - log_alpha)) == direction
