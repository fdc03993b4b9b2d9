"""The runtime safety filter in numpy (``safety.filter`` without JAX): the action u ∈ [-1, 1]^m
closest to u0 with

    c(u) = (h(b(s_n(s, u))) − h(b(s))) / Δt + α(h(b(s))) ≥ 0,    s_n(s, u) = s + f_n(s, u) Δt,

by ``iters`` rounds of linearising c at the iterate and projecting u0 exactly onto the half-space
within the box (bisection). The same arithmetic as the JAX filter, step for step; ∇_u c comes from
forward-mode derivatives (``deploy.dual``) through f_n, the ray casts on the map and h.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from d2spo.deploy import dual as ad
from d2spo.deploy.dual import F32
from d2spo.deploy.geometry import Map
from d2spo.deploy.nets import Mlp, network_input


def project_halfspace_box(u0: np.ndarray, a: np.ndarray, b, n_bisect: int = 50) -> np.ndarray:
    """argmin ||u − u0||² s.t. a·u ≥ b, u ∈ [-1, 1]^m (``safety.filter.project_halfspace_box``)."""
    u0 = np.clip(u0, F32(-1.0), F32(1.0))
    absa = np.abs(a)
    a_min = np.min(np.where(absa > F32(1e-9), absa, F32(np.inf)))
    mu_hi = F32(2.0) / np.maximum(a_min, F32(1e-9)) if np.isfinite(a_min) else F32(0.0)
    lo, hi = F32(0.0), F32(mu_hi)
    one = F32(1.0)
    u_of = lambda mu: np.minimum(np.maximum(u0 + mu * a, -one), one)  # noqa: E731
    for _ in range(n_bisect):
        mid = F32(0.5) * (lo + hi)
        if np.dot(a, u_of(mid)) >= b:
            hi = mid
        else:
            lo = mid
    return u0 if np.dot(a, u0) >= b else u_of(hi)


@dataclass(frozen=True)
class Filter:
    """The filter's networks, map and settings (the manifest's ``filter``)."""

    cbf: Mlp
    """h_Θ on network_input(x) (its output [1])."""
    nominal: Mlp
    """f_n on (cos θ, sin θ, u) -> ṡ [3]."""
    map: Map
    dt: float
    """Δt (s) of Eq. (5)."""
    alpha: str
    """'linear' (a·h) or 'cubic' (a·h³)."""
    alpha_coef: float
    iters: int
    n_bisect: int = 50

    def h(self, x):
        return self.cbf(network_input(x, self.map.H))[0]

    def _alpha(self, h):
        a = F32(self.alpha_coef)
        return a * h if self.alpha == "linear" else a * (h * h * h)

    def next_pose(self, pose: np.ndarray, u):
        """s_n(s, u) of Eq. (5)."""
        th = pose[2]
        rate = self.nominal(ad.concat([np.array([np.cos(th), np.sin(th)], F32), u]))
        return pose + rate * F32(self.dt)

    def __call__(self, pose, u0) -> tuple[np.ndarray, bool, float]:
        """(action, c(action) ≥ 0, c(action)) for the measured pose (x, y, θ) and the action u0."""
        pose, u0 = np.asarray(pose, F32), np.asarray(u0, F32)
        h0 = self.h(self.map.features(pose))
        dt = F32(self.dt)

        def c(u):
            return (self.h(self.map.features(self.next_pose(pose, u))) - h0) / dt + self._alpha(h0)

        c0 = c(u0)
        if c0 >= 0:  # u0 is returned unchanged (as the JAX filter's final select does): skip the iterations
            return u0, True, float(c0)
        u_k, best, best_c = u0, u0, c0
        for _ in range(self.iters):
            jet = c(ad.seed(u_k))
            val, grad = jet.v, jet.d
            u_new = project_halfspace_box(u0, grad, np.dot(grad, u_k) - val, self.n_bisect)
            c_new = c(u_new)
            closer = np.sum((u_new - u0) ** 2) < np.sum((best - u0) ** 2)
            better = (c_new >= 0 and closer) if best_c >= 0 else c_new > best_c
            u_k = u_new
            if better:
                best, best_c = u_new, c_new
        return best, bool(best_c >= 0), float(best_c)
