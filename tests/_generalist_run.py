"""A generalist run directory that was never trained, for the zero-shot evaluation tests
(tests/test_zero_shot.py, tests/test_eval_options.py): its config and a checkpoint of zeros, a robot
that stands still, which is as good as any policy for the plumbing."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp

from d2spo.algos.d2spo import D2SPOConfig
from d2spo.algos.td3 import TD3Config
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.safety.cbf import CBFConfig

SMALL = {"td3": TD3Config(buffer_size=1024),
         "cbf": CBFConfig(transitions_capacity=1024, p_exp_capacity=1024, unsafe_capacity=1024)}
"""Small replay buffer and safety datasets: the runs here are never trained, and a checkpoint of the
default ones is 232 MB of zeros, written, copied and read by several tests (about 1 MB so)."""


def gen_cfg(**d2spo) -> TrainConfig:
    """A small generalist's config on ϕ1, ideal dynamics, four environments, no pretraining."""
    return TrainConfig(algo="d2spo", task="phi1", generalist=True, generalist_layouts=1, num_envs=4,
                       env=EnvConfig(preset="ideal"), d2spo=D2SPOConfig(pretrain=False, **d2spo), **SMALL)


def zeros_generalist_run(out: Path, cfg: TrainConfig | None = None) -> Path:
    """Write ``cfg``'s (``gen_cfg()``'s) config.json and a checkpoint of zeros into the new directory ``out``."""
    from d2spo.algos.generalist import build_generalist
    from d2spo.checkpoint import Checkpoints, run_fingerprint
    from d2spo.config import config_to_dict
    from d2spo.envs import generator

    cfg = gen_cfg() if cfg is None else cfg
    out.mkdir()
    (out / "config.json").write_text(json.dumps(config_to_dict(cfg)))
    _, _, learner = build_generalist(cfg, [generator.generate(3)], 400)
    shapes = jax.eval_shape(learner.init, jax.random.PRNGKey(0))
    Checkpoints(out, run_fingerprint(out)).save(jax.tree_util.tree_map(lambda t: jnp.zeros(t.shape, t.dtype), shapes),
                                                {"episodes": 0, "env_steps": 0, "chunks": 0, "wall_seconds": 0.0})
    return out


def main(args: list[str]) -> int:
    """``d2spo ARGS``'s exit status, whether it returns or exits."""
    from d2spo.cli import main as cli_main

    try:
        return cli_main(args)
    except SystemExit as e:
        return e.code
