"""PPO-Lagrangian (Ray et al., 2019; OmniSafe's PPOLag) on the vectorised env, fused into one
jitted chunk. Baseline "LPPO" of Tables II-III.

Per iteration: a rollout of ``rollout_steps`` vectorised steps with the Gaussian policy; the
Lagrange multiplier takes one projected ascent step on (J_c - d), J_c = mean cost of the episodes
that ended in the rollout (``common.lagrange``); GAE for reward and cost (separate critics);
advantages standardised, then combined as A = (A_r - lambda A_c) / (1 + lambda); ``epochs`` passes
of the clipped surrogate over shuffled minibatches (critics trained on the same minibatches),
stopping early once KL(pi_old || pi) > ``target_kl`` over the rollout.

Here one episode's cost is the number of collision steps, 0 or 1 (a collision ends it), so J_c is
the collision rate and ``cost_limit`` a tolerated rate.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from d2spo.algos.base import ChunkLog, params_finite
from d2spo.algos.common import lagrange
from d2spo.algos.common.lagrange import LagrangeConfig, LagrangeState
from d2spo.algos.common.networks import gaussian_entropy, gaussian_kl, gaussian_log_prob
from d2spo.algos.common.rollout import flatten_time_env, minibatches
from d2spo.algos.onpolicy import (
    Critics,
    Rollouts,
    RolloutState,
    act,
    advantages,
    critic_step,
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


@dataclass(frozen=True)
class PPOLagConfig:
    """PPO-Lagrangian. Defaults: OmniSafe PPOLag and Schulman et al. (2017), except where
    docs/baselines.md says otherwise; sources per field there."""

    hidden: tuple[int, ...] = (64, 64)
    """Hidden widths of the policy and each critic (tanh)."""
    log_std_init: float = -0.5
    """Initial log std of the state-independent Gaussian."""
    rollout_steps: int = 250
    """Vectorised steps per rollout; divides --chunk-steps."""
    epochs: int = 10
    """Passes over each rollout (cut short by target_kl)."""
    n_minibatches: int = 32
    """Minibatches per pass (must divide the rollout)."""
    lr: float = 3e-4
    """Adam learning rate of the policy."""
    critic_lr: float = 3e-4
    """Adam learning rate of the reward and cost critics."""
    gamma: float = 0.99
    """Reward discount."""
    lam: float = 0.95
    """GAE lambda of the reward."""
    cost_gamma: float = 0.99
    """Cost discount (the cost critic and its GAE)."""
    cost_lam: float = 0.95
    """GAE lambda of the cost."""
    clip: float = 0.2
    """PPO ratio clip epsilon."""
    target_kl: float = 0.02
    """Stop the epochs once the mean KL(pi_old || pi) > this."""
    entropy_coef: float = 0.0
    """Weight of the entropy bonus."""
    max_grad_norm: float | None = 40.0
    """Gradient-norm clip of policy and critics; None = off."""
    normalize_obs: bool = True
    """Normalise observations with running moments."""
    scale_cost_advantage: bool = False
    """Divide the cost advantages by their std too (False: centre them only, as OmniSafe's buffer and
    safety-starter-agents do; True: the standardisation d2spo used until 2026-12-02)."""
    lagrange: LagrangeConfig = field(default_factory=lambda: LagrangeConfig(cost_limit=0.05))
    """Multiplier; cost_limit: a tolerated collision rate (0.05: 95 % safe)."""

    def __post_init__(self) -> None:
        check_fields(self, "ppo_lag", nullable=("max_grad_norm",), widths=("hidden",), finite=("log_std_init",),
                     count=("rollout_steps", "epochs", "n_minibatches"), lr=("lr", "critic_lr"),
                     positive=("clip", "target_kl", "max_grad_norm"), non_negative=("entropy_coef",),
                     discount=("gamma", "cost_gamma"), fraction=("lam", "cost_lam"),
                     flag=("normalize_obs", "scale_cost_advantage"))


def ppo_clip_loss(log_prob: jax.Array, old_log_prob: jax.Array, adv: jax.Array, clip: float):
    """Clipped surrogate (Schulman et al., 2017, Eq. (7)), as a loss to minimise.

    -mean(min(rho A, clip(rho, 1 - eps, 1 + eps) A)), rho = pi(a|s) / pi_old(a|s).
    Returns (loss, fraction of samples whose ratio lies outside [1 - eps, 1 + eps]).
    """
    ratio = jnp.exp(log_prob - old_log_prob)
    surrogate = jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - clip, 1.0 + clip) * adv)
    return -jnp.mean(surrogate), jnp.mean((jnp.abs(ratio - 1.0) > clip).astype(jnp.float32))


def lagrangian_advantage(adv_r: jax.Array, adv_c: jax.Array, lam: jax.Array) -> jax.Array:
    """(A_r - lambda A_c) / (1 + lambda): the Lagrangian's advantage, rescaled to keep its size."""
    return (adv_r - lam * adv_c) / (1.0 + lam)


