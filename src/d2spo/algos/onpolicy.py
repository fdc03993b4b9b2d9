"""What PPO-Lagrangian and CPO share: Gaussian policy and two critics, the vectorised rollout,
GAE for reward and cost, and the critic regression.

One iteration of an on-policy learner is

    state, batch, log = rollouts.collect(state, policy)      # lax.scan over rollout_steps
    adv = advantages(nets, critics, batch, state.obs, ...)   # GAE, reward and cost
    ... the algorithm's policy step ...                      # ppo_lag.py / cpo.py
    critics = fit_critics(...)                               # or critic_step per minibatch
    state = rollouts.update_obs_stats(state, batch)

Observations are normalised with running moments that stay frozen during a rollout; the batch
stores the *normalised* observations, so the policy that is trained sees exactly what the
behaviour policy saw. The moments are updated after the update.

Time limits bootstrap: where the env truncates an episode, GAE continues from V(final obs)
(``common.gae`` with ``truncated``); collisions and task ends terminate.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from d2spo.algos.base import ChunkLog, RunSchedule, episode_log
from d2spo.algos.common import gae as gae_lib
from d2spo.algos.common import normalize
from d2spo.algos.common.networks import (
    GaussianPolicy,
    ValueNetwork,
    gaussian_log_prob,
    gaussian_sample,
    init_params,
)
from d2spo.algos.common.normalize import RunningMeanStd
from d2spo.algos.common.rollout import flatten_time_env, minibatches
from d2spo.errors import ConfigError
from d2spo.ltl.anneal import AnnealConfig


@struct.dataclass
class OnPolicyNets:
    """The modules and the critics' optimizer (all static)."""

    policy: GaussianPolicy = struct.field(pytree_node=False)
    value: ValueNetwork = struct.field(pytree_node=False)
    critic_tx: Any = struct.field(pytree_node=False)


def make_nets(action_size: int, hidden: tuple[int, ...], log_std_init: float, critic_lr: float,
              max_grad_norm: float | None) -> OnPolicyNets:
    clip = [] if max_grad_norm is None else [optax.clip_by_global_norm(max_grad_norm)]
    return OnPolicyNets(GaussianPolicy(action_size, tuple(hidden), log_std_init=log_std_init),
                        ValueNetwork(tuple(hidden)), optax.chain(*clip, optax.adam(critic_lr)))


@struct.dataclass
class Critics:
    """V_r and V_c (separate networks) and one optimizer state over both."""

    value: Any
    cost_value: Any
    opt_state: Any


def init_networks(nets: OnPolicyNets, key: jax.Array, obs_size: int) -> tuple[Any, Critics]:
    k_pi, k_v, k_c = jax.random.split(key, 3)
    obs = jnp.zeros((1, obs_size))
    policy = init_params(nets.policy, k_pi, obs)
    pair = (init_params(nets.value, k_v, obs), init_params(nets.value, k_c, obs))
    return policy, Critics(pair[0], pair[1], nets.critic_tx.init(pair))


class Batch(NamedTuple):
    """One rollout, leaves [T, N, ...]. ``obs``/``next_obs`` are normalised (frozen moments)."""

    obs: jax.Array
    next_obs: jax.Array
    """Observation after the step, before any reset (bootstraps truncated episodes)."""
    raw_obs: jax.Array
    """Un-normalised ``obs`` (updates the running moments)."""
    action: jax.Array
    """Unclipped Gaussian sample (the env clips it to [-1, 1])."""
    log_prob: jax.Array
    mean: jax.Array
    log_std: jax.Array
    reward: jax.Array
    cost: jax.Array
    terminated: jax.Array
    truncated: jax.Array


class Advantages(NamedTuple):
    """GAE advantages and TD(lambda) targets, [T, N]."""

    reward: jax.Array
    reward_target: jax.Array
    cost: jax.Array
    cost_target: jax.Array


