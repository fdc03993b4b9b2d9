"""The optional runtime safety filter: exact box/half-space projection and the CBF condition."""

import itertools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from d2spo.safety.cbf import CBFConfig
from d2spo.safety.filter import cbf_condition, project_halfspace_box, safety_filter
from d2spo.safety.joint_policy import SafetyNets
from d2spo.safety.nominal import unicycle_prior

DT = 0.1
CFG = CBFConfig(alpha="linear", alpha_coef=3.0, filter_iters=3)


class Kinematic(nn.Module):
    """A parameter-free nominal model: the unicycle prior with v = u[0], ω = 2 u[1]."""

    @nn.compact
    def __call__(self, s, u):
        return unicycle_prior(1.0, 2.0)(s, u)


class MockH(nn.Module):
    """h(x) = x[0] − 0.25: positive beyond 0.25 m of clearance."""

    @nn.compact
    def __call__(self, x):
        return x[..., 0] - 0.25


def disk_clearance(pose, ctx):
    return jnp.atleast_1d(jnp.linalg.norm(pose[:2] - ctx) - 0.3)


NETS = SafetyNets(cbf=MockH(), policy=None, nominal=Kinematic())
ORIGIN = jnp.zeros(2)


def _filter(pose, u0):
    return safety_filter(NETS, {}, {}, pose, ORIGIN, u0, cfg=CFG, features_fn=disk_clearance, dt=DT)


def test_projection_matches_brute_force():
    grid = jnp.stack(jnp.meshgrid(jnp.linspace(-1, 1, 801), jnp.linspace(-1, 1, 801)), -1).reshape(-1, 2)
    rng = np.random.default_rng(0)
    for _ in range(20):
        u0 = jnp.asarray(rng.uniform(-1, 1, 2), jnp.float32)
        a = jnp.asarray(rng.normal(size=2), jnp.float32)
        b = jnp.float32(rng.uniform(-1, 1) * float(jnp.abs(a).sum()))
        u = project_halfspace_box(u0, a, b)
        feasible = grid @ a >= b
        if not bool(feasible.any()):
            continue
        best = float(jnp.min(jnp.where(feasible, jnp.sum((grid - u0) ** 2, -1), jnp.inf)))
        assert float(a @ u) >= float(b) - 1e-5
        assert bool(jnp.all(jnp.abs(u) <= 1.0))
        assert float(jnp.sum((u - u0) ** 2)) <= best + 1e-5


def test_filter_leaves_a_safe_action_alone():
    pose = jnp.array([-0.6, 0.0, 0.0])  # 0.3 m of clearance, facing the disk: h = 0.05
    u0 = jnp.array([0.1, 0.5])  # c = -0.1 + 3 * 0.05 > 0
    res = _filter(pose, u0)
    np.testing.assert_array_equal(np.asarray(res.action), np.asarray(u0))
    assert bool(res.ok) and float(res.value_u0) > 0


def test_filter_slows_down_to_the_boundary_of_the_condition():
    pose = jnp.array([-0.6, 0.0, 0.0])
    u0 = jnp.array([1.0, 0.0])  # full speed at the disk: c(u0) = -1 + 0.15 < 0
    res = _filter(pose, u0)
    assert float(res.value_u0) < 0
    # c is linear in the speed here (c = 0.15 - v), so the projection is exact: v = 0.15
    np.testing.assert_allclose(res.action, [0.15, 0.0], atol=2e-3)
    assert bool(res.ok)
    assert float(jnp.linalg.norm(res.action - u0)) < float(jnp.linalg.norm(u0))  # closer than stopping


def test_filter_alpha_coef_makes_the_filter_brake_earlier():
    """With α(h) = a·h and h = 0.05, the condition is c = a·0.05 − v: a = 1.5 allows half the speed."""
    import dataclasses

    import pytest

    from d2spo.errors import ConfigError

    pose = jnp.array([-0.6, 0.0, 0.0])
    cfg = dataclasses.replace(CFG, filter_alpha_coef=1.5)
    res = safety_filter(NETS, {}, {}, pose, ORIGIN, jnp.array([1.0, 0.0]), cfg=cfg, features_fn=disk_clearance, dt=DT)
    np.testing.assert_allclose(res.action, [0.075, 0.0], atol=2e-3)
    with pytest.raises(ConfigError):
        CBFConfig(filter_alpha_coef=-1.0)


def test_filter_handles_a_nonlinear_condition():
    checked = 0
    for y, th in itertools.product([0.15, 0.3], [0.0, 0.4]):
        pose = jnp.array([-0.55, y, th])
        u0 = jnp.array([1.0, -0.8])

        def c(u, pose=pose):
            return cbf_condition(NETS, {}, {}, pose, ORIGIN, u, cfg=CFG, features_fn=disk_clearance, dt=DT)

        res = jax.jit(_filter)(pose, u0)
        if float(c(u0)) >= 0:
            continue
        assert bool(res.ok) and float(c(res.action)) >= -1e-5
        assert float(jnp.linalg.norm(res.action - u0)) < float(jnp.linalg.norm(u0 - jnp.zeros(2)))
        checked += 1
    assert checked >= 3
