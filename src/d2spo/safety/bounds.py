"""Sound bounds on a tanh MLP over a box of inputs, by interval bound propagation (IBP).

Used by `safety/certify.py` to check Propositions 1 and 2 of the paper on the learned h_Θ. An
interval is a pair (lo, hi) of arrays; every function here works on one point (vmap for a batch).

* `forward` propagates an input box through the layers: intervals of every pre-activation and of
  the output (a sound enclosure of h over the box).
* `gradient` propagates the exact output weights backwards through intervals of tanh' and gives,
  per input coordinate, an interval that contains ∂h/∂s at every s of the box. The ℓ1 norm of its
  largest magnitudes is a local Lipschitz constant of h w.r.t. the ℓ∞ norm on the box
  (mean-value theorem on a convex set).
* `gradient_difference` encloses g(s + δ) − g(s) for s in one box and δ in another by carrying the
  differences of the pre-activations and of the backward signals through the layers, with
  tanh(b) − tanh(a) ∈ tanh'(ξ)(b − a) and tanh'(b) − tanh'(a) ∈ tanh''(ξ)(b − a) for ξ in the hull.
  It keeps the correlation between g(s + δ) and g(s) that two separate enclosures would lose (that
  loss costs a factor ~2/Δt in the Lipschitz constant of the discrete ḣ).

Why IBP and not the product of the layers' norms: the product bounds the gradient everywhere at
once, as if every tanh were at its steepest and every weight row aligned; IBP bounds it on the ball
only, where most units are saturated or their slopes known. `global_lipschitz` gives the product
(ℓ∞ operator norms, and spectral norms times √n) for comparison. Linear bound propagation (CROWN)
would be tighter still, at several times the code; IBP on balls of a few centimetres was tight
enough here (docs/certify.md gives the ratio measured on a trained run).

Float32 rounding is covered by widening every propagated radius by a relative 1e-5 plus 1e-7.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

_WIDEN_REL, _WIDEN_ABS = 1e-5, 1e-7
_TANH2_Z = math.atanh(1.0 / math.sqrt(3.0))
"""tanh'' = −2 tanh (1 − tanh²) has its extrema at ±atanh(1/√3)."""
_TANH2_MAX = 4.0 / (3.0 * math.sqrt(3.0))


def dense_layers(params) -> list[tuple[jnp.ndarray, jnp.ndarray]]:
    """The (kernel [in, out], bias [out]) of a flax MLP's Dense_0, Dense_1, ... in order."""
    p = params["params"] if "params" in params else params
    names = sorted((k for k in p if k.startswith("Dense_")), key=lambda k: int(k.split("_")[1]))
    return [(p[k]["kernel"], p[k]["bias"]) for k in names]


def _widen(r):
    return r * (1.0 + _WIDEN_REL) + _WIDEN_ABS


def affine(lo, hi, kernel, bias=None):
    """{s K + b : s ∈ [lo, hi]} (exact per output, up to rounding), centre–radius form."""
    c, r = 0.5 * (lo + hi), 0.5 * (hi - lo)
    c = c @ kernel + (0.0 if bias is None else bias)
    r = _widen(r @ jnp.abs(kernel))
    return c - r, c + r


def mul(alo, ahi, blo, bhi):
    """{a b : a ∈ [alo, ahi], b ∈ [blo, bhi]}, elementwise."""
    p = jnp.stack([alo * blo, alo * bhi, ahi * blo, ahi * bhi])
    return jnp.min(p, 0), jnp.max(p, 0)


def matvec(kernel, lo, hi):
    """{K v : v ∈ [lo, hi]} for K [in, out] and v [out]: the backward step of a Dense layer."""
    c, r = 0.5 * (lo + hi), 0.5 * (hi - lo)
    c = kernel @ c
    r = _widen(jnp.abs(kernel) @ r)
    return c - r, c + r


def tanh_prime(lo, hi):
    """Enclosure of tanh' = 1 − tanh² (even, decreasing in |z|) over [lo, hi]."""
    near = jnp.where((lo <= 0) & (hi >= 0), 0.0, jnp.minimum(jnp.abs(lo), jnp.abs(hi)))
    far = jnp.maximum(jnp.abs(lo), jnp.abs(hi))
    return 1.0 - jnp.tanh(far) ** 2, 1.0 - jnp.tanh(near) ** 2


