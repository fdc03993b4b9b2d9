"""The Gymnasium front ends: the env checker, Gymnasium's five values with the cost in info,
next-step and same-step vector autoreset, Gymnasium's own wrappers, the real observation bounds,
rendering, the Safety-Gymnasium six-value wrappers, and a CleanRL-style PPO that learns "F A1"."""

from __future__ import annotations

import warnings
from functools import partial

import pytest

# Beside safety-gymnasium (which pins gymnasium 0.28.1) d2spo runs without its Gymnasium front end.
gym = pytest.importorskip("gymnasium", minversion="1.1", reason="d2spo's Gymnasium front end needs gymnasium>=1.1")

import _ppo
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import d2spo.envs  # noqa: F401  registers d2spo/Nav-v0
from d2spo.envs import CostTuple, VectorCostTuple
from d2spo.envs.gym_env import EPISODE_STATS, NavEnv
from d2spo.errors import ConfigError

SMALL = {"task": "relaxed", "layout": "relaxed", "max_steps": 3}  # one config: its programs compile once


def test_gymnasium_env_checker_passes_without_a_warning():
    env = gym.make("d2spo/Nav-v0", render_mode="rgb_array", **SMALL)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)  # spaces, seeding, determinism, the five values, rendering
    env.reset(seed=0)
    _, reward, _, _, info = env.step(env.action_space.sample())
    assert isinstance(reward, float) and info["cost"] in (0.0, 1.0) and "episode" not in info
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3


def test_vector_env_resets_on_the_next_step_by_default():
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=4, **SMALL)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs0, _ = envs.reset(seed=0)
    for _ in range(3):
        obs, reward, terminated, truncated, info = envs.step(np.ones((4, 2), np.float32))
        assert obs.shape == (4, envs.single_observation_space.shape[0]) and info["cost"].shape == (4,)
    assert truncated.all() and not terminated.any()
    assert np.array_equal(info["_" + EPISODE_STATS], truncated)
    np.testing.assert_array_equal(info[EPISODE_STATS]["ep_length"], 3)
    assert not np.allclose(obs, obs0)  # the last observation of the episode, three steps in
    obs, reward, terminated, truncated, info = envs.step(np.ones((4, 2), np.float32))  # the reset step
    assert not (terminated | truncated).any() and np.all(reward == 0) and np.all(info["cost"] == 0)
    np.testing.assert_allclose(obs[:, 16:18], obs0[:, 16:18], atol=0.05)  # back at the start (x, y)
    envs.close()


def test_vector_env_same_step_mode_and_the_six_value_wrappers():
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=4, autoreset_mode=AutoresetMode.SAME_STEP, **SMALL)
    envs = VectorCostTuple(envs)
    envs.reset(seed=0)
    for _ in range(3):
        obs, _, cost, _, truncated, info = envs.step(np.ones((4, 2), np.float32))
    assert np.array_equal(cost, info["cost"]) and truncated.all()
    assert np.array_equal(info["_final_obs"], truncated) and not np.allclose(info["final_obs"], obs)
    env = CostTuple(gym.make("d2spo/Nav-v0", **SMALL))
    env.reset(seed=0)
    _, reward, cost, _, _, info = env.step(np.zeros(2, np.float32))
    assert cost == info["cost"] == 0.0 and isinstance(reward, float)


def test_gymnasium_wrappers_single_and_vector():
    # single: TimeLimit (gym.make's max_episode_steps), RecordEpisodeStatistics, NormalizeObservation
    env = gym.make("d2spo/Nav-v0", max_episode_steps=2, **SMALL)
    env = gym.wrappers.NormalizeObservation(gym.wrappers.RecordEpisodeStatistics(env))
    env.reset(seed=0)
    returns = []
    for _ in range(2):
        _, reward, _, truncated, info = env.step(np.ones(2, np.float32))
        returns.append(reward)
    assert truncated and info["episode"]["l"] == 2 and info["episode"]["r"] == pytest.approx(sum(returns), abs=1e-5)
    assert EPISODE_STATS not in info  # our own limit (3) was not reached: TimeLimit cut the episode

    # vector: make_vec's max_episode_steps, RecordEpisodeStatistics, NormalizeObservation, TransformObservation
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=3, max_episode_steps=3, task="relaxed", layout="relaxed")
    envs = gym.wrappers.vector.RecordEpisodeStatistics(envs)
    envs = gym.wrappers.vector.NormalizeObservation(envs)
    envs = gym.wrappers.vector.TransformObservation(envs, lambda o: np.clip(o, -5, 5))
    envs.reset(seed=0)
    for _ in range(3):
        obs, _, _, truncated, info = envs.step(np.ones((3, 2), np.float32))
    assert truncated.all() and np.abs(obs).max() <= 5
    np.testing.assert_array_equal(info["episode"]["l"], 3)
    np.testing.assert_allclose(info["episode"]["r"], info[EPISODE_STATS]["ep_return"], rtol=1e-5)


