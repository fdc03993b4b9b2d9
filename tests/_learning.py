"""Shared check for the short learning tests of the off-policy baselines."""

from __future__ import annotations

import csv
import dataclasses

import jax
import numpy as np
import pytest

from d2spo._xla import CHUNK_LEVEL
from d2spo.rollout import make_rollout, rates
from d2spo.run import build
from d2spo.train import train


def untrained_eval(cfg, episodes: int) -> dict:
    """Evaluation of the freshly initialised policy, on the same episodes ``train`` evaluates on,
    computed independently of ``train`` (its own build, init and rollout)."""
    env, params, learner = build(cfg)
    policy = learner.policy(jax.jit(learner.init)(jax.random.PRNGKey(cfg.seed)))
    rollout = make_rollout(learner, env, episodes, int(params.max_steps))
    return rates(*rollout(params, policy, jax.random.PRNGKey(cfg.seed + 10_000)))


def assert_trains_without_nans_and_improves(cfg, run_dir) -> None:
    """300 episodes (of at most 200 steps: the tests set ``max_steps=200``, the limit they were
    written for): collisions fall by at least half, and by at least 0.08, from the first to the
    last 75 episodes (0.2 was the fall asked before the path direction joined the observation; the
    tests pick seeds whose first 75 collide often enough to show a fall against), and the final
    policy's evaluation return beats the untrained one's by 1 (``eval_untrained``, the same
    episodes and compilation as the final evaluation). The chunk compiles at XLA's level 2, not the
    suite's 0: it runs 10-20 times, and running it was most of these tests' time (d2spo/_xla.py,
    chunk_options)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(CHUNK_LEVEL, "2")
        summary = train(dataclasses.replace(cfg, eval_untrained=True), run_dir)  # raises NaNError on NaNs
    untrained = summary["eval_untrained"]
    with open(run_dir / "episodes.csv") as f:
        rows = np.array([[float(r[1]), float(r[3])] for r in list(csv.reader(f))[1:]])
    assert len(rows) == 300 and cfg.env.max_steps == 200
    collided_first, collided_last = rows[:75, 1].mean(), rows[-75:, 1].mean()
    # it learns to be safe
    assert collided_last <= 0.5 * collided_first and collided_last <= collided_first - 0.08, (collided_first,
                                                                                               collided_last)
    assert summary["eval"]["mean_return"] > untrained["mean_return"] + 1.0, (untrained, summary["eval"])
