"""The learned CBF h_Θ and the loss of Eq. (9), Sec. IV-B/IV-D of the paper.

h_Θ reads the sensor features x = b(z, O_s) (``envs.sensors.cbf_input``: K lidar ranges and the
nearest-obstacle distance, clipped at H), rescaled by ``network_input``, and returns a scalar;
{h ≥ 0} is the learned safe set. The sensor reaches this package only as a ``features_fn(pose,
context) -> x``. Every term of Eq. (9) is a small pure function below. All terms
are *weighted means* over a batch instead of the paper's sums, so the λ's do not depend on the
batch size; a weight of 0 marks padding (an empty buffer gives a term of exactly 0).

For lidar features, "x ≥ d" reads min(x) ≥ d. X_s = {x : min(x) ≥ d}; X_L = ring samples with
min(x) in [unsafe_max − σ, unsafe_max]. By default P_exp (where T_e and T_g act) reaches down to
unsafe_max rather than d (`te_in_band`), so the derivative condition also holds where h < 0
between the ring and X_s; docs/cbf.md explains why and how to get the paper's P_exp.

Gradients: T_s and T_u reach Θ only. T_e reaches Θ (through h(x) and h(x')) and Ω, the executed
policy π_Ω, through x' = b(s_g, O_s) where s_g = Eq. (6) depends on u = π_Ω(x, u_rl) via f_n. The
nominal model's parameters are held fixed here (stop_gradient); they are fitted separately.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from d2spo.errors import ConfigError
from d2spo.fields import check_choice, check_fields
from d2spo.safety.nominal import nominal_next, straight_through_next

ALPHAS = ("linear", "cubic")
UPDATE_STEPS = 10
"""Steps of each half of UPDATE(Ω, Θ) (f_n, then Eq. (9)) when ``updates_per_iter`` and
``nominal_updates_per_iter`` are unset (TrainConfig fills them in), save for a recurrence below."""
RECURRENCE_UPDATE_STEPS = 5
"""The same for a recurrence (a patrol) on one layout with the default robot, without --fast: half
the count, where it made more accepting visits (README, "Departures from the paper"). From
2026-11-30 to 2026-12-04 it was every task's on one layout; Table II's completions then fell
below 99.5% on four seeds of six (bench/RESULTS.md, "2026-12-04, late morning")."""
BATCH_SIZE = 256
"""Minibatch size of UPDATE(Ω, Θ) (from each of T, P_exp and X_L) and of the cautious start when
``batch_size`` is unset (TrainConfig fills it in), save for the one below."""
ONE_LAYOUT_BATCH_SIZE = 128
"""The same for a task that is not a recurrence, on one layout, with the default robot, without
--fast (where ``RECURRENCE_UPDATE_STEPS`` would halve a patrol's steps): half the arithmetic
of UPDATE(Ω, Θ), with Tables II-III held (README, "Departures from the paper"; bench/RESULTS.md,
"2026-12-04, afternoon")."""


@dataclass(frozen=True)
class CBFConfig:
    """Hyperparameters of the data-driven CBF, its datasets and the executed policy π_Ω.

    Distances are lidar ranges measured from the robot's centre (metres). Defaults suit a
    unicycle with Δt = 0.1 s, v_max ≈ 1 m/s, sensing range H ≈ 1-1.5 m and radius 0.15 m.
    """

    hidden: tuple[int, ...] = (64, 64)
    """Hidden widths of the CBF network h_Θ (tanh)."""
    policy_hidden: tuple[int, ...] = (64, 64)
    """Hidden widths of π_Ω's correction network."""
    nominal_hidden: tuple[int, ...] = (64, 64)
    """Hidden widths of the nominal model f_n."""
    gamma_s: float = 0.1
    """γ_s: margin of T_s, h(x) ≥ γ_s on safe samples X_s."""
    gamma_u: float = 0.1
    """γ_u: margin of T_u, h(x) ≤ -γ_u on unsafe samples X_L."""
    gamma_exp: float = 0.1
    """γ_exp: margin of T_e, Δh/Δt + α(h(x)) ≥ γ_exp."""
    alpha: str = "linear"
    """Class-K α: 'linear' (a·h) or 'cubic' (a·h³)."""
    alpha_coef: float = 3.0
    """Coefficient a of α (1/s); keep a·Δt < 1."""
    lambda_s: float = 10.0
    """λ_s: weight of T_s in Eq. (9)."""
    lambda_u: float = 10.0
    """λ_u: weight of T_u in Eq. (9)."""
    lambda_e: float = 1.0
    """λ_e: weight of T_e in Eq. (9)."""
    lambda_g: float = 0.1
    """λ_g: weight of T_g in Eq. (9) (π_Ω toward π_rl), < λ_e."""
    weight_decay: float = 1e-4
    """Weight of ||Θ||² in Eq. (9) (sums are means)."""
    d: float = 0.3
    """Safety threshold d (m): X_s = {x : min(x) ≥ d}."""
    te_in_band: bool = True
    """P_exp: min range ≥ unsafe_max; False: ≥ d (paper)."""
    unsafe_max: float = 0.2
    """Outer edge (m) of the unsafe ring X_L (≥ robot radius)."""
    sigma: float = 0.1
    """Width σ (m) of the unsafe ring X_L."""
    cbf_lr: float = 1e-3
    """Adam learning rate for Θ."""
    policy_lr: float = 1e-3
    """Adam learning rate for Ω."""
    nominal_lr: float = 1e-3
    """Adam learning rate for the nominal model f_n."""
    transitions_capacity: int = 100_000
    """Capacity of the transition set T (fits f_n)."""
    p_exp_capacity: int = 100_000
    """Capacity of P_exp (and so of X_s)."""
    unsafe_capacity: int = 100_000
    """Capacity of X_L (synthesised unsafe samples)."""
    batch_size: int | None = None
    """Minibatch from each of P_exp, X_L and T; None: 128 on one layout (default robot; not a patrol, not --fast), else 256."""
    updates_per_iter: int | None = None
    """Gradient steps on Eq. (9) per UPDATE(Ω, Θ); None: 10, or 5 for a patrol on one layout with the default robot
    without --fast."""
    nominal_updates_per_iter: int | None = None
    """Gradient steps on the nominal model per UPDATE; None: 10, or 5 for a patrol on one layout with the default
    robot without --fast."""
    pretrain_samples: int = 16_384
    """Synthetic poses drawn for the cautious start."""
    pretrain_steps: int = 2_000
    """Gradient steps on Eq. (9) in the cautious start."""
    prior_steps: int = 1_000
    """Steps fitting f_n to the kinematic prior at the start."""
    ring_newton_iters: int = 3
    """Newton iterations that put a pose in the unsafe ring."""
    synthetic_replay: float = 0.0
    """Weight of a replayed synthetic batch (0 = off)."""
    replay_correction: bool = True
    """T_e at π_Ω's current action on replayed data; False: Eq. (6) as printed."""
    filter_iters: int = 3
    """Iterations of the runtime safety filter (at least 1: with none it would return the action as it is)."""
    filter_alpha_coef: float | None = None
    """a of α in the runtime filter; None: alpha_coef."""

    @property
    def filter_alpha(self) -> float:
        """The coefficient of α the runtime filter uses: filter_alpha_coef, or alpha_coef if unset."""
        return self.alpha_coef if self.filter_alpha_coef is None else self.filter_alpha_coef

    @property
    def eq9_steps(self) -> int:
        """Steps on Eq. (9) per UPDATE(Ω, Θ): updates_per_iter, or ``UPDATE_STEPS`` if unset (a
        TrainConfig always sets it; this is for a CBFConfig used on its own)."""
        return UPDATE_STEPS if self.updates_per_iter is None else self.updates_per_iter

    @property
    def minibatch(self) -> int:
        """Minibatch size: batch_size, or ``BATCH_SIZE`` if unset (a TrainConfig always sets it)."""
        return BATCH_SIZE if self.batch_size is None else self.batch_size

    @property
    def nominal_steps(self) -> int:
        """Steps on f_n per UPDATE(Ω, Θ): nominal_updates_per_iter, or ``UPDATE_STEPS`` if unset."""
        return UPDATE_STEPS if self.nominal_updates_per_iter is None else self.nominal_updates_per_iter

    def __post_init__(self):
        check_choice(self, "alpha", ALPHAS, "cbf")
        check_fields(self, "cbf", nullable=("filter_alpha_coef", "updates_per_iter", "nominal_updates_per_iter", "batch_size"),
                     widths=("hidden", "policy_hidden", "nominal_hidden"),
                     positive=("gamma_s", "gamma_u", "gamma_exp", "alpha_coef", "d", "unsafe_max", "sigma",
                               "filter_alpha_coef"),
                     lr=("cbf_lr", "policy_lr", "nominal_lr"),
                     non_negative=("lambda_s", "lambda_u", "lambda_e", "lambda_g", "weight_decay", "synthetic_replay"),
                     count=("transitions_capacity", "p_exp_capacity", "unsafe_capacity", "batch_size",
                            "ring_newton_iters", "pretrain_samples", "updates_per_iter", "pretrain_steps", "filter_iters"),
                     natural=("nominal_updates_per_iter", "prior_steps"),
                     flag=("te_in_band", "replay_correction"))


def check_geometry(cfg: CBFConfig, robot_radius: float, sensing_range: float) -> None:
    """Raise ConfigError unless 0 < unsafe_max - σ, r_robot ≤ unsafe_max < d < H.

    Then h is trained negative on every min range up to unsafe_max (contact happens at r_robot), and
    the ring lies below the safe threshold d, leaving a band where h crosses zero.
    """
    if not cfg.sigma < cfg.unsafe_max:
        raise ConfigError("sigma", f"ring width {cfg.sigma} must be below unsafe_max {cfg.unsafe_max}")
    if not robot_radius <= cfg.unsafe_max:
        raise ConfigError("unsafe_max", f"{cfg.unsafe_max} must be at least the robot radius {robot_radius}")
    if not cfg.unsafe_max < cfg.d < sensing_range:
        raise ConfigError("d", f"safety threshold {cfg.d} must lie in (unsafe_max {cfg.unsafe_max}, H {sensing_range})")


def p_exp_threshold(cfg: CBFConfig) -> float:
    """The min range from which a transition is in P_exp: unsafe_max if `te_in_band`, else d."""
    return cfg.unsafe_max if cfg.te_in_band else cfg.d


def network_input(x: jnp.ndarray, feature_scale: float) -> jnp.ndarray:
    """What h_Θ and π_Ω read of x = b(z, O_s) (``envs.sensors.cbf_input``, metres): x/H, in [0, 1],
    with min(x)/H appended. With x from ``cbf_input`` that is its last entry (the nearest-obstacle
    distance) again, as no ray reads less; kept so that trained networks keep their input."""
    x = x / feature_scale
    return jnp.concatenate([x, jnp.min(x, axis=-1, keepdims=True)], axis=-1)


class CBFNet(nn.Module):
    """h_Θ(x): an MLP on `network_input(x, H)` -> scalar."""

    hidden: Sequence[int] = (64, 64)
    feature_scale: float = 1.0

    @nn.compact
    def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
        h = network_input(x, self.feature_scale)
        for width in self.hidden:
            h = nn.tanh(nn.Dense(width)(h))
        return nn.Dense(1)(h)[..., 0]


def class_k(kind: str, coef: float) -> Callable[[jnp.ndarray], jnp.ndarray]:
    """The extended class-K function α of Eq. (3): a·h ('linear') or a·h³ ('cubic')."""
    if kind == "linear":
        return lambda h: coef * h
    if kind == "cubic":
        return lambda h: coef * h**3
    raise ConfigError("alpha", f"unknown class-K function {kind!r}; choose one of {ALPHAS}")


def _wmean(v: jnp.ndarray, w: jnp.ndarray | None) -> jnp.ndarray:
    if w is None:
        return jnp.mean(v)
    total = jnp.sum(w)
    return jnp.where(total > 0, jnp.sum(w * v) / jnp.maximum(total, 1e-12), 0.0)


def t_s(h_safe: jnp.ndarray, gamma_s: float, w: jnp.ndarray | None = None) -> jnp.ndarray:
    # Eq. (9), T_s = Σ_{x ∈ X_s} max(γ_s − h(x), 0)   (weighted mean here)
    return _wmean(jnp.maximum(gamma_s - h_safe, 0.0), w)


def t_u(h_unsafe: jnp.ndarray, gamma_u: float, w: jnp.ndarray | None = None) -> jnp.ndarray:
    # Eq. (9), T_u = Σ_{x ∈ X_L} max(γ_u + h(x), 0)   (weighted mean here)
    return _wmean(jnp.maximum(gamma_u + h_unsafe, 0.0), w)


def t_e_residual(h_x: jnp.ndarray, h_next: jnp.ndarray, dt: float, alpha: Callable, gamma_exp: float) -> jnp.ndarray:
    # Eq. (9), the argument of T_e's hinge: γ_exp − (h(x') − h(x))/Δt − α(h(x)); ≤ 0 means satisfied
    return gamma_exp - (h_next - h_x) / dt - alpha(h_x)


def t_e(h_x, h_next, dt: float, alpha: Callable, gamma_exp: float, w=None) -> jnp.ndarray:
    # Eq. (9), T_e = Σ_{(x, x') ∈ P_exp} max(γ_exp − (h(x') − h(x))/Δt − α(h(x)), 0)   (weighted mean)
    return _wmean(jnp.maximum(t_e_residual(h_x, h_next, dt, alpha, gamma_exp), 0.0), w)


def t_g(u_omega: jnp.ndarray, u_rl: jnp.ndarray, w: jnp.ndarray | None = None) -> jnp.ndarray:
    # Eq. (9), T_g = Σ ||π_Ω(x) − π_rl(z)||²   (weighted mean)
    return _wmean(jnp.sum((u_omega - u_rl) ** 2, axis=-1), w)


def sq_norm(params) -> jnp.ndarray:
    # Eq. (9), ||Θ||²
    return sum(jnp.sum(p**2) for p in jax.tree_util.tree_leaves(params))


class TeBatch(NamedTuple):
    """Pairs for T_e and T_g: poses z, next poses z' (None: use s_n, for synthetic data), the
    sensed context O_s (any pytree with a leading batch axis), the RL proposal u_rl = π_rl(z), a
    weight per row (1 = use, 0 = padding) and the action that produced z' (None: not known)."""

    pose: jnp.ndarray
    next_pose: jnp.ndarray | None
    context: Any
    u_rl: jnp.ndarray
    weight: jnp.ndarray
    action: jnp.ndarray | None = None


def features(features_fn: Callable, pose: jnp.ndarray, context) -> jnp.ndarray:
    """x = b(z, O_s) for a batch of poses [B, 3] and contexts with a leading batch axis."""
    return jax.vmap(features_fn)(pose, context)


def barrier_terms(cbf_params, policy_params, nominal_params, batch: TeBatch, *, nets, cfg: CBFConfig,
                  features_fn: Callable, dt: float):
    """T_e and T_g of Eq. (9) on a P_exp batch, differentiable in Θ and Ω (not in f_n's parameters).

    u = π_Ω(x, u_rl); z'_g = s_g(z, u, z') of Eq. (6) (or s_n of Eq. (5) when next_pose is None);
    x' = b(z'_g, O_s). Returns (T_e, T_g, aux) with aux = {"x", "h_x", "h_next", "u", "residual"}.
    """
    nominal_params = jax.lax.stop_gradient(nominal_params)
    x = features(features_fn, batch.pose, batch.context)
    u = nets.policy.apply(policy_params, x, batch.u_rl)
    if batch.next_pose is None:
        z_next = nominal_next(nets.nominal, nominal_params, batch.pose, u, dt)
    else:
        u_taken = batch.action if cfg.replay_correction else None
        z_next = straight_through_next(nets.nominal, nominal_params, batch.pose, u, batch.next_pose, dt, u_taken)
    x_next = features(features_fn, z_next, batch.context)
    h_x = nets.cbf.apply(cbf_params, x)
    h_next = nets.cbf.apply(cbf_params, x_next)
    alpha = class_k(cfg.alpha, cfg.alpha_coef)
    te = t_e(h_x, h_next, dt, alpha, cfg.gamma_exp, batch.weight)
    residual = t_e_residual(h_x, h_next, dt, alpha, cfg.gamma_exp)  # for the metrics (same ops: XLA shares them)
    tg = t_g(u, batch.u_rl, batch.weight)
    return te, tg, {"x": x, "h_x": h_x, "h_next": h_next, "u": u, "residual": residual}


def total_loss(params, nominal_params, batch: TeBatch, unsafe_x: jnp.ndarray, unsafe_w: jnp.ndarray, *,
               nets, cfg: CBFConfig, features_fn: Callable, dt: float):
    """Eq. (9): T = wd·||Θ||² + λs T_s + λu T_u + λe T_e + λg T_g, params = {"cbf": Θ, "policy": Ω}.

    X_s is the x of the P_exp rows with min x ≥ d (so T_s shares its forward pass with T_e).
    Returns (T, metrics) with flat keys `safety/...`.
    """
    te, tg, aux = barrier_terms(params["cbf"], params["policy"], nominal_params, batch,
                                nets=nets, cfg=cfg, features_fn=features_fn, dt=dt)
    h_u = nets.cbf.apply(params["cbf"], unsafe_x)
    safe_w = batch.weight * (jnp.min(aux["x"], axis=-1) >= cfg.d)
    ts = t_s(aux["h_x"], cfg.gamma_s, safe_w)
    tu = t_u(h_u, cfg.gamma_u, unsafe_w)
    wd = sq_norm(params["cbf"])
    total = cfg.weight_decay * wd + cfg.lambda_s * ts + cfg.lambda_u * tu + cfg.lambda_e * te + cfg.lambda_g * tg
    metrics = {
        "safety/total": total, "safety/t_s": ts, "safety/t_u": tu, "safety/t_e": te, "safety/t_g": tg,
        "safety/theta_sq": wd,
        "safety/safe_h_pos": _wmean((aux["h_x"] >= 0).astype(jnp.float32), safe_w),
        "safety/unsafe_h_neg": _wmean((h_u < 0).astype(jnp.float32), unsafe_w),
        "safety/te_satisfied": _wmean((aux["residual"] <= 0).astype(jnp.float32), batch.weight),
    }
    return total, metrics
