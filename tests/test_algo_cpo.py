"""CPO: the case selection and step of Eq. (10) against hand-solved and brute-force problems,
conjugate gradient, the Fisher-vector product, one policy step, and learning on `relaxed`."""

from __future__ import annotations

import csv
import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from d2spo.algos.common.networks import (
    GaussianPolicy,
    gaussian_kl,
    gaussian_log_prob,
    gaussian_sample,
)
from d2spo.algos.cpo import (
    INFEASIBLE,
    MIXED_STEP,
    REWARD_STEP,
    CPOConfig,
    PolicyData,
    conjugate_gradient,
    cpo_policy_update,
    cpo_step,
    kl_hessian_vector_product,
)
from d2spo.config import TrainConfig
from d2spo.errors import ConfigError
from d2spo.run import build
from d2spo.train import train

_direction = jax.jit(lambda *a: cpo_step(*a)[:2])  # (x, case)


def step(g, b, c, h, delta):
    """The CPO direction for an explicit H (exact inverses), as float64 numpy."""
    g, b, h = (np.asarray(a, np.float64) for a in (g, b, h))
    x, case = _direction(jnp.float32(g), jnp.float32(b), jnp.float32(c), jnp.float32(np.linalg.solve(h, g)),
                         jnp.float32(np.linalg.solve(h, b)), delta)
    return np.asarray(x, np.float64), int(case)


# ---- hand-solved problems, H = I, delta = 1/2: the trust region is the unit disk ------------------


def test_feasible_inactive_constraint_gives_the_pure_reward_step():
    # max x1 s.t. -1 + x2 <= 0, |x| <= 1: x = (1, 0), the constraint does not bind.
    x, case = step([1.0, 0.0], [0.0, 1.0], -1.0, np.eye(2), 0.5)
    assert case == REWARD_STEP
    np.testing.assert_allclose(x, [1.0, 0.0], atol=1e-6)
    assert 0.5 * x @ x == pytest.approx(0.5, rel=1e-5)  # KL model = delta: full trust-region size


def test_feasible_active_constraint_gives_the_mixed_step_on_both_boundaries():
    # max x1 s.t. -0.5 + x1 + x2 <= 0, |x| <= 1. The pure step (1, 0) violates it; on both
    # boundaries x1 + x2 = 0.5, x1^2 + x2^2 = 1  =>  x1 = (1 + sqrt 7) / 4, x2 = 0.5 - x1.
    g, b, c, delta = np.array([1.0, 0.0]), np.array([1.0, 1.0]), -0.5, 0.5
    x, case = step(g, b, c, np.eye(2), delta)
    x1 = (1.0 + math.sqrt(7.0)) / 4.0
    assert case == MIXED_STEP
    np.testing.assert_allclose(x, [x1, 0.5 - x1], atol=1e-5)
    assert c + b @ x == pytest.approx(0.0, abs=1e-5)  # linearised constraint with equality
    assert 0.5 * x @ x == pytest.approx(delta, rel=1e-5)  # KL model = delta


def test_violated_but_recoverable_constraint_gives_the_mixed_step():
    # Current policy over the limit (c > 0) but the half-plane meets the disk:
    # max x1 s.t. 0.5 + x2 <= 0, |x| <= 1  =>  x = (sqrt(0.75), -0.5).
    x, case = step([1.0, 0.0], [0.0, 1.0], 0.5, np.eye(2), 0.5)
    assert case == MIXED_STEP
    np.testing.assert_allclose(x, [math.sqrt(0.75), -0.5], atol=1e-5)


def test_infeasible_problem_gives_the_recovery_step_that_decreases_cost():
    # 2 + x2 <= 0 cannot be met inside |x| <= 1: x = -sqrt(2 delta / s) H^-1 b = (0, -1).
    b = np.array([0.0, 1.0])
    x, case = step([1.0, 0.0], b, 2.0, np.eye(2), 0.5)
    assert case == INFEASIBLE
    np.testing.assert_allclose(x, [0.0, -1.0], atol=1e-6)
    assert b @ x < 0
    # With a non-identity H the recovery step is still the steepest cost decrease of KL model delta.
    h = np.array([[2.0, 0.5], [0.5, 1.0]])
    b = np.array([0.3, 1.0])
    x, case = step([1.0, 0.0], b, 5.0, h, 0.01)
    expected = -math.sqrt(2 * 0.01 / (b @ np.linalg.solve(h, b))) * np.linalg.solve(h, b)
    assert case == INFEASIBLE
    np.testing.assert_allclose(x, expected, rtol=1e-5)
    assert 0.5 * x @ h @ x == pytest.approx(0.01, rel=1e-4)


# ---- random problems: brute force and the paper's dual --------------------------------------------


