"""Constrained Policy Optimization (Achiam et al., 2017) on the vectorised env, one jitted chunk.
Baseline "CPO" of Tables II-III.

Per iteration, on a rollout (``onpolicy``): g = grad of the reward surrogate mean(rho A_r), b =
grad of the cost surrogate mean(rho A_c) at theta_k, H = Hessian of the mean KL(pi_k || pi_theta)
(exact Fisher-vector products, one jvp and one vjp each, plus damping), H^-1 g and H^-1 b by
conjugate gradient. The step solves the linearised problem (CPO Eq. (10))

    max_x g^T x   s.t.   c + b^T x <= 0,   1/2 x^T H x <= delta,

through its dual (``cpo_step``), then a backtracking line search keeps the first
fraction of the step whose true KL, reward and cost surrogates are acceptable.

The constraint is on the mean *undiscounted* episode cost J_c of the episodes that ended in the
rollout (here the collision rate), c = J_c - cost_limit, divided by the mean episode length so that
it is in the per-step units of the surrogate (safety-starter-agents' rescale, Ray et al., 2019).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from jax.flatten_util import ravel_pytree

from d2spo.algos.base import ChunkLog, params_finite
from d2spo.algos.common.networks import gaussian_kl, gaussian_log_prob
from d2spo.algos.common.rollout import flatten_time_env
from d2spo.algos.onpolicy import (
    Critics,
    Rollouts,
    RolloutState,
    act,
    advantages,
    fit_critics,
    flatten_iterations,
    init_networks,
    iterations_per_chunk,
    make_nets,
    standardize,
    with_update_metrics,
)
from d2spo.errors import ConfigError
from d2spo.fields import check_fields
from d2spo.ltl.anneal import AnnealConfig

INFEASIBLE, REWARD_STEP, MIXED_STEP = 0, 1, 2
"""``cpo_step`` cases: recovery (no x satisfies both constraints), pure reward step
(the cost constraint is inactive at the optimum), step on both boundaries."""


@dataclass(frozen=True)
class CPOConfig:
    """CPO. Defaults: safety-starter-agents (Ray et al., 2019) and Achiam et al. (2017); critics as
    OmniSafe's CPO. Sources per field in docs/baselines.md."""

    hidden: tuple[int, ...] = (64, 64)
    """Hidden widths of the policy and each critic (tanh)."""
    log_std_init: float = -0.5
    """Initial log std of the state-independent Gaussian."""
    rollout_steps: int = 250
    """Vectorised steps per rollout; divides --chunk-steps."""
    target_kl: float = 0.01
    """delta: KL trust region and line-search bound."""
    cost_limit: float = 0.05
    """Tolerated collision rate; 0.05: a 95 % safety target."""
    cg_iters: int = 10
    """Conjugate gradient iterations for H^-1 g and H^-1 b."""
    cg_damping: float = 0.1
    """Damping of the Fisher-vector product (H + damping I)."""
    backtrack_iters: int = 10
    """Line-search trials, step fractions coeff^k."""
    backtrack_coeff: float = 0.8
    """Line-search shrink factor."""
    gamma: float = 0.99
    """Reward discount."""
    lam: float = 0.97
    """GAE lambda of the reward."""
    cost_gamma: float = 0.99
    """Cost discount (the cost critic and its GAE)."""
    cost_lam: float = 0.97
    """GAE lambda of the cost."""
    critic_lr: float = 1e-3
    """Adam learning rate of the reward and cost critics."""
    critic_epochs: int = 10
    """Critic passes over each rollout."""
    critic_minibatches: int = 32
    """Minibatches per critic pass."""
    max_grad_norm: float | None = 40.0
    """Gradient-norm clip of the critic updates; None = off."""
    normalize_obs: bool = False
    """Normalise observations with running moments."""

    def __post_init__(self) -> None:
        check_fields(self, "cpo", nullable=("max_grad_norm",), widths=("hidden",), finite=("log_std_init",),
                     count=("rollout_steps", "cg_iters", "backtrack_iters", "critic_epochs", "critic_minibatches"),
                     positive=("target_kl", "max_grad_norm"), lr=("critic_lr",),
                     non_negative=("cost_limit", "cg_damping"), discount=("gamma", "cost_gamma"),
                     fraction=("lam", "cost_lam"), flag=("normalize_obs",))
        if not 0 < self.backtrack_coeff < 1:
            raise ConfigError("cpo.backtrack_coeff", f"must be in (0, 1), got {self.backtrack_coeff}")


# ---- the maths --------------------------------------------------------------------------------


