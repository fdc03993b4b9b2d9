"""The device ring buffer: ring order, masked and oversized adds, size tracking, sampling of filled rows
only, jit; and the same masked write in the *-lag cost window."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo import replay
from d2spo.replay import ReplayBuffer, Transition


def _batch(values):
    v = jnp.asarray(values, jnp.float32)
    return {"x": v, "obs": jnp.stack([v, -v, 2 * v], axis=-1), "flag": v > 2}


def test_create_shapes_and_dtypes():
    example = {
        "x": jnp.float32(0),
        "obs": jnp.zeros(3),
        "flag": jnp.bool_(False),
        "q": jax.ShapeDtypeStruct((), jnp.int32),
    }
    buf = ReplayBuffer.create(7, example)
    assert buf.data["obs"].shape == (7, 3) and buf.data["x"].shape == (7,)
    assert buf.data["flag"].dtype == jnp.bool_ and buf.data["q"].dtype == jnp.int32
    assert int(buf.size) == 0 and not bool(buf.full)


def test_add_batch_wraps_around_in_ring_order():
    buf = ReplayBuffer.create(5, {"x": jnp.float32(0), "obs": jnp.zeros(3), "flag": jnp.bool_(False)})
    add = jax.jit(replay.add_batch)
    buf = add(buf, _batch([0, 1]))
    assert int(buf.size) == 2 and int(buf.ptr) == 2 and not bool(buf.full)
    buf = add(buf, _batch([2, 3]))
    buf = add(buf, _batch([4, 5]))  # rows 4 and 0
    np.testing.assert_array_equal(np.asarray(buf.data["x"]), [5, 1, 2, 3, 4])
    np.testing.assert_array_equal(np.asarray(buf.data["obs"][0]), [5, -5, 10])
    np.testing.assert_array_equal(np.asarray(buf.data["flag"]), [True, False, False, True, True])
    assert int(buf.size) == 5 and int(buf.ptr) == 1 and bool(buf.full)
    buf = replay.add(buf, {"x": 6.0, "obs": jnp.ones(3), "flag": True})
    np.testing.assert_array_equal(np.asarray(buf.data["x"]), [5, 6, 2, 3, 4])
    assert int(buf.ptr) == 2 and int(buf.size) == 5


def test_sample_draws_only_filled_rows():
    buf = ReplayBuffer.create(10, {"x": jnp.float32(0), "obs": jnp.zeros(3), "flag": jnp.bool_(False)})
    buf = replay.add_batch(buf, _batch([1, 2, 3]))
    sample = jax.jit(replay.sample, static_argnums=2)
    batch = sample(buf, jax.random.PRNGKey(0), 600)
    assert batch["x"].shape == (600,) and batch["obs"].shape == (600, 3)
    assert set(np.asarray(batch["x"]).tolist()) == {1.0, 2.0, 3.0}
    np.testing.assert_array_equal(np.asarray(batch["obs"][:, 1]), -np.asarray(batch["x"]))  # rows stay aligned
    other = sample(buf, jax.random.PRNGKey(1), 600)
    assert not np.array_equal(np.asarray(batch["x"]), np.asarray(other["x"]))


def test_buffer_is_a_scan_carry_with_transitions():
    example = Transition(jnp.zeros(2), jnp.zeros(1), 0.0, 0.0, jnp.zeros(2), 0.0, extras={"q": jnp.int32(0)})
    buf = ReplayBuffer.create(8, example)

    def step(b, t):
        n = 3
        tr = Transition(
            obs=jnp.full((n, 2), t, jnp.float32),
            action=jnp.zeros((n, 1)),
            reward=jnp.full((n,), t, jnp.float32),
            cost=jnp.zeros(n),
            next_obs=jnp.zeros((n, 2)),
            done=jnp.zeros(n),
            extras={"q": jnp.full((n,), t, jnp.int32)},
        )
        return replay.add_batch(b, tr), None

    buf, _ = jax.jit(lambda b: jax.lax.scan(step, b, jnp.arange(4)))(buf)
    # Step t writes rows 3t..3t+2 mod 8: step 1 -> 3, 4, 5; step 2 -> 6, 7, 0; step 3 -> 1, 2, 3.
    np.testing.assert_array_equal(np.asarray(buf.data.reward), [2, 3, 3, 3, 1, 1, 2, 2])
    assert buf.data.extras["q"].dtype == jnp.int32 and int(buf.size) == 8 and int(buf.ptr) == 4
    batch = replay.sample(buf, jax.random.PRNGKey(0), 5)
    assert isinstance(batch, Transition) and batch.obs.shape == (5, 2) and batch.extras["q"].shape == (5,)


def test_masked_and_oversized_adds_keep_the_newest_selected_rows():
    buf = ReplayBuffer.create(3, jnp.zeros(()))
    buf = replay.add_batch(buf, jnp.array([1.0, 2.0, 3.0, 4.0]), jnp.array([True, False, True, False]))
    assert int(buf.size) == 2 and int(buf.ptr) == 2
    np.testing.assert_array_equal(np.asarray(buf.data[:2]), [1.0, 3.0])
    buf = jax.jit(replay.add_batch)(buf, jnp.arange(10.0, 17.0), jnp.ones(7, bool))  # 7 rows into capacity 3
    assert int(buf.size) == 3 and int(buf.ptr) == 0
    np.testing.assert_array_equal(np.asarray(buf.data), [14.0, 15.0, 16.0])  # the last 3, in ring order
    buf = replay.add_batch(buf, jnp.array([20.0, 21.0]), jnp.zeros(2, bool))  # nothing selected: unchanged
    assert int(buf.size) == 3 and int(buf.ptr) == 0
    np.testing.assert_array_equal(np.asarray(buf.data), [14.0, 15.0, 16.0])


def test_add_batch_rejects_bad_shapes():
    buf = ReplayBuffer.create(4, {"obs": jnp.zeros(3)})
    with pytest.raises(ValueError, match="does not match"):
        replay.add_batch(buf, {"obs": jnp.zeros((2,))})
    with pytest.raises(ValueError, match="positive int"):
        ReplayBuffer.create(0, {"obs": jnp.zeros(3)})
