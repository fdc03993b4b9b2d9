"""Eq. (9) loss terms against hand-computed values, and the config's validation."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.errors import ConfigError
from d2spo.safety.cbf import (
    CBFConfig,
    check_geometry,
    class_k,
    sq_norm,
    t_e,
    t_g,
    t_s,
    t_u,
)

LIN = class_k("linear", 2.0)


def test_t_s_zero_iff_all_safe_points_clear_the_margin():
    assert float(t_s(jnp.array([0.1, 0.5, 3.0]), 0.1)) == 0.0
    # max(0.1 - 0.0, 0) + max(0.1 - (-0.2), 0) + 0 = 0.1 + 0.3, mean over 3
    np.testing.assert_allclose(t_s(jnp.array([0.0, -0.2, 1.0]), 0.1), 0.4 / 3, rtol=1e-6)


def test_t_u_zero_iff_all_unsafe_points_below_minus_margin():
    assert float(t_u(jnp.array([-0.1, -2.0]), 0.1)) == 0.0
    # max(0.1 + 0.05, 0) + max(0.1 - 0.5, 0) = 0.15, mean over 2
    np.testing.assert_allclose(t_u(jnp.array([0.05, -0.5]), 0.1), 0.075, rtol=1e-6)


def test_t_e_on_hand_made_h_values():
    dt, g = 0.1, 0.05
    h = jnp.array([1.0, 0.5, 0.2])
    h_next = jnp.array([1.0, 0.3, 0.2])
    # residuals γ - (h' - h)/Δt - 2h: 0.05 - 0 - 2 = -1.95; 0.05 + 2 - 1 = 1.05; 0.05 - 0 - 0.4 = -0.35
    np.testing.assert_allclose(t_e(h, h_next, dt, LIN, g), 1.05 / 3, rtol=1e-5)
    # increasing h is always fine when h ≥ 0 and the increase beats the margin
    assert float(t_e(h, h + 0.01, dt, LIN, g)) == 0.0
    # on the boundary h = 0 the barrier must grow by at least γ Δt
    np.testing.assert_allclose(t_e(jnp.zeros(1), jnp.zeros(1), dt, LIN, g), g, rtol=1e-6)
    np.testing.assert_allclose(t_e(jnp.zeros(1), jnp.full(1, g * dt), dt, LIN, g), 0.0, atol=1e-6)


def test_t_e_cubic_alpha():
    cub = class_k("cubic", 2.0)
    # h' = h, so the residual is γ - a h³: h = 0.5 -> 0.05 - 0.25 < 0; h = -0.5 -> 0.05 + 0.25 = 0.3
    np.testing.assert_allclose(t_e(jnp.array([0.5, -0.5]), jnp.array([0.5, -0.5]), 0.1, cub, 0.05), 0.15, rtol=1e-5)


def test_t_g_zero_iff_equal_actions():
    u = jnp.array([[0.3, -0.2], [1.0, 0.0]])
    assert float(t_g(u, u)) == 0.0
    np.testing.assert_allclose(t_g(u, u + jnp.array([[0.1, 0.2], [0.0, 0.0]])), 0.05 / 2, rtol=1e-5)


def test_weights_mask_rows_and_empty_batch_gives_zero():
    h = jnp.array([-1.0, 5.0])
    np.testing.assert_allclose(t_s(h, 0.1, jnp.array([1.0, 0.0])), 1.1, rtol=1e-6)
    assert float(t_s(h, 0.1, jnp.zeros(2))) == 0.0
    assert float(t_u(h, 0.1, jnp.zeros(2))) == 0.0


def test_sq_norm_counts_every_parameter():
    params = {"a": jnp.array([1.0, 2.0]), "b": {"c": jnp.array([[3.0]])}}
    assert float(sq_norm(params)) == 14.0


def test_hinge_gradients_point_the_right_way():
    g = jax.grad(lambda h: t_s(h, 0.1))(jnp.array([0.0]))
    assert g[0] < 0  # raising h on a violated safe point lowers T_s
    g = jax.grad(lambda h: t_u(h, 0.1))(jnp.array([0.0]))
    assert g[0] > 0  # lowering h on a violated unsafe point lowers T_u


def test_config_rejects_bad_values_in_one_line():
    with pytest.raises(ConfigError, match="alpha"):
        CBFConfig(alpha="quadratic")
    with pytest.raises(ConfigError, match="gamma_s"):
        CBFConfig(gamma_s=0.0)
    with pytest.raises(ConfigError, match="lambda_g"):
        CBFConfig(lambda_g=-1.0)
    cfg = CBFConfig()
    check_geometry(cfg, robot_radius=0.15, sensing_range=1.0)
    with pytest.raises(ConfigError, match="unsafe_max"):
        check_geometry(cfg, robot_radius=0.25, sensing_range=1.0)
    with pytest.raises(ConfigError, match="d:"):
        check_geometry(dataclasses.replace(cfg, d=1.5), robot_radius=0.15, sensing_range=1.0)
    with pytest.raises(ConfigError, match="sigma"):
        check_geometry(dataclasses.replace(cfg, sigma=0.3), robot_radius=0.15, sensing_range=1.0)


def test_every_config_field_has_a_docstring():
    import ast
    import inspect

    import d2spo.safety.cbf as mod

    tree = ast.parse(inspect.getsource(mod))
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "CBFConfig")
    body = cls.body
    for i, node in enumerate(body):
        if isinstance(node, ast.AnnAssign):
            nxt = body[i + 1]
            assert isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant), node.target.id
