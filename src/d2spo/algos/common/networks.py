"""Networks shared by every algorithm (flax.linen), and the Gaussian maths the policies need.

Conventions:

* Actions live in [-1, 1]^m. Deterministic and SAC actors squash with tanh; the PPO/CPO
  ``GaussianPolicy`` is unbounded and the environment clips its samples.
* Critics take ``(obs, action)`` and return one value per leading index: ``QNetwork`` -> [...],
  ``TwinQ`` -> [n_critics, ...] (critic axis first, so ``q[0]`` is Q1).
* Gaussian helpers work on a diagonal Gaussian given by ``(mean, log_std)`` and sum over the last
  (action) axis.
* ``init_params`` returns the full variables dict, ready for ``module.apply(params, ...)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

Activation = Callable[[jax.Array], jax.Array]
Initializer = Callable[..., jax.Array]

_LOG_2PI = math.log(2.0 * math.pi)


def init_params(module: nn.Module, key: jax.Array, *example_inputs) -> dict:
    """Variables of ``module`` for inputs shaped like ``example_inputs`` (batch axes allowed)."""
    return module.init(key, *example_inputs)


class MLP(nn.Module):
    """Dense layers with an activation after each hidden layer; optional linear output layer."""

    hidden: Sequence[int] = (256, 256)
    out_dim: int | None = None
    activation: Activation = nn.relu
    kernel_init: Initializer = nn.initializers.lecun_normal()
    final_kernel_init: Initializer = nn.initializers.lecun_normal()
    layer_norm: bool = False
    """LayerNorm between each hidden Dense and its activation."""

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.Dense(width, kernel_init=self.kernel_init)(x)
            x = self.activation(nn.LayerNorm()(x) if self.layer_norm else x)
        if self.out_dim is not None:
            x = nn.Dense(self.out_dim, kernel_init=self.final_kernel_init)(x)
        return x


class DeterministicActor(nn.Module):
    """TD3 actor: a = tanh(MLP(s)) in [-1, 1]^action_dim; with ``low`` (per coordinate, each in
    [-1, 1)), a = c0 + c1 tanh(MLP(s)) in [low, 1], c0 = (1 + low) / 2, c1 = (1 - low) / 2."""

    action_dim: int
    hidden: Sequence[int] = (256, 256)
    activation: Activation = nn.relu
    low: tuple[float, ...] | None = None
    """The smallest action of each coordinate; None: -1 for all (plain tanh)."""

    @nn.compact
    def __call__(self, obs: jax.Array, pre_tanh: bool = False) -> jax.Array:
        """The action; with ``pre_tanh`` the MLP's output before the tanh instead (the same weights)."""
        z = MLP(self.hidden, self.action_dim, self.activation)(obs)
        if pre_tanh:
            return z
        a = jnp.tanh(z)
        if self.low is None:
            return a
        c0, c1 = self.affine()
        return c0 + c1 * a

    def affine(self) -> tuple[jax.Array, jax.Array]:
        """(c0, c1) of a = c0 + c1 tanh(·): (0, 1) without ``low``."""
        low = self.action_low()
        return (1.0 + low) / 2.0, (1.0 - low) / 2.0

    def action_low(self) -> float | jax.Array:
        """The smallest action: -1.0 for every coordinate without ``low`` (a plain number, so that
        clipping to it is the plain [-1, 1] clip), else ``low`` as an [action_dim] array."""
        return -1.0 if self.low is None else jnp.asarray(self.low, jnp.float32)

    def speed_low(self) -> float:
        """The smallest linear speed (action[0]): -1.0, or 0.0 for a forward-only actor."""
        return -1.0 if self.low is None else float(self.low[0])


class QNetwork(nn.Module):
    """Q(s, a) -> [...] from the concatenation of observation and action."""

    hidden: Sequence[int] = (256, 256)
    activation: Activation = nn.relu
    layer_norm: bool = False

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, action], axis=-1)
        return MLP(self.hidden, 1, self.activation, layer_norm=self.layer_norm)(x)[..., 0]


class TwinQ(nn.Module):
    """``n_critics`` independent Q-networks -> [n_critics, ...]. Parameters carry a leading critic axis."""

    hidden: Sequence[int] = (256, 256)
    n_critics: int = 2
    activation: Activation = nn.relu
    layer_norm: bool = False

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        ensemble = nn.vmap(
            QNetwork,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=None,
            out_axes=0,
            axis_size=self.n_critics,
        )
        return ensemble(self.hidden, self.activation, self.layer_norm)(obs, action)


def first_critic(critic: TwinQ):
    """Q1 alone of ``critic`` as an apply function, ``(params, obs, action) -> [1, ...]``, taking the
    twin's own parameters: row 0 of the twin's output and its gradients, to float32 rounding (bit for
    bit in the default ϕ1 run), in half the arithmetic. TD3's actor loss reads Q1 only
    (``td3_losses.td3_actor_loss``); through the twin, Q2's forward pass and its backward pass of
    zeros were computed and thrown away (a bare TD3 update, 128-128, batch 128: 0.442 -> 0.410 ms,
    medians of six interleaved rounds on a 2-core AMD, bench/RESULTS.md 2026-12-04)."""
    single = critic.clone(n_critics=1)

    def apply(params, obs: jax.Array, action: jax.Array) -> jax.Array:
        return single.apply(jax.tree_util.tree_map(lambda p: p[:1], params), obs, action)

    return apply


