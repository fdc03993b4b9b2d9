"""The gymnax-compatible front end: gymnax's (obs, state) order and six-value step, the cost in
info, gymnax's own wrappers under vmap + scan, and a PureJaxRL-style PPO that learns "F A1"."""

from __future__ import annotations

import importlib
import sys

import _ppo
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import d2spo
from d2spo.envs import EnvConfig, make_env


def nav(**kw):
    """``GymnaxNav.make(**kw)``. gymnax (and d2spo.envs.gymnax_env, which uses its ``Box`` where it is
    installed) is imported by the tests that use it, not as the suite collects this file: it takes
    about 3 s (seaborn, scipy.stats), which both workers paid before they ran a test."""
    from d2spo.envs.gymnax_env import GymnaxNav

    return GymnaxNav.make(**kw)


def test_the_functional_envs_need_no_gymnasium_and_the_gymnasium_ones_say_what_to_install(monkeypatch):
    """gymnasium is optional (d2spo[gym]): d2spo.envs imports without it (or beside an older one)."""
    # imported first, so that the module put back afterwards is the one with gymnax's Box (imported
    # here, with gymnasium blocked, gymnax fails to import and the module keeps its own Box)
    importlib.import_module("d2spo.envs.gymnax_env")
    for name in [n for n in sys.modules if n == "d2spo.envs" or n.startswith("d2spo.envs.")]:
        monkeypatch.delitem(sys.modules, name)  # monkeypatch puts the modules back afterwards
    before = d2spo.envs
    monkeypatch.setattr(d2spo, "envs", before)
    monkeypatch.setitem(sys.modules, "gymnasium", None)  # `import gymnasium` now fails
    envs = importlib.import_module("d2spo.envs")
    assert envs is not before and "d2spo.envs.gym_env" not in sys.modules
    env, params = importlib.import_module("d2spo.envs.gymnax_env").GymnaxNav.make(task="F A1", layout="open")
    assert env.num_actions == 2 and env.env.config.layout == "open"
    with pytest.raises(ImportError, match=r"needs gymnasium>=1\.1 \('d2spo\[gym\]'\)"):
        envs.NavVectorEnv
    with pytest.raises(ImportError, match=r"needs gymnasium>=1\.1"):
        from d2spo.envs import NavEnv  # noqa: F401


def test_gymnax_order_cost_in_info_and_the_functional_env_underneath():
    from gymnax.environments import spaces

    env, params = nav(task="relaxed", layout="relaxed", max_steps=4)
    assert isinstance(env.observation_space(params), spaces.Box) and env.num_actions == 2
    obs, state = jax.jit(env.reset)(jax.random.key(0), params)
    _, ref_obs = make_env(EnvConfig(layout="relaxed", max_steps=4), "relaxed")[0].reset(jax.random.key(0), params)
    np.testing.assert_allclose(obs, ref_obs, rtol=1e-6, atol=1e-6)  # jitted vs op by op
    assert bool(env.observation_space(params).contains(obs))
    step = jax.jit(env.step)
    for _ in range(4):
        obs, state, _, terminated, truncated, info = step(jax.random.key(1), state, jnp.ones(2), params)
        assert {"cost", "final_observation", "discount", "collided", "completed"} <= set(info)
        assert float(info["cost"]) == float(info["collided"])
    assert bool(truncated) and not bool(terminated) and int(state.t) == 0  # reset in the same step
    assert not np.array_equal(info["final_observation"], obs)


def test_reset_and_step_are_jitted_as_gymnaxs_own_and_params_name_the_episode_limit(monkeypatch):
    """A Python loop over ``step`` traces the functional env once (gymnax's ``step`` is jitted);
    ``max_steps_in_episode`` is gymnax's name for the step limit."""
    env, params = nav(task="relaxed", layout="relaxed", max_steps=6)
    traces = []
    inner = env.env.step
    monkeypatch.setattr(env.env, "step", lambda *a: traces.append(1) or inner(*a))
    obs, state = env.reset(jax.random.key(0))
    for t in range(8):  # through an episode end and its reset
        obs, state, _, terminated, truncated, _ = env.step(jax.random.key(t), state, jnp.ones(2))
    assert len(traces) == 1 and int(params.max_steps_in_episode) == 6 == int(params.max_steps)
    assert int(state.t) == 2  # the episode of 6 steps ended and the next is 2 steps in


