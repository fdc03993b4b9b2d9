"""The executed policy π_Ω, the joint update of (Θ, Ω) on Eq. (9), and the cautious start.

π_Ω is a safety layer on top of the RL actor: it reads the sensor features x = b(z, O_s) and the
RL proposal u_rl = π_rl(z) and returns the action that is executed,

    π_Ω(x, u_rl) = u_rl + β ⊙ (a − u_rl),   β = sigmoid(·) ∈ (0, 1)^m,  a = tanh(·) ∈ (-1, 1)^m,

a per-coordinate blend of the proposal and a safe action a, both from one MLP on
(x/H, min(x)/H, u_rl). It stays inside [-1, 1]^m without clipping, its gradient does not vanish
when u_rl sits on a face of the box (as tanh(atanh(u_rl) + δ) would), and T_g = ||β ⊙ (a − u_rl)||²
is the size of the override. Ω never changes π_rl (u_rl is an input). Untrained, β ≈ 1/2, so
π_Ω must go through the cautious start before it drives the robot.

Cautious start (before the first environment step): fit f_n to a kinematic prior, then minimise
Eq. (9) on synthetic data: T_s/T_u on safe/ring features of random poses among random obstacles,
T_e/T_g with random proposals u_rl ~ U[-1, 1]^m and z' = s_n(z, π_Ω). π_Ω then already brakes or
turns in front of obstacles, whatever π_rl proposes, and h already separates safe from unsafe.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from d2spo.safety.cbf import (
    CBFConfig,
    CBFNet,
    TeBatch,
    network_input,
    p_exp_threshold,
    total_loss,
)
from d2spo.safety.datasets import PretrainData, SafetyData, te_batch, weighted_sample
from d2spo.safety.nominal import (
    NominalBatch,
    NominalNet,
    fit_nominal_prior,
    nominal_update,
)


class SafetyPolicy(nn.Module):
    """π_Ω(x, u_rl) = u_rl + β ⊙ (a − u_rl), see the module docstring."""

    hidden: Sequence[int] = (64, 64)
    feature_scale: float = 1.0

    @nn.compact
    def __call__(self, x: jnp.ndarray, u_rl: jnp.ndarray) -> jnp.ndarray:
        h = jnp.concatenate([network_input(x, self.feature_scale), u_rl], axis=-1)
        for width in self.hidden:
            h = nn.tanh(nn.Dense(width)(h))
        m = u_rl.shape[-1]
        beta = nn.sigmoid(nn.Dense(m)(h))
        a = nn.tanh(nn.Dense(m)(h))
        return u_rl + beta * (a - u_rl)


class SafetyNets(NamedTuple):
    """The three networks of the safety machinery (flax modules are static, hashable descriptions)."""

    cbf: CBFNet
    policy: SafetyPolicy
    nominal: NominalNet


def make_nets(cfg: CBFConfig, sensing_range: float) -> SafetyNets:
    """Networks sized by `cfg`; features are scaled by 1/H with H = `sensing_range`."""
    return SafetyNets(
        cbf=CBFNet(hidden=cfg.hidden, feature_scale=sensing_range),
        policy=SafetyPolicy(hidden=cfg.policy_hidden, feature_scale=sensing_range),
        nominal=NominalNet(hidden=cfg.nominal_hidden),
    )


@struct.dataclass
class SafetyState:
    """Θ, Ω, the nominal model's parameters and their Adam states."""

    cbf: dict
    policy: dict
    nominal: dict
    cbf_opt: optax.OptState
    policy_opt: optax.OptState
    nominal_opt: optax.OptState


def _txs(cfg: CBFConfig):
    return optax.adam(cfg.cbf_lr), optax.adam(cfg.policy_lr), optax.adam(cfg.nominal_lr)