@struct.dataclass
class RolloutState:
    key: jax.Array
    env_state: Any
    obs: jax.Array
    """Raw observation of every env, [N, D]."""
    obs_rms: RunningMeanStd
    steps: jax.Array
    """Vectorised env steps taken."""
    episodes: jax.Array
    """Episodes finished (I_ep of the annealed radius)."""
    ep_cost: jax.Array
    """Mean cost of the episodes that ended in the last rollout that had any (J_c estimate)."""
    ep_length: jax.Array
    """Mean length of the same episodes."""


class Rollouts:
    """Steps ``num_envs`` envs ``rollout_steps`` times with a stochastic Gaussian policy."""

    def __init__(self, env, params, anneal: AnnealConfig, nets: OnPolicyNets, num_envs: int,
                 rollout_steps: int, normalize_obs: bool, total_episodes: int):
        if rollout_steps < 1:
            raise ConfigError("rollout_steps", f"must be a positive integer, got {rollout_steps}")
        self.env, self.params, self.nets = env, params, nets
        self.schedule = RunSchedule.for_run(anneal, total_episodes)
        self.num_envs, self.rollout_steps, self.normalize_obs = num_envs, rollout_steps, normalize_obs

    def init(self, key: jax.Array) -> RolloutState:
        k_env, key = jax.random.split(key)
        env_state, obs = self.env.reset_batch(k_env, self.schedule.env_params(self.params, jnp.int32(0)), self.num_envs)
        zero = jnp.zeros((), jnp.int32)
        return RolloutState(key, env_state, obs, RunningMeanStd.create((self.env.observation_size,)), zero, zero,
                            jnp.float32(0.0), jnp.float32(self.params.max_steps))

    def norm(self, rms: RunningMeanStd, obs: jax.Array) -> jax.Array:
        return normalize.normalize(rms, obs) if self.normalize_obs else obs

    def collect(self, s: RolloutState, policy: Any) -> tuple[RolloutState, Batch, ChunkLog]:
        """One rollout. The ChunkLog has empty metrics but for ``charts/label_radius``."""

        def step(s: RolloutState, _):
            key, k_act, k_env = jax.random.split(s.key, 3)
            obs = self.norm(s.obs_rms, s.obs)
            mean, log_std = self.nets.policy.apply(policy, obs)
            action = gaussian_sample(k_act, mean, log_std)
            params = self.schedule.env_params(self.params, s.episodes)
            env_state, next_obs, reward, cost, done, info = self.env.step_batch(k_env, s.env_state, action, params)
            row = Batch(obs, self.norm(s.obs_rms, info["next_obs"]), s.obs, action,
                        gaussian_log_prob(mean, log_std, action), mean, log_std, reward, cost,
                        info["terminated"], info["truncated"])
            log = episode_log(done, info, {"charts/label_radius": jnp.mean(params.label_radius)})
            s = s.replace(key=key, env_state=env_state, obs=next_obs, steps=s.steps + 1,
                          episodes=s.episodes + jnp.sum(done).astype(jnp.int32))
            return s, (row, log)

        s, (batch, log) = jax.lax.scan(step, s, None, length=self.rollout_steps)
        n = jnp.sum(log.done)
        mean_of = lambda x: jnp.sum(jnp.where(log.done, x, 0.0)) / jnp.maximum(n, 1)
        s = s.replace(ep_cost=jnp.where(n > 0, mean_of(log.ep_cost), s.ep_cost),
                      ep_length=jnp.where(n > 0, mean_of(log.ep_length.astype(jnp.float32)), s.ep_length))
        return s, batch, log

    def update_obs_stats(self, s: RolloutState, batch: Batch) -> RolloutState:
        if not self.normalize_obs:
            return s
        return s.replace(obs_rms=normalize.update(s.obs_rms, batch.raw_obs))


def advantages(nets: OnPolicyNets, critics: Critics, batch: Batch, last_obs: jax.Array, gamma: float, lam: float,
               cost_gamma: float, cost_lam: float) -> Advantages:
    """GAE for reward and cost with separate critics; ``last_obs`` is normalised, [N, D]."""

    def both(params, signal, g, lm):
        v, v_next, v_last = (nets.value.apply(params, x) for x in (batch.obs, batch.next_obs, last_obs))
        return gae_lib.gae(signal, v, batch.terminated | batch.truncated, v_last, g, lm,
                           truncated=batch.truncated, bootstrap_values=v_next)

    adv, target = both(critics.value, batch.reward, gamma, lam)
    cadv, ctarget = both(critics.cost_value, batch.cost, cost_gamma, cost_lam)
    return Advantages(adv, target, cadv, ctarget)