def brute_force(g, b, c, h, delta, n=20_000):
    """max g'x over {1/2 x'Hx <= delta, c + b'x <= 0} in 2-D: the optimum is on the ellipse
    (dense angle grid) or at one of the two points where the line meets it."""
    chol = np.linalg.cholesky(np.linalg.inv(h) * 2 * delta)  # x = chol u, |u| = 1 <=> 1/2 x'Hx = delta
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    pts = (chol @ np.stack([np.cos(t), np.sin(t)])).T
    # line c + b'x = 0 through the ellipse: x = x0 + s d, b'd = 0
    x0 = -c * b / (b @ b)
    d = np.array([-b[1], b[0]])
    qa, qb, qc = 0.5 * d @ h @ d, d @ h @ x0, 0.5 * x0 @ h @ x0 - delta
    disc = qb**2 - 4 * qa * qc
    if disc >= 0:
        roots = [(-qb + sgn * math.sqrt(disc)) / (2 * qa) for sgn in (1, -1)]
        pts = np.concatenate([pts, np.stack([x0 + r * d for r in roots])])
    feasible = c + pts @ b <= 1e-9
    return pts[feasible][np.argmax(pts[feasible] @ g)] if feasible.any() else None


def paper_dual_step(g, b, c, h, delta):
    """CPO appendix: lambda* = argmax of f_a, f_b at the projected peaks; nu* = (lambda* c + r)_+ / s
    (safety-starter-agents' form, written for maximisation with r = g'H^-1 b)."""
    v, w = np.linalg.solve(h, g), np.linalg.solve(h, b)
    q, r, s = g @ v, g @ w, b @ w
    a, bb = q - r**2 / s, 2 * delta - c**2 / s
    if c > 0 and bb <= 0:
        return None
    bound = -r / c if c != 0 else (np.inf if r > 0 else -np.inf)
    if c < 0:  # Lambda_a = {lambda c + r > 0} = [0, bound), Lambda_b = [bound, inf)
        la, lb = (0.0, bound), (max(bound, 0.0), np.inf)
    else:
        la, lb = (max(bound, 0.0), np.inf), (0.0, max(bound, 0.0))
    f_a = lambda lam: -0.5 * (a / lam + bb * lam) + r * c / s
    f_b = lambda lam: -0.5 * (q / lam + 2 * delta * lam)
    cands = []
    if la[1] > la[0] and bb > 0:
        lam = float(np.clip(math.sqrt(a / bb), *la))
        if lam > 0:
            cands.append((f_a(lam), lam))
    if lb[1] > lb[0]:
        lam = float(np.clip(math.sqrt(q / (2 * delta)), *lb))
        if lam > 0:
            cands.append((f_b(lam), lam))
    lam = max(cands)[1]
    nu = max(0.0, lam * c + r) / s
    return (v - nu * w) / lam


def test_step_matches_brute_force_and_the_papers_dual_on_random_problems():
    rng = np.random.default_rng(0)
    seen = set()
    for _ in range(150):
        m = rng.normal(size=(2, 2))
        h = m @ m.T + 0.2 * np.eye(2)
        g, b = rng.normal(size=2), rng.normal(size=2)
        delta = float(rng.uniform(0.005, 0.05))
        c = float(rng.normal() * 0.5 * math.sqrt(2 * delta * (b @ np.linalg.solve(h, b))))
        x, case = step(g, b, c, h, delta)
        seen.add(case)
        best = brute_force(g, b, c, h, delta)
        if best is None:
            assert case == INFEASIBLE
            assert b @ x < 0
            continue
        assert case in (REWARD_STEP, MIXED_STEP)
        scale = math.sqrt(2 * delta * (g @ np.linalg.solve(h, g)))  # the objective's size in the region
        assert g @ x == pytest.approx(g @ best, abs=2e-3 * scale)
        assert 0.5 * x @ h @ x <= delta * (1 + 1e-4)
        assert c + b @ x <= 1e-4 * abs(c) + 1e-5
        np.testing.assert_allclose(x, paper_dual_step(g, b, c, h, delta), rtol=2e-3, atol=1e-5)
    assert seen == {INFEASIBLE, REWARD_STEP, MIXED_STEP}


# ---- linear algebra ---------------------------------------------------------------------------------


def test_conjugate_gradient_solves_a_small_spd_system():
    rng = np.random.default_rng(1)
    m = rng.normal(size=(6, 6))
    a = jnp.asarray(m @ m.T + 0.5 * np.eye(6), jnp.float32)
    rhs = jnp.asarray(rng.normal(size=6), jnp.float32)
    x = jax.jit(conjugate_gradient, static_argnums=(0, 2))(lambda v: a @ v, rhs, 12)
    np.testing.assert_allclose(np.asarray(a @ x), np.asarray(rhs), atol=1e-4)
    # Fewer iterations than dimensions leave a residual: the iteration count is honoured.
    x2 = conjugate_gradient(lambda v: a @ v, rhs, 2)
    assert float(jnp.linalg.norm(a @ x2 - rhs)) > 1e-3