def init_safety_state(key: jax.Array, nets: SafetyNets, cfg: CBFConfig, n_features: int,
                      action_dim: int = 2) -> SafetyState:
    """Random Θ, Ω and f_n parameters with fresh optimiser states."""
    k1, k2, k3 = jax.random.split(key, 3)
    x = jnp.zeros((1, n_features))
    u = jnp.zeros((1, action_dim))
    cbf = nets.cbf.init(k1, x)
    policy = nets.policy.init(k2, x, u)
    nominal = nets.nominal.init(k3, jnp.zeros((1, 3)), u)
    tc, tp, tn = _txs(cfg)
    return SafetyState(cbf, policy, nominal, tc.init(cbf), tp.init(policy), tn.init(nominal))


def safe_action(nets: SafetyNets, state: SafetyState, x: jnp.ndarray, u_rl: jnp.ndarray) -> jnp.ndarray:
    """The executed action π_Ω(x, u_rl). Add exploration noise to u_rl *before* this call."""
    return nets.policy.apply(state.policy, x, u_rl)


def joint_step(state: SafetyState, batch: TeBatch, unsafe_x: jnp.ndarray, unsafe_w: jnp.ndarray, *,
               nets: SafetyNets, cfg: CBFConfig, features_fn: Callable, dt: float, synthetic=None):
    """One Adam step of (Θ, Ω) on Eq. (9). Returns (state, metrics).

    `synthetic` = (batch, unsafe_x, unsafe_w) from the cautious start's data adds
    `cfg.synthetic_replay` times Eq. (9) on it, so online updates do not forget it.
    """
    params = {"cbf": state.cbf, "policy": state.policy}

    def loss(p):
        total, metrics = total_loss(p, state.nominal, batch, unsafe_x, unsafe_w,
                                    nets=nets, cfg=cfg, features_fn=features_fn, dt=dt)
        if synthetic is not None:
            extra, m2 = total_loss(p, state.nominal, *synthetic, nets=nets, cfg=cfg, features_fn=features_fn, dt=dt)
            total = total + cfg.synthetic_replay * extra
            metrics["safety/synthetic_total"] = m2["safety/total"]
        return total, metrics

    grads, metrics = jax.grad(loss, has_aux=True)(params)
    tc, tp, _ = _txs(cfg)
    uc, cbf_opt = tc.update(grads["cbf"], state.cbf_opt, state.cbf)
    up, policy_opt = tp.update(grads["policy"], state.policy_opt, state.policy)
    state = state.replace(cbf=optax.apply_updates(state.cbf, uc), policy=optax.apply_updates(state.policy, up),
                          cbf_opt=cbf_opt, policy_opt=policy_opt)
    return state, metrics


def update(key: jax.Array, state: SafetyState, data: SafetyData, *, nets: SafetyNets, cfg: CBFConfig,
           features_fn: Callable, dt: float, u_rl_fn: Callable | None = None, pretrain: PretrainData | None = None):
    """UPDATE(Ω, Θ) of Algorithm 1 (line 17), plus refitting f_n on T. Returns (state, metrics).

    Runs `cfg.nominal_steps` steps on the nominal model, then `cfg.eq9_steps` steps of Eq. (9).
    `u_rl_fn(obs) -> u_rl` recomputes the current RL proposal for the sampled transitions; without
    it the proposal stored at collection time is used. With `pretrain` (the cautious start's data)
    and `cfg.synthetic_replay > 0`, each step also replays a synthetic batch.
    """
    _, _, tn = _txs(cfg)
    replay = pretrain is not None and cfg.synthetic_replay > 0
    k_nom, k_joint = jax.random.split(key)

    def nominal_body(carry, k):
        params, opt = carry
        tr, w = weighted_sample(data.transitions, k, cfg.minibatch)
        batch = NominalBatch(tr.pose, tr.action, tr.next_pose, w)
        params, opt, loss = nominal_update(nets.nominal, params, opt, batch, dt, tn)
        return (params, opt), loss

    (nominal, nominal_opt), nom_losses = jax.lax.scan(
        nominal_body, (state.nominal, state.nominal_opt), jax.random.split(k_nom, cfg.nominal_steps))
    state = state.replace(nominal=nominal, nominal_opt=nominal_opt)

    def joint_body(st, k):
        k1, k2, k3 = jax.random.split(k, 3)
        tr, w = weighted_sample(data.p_exp, k1, cfg.minibatch)
        xu, wu = weighted_sample(data.unsafe, k2, cfg.minibatch)
        batch = te_batch(tr, w, None if u_rl_fn is None else u_rl_fn(tr.obs))
        synthetic = synthetic_batch(k3, pretrain, cfg, batch.u_rl.shape[-1]) if replay else None
        return joint_step(st, batch, xu, wu, nets=nets, cfg=cfg, features_fn=features_fn, dt=dt, synthetic=synthetic)

    state, metrics = jax.lax.scan(joint_body, state, jax.random.split(k_joint, cfg.eq9_steps))
    metrics = jax.tree_util.tree_map(lambda m: m[-1], metrics)
    if cfg.nominal_steps > 0:
        metrics["safety/nominal_loss"] = nom_losses[-1]
    return state, metrics


