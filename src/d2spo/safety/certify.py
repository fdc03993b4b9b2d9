"""Propositions 1 and 2 of the paper (Sec. IV-B), checked on the learned h_Θ at a net of points.

h reads the sensor features x = b(z, O_s) ∈ R^n (ranges in metres, clipped at H) through
`network_input`: s(x) = (x/H, min(x)/H). The ε-balls live in this **feature space**, in the ℓ∞
norm: B_ε(x_i) = {x : |x_k − x_i,k| ≤ ε for every range k}. min is 1-Lipschitz in ℓ∞, so s maps
the ball into the box [s(x_i − ε), s(x_i + ε)], on which `bounds` works.

Proposition 1 (ℒ): h(x) < 0 on B_ε̄(x_i) if h(x_i) ≤ −γ_u with ε̄ < γ_u / L_h(x_i). We take the
largest γ_u the point allows, γ_u = −h(x_i), so a point is

* **violated** if h(x_i) ≥ 0 (the condition fails at the point itself),
* **certified** if h(x_i) + L_h(x_i) ε̄ < 0,
* **not certified** otherwise (the margin is too small for its ball).

Proposition 2 (D), with the discrete ḣ of Eq. (9): e(x) = (h(x + v) − h(x))/Δt + α(h(x)), where v
is the feature displacement over one step, x' − x. At a net point v is computed through the
learned nominal model, x'_n = b(s_n(z_i, π_Ω(x_i, u_rl)), O_s) (Eq. (5)). The true next features
differ from x'_n by the model's error, bounded in one of two ways: ‖x'_true − x'_n‖∞ ≤ ρ (metres,
carried through the weights) or |h(x'_true) − h(x'_n)| ≤ ρ_h (measured directly in h). Then, for
every x in B_ε(x_i),

    e ≥ e_n(x_i) − L_e(x_i) ε − R_i,

with L_e(x_i) the Lipschitz bound of e over the ball (the displacement held fixed) and
R_i = sup |∂e/∂v| ρ + ρ_h/Δt the model-error term. A point is violated if e_n(x_i) < 0, certified if the
right-hand side is ≥ 0, and not certified otherwise. L_h, L_e and R_i are *proofs about the
networks* (interval bound propagation through the weights, `bounds.py`); that the true
displacement lies within ρ of the nominal one is *measured*, not proven. The displacement is also
that of the anchor's action: a ball point does not change the action π_Ω takes (docs/certify.md).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.safety import bounds
from d2spo.safety.cbf import class_k, network_input

CERTIFIED, NOT_CERTIFIED, VIOLATED = 0, 1, 2
STATUS_NAMES = ("certified", "not certified", "violated")


class Prop1(NamedTuple):
    """Per point: h(x_i), the local Lipschitz bound L_h (w.r.t. ‖x‖∞, metres), the margin
    −h − L_h ε̄ (> 0: certified), the interval upper bound of h over the ball, and the status."""

    h: jnp.ndarray
    lip: jnp.ndarray
    margin: jnp.ndarray
    h_upper: jnp.ndarray
    status: jnp.ndarray


class Prop2(NamedTuple):
    """Per point: e_n(x_i) (through the nominal model), L_e, the model-error term R, the margin
    e_n − L_e ε − R (≥ 0: certified), L_h at the point's ball, and the status."""

    e: jnp.ndarray
    lip: jnp.ndarray
    residual_term: jnp.ndarray
    margin: jnp.ndarray
    h: jnp.ndarray
    status: jnp.ndarray


def feature_box(x: jnp.ndarray, r, scale: float):
    """The box in h's input space enclosing s(B_r(x)) (ℓ∞ ball of radius r around features x)."""
    return network_input(x - r, scale), network_input(x + r, scale)


def _argmin_candidates(lo: jnp.ndarray, hi: jnp.ndarray) -> jnp.ndarray:
    """bool [n]: coordinates that can be the minimum somewhere in the box [lo, hi]."""
    return lo <= jnp.min(hi)


def _h(layers, s: jnp.ndarray) -> jnp.ndarray:
    for kernel, bias in layers[:-1]:
        s = jnp.tanh(s @ kernel + bias)
    return (s @ layers[-1][0] + layers[-1][1])[0]


def prop1_point(layers, x: jnp.ndarray, eps: float, scale: float) -> Prop1:
    """Proposition 1 at one point x [n] with ε̄ = `eps` (metres); `scale` is H."""
    lo, hi = feature_box(x, eps, scale)
    zs, (_, h_hi) = bounds.forward(layers, lo, hi)
    lip = bounds.sup_abs_l1(*bounds.gradient(layers, zs)) / scale  # ‖s(a) − s(b)‖∞ ≤ ‖a − b‖∞ / H
    h = _h(layers, network_input(x, scale))
    margin = -h - lip * eps
    status = jnp.where(h >= 0, VIOLATED, jnp.where(margin > 0, CERTIFIED, NOT_CERTIFIED))
    return Prop1(h, lip, margin, h_hi, status)