def test_fisher_vector_product_is_the_hessian_of_the_mean_kl():
    pol = GaussianPolicy(2, (6, 6))
    obs = jax.random.normal(jax.random.PRNGKey(1), (40, 4))
    params = pol.init(jax.random.PRNGKey(0), obs)
    params = jax.tree_util.tree_map(lambda x: x + 0.3 * jax.random.normal(jax.random.PRNGKey(3), x.shape), params)
    theta, unravel = ravel_pytree(params)
    mean0, log_std0 = pol.apply(params, obs)
    hess = jax.jit(jax.hessian(lambda t: jnp.mean(gaussian_kl(mean0, log_std0, *pol.apply(unravel(t), obs)))))(theta)
    v = jax.random.normal(jax.random.PRNGKey(2), theta.shape)
    hv = kl_hessian_vector_product(lambda t: pol.apply(unravel(t), obs), theta, 0.1)(v)
    np.testing.assert_allclose(np.asarray(hv), np.asarray(hess @ v + 0.1 * v), rtol=1e-4, atol=1e-5)


# ---- one policy step on a synthetic batch ------------------------------------------------------------


def synthetic_batch():
    pol = GaussianPolicy(2, (16, 16))
    k = jax.random.split(jax.random.PRNGKey(4), 5)
    obs = jax.random.normal(k[0], (512, 6))
    params = pol.init(k[1], obs)
    mean, log_std = pol.apply(params, obs)
    action = gaussian_sample(k[2], mean, log_std)
    # reward favours a positive first action component, cost a positive second one
    adv = action[:, 0] - jnp.mean(action[:, 0])
    cost_adv = action[:, 1] - jnp.mean(action[:, 1])
    log_prob = gaussian_log_prob(mean, log_std, action)
    data = PolicyData(obs, action, log_prob, mean, log_std, adv / jnp.std(adv), cost_adv)
    return pol, params, data


@pytest.mark.parametrize("c, expect", [(-1.0, REWARD_STEP), (1.0, INFEASIBLE)])
def test_policy_step_stays_in_the_trust_region_and_moves_the_right_surrogate(c, expect):
    pol, params, data = synthetic_batch()
    cfg = CPOConfig(target_kl=0.01)
    new, m = jax.jit(cpo_policy_update, static_argnums=(0, 4))(pol.apply, params, data, jnp.float32(c), cfg)
    assert int(m["cpo/case"]) == expect and float(m["cpo/accepted"]) == 1.0
    mean0, log_std0 = pol.apply(params, data.obs)
    mean1, log_std1 = pol.apply(new, data.obs)
    assert 0.0 < float(jnp.mean(gaussian_kl(mean0, log_std0, mean1, log_std1))) <= cfg.target_kl
    shift = jnp.mean(mean1 - mean0, axis=0)
    if expect == REWARD_STEP:
        assert float(shift[0]) > 0.01  # reward surrogate: push action 0 up
    else:
        assert float(shift[1]) < -0.01  # recovery: push action 1 (the cost) down
        assert float(m["cpo/cost_change"]) < 0


# ---- the learner -------------------------------------------------------------------------------------


def test_rollout_steps_must_divide_chunk_steps():
    cfg = TrainConfig(algo="cpo", task="relaxed", chunk_steps=100, cpo=CPOConfig(rollout_steps=30))
    cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, layout="relaxed"))
    with pytest.raises(ConfigError, match="chunk_steps"):
        build(cfg)


def test_cpo_learns_relaxed(tmp_path):
    # Tiny nets, the annealed radius held at its initial (wide) value; 16 envs x 250 steps per update.
    cfg = TrainConfig(algo="cpo", task="relaxed", episodes=500, seed=0, eval_episodes=0, checkpoint_every=10**6,
                      cpo=CPOConfig(hidden=(32, 32)))
    cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, layout="relaxed"),
                              anneal=dataclasses.replace(cfg.anneal, k2=0.0))
    summary = train(cfg, tmp_path / "run")
    with open(tmp_path / "run" / "episodes.csv") as f:
        rows = list(csv.DictReader(f))
    returns = np.array([float(r["return"]) for r in rows])
    collided = np.array([int(r["collided"]) for r in rows])
    assert np.all(np.isfinite(returns)) and len(returns) == 500
    first, last = returns[:100].mean(), returns[-100:].mean()
    assert last > first + 3.0, (first, last)
    assert collided[-100:].mean() <= 0.1
    assert summary["episodes"] == 500
    # `d2spo eval` runs its policy (it once stopped at the on-policy learners' missing ``env``)
    from d2spo.evaluate import EvalConfig, evaluate_run

    ev = evaluate_run(tmp_path / "run", EvalConfig(episodes=4))
    assert ev["episodes"] == 4 and 0.0 <= ev["safety_rate"] <= 1.0 and ev["max_steps"] > 0
