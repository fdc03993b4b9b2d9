"""PPO-Lagrangian: the clipped surrogate and the Lagrangian advantage on hand values, the
multiplier inside the learner, the chunk layout, and learning on `relaxed`."""

from __future__ import annotations

import csv
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.algos.base import ChunkLog
from d2spo.algos.common.lagrange import LagrangeConfig
from d2spo.algos.onpolicy import flatten_iterations
from d2spo.algos.ppo_lag import PPOLagConfig, lagrangian_advantage, ppo_clip_loss
from d2spo.config import TrainConfig
from d2spo.errors import ConfigError
from d2spo.run import build
from d2spo.train import train


def relaxed(**kw) -> TrainConfig:
    cfg = TrainConfig(algo="ppo-lag", task="relaxed", **kw)
    # 200-step episodes (the default limit is 300): some end in every 250-step rollout
    return dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, layout="relaxed", max_steps=200))


def test_clipped_surrogate_on_hand_values():
    # ratios 1.5, 0.5, 0.5, 1.5 with advantages +1, +1, -1, -1 and eps = 0.2:
    # min(rho A, clip(rho) A) = min(1.5, 1.2) = 1.2, min(0.5, 0.8) = 0.5, min(-0.5, -0.8) = -0.8,
    # min(-1.5, -1.2) = -1.5  ->  loss = -mean = -(1.2 + 0.5 - 0.8 - 1.5) / 4 = 0.15.
    ratio = jnp.array([1.5, 0.5, 0.5, 1.5])
    adv = jnp.array([1.0, 1.0, -1.0, -1.0])
    old = jnp.zeros(4)
    loss, clipfrac = ppo_clip_loss(jnp.log(ratio), old, adv, 0.2)
    assert float(loss) == pytest.approx(0.15, abs=1e-6)
    assert float(clipfrac) == 1.0
    # Gradient flows only where the unclipped term is the minimum (samples 2 and 4): d/d logp of
    # -rho A / 4 = -rho A / 4.
    grad = jax.grad(lambda lp: ppo_clip_loss(lp, old, adv, 0.2)[0])(jnp.log(ratio))
    np.testing.assert_allclose(np.asarray(grad), [0.0, -0.125, 0.0, 0.375], atol=1e-6)
    # Inside the clip range nothing is clipped: loss = -mean(rho A).
    loss, clipfrac = ppo_clip_loss(jnp.log(jnp.array([1.1, 0.9])), jnp.zeros(2), jnp.array([2.0, 1.0]), 0.2)
    assert float(loss) == pytest.approx(-(2.2 + 0.9) / 2, abs=1e-6) and float(clipfrac) == 0.0


def test_lagrangian_advantage_on_hand_values():
    adv = lagrangian_advantage(jnp.array([1.0, -2.0]), jnp.array([3.0, 0.5]), jnp.float32(1.0))
    np.testing.assert_allclose(np.asarray(adv), [(1 - 3) / 2, (-2 - 0.5) / 2])
    np.testing.assert_allclose(np.asarray(lagrangian_advantage(jnp.array([1.5]), jnp.array([9.0]), 0.0)), [1.5])


def small_run(episodes: int, lagrange: LagrangeConfig = LagrangeConfig(cost_limit=0.05)) -> TrainConfig:
    """Tiny nets, the annealed radius held at its initial (wide) value, 16 envs x 250 steps per update.

    The multiplier test and the learning test share this program (the persistent XLA cache
    compiles it once); the cost limit and lambda live in the carry, not in the program.
    """
    cfg = relaxed(episodes=episodes, seed=0, eval_episodes=0, checkpoint_every=10**6,
                  ppo_lag=PPOLagConfig(hidden=(32, 32), lagrange=lagrange))
    return dataclasses.replace(cfg, anneal=dataclasses.replace(cfg.anneal, k2=0.0))


