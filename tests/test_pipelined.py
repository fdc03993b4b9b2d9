"""D²SPO's pipelined chunk (d2spo/pipelined.py): the rollout and TD3's updates as two programs run
side by side, one chunk apart, deterministic and resumable as the fused chunk is."""

from __future__ import annotations

import csv
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _tiny import TINY_CBF

from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.pipelined import Pipelined
from d2spo.run import build
from d2spo.train import learner_program, train


def small(pipeline: bool = True, **kw) -> TrainConfig:
    """Tiny networks, 2 envs, chunks of 8 steps, TD3 updating from the 40th transition on: the
    pipelined chunk's gate opens mid-chunk, in the run's third chunk."""
    cfg = TrainConfig(algo="d2spo", task="relaxed", episodes=12, num_envs=2, chunk_steps=8, checkpoint_every=4,
                      eval_episodes=0, env=EnvConfig(layout="relaxed", max_steps=10), cbf=TINY_CBF)
    cfg = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, pretrain=False, update_every=4, pipeline=pipeline),
                              td3=dataclasses.replace(cfg.td3, buffer_size=256, hidden=(8,), batch_size=8,
                                                      learning_starts=40), **kw)
    return cfg.check()


def _same(a, b) -> bool:
    return all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
               for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True))


def test_the_pipeline_is_an_option_off_by_default():
    assert TrainConfig().check().d2spo.pipeline is False
    _, _, learner = build(small(pipeline=False))
    assert not isinstance(learner_program(learner, "chunk", donate=True), Pipelined)
    assert learner_program(learner, "chunk", donate=True) is learner_program(learner, "chunk", donate=True)


@pytest.fixture(scope="module")
def warm():
    """The small learner, its pipelined chunk and a carry three chunks in: past ``learning_starts``
    (2 envs x 8 steps per chunk, 40 transitions). The chunk donates its carry to the rollout, as
    ``train`` runs it, so that the resume test below finds its programs compiled (d2spo.memo); the
    tests give it copies (``fresh``) of a carry they read again."""
    _, _, learner = build(small())
    chunk = learner_program(learner, "chunk", donate=True)
    carry = learner_program(learner, "init")(jax.random.PRNGKey(0))
    for _ in range(3):
        carry, _ = chunk(carry)
    return learner, chunk, carry


@jax.jit
def fresh(carry):
    """A copy of ``carry`` for a program that donates (deletes) its argument."""
    return jax.tree_util.tree_map(jnp.copy, carry)


def test_a_pipelined_chunk_is_its_two_programs_run_one_after_the_other(warm):
    """Threads change nothing: ``Pipelined`` equals td3_batches, then rollout and td3_chunk called in
    turn; the rollout acts with the actor it was given and leaves it as it was, with UPDATE(Ω, Θ) as
    often as the fused chunk; the TD3 updates, as many per chunk as the fused chunk makes, land in
    the carry, their metrics in the log."""
    learner, chunk, carry = warm
    assert isinstance(chunk, Pipelined)
    work = chunk.batches(carry)
    assert bool(jnp.all(work.ready)) and work.keys.shape == (8, 1, *jax.random.PRNGKey(0).shape)
    rolled, rlog = chunk.rollout(fresh(carry))
    assert _same(rolled.agent, carry.agent)
    # UPDATE(Ω, Θ) after every 4th of the 8 steps, as in the fused chunk: 2
    adam_steps = int(rolled.safety.policy_opt[0].count) - int(carry.safety.policy_opt[0].count)
    assert adam_steps == 2 * learner.cbf_cfg.updates_per_iter, adam_steps
    agent, metrics, finite = chunk.learn(work)
    assert bool(finite) and not _same(agent, carry.agent)
    assert int(agent.updates) == int(carry.agent.updates) + 8  # one per vectorised step
    assert np.isnan(np.asarray(rlog.metrics["losses/qf"])).all()
    piped, plog = chunk(fresh(carry))
    assert _same(piped.agent, agent) and _same(piped.safety, rolled.safety) and _same(piped.buffer, rolled.buffer)
    assert np.array_equal(np.asarray(plog.metrics["losses/qf"]), np.asarray(metrics["losses/qf"]))
    assert np.isfinite(np.asarray(plog.metrics["losses/qf"])).all() and not bool(plog.nonfinite)


def test_a_nonfinite_td3_program_marks_the_chunks_log(warm):
    """A NaN in the TD3 program (the other thread) sets the log's ``nonfinite``, which stops a run
    (``record.NaNGuard``) as the fused chunk's does."""
    from d2spo.algos.base import params_finite

    learner, chunk, carry = warm

    def poisoned(work):
        agent, metrics, _ = chunk.learn(work)
        agent = agent.replace(critic=jax.tree_util.tree_map(lambda x: x * jnp.nan, agent.critic))
        return agent, metrics, params_finite(agent)

    parts = {"td3_batches": chunk.batches, "rollout": chunk.rollout, "td3_chunk": poisoned}
    _, log = Pipelined(lambda name, donate: parts[name], donate=False)(fresh(carry))
    assert bool(log.nonfinite)


def test_the_pipeline_makes_the_fused_chunks_updates_one_chunk_later(warm):
    """As many TD3 updates per chunk as the fused chunk makes: one per vectorised step t once
    t x num_envs >= learning_starts (40 transitions: t >= 20, so 5 in the third chunk's steps 17-24
    and 8 in each after), drawn from the buffer one chunk earlier."""
    learner, chunk, _ = warm
    carry = learner_program(learner, "init")(jax.random.PRNGKey(3))
    updates = []
    for _ in range(4):
        carry, _ = chunk(carry)
        updates.append(int(carry.agent.updates))
    assert updates == [0, 0, 5, 13]


def _episodes(path):
    with open(path / "episodes.csv") as f:
        return list(csv.reader(f))


def test_a_pipelined_run_resumes_exactly(tmp_path, warm):
    """Interrupted after three chunks and resumed, a pipelined run writes the episodes.csv of an
    uninterrupted one (its checkpoints hold the whole carry: the rollout's and TD3's parts)."""
    cfg = small()
    assert train(cfg, tmp_path / "a")["episodes"] == 12
    assert train(cfg, tmp_path / "b", stop_after_chunks=3) is None
    assert 1 < len(_episodes(tmp_path / "b")) < 13
    train(cfg, tmp_path / "b", resume=True)
    assert _episodes(tmp_path / "a") == _episodes(tmp_path / "b")
    train(dataclasses.replace(cfg, seed=1), tmp_path / "c")
    assert _episodes(tmp_path / "a") != _episodes(tmp_path / "c")  # another seed, another run
