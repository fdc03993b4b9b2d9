"""Ecosystem conventions (issue #35): the module-prefixed Gymnasium id and its spec's step limit,
Safety-Gym-style episodes, ``d2spo train --config``, per-episode TensorBoard scalars and the
optional Weights & Biases logging."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from _tb import tb_scalars

gym = pytest.importorskip("gymnasium")

from d2spo import cli  # noqa: E402
from d2spo.algos.base import ChunkLog  # noqa: E402
from d2spo.config import TrainConfig, config_to_dict  # noqa: E402
from d2spo.envs import EnvConfig, make_env  # noqa: E402
from d2spo.record import EPISODE_SCALARS, RunRecord  # noqa: E402

# ------------------------------------------------------------------------------------ Gymnasium


def test_module_prefixed_id_needs_no_prior_import():
    code = textwrap.dedent("""
        import sys, gymnasium
        assert "d2spo" not in sys.modules
        env = gymnasium.make("d2spo.envs:d2spo/Nav-v0", task="relaxed", layout="relaxed")
        obs, _ = env.reset(seed=0)
        assert env.observation_space.contains(obs)
        print(env.spec.id, env.spec.max_episode_steps)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["d2spo/Nav-v0", "300"]


def test_spec_step_limit_is_the_default_configs_and_leaves_the_vector_envs_own():
    assert gym.spec("d2spo/Nav-v0").max_episode_steps == int(make_env(EnvConfig(), "phi1")[1].max_steps) == 300
    envs = gym.make_vec("d2spo/Nav-v0", num_envs=2, task="relaxed", layout="relaxed", max_steps=7)
    assert int(envs.unwrapped.params.max_steps) == 7  # not the spec's 300


def test_safety_gym_style_episode_goes_on_through_collisions():
    env = gym.make("d2spo/Nav-v0", task="phi1", preset="ideal", start_jitter_xy=0.0, start_jitter_theta=0.0,
                   collision_terminates=False, max_steps=30)
    env.reset(seed=0)
    costs = []
    for t in range(30):  # straight ahead, into the obstacle in front of the start
        _, _, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))
        costs.append(info["cost"])
        assert not terminated and truncated == (t == 29)
    assert sum(costs) >= 5 and costs[-1] == 1.0  # it kept colliding, and kept paying
    assert info["episode_stats"]["ep_cost"] == sum(costs) and info["episode_stats"]["ep_length"] == 30


# ---------------------------------------------------------------------------- train --config

TINY = TrainConfig(algo="tlgrl", task="relaxed", env=EnvConfig(layout="relaxed", collision_terminates=False),
                   episodes=4, seed=3, num_envs=2, chunk_steps=10, eval_episodes=2)


def test_train_config_file_is_parsed_and_flags_override_it(tmp_path):
    path = tmp_path / "config.json"
    path.write_text(json.dumps(config_to_dict(TINY)))
    assert cli.parse(["train", "--config", str(path)]).config() == TINY
    given = cli.parse(["train", "--config", str(path), "--seed", "0", "--layout", "paper"]).config()
    assert given == dataclasses.replace(TINY, seed=0, env=dataclasses.replace(TINY.env, layout="paper"))