def test_observations_stay_inside_the_declared_bounds_through_collisions():
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=64, task="phi1", layout="paper",
                        autoreset_mode=AutoresetMode.SAME_STEP)
    space = envs.single_observation_space
    assert np.isfinite(space.low).all() and np.isfinite(space.high).all()
    pose = envs.unwrapped.env.observation_slices["pose"]
    assert space.high[pose].max() < 1.05 and space.low[:16].min() == 0.0  # tight: scaled x, y; lidar
    envs.reset(seed=1)
    envs.action_space.seed(1)
    collisions = 0
    for _ in range(60):
        obs, _, _, _, info = envs.step(envs.action_space.sample())
        collisions += int(info["collided"].sum())
        for o in (obs, info["final_obs"][info["_final_obs"]]):
            assert np.all((o >= space.low) & (o <= space.high))
    assert collisions > 0  # the terminal observations of collisions were checked


def test_render_modes():
    env = NavEnv(render_mode="rgb_array", **SMALL)
    env.reset(seed=0)
    first = env.render()
    for _ in range(3):
        env.step(np.array([1.0, 0.0], np.float32))
    assert first.shape == env.render().shape and not np.array_equal(first, env.render())
    assert NavEnv(**SMALL).render() is None


def test_human_rendering_without_a_display_is_a_config_error(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    with pytest.raises(ConfigError) as e:
        NavEnv(render_mode="human", **SMALL)
    assert e.value.field == "render_mode" and "display" in str(e.value)
    with pytest.raises(ConfigError, match="needs a display"):  # not gymnasium's pygame wrapper instead
        gym.make("d2spo/Nav-v0", render_mode="human", **SMALL)


def test_a_nan_action_is_a_value_error_not_a_safe_episode():
    """A NaN action once moved the robot to a NaN pose that every later step reported collision-free."""
    env = NavEnv(**SMALL)
    env.reset(seed=0)
    for bad in ([np.nan, 0.0], [0.0, np.inf]):
        with pytest.raises(ValueError, match="not finite"):
            env.step(np.array(bad, np.float32))
    _, _, _, _, info = env.step(np.array([0.5, 0.0], np.float32))  # the env is unharmed
    assert np.isfinite(env._pose).all() and info["cost"] == 0.0
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=2, **SMALL)
    envs.reset(seed=0)
    with pytest.raises(ValueError, match="not finite"):
        envs.step(np.array([[0.0, 0.0], [np.nan, 0.0]], np.float32))


def test_seeded_vector_envs_repeat_and_unknown_options_are_config_errors():
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=2, **SMALL)
    runs = []
    for seed in (3, 3, 4):
        envs.reset(seed=seed)
        obs, *_ = envs.step(np.full((2, 2), 0.5, np.float32))
        runs.append(obs)
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])
    for bad in ({"colour": "red"}, {"autoreset_mode": "sometimes"}):
        with pytest.raises(ConfigError) as e:
            gym.make_vec("d2spo/Nav-v0", num_envs=2, **bad)
        assert e.value.field == next(iter(bad))


N_ENVS, N_STEPS, N_UPDATES, MAX_STEPS = 16, 64, 15, 80


def _first_episode_success(envs, policy) -> float:
    """Fraction of the sub-environments whose first episode completes the task."""
    obs, _ = envs.reset(seed=123)
    ended, success = np.zeros(envs.num_envs, bool), np.zeros(envs.num_envs, bool)
    while not ended.all():
        obs, _, _, _, info = envs.step(policy(obs))
        new = info["_" + EPISODE_STATS] & ~ended
        success |= new & info[EPISODE_STATS]["ep_completed"]
        ended |= new
    return float(success.mean())