class ValueNetwork(nn.Module):
    """V(s) -> [...], orthogonal init as in common PPO implementations."""

    hidden: Sequence[int] = (64, 64)
    activation: Activation = nn.tanh

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        mlp = MLP(
            self.hidden,
            1,
            self.activation,
            kernel_init=nn.initializers.orthogonal(math.sqrt(2.0)),
            final_kernel_init=nn.initializers.orthogonal(1.0),
        )
        return mlp(obs)[..., 0]


class GaussianPolicy(nn.Module):
    """PPO/CPO policy: diagonal Gaussian, state-dependent mean, state-independent log std.

    Returns ``(mean, log_std)``, both shaped [..., action_dim]. The mean is not squashed.
    """

    action_dim: int
    hidden: Sequence[int] = (64, 64)
    activation: Activation = nn.tanh
    log_std_init: float = -0.5

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        mean = MLP(
            self.hidden,
            self.action_dim,
            self.activation,
            kernel_init=nn.initializers.orthogonal(math.sqrt(2.0)),
            final_kernel_init=nn.initializers.orthogonal(0.01),
        )(obs)
        log_std = self.param("log_std", nn.initializers.constant(self.log_std_init), (self.action_dim,))
        return mean, jnp.broadcast_to(log_std, mean.shape)


class GaussianActor(nn.Module):
    """SAC actor: parameters of a tanh-squashed diagonal Gaussian, ``(mean, log_std)`` of the
    pre-tanh variable u. log_std is squashed smoothly into [log_std_min, log_std_max].

    Sample and score with ``tanh_gaussian_sample`` / ``tanh_gaussian_log_prob``.
    """

    action_dim: int
    hidden: Sequence[int] = (256, 256)
    activation: Activation = nn.relu
    log_std_min: float = -5.0
    log_std_max: float = 2.0

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        h = MLP(self.hidden, None, self.activation)(obs)
        mean = nn.Dense(self.action_dim)(h)
        raw = jnp.tanh(nn.Dense(self.action_dim)(h))
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (raw + 1.0)
        return mean, log_std


# ---- diagonal Gaussian -------------------------------------------------------------------------


def gaussian_log_prob(mean: jax.Array, log_std: jax.Array, x: jax.Array) -> jax.Array:
    """log N(x; mean, diag(exp(log_std)^2)), summed over the last axis."""
    z = (x - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z**2 - log_std - 0.5 * _LOG_2PI, axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """Entropy of a diagonal Gaussian: sum(log_std + 0.5 log(2 pi e)) over the last axis."""
    return jnp.sum(log_std + 0.5 * (_LOG_2PI + 1.0), axis=-1)


def gaussian_kl(mean_p: jax.Array, log_std_p: jax.Array, mean_q: jax.Array, log_std_q: jax.Array) -> jax.Array:
    """KL(p || q) between diagonal Gaussians, summed over the last axis.

    For trust regions, p is the old (data-collecting) policy and q the new one.
    """
    var_ratio = jnp.exp(2.0 * (log_std_p - log_std_q))
    mahalanobis = ((mean_p - mean_q) * jnp.exp(-log_std_q)) ** 2
    return jnp.sum(0.5 * (var_ratio + mahalanobis - 1.0) + log_std_q - log_std_p, axis=-1)


def gaussian_sample(key: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """x = mean + exp(log_std) * eps, eps ~ N(0, I)."""
    return mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)


# ---- tanh-squashed Gaussian (SAC) --------------------------------------------------------------


def _log_one_minus_tanh_sq(u: jax.Array) -> jax.Array:
    # log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), stable for large |u|.
    return 2.0 * (math.log(2.0) - u - jax.nn.softplus(-2.0 * u))


def tanh_gaussian_log_prob(mean: jax.Array, log_std: jax.Array, pre_tanh: jax.Array) -> jax.Array:
    """log density of a = tanh(u) at u = ``pre_tanh``, u ~ N(mean, exp(log_std)^2).

    log pi(a) = log N(u) - sum_i log(1 - tanh(u_i)^2)   (change of variables).
    Takes u rather than a because atanh is ill-conditioned near |a| = 1.
    """
    return gaussian_log_prob(mean, log_std, pre_tanh) - jnp.sum(_log_one_minus_tanh_sq(pre_tanh), axis=-1)


def tanh_gaussian_sample(key: jax.Array, mean: jax.Array, log_std: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Reparameterised sample ``(action in [-1, 1]^m, log_prob)`` of the tanh-squashed Gaussian."""
    u = gaussian_sample(key, mean, log_std)
    return jnp.tanh(u), tanh_gaussian_log_prob(mean, log_std, u)
