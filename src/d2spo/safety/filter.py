"""Optional runtime safety filter (not in the paper).

Given a proposed action u0 (e.g. π_Ω's), return the action u ∈ [-1, 1]^m closest to u0 that meets
the discrete CBF condition under the nominal model,

    c(u) = (h(b(s_n(s, u), O_s)) − h(b(s, O_s))) / Δt + α(h(b(s, O_s))) ≥ 0,    s_n from Eq. (5).

c is nonlinear in u, so it is linearised at the current iterate u_k and u0 is projected exactly
onto {u ∈ box : c(u_k) + ∇c(u_k)·(u − u_k) ≥ 0}; this repeats a fixed number of times, so the
filter is jit-able. Among the iterates meeting c ≥ 0 the one closest to u0 is returned; if none
does, the one with the largest c. When u0 already satisfies the condition it is returned unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from d2spo.safety.cbf import class_k
from d2spo.safety.nominal import nominal_next


class FilterResult(NamedTuple):
    """The filtered action, whether c(u) ≥ 0 holds, c(u), and c(u0)."""

    action: jnp.ndarray
    ok: jnp.ndarray
    value: jnp.ndarray
    value_u0: jnp.ndarray


def project_halfspace_box(u0: jnp.ndarray, a: jnp.ndarray, b: jnp.ndarray, n_bisect: int = 50) -> jnp.ndarray:
    """argmin ||u − u0||² s.t. a·u ≥ b, u ∈ [-1, 1]^m (exact up to bisection precision).

    By the KKT conditions the minimiser is u(μ) = clip(u0 + μ a, -1, 1) for the smallest μ ≥ 0 with
    a·u(μ) ≥ b; a·u(μ) is non-decreasing in μ, so μ is found by bisection, keeping the feasible end.
    If the set is empty, the box point maximising a·u nearest u0 is returned.
    """
    u0 = jnp.clip(u0, -1.0, 1.0)
    absa = jnp.abs(a)
    a_min = jnp.min(jnp.where(absa > 1e-9, absa, jnp.inf))
    mu_hi = jnp.where(jnp.isfinite(a_min), 2.0 / jnp.maximum(a_min, 1e-9), 0.0)  # every moving coordinate saturates

    def u_of(mu):
        return jnp.clip(u0 + mu * a, -1.0, 1.0)

    def bisect(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        feasible = jnp.dot(a, u_of(mid)) >= b
        return jnp.where(feasible, lo, mid), jnp.where(feasible, mid, hi)

    _, hi = jax.lax.fori_loop(0, n_bisect, bisect, (jnp.zeros(()), mu_hi))
    return jnp.where(jnp.dot(a, u0) >= b, u0, u_of(hi))


def cbf_condition(nets, cbf_params, nominal_params, pose, context, u, *, cfg, features_fn: Callable, dt: float):
    """c(u) of the module docstring for one pose (unbatched)."""
    alpha = class_k(cfg.alpha, cfg.filter_alpha)
    h = nets.cbf.apply(cbf_params, features_fn(pose, context))
    h_next = nets.cbf.apply(cbf_params, features_fn(nominal_next(nets.nominal, nominal_params, pose, u, dt), context))
    return (h_next - h) / dt + alpha(h)


def safety_filter(nets, cbf_params, nominal_params, pose: jnp.ndarray, context, u0: jnp.ndarray, *,
                  cfg, features_fn: Callable, dt: float, iters: int | None = None) -> FilterResult:
    """Filter one action; vmap over poses/contexts/actions for a batch. `iters` defaults to cfg.filter_iters."""
    iters = cfg.filter_iters if iters is None else iters

    def c(u):
        return cbf_condition(nets, cbf_params, nominal_params, pose, context, u,
                             cfg=cfg, features_fn=features_fn, dt=dt)

    c0 = c(u0)

    def body(_, carry):
        u_k, best, best_c = carry
        val, grad = jax.value_and_grad(c)(u_k)
        u_new = project_halfspace_box(u0, grad, jnp.dot(grad, u_k) - val)
        c_new = c(u_new)
        closer = jnp.sum((u_new - u0) ** 2) < jnp.sum((best - u0) ** 2)
        better = jnp.where(best_c >= 0, (c_new >= 0) & closer, c_new > best_c)
        return u_new, jnp.where(better, u_new, best), jnp.where(better, c_new, best_c)

    _, best, best_c = jax.lax.fori_loop(0, iters, body, (u0, u0, c0))
    action = jnp.where(c0 >= 0, u0, best)
    value = jnp.where(c0 >= 0, c0, best_c)
    return FilterResult(action=action, ok=value >= 0, value=value, value_u0=c0)