def prop2_point(layers, x: jnp.ndarray, x_next: jnp.ndarray, rho, eps: float, scale: float, dt: float,
                alpha: str, alpha_coef: float, h_residual=0.0) -> Prop2:
    """Proposition 2 at one point: features x [n], nominal next features x_next [n], ε (metres),
    H = `scale`, the step Δt and α. The model's error enters as ρ (‖x'_true − x'_n‖∞ ≤ ρ, metres;
    bounded through the weights) and/or as `h_residual` (|h(x'_true) − h(x'_n)| ≤ h_residual,
    measured directly; adds h_residual/Δt to the residual term)."""
    v = x_next - x
    s_lo, s_hi = feature_box(x, eps, scale)
    n_lo, n_hi = feature_box(x + v, eps + rho, scale)
    # δ = s(x + v') − s(x): rays move by v' ∈ v ± ρ; min(x + v') − min(x) is v'_j when one range j is
    # the minimum all over both boxes, and lies in [min v' , max v'] in any case.
    j_here = _argmin_candidates(x - eps, x + eps)
    j_next = _argmin_candidates(x + v - eps - rho, x + v + eps + rho)
    single = (jnp.sum(j_here) == 1) & jnp.all(j_here == j_next)
    # Otherwise min(x + v') − min(x) also lies within 2ε + ρ of its value at the anchor (min is
    # 1-Lipschitz in ℓ∞): this part of the displacement moves with x, at most twice as fast.
    d_c = network_input(x_next, scale) - network_input(x, scale)
    vj = jnp.sum(jnp.where(j_here, v, 0.0))
    wide = 2 * eps + rho
    m_lo = jnp.where(single, vj - rho, jnp.maximum(jnp.min(v) - rho, d_c[-1] * scale - wide))
    m_hi = jnp.where(single, vj + rho, jnp.minimum(jnp.max(v) + rho, d_c[-1] * scale + wide))
    d_lo = jnp.concatenate([v - rho, m_lo[None]]) / scale
    d_hi = jnp.concatenate([v + rho, m_hi[None]]) / scale

    zs, (h_lo, h_hi) = bounds.forward(layers, s_lo, s_hi)
    zs_next, _ = bounds.forward(layers, n_lo, n_hi)
    g_lo, g_hi = bounds.gradient(layers, zs)
    dg_lo, dg_hi, gn_lo, gn_hi = bounds.gradient_difference(layers, zs, zs_next, d_lo, d_hi)
    if alpha == "linear":
        a_lo = a_hi = jnp.asarray(alpha_coef, jnp.float32)
    else:  # cubic: α'(h) = 3 a h²
        h2_lo = jnp.where((h_lo <= 0) & (h_hi >= 0), 0.0, jnp.minimum(h_lo**2, h_hi**2))
        a_lo, a_hi = 3 * alpha_coef * h2_lo, 3 * alpha_coef * jnp.maximum(h_lo**2, h_hi**2)
    ag_lo, ag_hi = bounds.mul(a_lo, a_hi, g_lo, g_hi)
    grad_lo, grad_hi = dg_lo / dt + ag_lo, dg_hi / dt + ag_hi  # ∇_s e = (g(s + δ) − g(s))/Δt + α'(h) g(s)
    lip = bounds.sup_abs_l1(grad_lo, grad_hi) / scale
    dev = jnp.maximum(jnp.abs(d_lo - d_c), jnp.abs(d_hi - d_c))  # |δ_k − δ_c,k| over the displacement box
    residual_term = jnp.sum(jnp.maximum(jnp.abs(gn_lo), jnp.abs(gn_hi)) * dev) / dt + h_residual / dt

    h = _h(layers, network_input(x, scale))
    h_next = _h(layers, network_input(x_next, scale))
    e = (h_next - h) / dt + class_k(alpha, alpha_coef)(h)
    margin = e - residual_term - lip * eps
    status = jnp.where(e < 0, VIOLATED, jnp.where(margin >= 0, CERTIFIED, NOT_CERTIFIED))
    return Prop2(e, lip, residual_term, margin, h, status)


def prop1(layers, x: jnp.ndarray, eps: float, scale: float) -> Prop1:
    """`prop1_point` for a batch x [N, n]."""
    return jax.vmap(lambda xi: prop1_point(layers, xi, eps, scale))(x)


def prop2(layers, x: jnp.ndarray, x_next: jnp.ndarray, rho, eps: float, scale: float, dt: float,
          alpha: str = "linear", alpha_coef: float = 3.0, h_residual=0.0) -> Prop2:
    """`prop2_point` for a batch x, x_next [N, n] (ρ a scalar or [N])."""
    rho = jnp.broadcast_to(jnp.asarray(rho, jnp.float32), x.shape[:1])
    return jax.vmap(lambda a, b, r: prop2_point(layers, a, b, r, eps, scale, dt, alpha, alpha_coef, h_residual))(
        x, x_next, rho)


def fractions(status: jnp.ndarray, mask: jnp.ndarray | None = None) -> dict[str, float | int]:
    """Counts and fractions of each status among the rows where `mask` holds."""
    status = np.asarray(status)
    keep = np.ones(status.shape, bool) if mask is None else np.asarray(mask, bool)
    n = int(keep.sum())
    out: dict[str, float | int] = {"points": n}
    for code, name in enumerate(STATUS_NAMES):
        out[name.replace(" ", "_")] = float(((status == code) & keep).sum() / n) if n else float("nan")
    return out