def test_vmap_and_scan_through_gymnax_wrappers():
    from gymnax.wrappers.purerl import FlattenObservationWrapper, LogWrapper

    base, params = nav(task="F A1", layout="open", max_steps=10)
    env = LogWrapper(FlattenObservationWrapper(base))
    n = 3
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), n), params)

    def body(carry, key):
        obs, state = carry
        obs, state, reward, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(key, n), state, jnp.tile(jnp.array([0.5, 0.0]), (n, 1)), params)
        return (obs, state), (reward, terminated | truncated, info["returned_episode_returns"], info["cost"])

    _, (reward, done, logged, cost) = jax.lax.scan(body, (obs, state), jax.random.split(jax.random.key(1), 25))
    assert reward.shape == done.shape == cost.shape == (25, n)
    assert np.array_equal(np.asarray(done[9]), np.ones(n, bool)) and not np.asarray(done[:9]).any()
    # LogWrapper's episode return is the sum of the rewards of the first episode
    np.testing.assert_allclose(np.asarray(logged[9]), np.asarray(reward[:10].sum(0)), rtol=1e-5)


def _success_rate(env, params, n: int, steps: int):
    """agent -> fraction of n first episodes that complete the task under the deterministic policy."""

    @jax.jit
    def rate(agent):
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(123), n), params)

        def body(carry, key):
            obs, state, ended, success = carry
            action = _ppo.mean_action(agent, obs)
            obs, state, _, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key, n), state, action, params)
            done = terminated | truncated
            success = success | (done & ~ended & info["completed"])
            return (obs, state, ended | done, success), None

        init = (obs, state, jnp.zeros(n, bool), jnp.zeros(n, bool))
        (_, _, ended, success), _ = jax.lax.scan(body, init, jax.random.split(jax.random.key(7), steps))
        return ended.all(), success.mean()

    def run(agent) -> float:
        all_ended, success = rate(agent)
        assert bool(all_ended)
        return float(success)

    return run


N_ENVS, N_STEPS, N_UPDATES, MAX_STEPS = 16, 64, 15, 80


def test_purejaxrl_style_ppo_learns_F_A1_on_open():
    from gymnax.wrappers.purerl import FlattenObservationWrapper, LogWrapper

    base, params = nav(task="F A1", layout="open", max_steps=MAX_STEPS)
    env = LogWrapper(FlattenObservationWrapper(base))
    n_obs = env.observation_space(params).shape[0]
    tx = _ppo.optimizer()

    def train(key):
        k_init, k_reset, k_train = jax.random.split(key, 3)
        agent = _ppo.init(k_init, n_obs, env.num_actions)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, N_ENVS), params)

        def env_step(carry, key):
            agent, obs, state = carry
            k_act, k_env = jax.random.split(key)
            action, logp = _ppo.sample(k_act, agent, obs)
            next_obs, state, reward, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(k_env, N_ENVS), state, action, params)
            done = terminated | truncated
            return (agent, next_obs, state), {
                "obs": obs, "action": action, "logp": logp, "reward": reward, "done": done.astype(jnp.float32),
                "value": _ppo.value(agent, obs), "returned": info["returned_episode"]}

        def iteration(carry, key):
            agent, opt_state, obs, state = carry
            k_roll, k_update = jax.random.split(key)
            (_, obs, state), tr = jax.lax.scan(env_step, (agent, obs, state), jax.random.split(k_roll, N_STEPS))
            adv, ret = _ppo.gae(tr["reward"], tr["value"], tr["done"], _ppo.value(agent, obs))
            batch = {"obs": tr["obs"], "action": tr["action"], "logp": tr["logp"], "adv": adv, "ret": ret,
                     "mask": jnp.ones_like(adv)}
            batch = jax.tree.map(lambda a: a.reshape((N_STEPS * N_ENVS,) + a.shape[2:]), batch)
            agent, opt_state = _ppo.update(agent, opt_state, batch, k_update, tx)
            return (agent, opt_state, obs, state), tr["returned"].sum()

        carry = (agent, tx.init(agent), obs, state)
        (agent, *_), episodes = jax.lax.scan(iteration, carry, jax.random.split(k_train, N_UPDATES))
        return agent, episodes

    untrained = _ppo.init(jax.random.split(jax.random.key(0), 3)[0], n_obs, 2)
    agent, episodes = jax.jit(train)(jax.random.key(0))
    success_rate = _success_rate(env, params, 32, MAX_STEPS)
    before, after = success_rate(untrained), success_rate(agent)
    assert before <= 0.1 and after >= 0.9, (before, after, np.asarray(episodes))