def conjugate_gradient(matvec: Callable[[jax.Array], jax.Array], b: jax.Array, iters: int,
                       tol: float = 1e-10) -> jax.Array:
    """x ~= A^-1 b for SPD A given by ``matvec``: ``iters`` CG steps, frozen once |r|^2 < tol."""

    def body(_, state):
        x, r, p, rr = state
        ap = matvec(p)
        pap = p @ ap
        live = (rr > tol) & (pap > 0)  # converged (or a non-SPD direction): freeze
        alpha = jnp.where(live, rr / jnp.where(live, pap, 1.0), 0.0)
        x, r = x + alpha * p, r - alpha * ap
        rr_new = r @ r
        beta = jnp.where(live, rr_new / jnp.where(live, rr, 1.0), 0.0)
        return x, r, jnp.where(live, r + beta * p, p), jnp.where(live, rr_new, rr)

    x, *_ = jax.lax.fori_loop(0, iters, body, (jnp.zeros_like(b), b, b, b @ b))
    return x


def cpo_dual(q, r, s, c, delta, a=None, eps: float = 1e-8):
    """Dual solution (lambda*, nu*, case) of CPO Eq. (10); q = g'H^-1 g, r = g'H^-1 b, s = b'H^-1 b.

    With the multipliers lambda of the trust region and nu of the cost constraint, the primal
    solution is x* = (H^-1 g - nu* H^-1 b) / lambda*, nu*(lambda) = max(0, (lambda c + r) / s),
    and lambda* maximises the concave dual (CPO appendix, Theorem 2; written here for a
    maximisation with r = g'H^-1 b, where the paper's appendix minimises and its r has the other
    sign) over two intervals:
      Lambda_b = {lambda c + r <= 0}: f_b = -1/2 (q / lambda + 2 delta lambda), peak lambda_b = sqrt(q / 2 delta);
      Lambda_a = {lambda c + r > 0}:  f_a = -1/2 (A / lambda + B lambda) + r c / s, peak lambda_a = sqrt(A / B),
    A = q - r^2 / s, B = 2 delta - c^2 / s. By concavity the paper's argmax{f_a(proj lambda_a),
    f_b(proj lambda_b)} is lambda_b exactly when lambda_b lies in Lambda_b, i.e. when the pure
    reward step sqrt(2 delta / q) H^-1 g satisfies c + b'x <= 0 (case REWARD_STEP, nu* = 0), and
    lambda_a otherwise (MIXED_STEP). No feasible x exists when c > 0 and B <= 0 (INFEASIBLE).
    ``a`` may pass A computed more accurately than q - r^2 / s (see ``cpo_step``).
    Returns (lambda*, nu*, case, A, B).
    """
    q_safe, s_safe = jnp.maximum(q, eps), jnp.maximum(s, eps)
    a = jnp.maximum(q - r**2 / s_safe if a is None else a, 0.0)
    b_ = 2.0 * delta - c**2 / s_safe
    lam_b = jnp.sqrt(q_safe / (2.0 * delta))
    feasible = (c <= 0) | (b_ > 0)
    case = jnp.where(feasible, jnp.where(lam_b * c + r <= 0, REWARD_STEP, MIXED_STEP), INFEASIBLE)
    lam_a = jnp.sqrt(a / jnp.maximum(b_, eps))
    lam = jnp.where(case == REWARD_STEP, lam_b, jnp.where(case == MIXED_STEP, lam_a, 0.0))
    nu = jnp.where(case == MIXED_STEP, jnp.maximum(lam_a * c + r, 0.0) / s_safe,
                   jnp.where(case == INFEASIBLE, jnp.sqrt(2.0 * delta / s_safe), 0.0))
    return lam, nu, case, a, b_