@pytest.mark.parametrize("content, says", [
    (None, "cannot read"), ("{not json", "not valid JSON"), ('{"algo": "tlgrl", "colour": 1}', "colour: unknown field"),
    ('{"episodes": -1}', "episodes"), ('{"episdoes": 10}', "episdoes: unknown field (did you mean 'episodes'?)"),
    ('{"td3": {"batch_sise": 8}}', "td3.batch_sise: unknown field (did you mean 'batch_size'?)"),
])
def test_train_config_file_errors_are_one_line(tmp_path, capsys, content, says):
    path = tmp_path / "config.json"
    if content is not None:
        path.write_text(content)
    assert cli.main(["train", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err and str(path) in err


# -------------------------------------------------------------------------------- TensorBoard


def _chunk_log(done: np.ndarray, ret: np.ndarray, cost: np.ndarray, completed: np.ndarray) -> ChunkLog:
    z = np.zeros(done.shape)
    return ChunkLog(done=done, ep_return=ret, ep_cost=cost, ep_length=z + 5, ep_collided=cost > 0,
                    ep_completed=completed, ep_completed_relaxed=completed, ep_end_xy=np.zeros(done.shape + (2,)),
                    metrics={}, nonfinite=np.array(False))


def test_tensorboard_holds_one_value_per_episode_at_its_index(tmp_path):
    cfg = dataclasses.replace(TINY, episodes=5)
    run = RunRecord(cfg, tmp_path, None, checkpoints=None)
    done = np.array([[True, False], [False, False], [True, True]] + [[False, False]] * 7)  # [chunk_steps, envs]
    ret, cost = np.arange(20.0).reshape(10, 2), (np.arange(20) % 3 == 0).reshape(10, 2) * 1.0
    run.record(_chunk_log(done, ret, cost, np.arange(20).reshape(10, 2) % 2 == 1), None)  # episodes 0, 1, 2
    run.record(_chunk_log(done, ret + 100, cost, done), None)  # episodes 3, 4 (cfg.episodes caps it)
    run.tb.close()
    got = tb_scalars(tmp_path / "tb")
    assert got["episode/return"] == [(0, 0.0), (1, 4.0), (2, 5.0), (3, 100.0), (4, 104.0)]
    assert got["episode/cost"] == [(0, 1.0), (1, 0.0), (2, 0.0), (3, 1.0), (4, 0.0)]
    assert got["episode/completed"] == [(0, 0.0), (1, 0.0), (2, 1.0), (3, 1.0), (4, 1.0)]
    assert set(EPISODE_SCALARS) <= set(got)


def test_a_checkpoint_makes_every_scalar_logged_before_it_durable(tmp_path, monkeypatch):
    """tensorboardX queues events for a writer thread, and its flush() writes out only what that
    thread has taken; before a checkpoint the record drains the queue (``durable_tensorboard``), so
    what TensorBoard holds on disk reaches the checkpoint even if the process dies right after it.
    The writer thread is held back here, as a loaded machine does."""
    import threading

    from tensorboardX import event_file_writer

    from d2spo.record import _tensorboard, durable_tensorboard

    slow = threading.Event()
    write = event_file_writer.EventsWriter.write_event

    def held_back(self, event):
        slow.wait(0.002)  # a busy machine: the thread takes events from the queue slowly
        return write(self, event)

    monkeypatch.setattr(event_file_writer.EventsWriter, "write_event", held_back)
    tb = _tensorboard(tmp_path)
    for step in range(300):
        tb.add_scalar("episode/return", float(step), step)
    tb.flush()  # what the record did before: the queue is not drained
    assert len(tb_scalars(tmp_path).get("episode/return", [])) < 300, "the writer thread was not held back"
    tb = durable_tensorboard(tb, tmp_path, 1)
    assert [s for s, _ in tb_scalars(tmp_path)["episode/return"]] == list(range(300))
    tb.add_scalar("episode/return", 300.0, 300)  # it goes on, in a second event file of the same run
    tb = durable_tensorboard(tb, tmp_path, 2)
    assert [s for s, _ in tb_scalars(tmp_path)["episode/return"]] == list(range(301))
    assert len(list(tmp_path.glob("events.out.tfevents.*"))) == 3
    tb.close()


def test_a_resumed_runs_event_files_never_overwrite_the_earlier_sessions_of_the_same_second(tmp_path, monkeypatch):
    """A run resumed within the second its first session opened its event files: the resumed
    session's files get names of their own (they once took the first session's names, truncating
    its first chunks' scalars: tests/test_wandb.py saw TensorBoard start at step 600, W&B at 200)."""
    from _tb import tb_scalars
    from tensorboardX import event_file_writer

    from d2spo.record import _tensorboard, durable_tensorboard

    monkeypatch.setattr(event_file_writer.time, "time", lambda: 1_800_000_000.0)  # one second for all
    for session, steps in enumerate(((0, 1), (2, 3))):
        tb = _tensorboard(tmp_path)
        for part, step in enumerate(steps, start=1):
            tb.add_scalar("charts/label_radius", float(session), step)
            tb = durable_tensorboard(tb, tmp_path, part)
        tb.close()
    assert tb_scalars(tmp_path)["charts/label_radius"] == [(0, 0.0), (1, 0.0), (2, 1.0), (3, 1.0)]
    assert len(list(tmp_path.glob("events.out.tfevents.1800000000.*"))) == 6
