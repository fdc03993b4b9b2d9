"""Generalised advantage estimation over time-major [T, N] arrays.

Convention (one row per time step t, one column per env):

* ``values[t]`` = V(s_t), the value of the observation the action at step t was taken in;
  ``last_value`` [N] = V(s_T), the observation after the last stored step.
* ``dones[t] = 1`` means the episode ended at step t: s_{t+1} in the rollout already belongs to
  the next episode, so it is not bootstrapped and the advantage trace is cut.
* Time-limit truncation (optional): ``truncated[t] = 1`` marks an end caused by the time limit,
  where the episode should still be bootstrapped from ``bootstrap_values[t]`` = V(final obs before
  the reset). The trace is cut there too. ``truncated`` must be 0 where the episode terminated,
  as the env's ``info['truncated']`` already is; where it is 1, ``dones`` may be 0 or 1.

    delta_t = r_t + gamma * next_t - V(s_t),
      next_t = bootstrap_values[t] if truncated[t] else (0 if dones[t] else V(s_{t+1}))
    A_t     = delta_t + gamma * lam * (1 - end_t) * A_{t+1},   end_t = dones[t] or truncated[t]
    returns = A + values    (the TD(lambda) targets for the value function)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def gae(
    rewards: jax.Array,
    values: jax.Array,
    dones: jax.Array,
    last_value: jax.Array,
    gamma: float,
    lam: float,
    truncated: jax.Array | None = None,
    bootstrap_values: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """(advantages, returns), both [T, N] float32. See the module docstring for the convention."""
    rewards = jnp.asarray(rewards, jnp.float32)
    values = jnp.asarray(values, jnp.float32)
    ended = jnp.asarray(dones).astype(bool)
    last_value = jnp.asarray(last_value, jnp.float32)
    next_values = jnp.concatenate([values[1:], last_value[None]], axis=0)
    next_values = jnp.where(ended, 0.0, next_values)
    if truncated is not None:
        if bootstrap_values is None:
            raise ValueError("gae: `truncated` needs `bootstrap_values` (V of the final observation)")
        trunc = jnp.asarray(truncated).astype(bool)
        next_values = jnp.where(trunc, jnp.asarray(bootstrap_values, jnp.float32), next_values)
        ended = ended | trunc
    deltas = rewards + gamma * next_values - values
    carry_on = (~ended).astype(jnp.float32) * (gamma * lam)

    def backward(adv_next: jax.Array, x: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        delta, decay = x
        adv = delta + decay * adv_next
        return adv, adv

    _, advantages = jax.lax.scan(backward, jnp.zeros_like(last_value), (deltas, carry_on), reverse=True)
    return advantages, advantages + values