class Samples(NamedTuple):
    """What the minibatch updates read, leaves [B, ...] (flattened rollout)."""

    obs: jax.Array
    action: jax.Array
    log_prob: jax.Array
    mean: jax.Array
    log_std: jax.Array
    adv: jax.Array
    """Lagrangian advantage (A_r - lambda A_c) / (1 + lambda)."""
    target: jax.Array
    cost_target: jax.Array


@struct.dataclass
class PPOLagCarry:
    rollout: RolloutState
    policy: Any
    policy_opt: Any
    critics: Critics
    lagrange: LagrangeState


class PPOLagLearner:
    """``--algo ppo-lag``: see the module docstring."""

    def __init__(self, env, params, cfg: PPOLagConfig, anneal: AnnealConfig, num_envs: int, chunk_steps: int,
                 total_episodes: int):
        self.cfg, self.num_envs, self.env = cfg, num_envs, env  # the env, as every learner has it (``d2spo eval``)
        if (num_envs * cfg.rollout_steps) % cfg.n_minibatches != 0:
            raise ConfigError("ppo_lag.n_minibatches", f"must divide num_envs * rollout_steps = "
                              f"{num_envs * cfg.rollout_steps}, got {cfg.n_minibatches}")
        self.iterations = iterations_per_chunk(chunk_steps, cfg.rollout_steps, "ppo_lag.rollout_steps")
        self.nets = make_nets(env.action_size, cfg.hidden, cfg.log_std_init, cfg.critic_lr, cfg.max_grad_norm)
        clip = [] if cfg.max_grad_norm is None else [optax.clip_by_global_norm(cfg.max_grad_norm)]
        self.policy_tx = optax.chain(*clip, optax.adam(cfg.lr))
        self.rollouts = Rollouts(env, params, anneal, self.nets, num_envs, cfg.rollout_steps, cfg.normalize_obs,
                                 total_episodes)

    def init(self, key: jax.Array) -> PPOLagCarry:
        k_roll, k_net = jax.random.split(key)
        policy, critics = init_networks(self.nets, k_net, self.rollouts.env.observation_size)
        return PPOLagCarry(self.rollouts.init(k_roll), policy, self.policy_tx.init(policy), critics,
                           lagrange.create(self.cfg.lagrange))

    def chunk(self, carry: PPOLagCarry) -> tuple[PPOLagCarry, ChunkLog]:
        carry, log = jax.lax.scan(lambda c, _: self._iteration(c), carry, None, length=self.iterations)
        log = flatten_iterations(log)
        finite = params_finite((carry.policy, carry.critics.value, carry.critics.cost_value))
        return carry, log._replace(nonfinite=jnp.any(log.nonfinite) | ~finite)

    def _policy_loss(self, policy, mb: Samples):
        mean, log_std = self.nets.policy.apply(policy, mb.obs)
        loss, clipfrac = ppo_clip_loss(gaussian_log_prob(mean, log_std, mb.action), mb.log_prob, mb.adv, self.cfg.clip)
        entropy = jnp.mean(gaussian_entropy(log_std))
        return loss - self.cfg.entropy_coef * entropy, {"losses/policy": loss, "charts/clipfrac": clipfrac,
                                                        "charts/entropy": entropy}

    def _kl(self, flat: Samples, policy) -> jax.Array:
        """Mean KL(pi_old || pi) over the rollout."""
        mean, log_std = self.nets.policy.apply(policy, flat.obs)
        return jnp.mean(gaussian_kl(flat.mean, flat.log_std, mean, log_std))

    def _minibatch_step(self, state, mb: Samples):
        policy, opt, critics = state
        (_, m), grads = jax.value_and_grad(self._policy_loss, has_aux=True)(policy, mb)
        updates, opt = self.policy_tx.update(grads, opt, policy)
        policy = optax.apply_updates(policy, updates)
        critics, cm = critic_step(self.nets, critics, mb.obs, mb.target, mb.cost_target)
        return (policy, opt, critics), {**m, **cm}

    def _iteration(self, c: PPOLagCarry):
        cfg = self.cfg
        rs, batch, log = self.rollouts.collect(c.rollout, c.policy)
        # Multiplier first, from this rollout's mean episode cost (if any episode ended in it).
        stepped = lagrange.update(c.lagrange, rs.ep_cost)
        lag = jax.tree_util.tree_map(lambda new, old: jnp.where(jnp.any(log.done), new, old), stepped, c.lagrange)
        lam = lagrange.value(lag)
        adv = advantages(self.nets, c.critics, batch, self.rollouts.norm(rs.obs_rms, rs.obs), cfg.gamma, cfg.lam,
                         cfg.cost_gamma, cfg.cost_lam)
        # reward advantages standardised; cost advantages centred only (OmniSafe, safety-starter-agents):
        # rescaled, a rollout without collisions (std(A_c) ~ 0.01) blew the cost critic's noise up to unit size
        combined = lagrangian_advantage(standardize(adv.reward), standardize(adv.cost, scale=cfg.scale_cost_advantage),
                                        lam)
        flat = flatten_time_env(Samples(batch.obs, batch.action, batch.log_prob, batch.mean, batch.log_std, combined,
                                        adv.reward_target, adv.cost_target))
        nan = jnp.float32(jnp.nan)
        empty = {k: nan for k in ("losses/policy", "charts/clipfrac", "charts/entropy", "losses/value",
                                  "losses/cost_value")}

        def epoch(state, k):
            (policy, opt, critics), stopped = state

            def run(_):
                mbs = minibatches(k, flat, cfg.n_minibatches)
                new, m = jax.lax.scan(self._minibatch_step, (policy, opt, critics), mbs)
                return (new, self._kl(flat, new[0]) > cfg.target_kl), ({kk: jnp.mean(v) for kk, v in m.items()},
                                                                        jnp.float32(1))

            def skip(_):
                return ((policy, opt, critics), stopped), (empty, jnp.float32(0))

            return jax.lax.cond(stopped, skip, run, None)

        init = ((c.policy, c.policy_opt, c.critics), jnp.bool_(False))
        ((policy, opt, critics), _), (m, ran) = jax.lax.scan(epoch, init, jax.random.split(rs.key, cfg.epochs))
        rs = self.rollouts.update_obs_stats(rs.replace(key=jax.random.fold_in(rs.key, 1)), batch)
        metrics = {k: jnp.nanmean(v) for k, v in m.items()}
        metrics.update({"charts/approx_kl": self._kl(flat, policy), "charts/epochs": jnp.sum(ran),
                        "charts/lambda": lam, "charts/ep_cost_estimate": rs.ep_cost})
        return PPOLagCarry(rs, policy, opt, critics, lag), with_update_metrics(log, metrics)

    # -- evaluation ---------------------------------------------------------------------
    def policy(self, carry: PPOLagCarry):
        return carry.policy, carry.rollout.obs_rms

    def act(self, policy, obs, env_state, key):
        return act(self.nets, self.cfg.normalize_obs, policy, obs)
