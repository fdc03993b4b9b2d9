"""Faults a hostile user can cause, each of which once ended in a wrong result with exit 0 or in a
traceback: an interrupted `reproduce`, hyper-parameters out of range, bad `eval` counts, a rejected
`train` writing to --out, unbounded work (long ordered tasks, huge arenas, deep formulas)."""

from __future__ import annotations

import csv
import dataclasses
import re

import pytest

from d2spo import reproduce as rp
from d2spo import train as train_mod

TINY_EPISODES = 24


def _table(path) -> str:
    """A table without its wall-time column (the only thing that may differ between two runs)."""
    text = path.read_text()
    if path.suffix == ".csv":
        rows = list(csv.DictReader(text.splitlines()))
        return "\n".join(str({k: v for k, v in r.items() if k != "wall_seconds_mean"}) for r in rows)
    return re.sub(r"\| [^|]* \|\n", "|\n", text)  # the last column of every row


def test_interrupted_reproduce_resumes_its_seed_group_exactly(tmp_path, monkeypatch):
    """Two seeds trained as one vmapped group, stopped in their third chunk after the group and each
    seed had checkpointed: the rerun resumes the group (not each seed alone from its own checkpoint),
    so the tables are those of an uninterrupted run, and the group directory is removed."""
    config = rp.RunSpec.config

    def small(spec):  # checkpoints every 10 episodes, so the group and each seed checkpoint mid-run
        c = config(spec)
        ppo = dataclasses.replace(c.ppo_lag, hidden=(16, 16), rollout_steps=50, n_minibatches=4, epochs=2)
        return dataclasses.replace(c, checkpoint_every=10, num_envs=4, chunk_steps=50, eval_episodes=4,
                                   env=dataclasses.replace(c.env, max_steps=40), ppo_lag=ppo)

    monkeypatch.setattr(rp.RunSpec, "config", small)
    kw = dict(seeds=2, episodes=TINY_EPISODES, methods=["ppo-lag"], progress=False, log=lambda s: None)
    rp.reproduce(["table3"], tmp_path / "a", **kw)

    record, calls = train_mod._Run.record, []

    def killed_in_chunk_3(run, log, progress):
        calls.append(run)
        if len(calls) == 5:  # the third chunk
            raise KeyboardInterrupt
        record(run, log, progress)

    monkeypatch.setattr(train_mod._Run, "record", killed_in_chunk_3)
    with pytest.raises(KeyboardInterrupt):
        rp.reproduce(["table3"], tmp_path / "b", **kw)
    monkeypatch.setattr(train_mod._Run, "record", record)
    runs = tmp_path / "b" / "runs"
    assert len(list(runs.glob(".group-*/checkpoint.json"))) == 1
    assert list(runs.glob("ppo-lag-*/checkpoint.json"))  # what made a seed resume alone, the other restart
    rp.reproduce(["table3"], tmp_path / "b", **kw)
    for name in ("table3.md", "table3.csv"):
        assert _table(tmp_path / "b" / name) == _table(tmp_path / "a" / name), name
    for spec in rp.runs_for("table3", 2, TINY_EPISODES, ["ppo-lag"]):
        a, b = rp.run_dir(tmp_path / "a", spec), rp.run_dir(tmp_path / "b", spec)
        assert (a / "episodes.csv").read_bytes() == (b / "episodes.csv").read_bytes()
    assert not list(runs.glob(".group-*")), "the group directory is removed"


def test_a_finished_groups_leftover_directory_is_removed(tmp_path):
    (spec0, spec1) = rp.runs_for("table3", 2, TINY_EPISODES, ["ppo-lag"])
    for s in (spec0, spec1):
        rp.run_dir(tmp_path, s).mkdir(parents=True)
        (rp.run_dir(tmp_path, s) / "summary.json").write_text("{}")
    group = train_mod.group_dir([rp.run_dir(tmp_path, spec0), rp.run_dir(tmp_path, spec1)])
    group.mkdir()
    (group / "checkpoint.msgpack").write_bytes(b"x" * 1000)
    assert rp.started_groups(tmp_path, [spec0, spec1]) == [] and not group.exists()
