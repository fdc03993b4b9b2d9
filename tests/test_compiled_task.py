"""A task is compiled onto a layout once per training run (envs/compiled_task.py)."""

from __future__ import annotations

import dataclasses

from d2spo.algos.d2spo import D2SPOConfig
from d2spo.algos.td3 import TD3Config
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig, compiled_task, routes
from d2spo.ltl.automaton import Automaton
from d2spo.train import train


def test_a_training_run_computes_the_tasks_distances_routes_and_fields_once(tmp_path, monkeypatch):
    calls = {"distances": 0, "route_length": 0, "reachable_states": 0, "state_fields": 0}

    def counted(name, f):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return f(*args, **kwargs)
        return wrapper

    monkeypatch.setattr(Automaton, "distances", counted("distances", Automaton.distances))
    monkeypatch.setattr(routes, "route_length", counted("route_length", routes.route_length))
    monkeypatch.setattr(routes, "reachable_states", counted("reachable_states", routes.reachable_states))
    monkeypatch.setattr(compiled_task, "state_fields", counted("state_fields", compiled_task.state_fields))
    # D²SPO: its barrier's margin is checked too; max_steps unset: the step limit follows the route
    cfg = TrainConfig(algo="d2spo", task="relaxed", episodes=4, num_envs=2, chunk_steps=25, checkpoint_every=4,
                      eval_episodes=2, env=EnvConfig(layout="relaxed"),
                      td3=dataclasses.replace(TD3Config(), hidden=(16, 16), batch_size=16, learning_starts=16,
                                              buffer_size=256),
                      d2spo=D2SPOConfig(pretrain=False)).check()  # no cautious start: a smaller program to compile
    train(cfg, tmp_path / "run")
    # one distance computation, one route, one set of fields; the grid search for the robot (make_env's
    # feasibility check) and for the barrier's margin d
    assert calls == {"distances": 1, "route_length": 1, "reachable_states": 2, "state_fields": 1}
