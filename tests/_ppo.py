"""A tiny PPO written as a user would, for the tests that train stock-style loops on the env.

Only the maths lives here (networks, GAE, the clipped update); each test writes its own loop
against one API (Gymnasium in test_env_gym.py, gymnax in test_env_gymnax.py), as CleanRL and
PureJaxRL scripts do.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import optax

GAMMA, LAMBDA, CLIP = 0.99, 0.95, 0.2


def _mlp_init(key, sizes, last_scale):
    layers = []
    for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
        key, k = jax.random.split(key)
        scale = last_scale if i == len(sizes) - 2 else 1.0
        layers.append((scale * jax.random.normal(k, (n_in, n_out)) / jnp.sqrt(n_in), jnp.zeros(n_out)))
    return layers


def _mlp(layers, x):
    for w, b in layers[:-1]:
        x = jnp.tanh(x @ w + b)
    w, b = layers[-1]
    return x @ w + b


def init(key, n_obs: int, n_act: int, hidden: int = 32) -> dict:
    """Actor (Gaussian, state-independent std) and critic; the actor's mean starts near 0."""
    k_pi, k_v = jax.random.split(key)
    return {"pi": _mlp_init(k_pi, [n_obs, hidden, hidden, n_act], 0.01),
            "v": _mlp_init(k_v, [n_obs, hidden, hidden, 1], 1.0),
            "log_std": jnp.full((n_act,), -0.5)}


def mean_action(params, obs):
    return _mlp(params["pi"], obs)


def value(params, obs):
    return _mlp(params["v"], obs)[..., 0]


def log_prob(params, obs, action):
    z = (action - mean_action(params, obs)) / jnp.exp(params["log_std"])
    return jnp.sum(-0.5 * z * z - params["log_std"] - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


def sample(key, params, obs):
    """(action, log-prob) from the Gaussian policy."""
    mean = mean_action(params, obs)
    action = mean + jnp.exp(params["log_std"]) * jax.random.normal(key, mean.shape)
    return action, log_prob(params, obs, action)


def gae(reward, val, done, last_val):
    """Advantages and returns over [T, n]; ``done[t]``: the episode ended at step t (no bootstrap)."""
    def back(carry, x):
        adv_next, v_next = carry
        r, v, d = x
        delta = r + GAMMA * v_next * (1.0 - d) - v
        adv = delta + GAMMA * LAMBDA * (1.0 - d) * adv_next
        return (adv, v), adv

    _, adv = jax.lax.scan(back, (jnp.zeros_like(last_val), last_val), (reward, val, done), reverse=True)
    return adv, adv + val


def optimizer(lr: float = 3e-3):
    return optax.chain(optax.clip_by_global_norm(0.5), optax.adam(lr))


def update(params, opt_state, batch, key, tx, epochs: int = 8, minibatches: int = 4):
    """Clipped-surrogate PPO epochs over a flat batch (obs, action, logp, adv, ret, mask)."""
    n = batch["mask"].shape[0]

    def loss_fn(p, mb):
        m = mb["mask"]
        count = jnp.maximum(m.sum(), 1.0)
        adv = mb["adv"]
        mu = jnp.sum(m * adv) / count
        adv = (adv - mu) / (jnp.sqrt(jnp.sum(m * (adv - mu) ** 2) / count) + 1e-8)
        ratio = jnp.exp(log_prob(p, mb["obs"], mb["action"]) - mb["logp"])
        surrogate = jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - CLIP, 1 + CLIP) * adv)
        v_loss = (value(p, mb["obs"]) - mb["ret"]) ** 2
        return jnp.sum(m * (-surrogate + 0.5 * v_loss)) / count

    def epoch(carry, k):
        p, s = carry
        perm = jax.random.permutation(k, n).reshape(minibatches, -1)

        def step(carry, idx):
            p, s = carry
            grads = jax.grad(loss_fn)(p, jax.tree.map(lambda a: a[idx], batch))
            updates, s = tx.update(grads, s, p)
            return (optax.apply_updates(p, updates), s), None

        return jax.lax.scan(step, (p, s), perm)[0], None

    return jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, epochs))[0]