def standardize(x: jax.Array, scale: bool = True) -> jax.Array:
    """x - mean(x), divided by std(x) when ``scale``."""
    x = x - jnp.mean(x)
    return x / (jnp.std(x) + 1e-8) if scale else x


def critic_loss(pair: tuple[Any, Any], nets: OnPolicyNets, obs: jax.Array, target: jax.Array,
                cost_target: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
    """MSE of V_r to the reward TD(lambda) targets plus MSE of V_c to the cost targets."""
    loss_r = jnp.mean((nets.value.apply(pair[0], obs) - target) ** 2)
    loss_c = jnp.mean((nets.value.apply(pair[1], obs) - cost_target) ** 2)
    return loss_r + loss_c, {"losses/value": loss_r, "losses/cost_value": loss_c}


def critic_step(nets: OnPolicyNets, critics: Critics, obs, target, cost_target) -> tuple[Critics, dict]:
    """One optimizer step of both critics on a minibatch."""
    pair = (critics.value, critics.cost_value)
    (_, m), grads = jax.value_and_grad(critic_loss, has_aux=True)(pair, nets, obs, target, cost_target)
    updates, opt_state = nets.critic_tx.update(grads, critics.opt_state, pair)
    pair = optax.apply_updates(pair, updates)
    return Critics(pair[0], pair[1], opt_state), m


def fit_critics(nets: OnPolicyNets, critics: Critics, key: jax.Array, obs: jax.Array, adv: Advantages,
                epochs: int, n_minibatches: int) -> tuple[Critics, dict]:
    """``epochs`` passes of shuffled minibatches over the rollout; metrics of the last pass."""
    flat = flatten_time_env((obs, adv.reward_target, adv.cost_target))

    def epoch(critics, k):
        mbs = minibatches(k, flat, n_minibatches)
        critics, m = jax.lax.scan(lambda c, mb: critic_step(nets, c, *mb), critics, mbs)
        return critics, jax.tree_util.tree_map(jnp.mean, m)

    critics, m = jax.lax.scan(epoch, critics, jax.random.split(key, epochs))
    return critics, jax.tree_util.tree_map(lambda v: v[-1], m)


def with_update_metrics(log: ChunkLog, update: dict[str, jax.Array]) -> ChunkLog:
    """Put the update's scalars on the rollout's last step, NaN ('no value') on the others."""
    steps = log.done.shape[0]
    metrics = dict(log.metrics)
    for k, v in update.items():
        metrics[k] = jnp.full((steps,), jnp.nan, jnp.float32).at[-1].set(jnp.asarray(v, jnp.float32))
    return log._replace(metrics=metrics)


def flatten_iterations(log: ChunkLog) -> ChunkLog:
    """[iterations, rollout_steps, ...] -> [iterations * rollout_steps, ...] (the chunk's steps)."""
    return jax.tree_util.tree_map(lambda x: x.reshape((-1, *x.shape[2:])) if x.ndim >= 2 else x, log)


def iterations_per_chunk(chunk_steps: int, rollout_steps: int, field: str) -> int:
    """A chunk holds whole rollouts, so the run loop's step count stays exact."""
    if chunk_steps % rollout_steps != 0:
        raise ConfigError("chunk_steps", f"must be a multiple of {field} ({rollout_steps}) for on-policy "
                          f"learners, got {chunk_steps}; e.g. --chunk-steps {rollout_steps}")
    return chunk_steps // rollout_steps


def act(nets: OnPolicyNets, normalize_obs: bool, policy: tuple[Any, RunningMeanStd], obs: jax.Array) -> jax.Array:
    """Deterministic evaluation action: the Gaussian's mean, clipped to the action box."""
    params, rms = policy
    x = normalize.normalize(rms, obs) if normalize_obs else obs
    mean, _ = nets.policy.apply(params, x)
    return jnp.clip(mean, -1.0, 1.0)
