"""A tiny D²SPO run directory written without training (config.json and a checkpoint of a carry):
tests/test_certify_run.py and tests/test_export.py build the same learner, so they share its
compiled programs (through the persistent cache; one xdist group in tests/conftest.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from d2spo.checkpoint import Checkpoints, run_fingerprint
from d2spo.config import TrainConfig, config_to_dict
from d2spo.envs import EnvConfig
from d2spo.runio import atomic_write_json
from d2spo.safety.cbf import CBFConfig

TINY_CBF = CBFConfig(hidden=(8,), policy_hidden=(8,), nominal_hidden=(8,), transitions_capacity=64,
                     p_exp_capacity=64, unsafe_capacity=64, batch_size=8)
"""Tiny barrier, π_Ω and nominal networks, and datasets."""


def tiny_cfg(algo: str = "d2spo", layout: str = "paper", task: str = "phi1") -> TrainConfig:
    """4 episodes of at most 8 steps, 2 envs, no cautious start, tiny networks and buffers."""
    cfg = TrainConfig(algo=algo, task=task, episodes=4, num_envs=2, env=EnvConfig(layout=layout, max_steps=8),
                      cbf=TINY_CBF)
    cfg = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, pretrain=False),
                              td3=dataclasses.replace(cfg.td3, buffer_size=64, hidden=(8,)))
    return cfg.check()


def write_run(path: Path, cfg: TrainConfig, carry=None) -> None:
    """A run directory of ``cfg``: config.json, and a checkpoint of ``carry`` at episode 0 if given."""
    path.mkdir(parents=True)
    atomic_write_json(path / "config.json", config_to_dict(cfg))
    if carry is not None:
        Checkpoints(path, run_fingerprint(path)).save(carry, {"episodes": 0, "env_steps": 0, "chunks": 0, "wall_seconds": 0.0})
