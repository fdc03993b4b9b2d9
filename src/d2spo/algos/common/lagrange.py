"""Lagrange multiplier shared by every ``*-lag`` algorithm (PPO-Lag, TD3-Lag, SAC-Lag).

The constrained problem max_pi J_r(pi) s.t. J_c(pi) <= d is solved through the Lagrangian
L(pi, lambda) = J_r(pi) - lambda (J_c(pi) - d). The policy maximises L; the multiplier takes a
projected gradient *ascent* step on lambda (J_c - d):

    lambda <- max(0, lambda + step(J_c - d))        (with SGD, step = lr * (J_c - d) exactly)

The step is made by the configured optax optimizer on the loss -lambda (J_c - d), then lambda is
projected back onto [0, upper_bound]. The defaults are OmniSafe's (Adam, lr 0.035, init 0.001).

    lag = lagrange.create(LagrangeConfig(cost_limit=5.0))
    lag = lagrange.update(lag, mean_episode_cost)      # jit-able, vmap-able
    lam = lagrange.value(lag)
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import optax
from flax import struct

from d2spo.errors import ConfigError
from d2spo.fields import check_choice, check_fields

OPTIMIZERS = ("adam", "sgd")


@dataclass(frozen=True)
class LagrangeConfig:
    """Settings of the Lagrange multiplier update."""

    cost_limit: float = 25.0
    """Cost limit d: lambda grows while J_c > d."""
    lr: float = 0.035
    """Learning rate of the multiplier's own optimizer."""
    init: float = 0.001
    """Initial value of lambda (>= 0)."""
    optimizer: str = "adam"
    """'adam' (OmniSafe's) or 'sgd' (step lr * (J_c - d))."""
    upper_bound: float | None = None
    """Cap on lambda; None: unbounded."""

    def __post_init__(self) -> None:
        # bare field names: this section sits under ppo_lag, td3_lag and sac_lag alike
        check_fields(self, nullable=("upper_bound",), non_negative=("cost_limit", "init", "upper_bound"),
                     lr=("lr",))
        check_choice(self, "optimizer", OPTIMIZERS)
        if self.upper_bound is not None and self.upper_bound < self.init:
            raise ConfigError("upper_bound", f"must be >= init ({self.init}), got {self.upper_bound}")


@struct.dataclass
class LagrangeState:
    """The multiplier, its optimizer state and its cost limit (a pytree; ``tx`` is static)."""

    multiplier: jax.Array
    """float32 []: lambda, always within [0, upper_bound]."""
    opt_state: optax.OptState
    cost_limit: jax.Array
    """float32 []: d, used when ``update`` is called without an explicit limit."""
    tx: optax.GradientTransformation = struct.field(pytree_node=False)
    upper_bound: float | None = struct.field(pytree_node=False, default=None)


def create(cfg: LagrangeConfig) -> LagrangeState:
    """Fresh multiplier at ``cfg.init``."""
    tx = optax.adam(cfg.lr) if cfg.optimizer == "adam" else optax.sgd(cfg.lr)
    multiplier = jnp.float32(cfg.init)
    return LagrangeState(
        multiplier=multiplier,
        opt_state=tx.init(multiplier),
        cost_limit=jnp.float32(cfg.cost_limit),
        tx=tx,
        upper_bound=cfg.upper_bound,
    )


def update(state: LagrangeState, cost: jax.Array, cost_limit: jax.Array | None = None) -> LagrangeState:
    """One projected ascent step on lambda (J_c - d). ``cost`` is J_c (averaged if not a scalar)."""
    limit = state.cost_limit if cost_limit is None else jnp.asarray(cost_limit, jnp.float32)
    violation = jnp.mean(jnp.asarray(cost, jnp.float32)) - limit
    grad = -violation  # d/d lambda of the loss -lambda (J_c - d)
    updates, opt_state = state.tx.update(grad, state.opt_state, state.multiplier)
    multiplier = jnp.maximum(optax.apply_updates(state.multiplier, updates), 0.0)
    if state.upper_bound is not None:
        multiplier = jnp.minimum(multiplier, state.upper_bound)
    return state.replace(multiplier=multiplier.astype(jnp.float32), opt_state=opt_state)


def value(state: LagrangeState) -> jax.Array:
    """lambda as a float32 scalar, with gradients stopped (use it as a constant in policy losses)."""
    return jax.lax.stop_gradient(state.multiplier)