def cpo_step(g, b, c, h_inv_g, h_inv_b, delta, eps: float = 1e-8):
    """(direction x, case id, lambda*, nu*) of the CPO step for flat gradients g, b and cost gap c.

    REWARD_STEP:  x = sqrt(2 delta / q) H^-1 g                     (1/2 x'Hx = delta, nu = 0);
    MIXED_STEP:   x = (H^-1 g - nu H^-1 b) / lambda, written as
                  sqrt(B / A) (H^-1 g - (r / s) H^-1 b) - (c / s) H^-1 b, so that b'x = -c and
                  1/2 x'Hx = delta exactly (the two terms are H-orthogonal), without dividing by a
                  small lambda when g and b are nearly parallel;
    INFEASIBLE:   x = -sqrt(2 delta / s) H^-1 b, the recovery step that only decreases the cost (CPO Eq. (14)).
    """
    q, r, s = g @ h_inv_g, g @ h_inv_b, b @ h_inv_b
    s_safe = jnp.maximum(s, eps)
    # A = q - r^2/s = (g - (r/s) b)' H^-1 (g - (r/s) b): subtracting vectors before the dot
    # product keeps its accuracy in float32 when g and b are nearly parallel (A << q).
    h_inv_g_perp = h_inv_g - (r / s_safe) * h_inv_b
    lam, nu, case, a, b_ = cpo_dual(q, r, s, c, delta, (g - (r / s_safe) * b) @ h_inv_g_perp, eps)
    reward_step = jnp.sqrt(2.0 * delta / jnp.maximum(q, eps)) * h_inv_g
    scale = jnp.where(a > 0, jnp.sqrt(jnp.maximum(b_, 0.0) / jnp.maximum(a, 1e-30)), 0.0)
    mixed_step = scale * h_inv_g_perp - (c / s_safe) * h_inv_b
    recovery = -jnp.sqrt(2.0 * delta / s_safe) * h_inv_b
    x = jnp.where(case == REWARD_STEP, reward_step, jnp.where(case == MIXED_STEP, mixed_step, recovery))
    return x, case, lam, nu


def kl_hessian_vector_product(dist: Callable, theta0: jax.Array, damping: float) -> Callable:
    """v -> (H + damping I) v, H = Hessian in theta of mean_i KL(pi_theta0(.|s_i) || pi_theta(.|s_i)) at theta0.

    ``dist(theta) -> (mean, log_std)``, both [B, m]. At theta0 the KL's gradient in the Gaussian's
    parameters vanishes, so its Hessian is J' M J (J: Jacobian of (mean, log_std) in theta) with the
    KL's Hessian in those parameters, M = diag(1 / sigma^2, 2) / B, exactly. Each product is one
    jvp and one vjp through the linearised network (``jax.linearize`` once, then its transpose),
    about half the cost of differentiating the KL's gradient again (forward-over-reverse).
    """
    (mean, log_std), jvp = jax.linearize(dist, theta0)
    vjp = jax.linear_transpose(jvp, theta0)
    n = mean.shape[0]
    inv_var = jnp.exp(-2.0 * log_std) / n

    def product(v):
        d_mean, d_log_std = jvp(v)
        (hv,) = vjp((inv_var * d_mean, 2.0 * d_log_std / n))
        return hv + damping * v

    return product


class PolicyData(struct.PyTreeNode):
    """Flat rollout data the policy step needs, leaves [B, ...]."""

    obs: jax.Array
    action: jax.Array
    log_prob: jax.Array
    mean: jax.Array
    log_std: jax.Array
    adv: jax.Array
    cost_adv: jax.Array


def cpo_policy_update(apply: Callable, policy: Any, data: PolicyData, c: jax.Array, cfg: CPOConfig):
    """One CPO step of the policy parameters. ``apply(params, obs) -> (mean, log_std)``.

    Line search (safety-starter-agents / OmniSafe): a fraction of the step is accepted when it is
    finite, its mean KL(pi_k || pi) <= delta, the cost surrogate grows by at most max(-c, 0) (stays
    within the limit; must not grow while c > 0), and, while the current policy satisfies the
    constraint (c <= 0), the reward surrogate does not decrease.
    """
    theta0, unravel = ravel_pytree(policy)

    def surrogates(theta):
        mean, log_std = apply(unravel(theta), data.obs)
        ratio = jnp.exp(gaussian_log_prob(mean, log_std, data.action) - data.log_prob)
        return jnp.mean(ratio * data.adv), jnp.mean(ratio * data.cost_adv)

    def kl(theta):
        mean, log_std = apply(unravel(theta), data.obs)
        return jnp.mean(gaussian_kl(data.mean, data.log_std, mean, log_std))

    reward0, cost0 = surrogates(theta0)
    g = jax.grad(lambda t: surrogates(t)[0])(theta0)
    b = jax.grad(lambda t: surrogates(t)[1])(theta0)
    fisher = kl_hessian_vector_product(lambda t: apply(unravel(t), data.obs), theta0, cfg.cg_damping)
    h_inv_g = conjugate_gradient(fisher, g, cfg.cg_iters)
    h_inv_b = conjugate_gradient(fisher, b, cfg.cg_iters)
    x, case, lam, nu = cpo_step(g, b, c, h_inv_g, h_inv_b, cfg.target_kl)

    fractions = cfg.backtrack_coeff ** jnp.arange(cfg.backtrack_iters, dtype=jnp.float32)

    def trial(f):
        theta = theta0 + f * x
        reward, cost = surrogates(theta)
        return kl(theta), reward, cost

    kls, rewards, costs = jax.vmap(trial)(fractions)
    ok = (jnp.isfinite(kls) & jnp.isfinite(rewards) & jnp.isfinite(costs) & (kls <= cfg.target_kl)
          & (costs - cost0 <= jnp.maximum(-c, 0.0)) & ((rewards >= reward0) | (c > 0)))
    accepted = jnp.any(ok)
    j = jnp.argmax(ok)
    theta = jnp.where(accepted, theta0 + fractions[j] * x, theta0)
    taken = lambda v: jnp.where(accepted, v, 0.0)
    metrics = {
        "cpo/case": case.astype(jnp.float32), "cpo/lambda": lam, "cpo/nu": nu, "cpo/c": c,
        "cpo/accepted": accepted.astype(jnp.float32), "cpo/backtracks": jnp.where(accepted, j, -1).astype(jnp.float32),
        "charts/approx_kl": taken(kls[j]), "cpo/reward_improve": taken(rewards[j] - reward0),
        "cpo/cost_change": taken(costs[j] - cost0),
    }
    return unravel(theta), metrics