def cautious_start(key: jax.Array, state: SafetyState, data: PretrainData, *, nets: SafetyNets, cfg: CBFConfig,
                   features_fn: Callable, dt: float, prior: Callable | None = None, action_dim: int = 2):
    """Make π_Ω and h safe before the first environment step. Returns (state, metrics).

    1. If `prior(s, u) -> ṡ` is given (e.g. `nominal.unicycle_prior`), fit f_n to it
       (`cfg.prior_steps` steps).
    2. `cfg.pretrain_steps` steps of Eq. (9) on `data` (from `synthetic_pretrain_data`): T_s on safe
       features, T_u on the synthesised ring features, T_e/T_g on safe poses with u_rl ~ U[-1, 1]^m
       and z' = s_n(z, π_Ω(x, u_rl)) (no real next state exists yet).
    """
    k_prior, k_train = jax.random.split(key)
    if prior is not None and cfg.prior_steps > 0:
        nominal, _ = fit_nominal_prior(k_prior, nets.nominal, state.nominal, prior, steps=cfg.prior_steps,
                                       batch_size=cfg.minibatch, lr=cfg.nominal_lr, action_dim=action_dim)
        state = state.replace(nominal=nominal)

    def body(st, k):
        return joint_step(st, *synthetic_batch(k, data, cfg, action_dim), nets=nets, cfg=cfg,
                          features_fn=features_fn, dt=dt)

    state, metrics = jax.lax.scan(body, state, jax.random.split(k_train, cfg.pretrain_steps))
    return state, jax.tree_util.tree_map(lambda m: m[-1], metrics)


def synthetic_batch(key: jax.Array, data: PretrainData, cfg: CBFConfig, action_dim: int = 2):
    """(T_e batch, unsafe_x, unsafe_w) drawn from synthetic data: P_exp rows with u_rl ~ U[-1, 1]^m
    and no real next state (z' = s_n), and valid ring samples. Rows are drawn only among usable ones."""
    n = data.pose.shape[0]
    exp_w = (jnp.min(data.x, axis=-1) >= p_exp_threshold(cfg)).astype(jnp.float32)
    unsafe_w = data.unsafe_valid.astype(jnp.float32)
    k1, k2, k3 = jax.random.split(key, 3)
    i = jax.random.choice(k1, n, (cfg.minibatch,), p=(exp_w + 1e-9) / jnp.sum(exp_w + 1e-9))
    j = jax.random.choice(k2, n, (cfg.minibatch,), p=(unsafe_w + 1e-9) / jnp.sum(unsafe_w + 1e-9))
    u_rl = jax.random.uniform(k3, (cfg.minibatch, action_dim), minval=-1.0, maxval=1.0)
    ctx = jax.tree_util.tree_map(lambda c: c[i], data.context)
    return TeBatch(data.pose[i], None, ctx, u_rl, exp_w[i]), data.x_unsafe[j], unsafe_w[j]