def tanh_second(lo, hi):
    """Enclosure of tanh'' = −2 tanh (1 − tanh²) over [lo, hi]: endpoints and interior extrema."""
    def f(z):
        t = jnp.tanh(z)
        return -2.0 * t * (1.0 - t * t)

    flo, fhi = f(lo), f(hi)
    vlo = jnp.minimum(flo, fhi)
    vhi = jnp.maximum(flo, fhi)
    vlo = jnp.where((lo <= _TANH2_Z) & (hi >= _TANH2_Z), -_TANH2_MAX, vlo)
    vhi = jnp.where((lo <= -_TANH2_Z) & (hi >= -_TANH2_Z), _TANH2_MAX, vhi)
    return vlo, vhi


def forward(layers, lo, hi):
    """Pre-activation intervals of every hidden layer, and the output interval [lo, hi] of h."""
    zs = []
    for kernel, bias in layers[:-1]:
        lo, hi = affine(lo, hi, kernel, bias)
        zs.append((lo, hi))
        lo, hi = jnp.tanh(lo), jnp.tanh(hi)
    lo, hi = affine(lo, hi, *layers[-1])
    return zs, (lo[0], hi[0])


def gradient(layers, zs):
    """Interval of ∂h/∂s per input coordinate over the box whose pre-activations are `zs`."""
    g = layers[-1][0][:, 0]
    glo, ghi = g, g
    for (kernel, _), (zlo, zhi) in zip(reversed(layers[:-1]), reversed(zs)):
        dlo, dhi = tanh_prime(zlo, zhi)
        glo, ghi = matvec(kernel, *mul(dlo, dhi, glo, ghi))
    return glo, ghi


def gradient_difference(layers, zs, zs_next, dlo, dhi):
    """Interval of g(s + δ) − g(s) per coordinate, for s in the box with pre-activations `zs`, s + δ
    in the box with `zs_next`, and δ ∈ [dlo, dhi]. Returns (Δg_lo, Δg_hi, g_next_lo, g_next_hi)."""
    # forward: differences of the pre-activations, Δz_l, through tanh(b) − tanh(a) = tanh'(ξ)(b − a)
    dz = []
    for i, (kernel, _) in enumerate(layers[:-1]):
        dlo, dhi = affine(dlo, dhi, kernel)
        dz.append((dlo, dhi))
        (alo, ahi), (blo, bhi) = zs[i], zs_next[i]
        slo, shi = tanh_prime(jnp.minimum(alo, blo), jnp.maximum(ahi, bhi))
        dlo, dhi = mul(slo, shi, dlo, dhi)
    # backward: λ at s, λ' at s + δ, and Δλ = λ' − λ; μ = tanh'(z) λ, Δμ = tanh'(z') Δλ + Δtanh' λ
    g = layers[-1][0][:, 0]
    lam, lam2 = (g, g), (g, g)
    diff = (jnp.zeros_like(g), jnp.zeros_like(g))
    for i in reversed(range(len(layers) - 1)):
        kernel = layers[i][0]
        (alo, ahi), (blo, bhi) = zs[i], zs_next[i]
        d1, d2 = tanh_prime(alo, ahi), tanh_prime(blo, bhi)
        dd = mul(*tanh_second(jnp.minimum(alo, blo), jnp.maximum(ahi, bhi)), *dz[i])
        p1 = mul(*d2, *diff)
        p2 = mul(*dd, *lam)
        diff = matvec(kernel, p1[0] + p2[0], p1[1] + p2[1])
        lam = matvec(kernel, *mul(*d1, *lam))
        lam2 = matvec(kernel, *mul(*d2, *lam2))
    return diff[0], diff[1], lam2[0], lam2[1]


def sup_abs_l1(lo, hi) -> jnp.ndarray:
    """Σ_k max |[lo_k, hi_k]|: a bound on the ℓ1 norm of any vector in the box (the dual of ℓ∞)."""
    return jnp.sum(jnp.maximum(jnp.abs(lo), jnp.abs(hi)), axis=-1)


def global_lipschitz(layers) -> dict[str, float]:
    """Input-independent Lipschitz constants of the MLP w.r.t. the ℓ∞ norm of its input, from the
    product of the layers' norms (|tanh'| ≤ 1): with ℓ∞ operator norms, and with spectral norms
    times √n (ℓ2 constant converted to ℓ∞ inputs). For comparison with the local IBP bounds."""
    linf, spec = 1.0, 1.0
    for kernel, _ in layers:
        k = jnp.asarray(kernel)
        linf *= float(jnp.max(jnp.sum(jnp.abs(k), axis=0)))  # max over outputs of Σ_in |K|
        spec *= float(jnp.linalg.norm(k, ord=2))
    n = int(layers[0][0].shape[0])
    return {"linf_product": linf, "spectral_product_sqrt_n": spec * math.sqrt(n)}
