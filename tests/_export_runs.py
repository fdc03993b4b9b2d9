"""The tiny exported runs of tests/test_export.py, tests/test_export_cli.py and tests/test_deploy_runtime.py
(``tiny_run``; the session fixture ``tiny_export`` of tests/conftest.py builds ϕ1's once per worker for them)."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _tiny import write_run

from d2spo.config import TrainConfig
from d2spo.export import ExportConfig, export_run
from d2spo.run import build
from d2spo.train import learner_program


def has_module(module: str) -> bool:
    try:
        __import__(module)
    except ImportError:
        return False
    return True


OFFICE = {"name": "office", "arena": [5.0, 4.0], "start": [0.6, 0.6, 0.0],
          "obstacles": [{"center": [2.5, 2.0], "radius": 0.4}, {"center": [2.5, 0.5], "half_extents": [0.25, 0.25]},
                        {"center": [1.7, 2.6], "radius": 0.3}],
          "areas": [{"name": "desk-1", "label": "desk", "center": [4.2, 0.9], "radius": 0.35},
                    {"name": "desk-2", "label": "desk", "center": [0.8, 3.3], "radius": 0.35},
                    {"name": "kitchen", "center": [4.2, 3.2], "radius": 0.35}]}
"""A layout with disk obstacles, a non-square arena and two areas sharing a label (docs/layouts.md)."""


def tiny_run(root: Path, cfg: TrainConfig):
    """(run dir, export dir, cfg, learner, policy): an untrained tiny D²SPO run whose h is set by hand to
    tanh(4 min(x)/H - 1), a barrier that crosses zero 0.3 m from obstacles (so the filter acts at part
    of the arena), and its export (with ONNX where the onnx package is here)."""
    _, _, learner = build(cfg)
    carry = learner_program(learner, "init")(jax.random.PRNGKey(0))
    p = jax.tree_util.tree_map(np.zeros_like, carry.safety.cbf)
    p["params"]["Dense_0"]["kernel"][-1, 0] = 4.0  # the input's last entry is min(x)/H
    p["params"]["Dense_0"]["bias"][0] = -1.0
    p["params"]["Dense_1"]["kernel"][0, 0] = 1.0
    carry = carry.replace(safety=carry.safety.replace(cbf=jax.tree_util.tree_map(jnp.asarray, p)))
    write_run(root / "run", cfg, carry)
    export_run(root / "run", root / "out", ExportConfig(onnx=has_module("onnx")))
    return root / "run", root / "out", cfg, learner, learner.policy(carry)
