"""A config is built, traced and compiled once per process (d2spo.memo), and reusing it changes nothing."""

from __future__ import annotations

import collections
import dataclasses
import json

import jax
import pytest
from test_train import rows, tiny

from d2spo import memo
from d2spo.envs import EnvConfig
from d2spo.rollout import acting_on, make_rollout
from d2spo.run import build
from d2spo.train import learner_program, train

TRACE = "/jax/core/compile/jaxpr_trace_duration"


class _Events:
    """JAX's compile-pipeline events while the context is open."""

    def __init__(self):
        self.counts = collections.Counter()
        self._open = False
        jax.monitoring.register_event_duration_secs_listener(self._listen)

    def _listen(self, event: str, duration: float, **_) -> None:
        if self._open:
            self.counts[event] += 1

    def __enter__(self):
        self.counts.clear()
        self._open = True
        return self.counts

    def __exit__(self, *exc):
        self._open = False


def test_a_second_run_of_a_config_traces_nothing_and_equals_a_fresh_builds(tmp_path):
    events = _Events()
    cfg = tiny()
    train(cfg, tmp_path / "first")
    env, params, learner = build(cfg)
    assert build(dataclasses.replace(cfg, seed=7))[2] is learner  # no learner reads the seed
    assert build(tiny(td3=dataclasses.replace(cfg.td3, hidden=(8, 8))))[2] is not learner
    assert learner_program(learner, "chunk", donate=True) is learner_program(learner, "chunk", donate=True)
    assert learner_program(learner, "chunk") is not learner_program(learner, "chunk", donate=True)
    with events as counts:
        train(dataclasses.replace(cfg, seed=1), tmp_path / "seed1")
    assert counts[TRACE] == 0, dict(counts)  # the first run's programs, init, chunk and evaluation
    memo.clear()
    with events as counts:
        train(cfg, tmp_path / "fresh")
    assert counts[TRACE] > 0  # built, traced and compiled again
    assert build(cfg)[2] is not learner
    # the reused programs computed what freshly built ones compute, episode for episode
    assert rows(tmp_path / "first" / "episodes.csv") == rows(tmp_path / "fresh" / "episodes.csv")
    first, fresh = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("first", "fresh"))
    assert first["eval"] == fresh["eval"]
    assert rows(tmp_path / "seed1" / "episodes.csv") != rows(tmp_path / "first" / "episodes.csv")


def test_an_edited_layout_file_is_built_again(tmp_path):
    layout = {"name": "box", "arena": [5.0, 5.0], "start": [0.6, 0.6, 0.0],
              "obstacles": [{"center": [2.5, 2.5], "half_extents": [0.4, 0.4]}],
              "areas": [{"name": "A1", "center": [4.2, 0.9], "radius": 0.35},
                        {"name": "A2", "center": [4.1, 4.1], "radius": 0.35}]}
    path = tmp_path / "box.json"
    path.write_text(json.dumps(layout))
    cfg = tiny(env=dataclasses.replace(tiny().env, layout=str(path)))
    _, params, learner = build(cfg)
    assert build(cfg)[2] is learner
    layout["areas"][0]["center"] = [4.2, 1.5]  # A1 moved
    path.write_text(json.dumps(layout))
    _, moved, other = build(cfg)
    assert other is not learner
    assert float(params.area_center[0, 1]) == pytest.approx(0.9) and float(moved.area_center[0, 1]) == 1.5


def test_a_rollout_is_made_once_per_learner_and_a_copy_gets_its_own():
    env, params, learner = build(tiny(env=EnvConfig(layout="relaxed", max_steps=40)))
    one = make_rollout(learner, env, 4, 40)
    assert make_rollout(learner, env, 4, 40) is one
    assert make_rollout(learner, env, 5, 40) is not one
    assert make_rollout(acting_on(learner, params), env, 4, 40) is not one
