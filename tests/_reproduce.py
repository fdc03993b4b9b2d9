"""Small configs for the tests that run ``d2spo reproduce`` in-process: every such test trains the
same small program (ppo-lag on `relaxed`, two seeds vmapped together), so XLA compiles it once per
session and the persistent cache (tests/conftest.py) serves the others. Also the config of the short
D²SPO run that Figs. 4-5's test draws from (``short_run_config``)."""

from __future__ import annotations

import dataclasses

from d2spo import reproduce as rp

TINY_EPISODES = 24
FIG5_EPISODES = 32
"""The episodes of a short Fig. 5 run: tests/test_plots.py renders Fig. 5 for it, from the short
D²SPO run (``short_run_config``), which takes its snapshots."""
_CONFIG = rp.RunSpec.config  # the real one, captured before any test patches it


def short_run_config():
    """The short D²SPO run of the tests: 250 episodes on the `relaxed` layout, task F A1, with Fig.
    5's policy snapshots. tests/conftest.py trains it (``short_d2spo_run``); tests/test_d2spo.py
    builds the same learner to check its cautious start, so the worker that trains it has the
    program compiled (d2spo.memo)."""
    from d2spo.algos.td3 import TD3Config
    from d2spo.config import EnvConfig, TrainConfig

    (fig5,) = rp.runs_for("fig5", 1, FIG5_EPISODES)
    return TrainConfig(algo="d2spo", task="F A1", env=EnvConfig(layout="relaxed"), episodes=250, seed=0,
                       eval_episodes=32, eval_untrained=True, snapshots=fig5.snapshots,
                       td3=dataclasses.replace(TD3Config(), updates_per_step=2)).check()


def small_config(spec: rp.RunSpec):
    """``spec.config()`` shrunk: checkpoints every 10 episodes (so a group and each seed checkpoint
    mid-run), 4 envs, chunks of 50 steps, episodes of at most 40 steps, 4 evaluation episodes."""
    c = _CONFIG(spec)
    ppo = dataclasses.replace(c.ppo_lag, hidden=(16, 16), rollout_steps=50, n_minibatches=4, epochs=2)
    return dataclasses.replace(c, checkpoint_every=10, num_envs=4, chunk_steps=50, eval_episodes=4,
                               env=dataclasses.replace(c.env, max_steps=40), ppo_lag=ppo)


def use_small_configs(monkeypatch) -> None:
    """Make ``reproduce`` train ``small_config`` runs for the rest of the test."""
    monkeypatch.setattr(rp.RunSpec, "config", small_config)