def test_cleanrl_style_ppo_on_the_gymnasium_api_learns_F_A1_on_open():
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=N_ENVS, task="F A1", layout="open", max_steps=MAX_STEPS)
    envs = gym.wrappers.vector.RecordEpisodeStatistics(envs)
    n_obs, n_act = envs.single_observation_space.shape[0], envs.single_action_space.shape[0]
    tx = _ppo.optimizer()
    agent = _ppo.init(jax.random.key(0), n_obs, n_act)
    opt_state = tx.init(agent)
    act = jax.jit(lambda key, agent, obs: (*_ppo.sample(key, agent, obs), _ppo.value(agent, obs)))
    update = jax.jit(partial(_ppo.update, tx=tx))
    gae = jax.jit(_ppo.gae)
    greedy = jax.jit(_ppo.mean_action)
    before = _first_episode_success(envs, lambda obs: np.asarray(greedy(agent, obs)))

    key = jax.random.key(1)
    obs, _ = envs.reset(seed=0)
    autoreset = np.zeros(N_ENVS, bool)  # next-step autoreset: the step after an episode's end resets
    lengths = []
    for _ in range(N_UPDATES):
        rollout = {k: [] for k in ("obs", "action", "logp", "value", "reward", "done", "mask")}
        for _ in range(N_STEPS):
            key, k = jax.random.split(key)
            action, logp, value = act(k, agent, obs)
            next_obs, reward, terminated, truncated, info = envs.step(np.asarray(action))
            done = terminated | truncated
            for name, x in zip(rollout, (obs, action, logp, value, reward, done, ~autoreset)):
                rollout[name].append(np.asarray(x, np.float32))
            lengths += list(info["episode"]["l"][info["_episode"]]) if "episode" in info else []
            obs, autoreset = next_obs, done
        r = {k: jnp.asarray(np.stack(v)) for k, v in rollout.items()}
        adv, ret = gae(r["reward"], r["value"], r["done"], act(key, agent, obs)[2])
        batch = {"obs": r["obs"], "action": r["action"], "logp": r["logp"], "adv": adv, "ret": ret, "mask": r["mask"]}
        batch = jax.tree.map(lambda a: a.reshape((N_STEPS * N_ENVS,) + a.shape[2:]), batch)
        key, k = jax.random.split(key)
        agent, opt_state = update(agent, opt_state, batch, k)

    after = _first_episode_success(envs, lambda obs: np.asarray(greedy(agent, obs)))
    assert before <= 0.1 and after >= 0.9, (before, after)
    assert np.mean(lengths[-N_ENVS:]) < MAX_STEPS  # RecordEpisodeStatistics: episodes now end early


def test_seeding_follows_gymnasiums_contract():
    """A reset without a seed drew nothing (every env and process began alike, a vector env's sub-envs
    too); seeds of 2**32 and above were the low 32 bits' (2**32 was seed 0); a list of seeds was a
    JAX TypeError."""
    first = [gym.make("d2spo/Nav-v0", **SMALL).reset()[0] for _ in range(2)]
    assert not np.array_equal(*first)  # each from entropy
    env = gym.make("d2spo/Nav-v0", **SMALL)
    at = {s: env.reset(seed=s)[0] for s in (0, 7, 2**32, 2**32 + 7, 2**63)}
    assert not np.array_equal(at[0], at[2**32]) and not np.array_equal(at[7], at[2**32 + 7])
    assert np.array_equal(at[7], env.reset(seed=7)[0])  # repeatable
    with pytest.raises(gym.error.Error, match="greater or equal to zero"):  # Gymnasium's own check
        env.reset(seed=-1)
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=3, **SMALL)
    a, _ = envs.reset(seed=[0, 1, 2])
    assert np.array_equal(a, envs.reset(seed=[0, 1, 2])[0]) and not np.array_equal(a, envs.reset(seed=[0, 1, 3])[0])
    with pytest.raises(ValueError, match="a list of 3 seeds"):
        envs.reset(seed=[0, 1])


def test_wrong_shapes_and_counts_are_refused_where_they_are_given():
    """The functional env stepped [0.7] as (0.7, 0.7) (JAX clamps an index) and ignored a third entry;
    the Gym env's error came from inside JAX; num_envs=0 was accepted."""
    from d2spo.envs import EnvConfig, make_env

    fenv, params = make_env(EnvConfig(layout="relaxed"), task="F A1")
    state, _ = fenv.reset(jax.random.PRNGKey(0), params)
    for bad in (jnp.array([0.7]), jnp.array([0.7, 0.0, 9.0])):
        with pytest.raises(ValueError, match=r"action: expected shape \(2,\)"):
            fenv.step(jax.random.PRNGKey(1), state, bad, params)
    states, _ = fenv.reset_batch(jax.random.PRNGKey(0), params, 4)
    with pytest.raises(ValueError, match="expected shape"):
        fenv.step_batch(jax.random.PRNGKey(1), states, jnp.zeros((4, 1)), params)
    env = gym.make("d2spo/Nav-v0", **SMALL)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action: expected Box.*got shape \(3,\)"):
        env.step(np.zeros(3, np.float32))
    with pytest.raises(ConfigError, match="num_envs: must be a whole number >= 1"):
        gym.make_vec("d2spo/Nav-v0", num_envs=0, **SMALL)
    with pytest.raises(ConfigError, match="config: expected a d2spo.envs.EnvConfig, got dict"):  # was replace()'s TypeError
        gym.make("d2spo/Nav-v0", config={"layout": "open"})
