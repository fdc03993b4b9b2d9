"""Certification of Propositions 1-2 (safety/bounds.py, safety/certify.py): the bounds are sound
(never below what sampling finds), a toy barrier that is valid is certified, broken ones are not."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from d2spo.safety import bounds
from d2spo.safety import certify as cert
from d2spo.safety.cbf import CBFNet, class_k, network_input

H, DT = 1.2, 0.1
N_FEAT = 4  # a small stand-in for the lidar (3 rays + the nearest distance)
NET = CBFNet(hidden=(6, 5), feature_scale=H)


@jax.jit
def _h(params, x):
    return NET.apply(params, x)


_prop1 = jax.jit(cert.prop1, static_argnums=(2, 3))
_prop2 = jax.jit(cert.prop2, static_argnums=(4, 5, 6, 7, 8))


@jax.jit
def _bounds(params, x, x_next, rho, eps):
    layers = bounds.dense_layers(params)
    p1 = cert.prop1(layers, x, eps, H)
    p2 = cert.prop2(layers, x, x_next, rho, eps, H, DT, "linear", 3.0)
    lo, hi = jax.vmap(lambda xi: cert.feature_box(xi, eps, H))(x)
    h_lo, h_hi = jax.vmap(lambda a, b: bounds.forward(layers, a, b)[1])(lo, hi)
    return p1, p2, h_lo, h_hi


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), eps=st.floats(0.002, 0.08), rho=st.floats(0.0, 0.03),
       wscale=st.floats(0.5, 3.0))
def test_bounds_are_never_below_sampled_finite_differences(seed, eps, rho, wscale):
    key = jax.random.PRNGKey(seed)
    kp, kx, kv, ka, kb, kd = jax.random.split(key, 6)
    params = NET.init(kp, jnp.zeros((1, N_FEAT)))
    params = jax.tree_util.tree_map(lambda w: w * wscale, params)  # steep nets too
    n, m = 8, 64
    x = jax.random.uniform(kx, (n, N_FEAT), minval=0.1, maxval=H)
    x_next = x + jax.random.uniform(kv, (n, N_FEAT), minval=-0.1, maxval=0.1)
    p1, p2, h_lo, h_hi = _bounds(params, x, x_next, rho, eps)
    # pairs of points in each ball (corners included: the sup of a difference quotient is often there)
    a = x[:, None] + eps * jax.random.uniform(ka, (n, m, N_FEAT), minval=-1, maxval=1)
    b = x[:, None] + eps * jnp.sign(jax.random.uniform(kb, (n, m, N_FEAT), minval=-1, maxval=1))
    ha, hb = _h(params, a), _h(params, b)
    quotient = jnp.abs(ha - hb) / jnp.maximum(jnp.max(jnp.abs(a - b), -1), 1e-9)
    assert np.all(np.asarray(quotient) <= np.asarray(p1.lip)[:, None] * (1 + 1e-4) + 1e-5)
    assert np.all(np.asarray(h_lo)[:, None] - 1e-5 <= np.asarray(ha))
    assert np.all(np.asarray(ha) <= np.asarray(h_hi)[:, None] + 1e-5)
    # e over the ball, with any displacement within ρ of the nominal one, is above the certified bound
    v = (x_next - x)[:, None] + rho * jax.random.uniform(kd, (n, m, N_FEAT), minval=-1, maxval=1)
    e = (_h(params, a + v) - ha) / DT + class_k("linear", 3.0)(ha)
    dist = jnp.max(jnp.abs(a - x[:, None]), -1)
    lower = p2.e[:, None] - p2.lip[:, None] * dist - p2.residual_term[:, None]
    assert np.all(np.asarray(e) >= np.asarray(lower) - 1e-4 * (1 + np.abs(np.asarray(lower))))
    # the local bound is no looser than the product of the layers' norms
    glob = bounds.global_lipschitz(bounds.dense_layers(params))["linf_product"] / H
    assert np.all(np.asarray(p1.lip) <= glob * (1 + 1e-4))


def _toy_barrier(zero: float, slope: float = 6.0):
    """h(x) = tanh(slope · (x − zero)) on a 1-D clearance x, written as a CBFNet's weights
    (input s = (x/H, min(x)/H), one hidden unit, identity output)."""
    w1 = jnp.array([[slope * H], [0.0]])
    return {"params": {"Dense_0": {"kernel": w1, "bias": jnp.array([-slope * zero])},
                       "Dense_1": {"kernel": jnp.ones((1, 1)), "bias": jnp.zeros((1,))}}}


def _toy_check(params, drift: float):
    """Toy system: clearance x to one wall, x' = x + Δt·drift·(1 − x) (drift > 0 moves away).
    ℒ = [0.1, 0.2] (Prop. 1), D = [0.2, 1.0] (Prop. 2); a dense 1-D net of each."""
    layers = bounds.dense_layers(params)
    ring = jnp.linspace(0.1, 0.2, 101)[:, None]
    safe = jnp.linspace(0.2, 1.0, 401)[:, None]
    nxt = safe + DT * drift * (1.0 - safe)
    p1 = _prop1(layers, ring, 0.001, H)
    p2 = _prop2(layers, safe, nxt, 0.0005, 0.001, H, DT, "linear", 3.0)
    return np.asarray(p1.status), np.asarray(p2.status), p1, p2


def test_a_valid_toy_barrier_is_certified_and_broken_ones_are_not():
    s1, s2, p1, p2 = _toy_check(_toy_barrier(0.25), drift=1.0)
    assert np.all(s1 == cert.CERTIFIED), cert.fractions(s1)
    assert np.all(s2 == cert.CERTIFIED), cert.fractions(s2)
    # broken 1: h crosses zero inside the ring -> violated there, the rest still certified
    s1b, _, p1b, _ = _toy_check(_toy_barrier(0.15), drift=1.0)
    assert np.all(s1b[np.asarray(p1b.h) >= 0] == cert.VIOLATED) and np.sum(s1b == cert.VIOLATED) > 40
    # broken 2: the system drifts toward the wall -> e < 0 where h > 0: violated, never certified there
    _, s2b, _, p2b = _toy_check(_toy_barrier(0.25), drift=-3.0)
    assert np.sum(s2b == cert.VIOLATED) > 100
    assert not np.any((s2b == cert.CERTIFIED) & (np.asarray(p2b.e) < 0))
    # a margin too small for its ball: a flat barrier near zero is neither certified nor violated
    s1c, _, _, _ = _toy_check(_toy_barrier(0.2005, slope=0.5), drift=1.0)
    assert np.any(s1c == cert.NOT_CERTIFIED)


def test_network_input_box_encloses_the_ball():
    x = jnp.array([0.5, 0.3, 0.9, 0.3])
    lo, hi = cert.feature_box(x, 0.05, H)
    pts = x + 0.05 * jax.random.uniform(jax.random.PRNGKey(0), (200, 4), minval=-1, maxval=1)
    s = network_input(pts, H)
    assert np.all(np.asarray(s) >= np.asarray(lo) - 1e-7) and np.all(np.asarray(s) <= np.asarray(hi) + 1e-7)