# ---- the learner ------------------------------------------------------------------------------


@struct.dataclass
class CPOCarry:
    rollout: RolloutState
    policy: Any
    critics: Critics


class CPOLearner:
    """``--algo cpo``: see the module docstring."""

    def __init__(self, env, params, cfg: CPOConfig, anneal: AnnealConfig, num_envs: int, chunk_steps: int,
                 total_episodes: int):
        self.cfg, self.env = cfg, env  # the env it acts in, as every learner has it (``d2spo eval``)
        if (num_envs * cfg.rollout_steps) % cfg.critic_minibatches != 0:
            raise ConfigError("cpo.critic_minibatches", f"must divide num_envs * rollout_steps = "
                              f"{num_envs * cfg.rollout_steps}, got {cfg.critic_minibatches}")
        self.iterations = iterations_per_chunk(chunk_steps, cfg.rollout_steps, "cpo.rollout_steps")
        self.nets = make_nets(env.action_size, cfg.hidden, cfg.log_std_init, cfg.critic_lr, cfg.max_grad_norm)
        self.rollouts = Rollouts(env, params, anneal, self.nets, num_envs, cfg.rollout_steps, cfg.normalize_obs,
                                 total_episodes)

    def init(self, key: jax.Array) -> CPOCarry:
        k_roll, k_net = jax.random.split(key)
        policy, critics = init_networks(self.nets, k_net, self.rollouts.env.observation_size)
        return CPOCarry(self.rollouts.init(k_roll), policy, critics)

    def chunk(self, carry: CPOCarry) -> tuple[CPOCarry, ChunkLog]:
        carry, log = jax.lax.scan(lambda c, _: self._iteration(c), carry, None, length=self.iterations)
        log = flatten_iterations(log)
        finite = params_finite((carry.policy, carry.critics.value, carry.critics.cost_value))
        return carry, log._replace(nonfinite=jnp.any(log.nonfinite) | ~finite)

    def _iteration(self, c: CPOCarry):
        cfg = self.cfg
        rs, batch, log = self.rollouts.collect(c.rollout, c.policy)
        adv = advantages(self.nets, c.critics, batch, self.rollouts.norm(rs.obs_rms, rs.obs), cfg.gamma, cfg.lam,
                         cfg.cost_gamma, cfg.cost_lam)
        # Reward advantages standardised; cost advantages only centred, so that b keeps the
        # per-step cost units of c (safety-starter-agents).
        data = PolicyData(*flatten_time_env((batch.obs, batch.action, batch.log_prob, batch.mean, batch.log_std,
                                             standardize(adv.reward), standardize(adv.cost, scale=False))))
        gap = (rs.ep_cost - cfg.cost_limit) / jnp.maximum(rs.ep_length, 1.0)
        policy, metrics = cpo_policy_update(self.nets.policy.apply, c.policy, data, gap, cfg)
        k_critic, key = jax.random.split(rs.key)
        critics, cm = fit_critics(self.nets, c.critics, k_critic, batch.obs, adv, cfg.critic_epochs,
                                  cfg.critic_minibatches)
        rs = self.rollouts.update_obs_stats(rs.replace(key=key), batch)
        metrics.update(cm)
        metrics["charts/ep_cost_estimate"] = rs.ep_cost
        return CPOCarry(rs, policy, critics), with_update_metrics(log, metrics)

    # -- evaluation ---------------------------------------------------------------------
    def policy(self, carry: CPOCarry):
        return carry.policy, carry.rollout.obs_rms

    def act(self, policy, obs, env_state, key):
        return act(self.nets, self.cfg.normalize_obs, policy, obs)