def test_multiplier_rises_while_cost_exceeds_limit_and_chunk_log_layout():
    # Episodes last at most 200 steps, so some end in every 250-step rollout; an untrained policy
    # collides in some of them (cost 1 each). Same jit calls as d2spo.train.
    _, _, learner = build(small_run(100, LagrangeConfig(cost_limit=0.0, init=0.5)))
    init, chunk = jax.jit(learner.init), jax.jit(learner.chunk, donate_argnums=0)
    carry, log = chunk(init(jax.random.PRNGKey(0)))  # limit 0: J_c >= 0 = d
    lam1 = float(carry.lagrange.multiplier)
    carry, _ = chunk(carry)
    lam2 = float(carry.lagrange.multiplier)
    assert float(np.asarray(log.ep_cost)[np.asarray(log.done)].sum()) > 0
    # ascent steps of Adam: the first exactly lr = 0.035, the next at most about lr
    assert lam1 == pytest.approx(0.5 + 0.035, abs=1e-5) and 0.5 + 0.035 < lam2 <= 0.5 + 2 * 0.035 + 1e-4
    start = init(jax.random.PRNGKey(0))
    carry, _ = chunk(start.replace(lagrange=start.lagrange.replace(cost_limit=jnp.float32(1.0))))
    assert float(carry.lagrange.multiplier) < 0.5  # J_c <= 1 = d: lambda can only fall
    # the ChunkLog covers every step of the rollout; the update's metrics sit on its last step
    assert log.done.shape == (250, 16) and log.ep_return.shape == (250, 16)
    lam = np.asarray(log.metrics["charts/lambda"])
    assert lam.shape == (250,) and np.isnan(lam[:-1]).all() and lam[-1] == pytest.approx(lam1)
    assert np.isfinite(np.asarray(log.metrics["charts/label_radius"])).all()
    assert not bool(log.nonfinite)


def test_flatten_iterations_puts_rollouts_end_to_end():
    log = ChunkLog(*(jnp.arange(2 * 3 * 4).reshape(2, 3, 4) for _ in range(7)),
                   ep_end_xy=jnp.arange(2 * 3 * 4 * 2.0).reshape(2, 3, 4, 2),
                   metrics={"m": jnp.arange(6.0).reshape(2, 3)}, nonfinite=jnp.array([False, True]))
    flat = flatten_iterations(log)
    assert flat.done.shape == (6, 4) and flat.metrics["m"].shape == (6,) and flat.ep_end_xy.shape == (6, 4, 2)
    np.testing.assert_array_equal(np.asarray(flat.done[3]), np.asarray(log.done[1, 0]))  # rollout 2, step 0
    np.testing.assert_array_equal(np.asarray(flat.metrics["m"]), np.arange(6.0))


def test_bad_sizes_are_config_errors():
    with pytest.raises(ConfigError, match="chunk_steps"):
        build(relaxed(chunk_steps=100, ppo_lag=PPOLagConfig(rollout_steps=30)))
    with pytest.raises(ConfigError, match="n_minibatches"):
        build(relaxed(num_envs=4, chunk_steps=50, ppo_lag=PPOLagConfig(rollout_steps=25, n_minibatches=7)))
    with pytest.raises(ConfigError, match="epochs"):
        PPOLagConfig(epochs=0)


def test_ppo_lag_learns_relaxed(tmp_path):
    summary = train(small_run(500), tmp_path / "run")
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


def test_cost_advantages_are_centred_only_unless_asked_and_old_runs_keep_their_setting():
    """OmniSafe's buffer and safety-starter-agents centre the cost advantages without rescaling; d2spo
    divided them by their std until 2026-12-02, which a config.json without the field still reads."""
    import json
    from pathlib import Path

    from d2spo.algos.onpolicy import standardize
    from d2spo.config import config_from_dict, config_to_dict

    assert PPOLagConfig().scale_cost_advantage is False
    x = jnp.array([0.01, -0.01, 0.03])
    np.testing.assert_allclose(np.asarray(standardize(x, scale=False)), np.asarray(x - jnp.mean(x)), atol=1e-7)
    data = config_to_dict(relaxed())
    del data["ppo_lag"]["scale_cost_advantage"]
    assert config_from_dict(data).ppo_lag.scale_cost_advantage is True
    published = Path(__file__).resolve().parent.parent / "docs" / "results" / "runs" / "ppo-lag-phi1-paper-s0"
    assert config_from_dict(json.loads((published / "config.json").read_text())).ppo_lag.scale_cost_advantage is \
        ("scale_cost_advantage" not in (published / "config.json").read_text())
