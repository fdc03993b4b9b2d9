"""A checkpoint's state file is flax's msgpack, written array by array from the arrays' own memory
(d2spo/checkpoint.py, ``state_parts``): byte for byte ``flax.serialization.to_bytes``, checksummed
as written, and never left half-written when a part fails."""

from __future__ import annotations

import hashlib
import json

import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization, struct

from d2spo import checkpoint
from d2spo.checkpoint import Checkpoints, state_parts

META = {"episodes": 3, "env_steps": 30, "chunks": 1, "wall_seconds": 0.5}


@struct.dataclass
class Carry:
    buffer: dict
    agent: tuple
    steps: jnp.ndarray


def _mixed() -> Carry:
    """Every kind of leaf a learner's carry or a group's state holds, either side of the size above
    which an array is written from its own memory (64 KiB)."""
    small = checkpoint._STREAMED_BYTES
    return Carry(
        buffer={"obs": np.arange(300 * 35, dtype=np.float32).reshape(300, 35),
                "big": jnp.linspace(0.0, 1.0, 100_000, dtype=jnp.float32).reshape(1000, 100),
                "edge_below": np.ones(small - 1, np.uint8), "edge": np.ones(small, np.uint8),
                "flags": np.arange(70_000) % 3 == 0, "half": jnp.ones((300, 300), jnp.bfloat16),
                "fortran": np.asfortranarray(np.arange(20_000.0).reshape(200, 100)),
                "empty": np.zeros((0, 3), np.float32), "nested": {}},
        agent=(jnp.int32(7), np.float32(2.5), {"w": np.full((256, 256), -1.5, np.float32)}),
        steps=jnp.asarray(12, jnp.int32))


def test_the_parts_are_flaxs_bytes_for_every_kind_of_leaf():
    state = _mixed()
    parts = list(state_parts(state))
    assert b"".join(bytes(p) for p in parts) == serialization.to_bytes(state)
    # the large arrays are views of their memory, not copies joined into one buffer
    assert sum(isinstance(p, memoryview) for p in parts) == 6  # big, edge, flags, half, fortran, w


def test_a_save_writes_those_bytes_with_their_size_and_checksum_and_loads_them_back(tmp_path):
    state = _mixed()
    Checkpoints(tmp_path, "c" * 64).save(state, META)
    manifest = json.loads((tmp_path / "checkpoint.json").read_text())
    data = (tmp_path / manifest["state"]).read_bytes()
    assert data == serialization.to_bytes(state)
    assert manifest["state_bytes"] == len(data) and manifest["state_sha256"] == hashlib.sha256(data).hexdigest()
    loaded, meta = Checkpoints(tmp_path, "c" * 64).load(state)
    assert meta == META
    for a, b in zip(serialization.to_state_dict(loaded).values(), serialization.to_state_dict(state).values(),
                    strict=True):
        assert serialization.msgpack_serialize(a) == serialization.msgpack_serialize(b)


def test_a_part_that_fails_leaves_no_file_and_the_last_checkpoint_standing(tmp_path, monkeypatch):
    state = _mixed()
    cps = Checkpoints(tmp_path, "c" * 64)
    cps.save(state, META)
    before = sorted(p.name for p in tmp_path.iterdir())

    def failing(s):
        yield next(state_parts(s))
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(checkpoint, "state_parts", failing)
    with pytest.raises(OSError, match="No space left"):
        cps.save(state, dict(META, episodes=6))
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no temporary, no new state, no new manifest
    monkeypatch.undo()
    _, meta = Checkpoints(tmp_path, "c" * 64).load(state)
    assert meta == META
