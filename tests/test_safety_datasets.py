"""The datasets of Sec. IV-A/B: weighted sampling, the P_exp filter, and the synthesised unsafe ring X_L."""

import jax
import jax.numpy as jnp
import numpy as np

from d2spo import replay
from d2spo.replay import ReplayBuffer
from d2spo.safety.cbf import CBFConfig
from d2spo.safety.datasets import (
    Transition,
    in_p_exp,
    init_safety_data,
    synthesize_unsafe,
    synthetic_pretrain_data,
    update_datasets,
    weighted_sample,
)

H = 1.0
CFG = CBFConfig(transitions_capacity=64, p_exp_capacity=64, unsafe_capacity=64)  # ring [0.1, 0.2], d = 0.3


def clearance_features(pose, ctx):
    """Toy b(z, O_s): distance from the robot's centre to each disk's surface, clipped at H.

    ctx = (centres [M, 2], radii [M], sensed [M]); unsensed disks read H.
    """
    centres, radii, sensed = ctx
    dist = jnp.linalg.norm(pose[:2] - centres, axis=-1) - radii
    return jnp.where(sensed, jnp.clip(dist, 0.0, H), H)


def _ctx(n=None):
    ctx = (jnp.array([[0.0, 0.0], [2.0, 0.0]]), jnp.array([0.3, 0.5]), jnp.array([True, True]))
    return ctx if n is None else jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), ctx)


def test_weighted_sample_draws_stored_items_and_flags_an_empty_buffer():
    buf = ReplayBuffer.create(8, jnp.zeros(()))
    _, w = weighted_sample(buf, jax.random.PRNGKey(0), 4)
    assert float(w.sum()) == 0.0
    buf = replay.add_batch(buf, jnp.array([5.0, 7.0]))
    items, w = weighted_sample(buf, jax.random.PRNGKey(0), 64)
    assert set(np.asarray(items).tolist()) <= {5.0, 7.0} and float(w.min()) == 1.0


def test_p_exp_is_min_range_at_least_d():
    x = jnp.array([[0.5, 0.3], [0.29, 1.0], [1.0, 1.0]])
    np.testing.assert_array_equal(np.asarray(in_p_exp(x, 0.3)), [True, False, True])


def test_synthesised_unsafe_samples_lie_in_the_ring():
    n = 256
    poses = jax.random.uniform(jax.random.PRNGKey(0), (n, 3), minval=-1.2, maxval=1.2)
    lo, hi = CFG.unsafe_max - CFG.sigma, CFG.unsafe_max
    x, pose_u, ok = jax.vmap(lambda k, p, c: synthesize_unsafe(k, p, c, clearance_features, lo, hi))(
        jax.random.split(jax.random.PRNGKey(1), n), poses, _ctx(n))
    ok, m = np.asarray(ok), np.asarray(x.min(-1))
    assert ok.mean() > 0.8  # every pose sees a disk within H = 1 except the far ones
    assert np.all((m[ok] >= lo) & (m[ok] <= hi))
    # the features really are those of the returned pose, and the true clearance is in the ring
    np.testing.assert_allclose(jax.vmap(clearance_features)(pose_u, _ctx(n)), x, atol=1e-6)
    # poses with nothing in range cannot be moved into the ring and are flagged invalid
    far = jnp.array([10.0, 10.0, 0.0])
    _, _, ok_far = synthesize_unsafe(jax.random.PRNGKey(2), far, _ctx(), clearance_features, lo, hi)
    assert not bool(ok_far)


def test_update_datasets_routes_transitions():
    # clearances 0.5, 0.15, 0.25 and nothing in range
    poses = jnp.array([[0.0, 0.8, 0.0], [0.0, 0.45, 0.0], [0.0, 0.55, 0.0], [5.0, 5.0, 0.0]])
    n = poses.shape[0]
    tr = Transition(pose=poses, next_pose=poses + 0.01, context=_ctx(n), obs=jnp.zeros((n, 4)),
                    action=jnp.zeros((n, 2)), u_rl=jnp.zeros((n, 2)))
    example = jax.tree_util.tree_map(lambda a: a[0], tr)
    data = init_safety_data(CFG, example, n_features=2)
    step = jax.jit(lambda d, k, t, m: update_datasets(d, k, t, features_fn=clearance_features, cfg=CFG, mask=m))
    data, stats = step(data, jax.random.PRNGKey(0), tr, jnp.array([True, True, True, False]))
    assert int(data.transitions.size) == 3
    # P_exp uses min range ≥ unsafe_max = 0.2 by default (te_in_band): clearances 0.5 and 0.25
    assert int(data.p_exp.size) == 2
    np.testing.assert_allclose(data.p_exp.data.pose[:2, 1], [0.8, 0.55])
    assert int(stats["safety/added_unsafe"]) == int(data.unsafe.size) >= 2
    m = np.asarray(data.unsafe.data[: int(data.unsafe.size)].min(-1))
    assert np.all((m >= 0.1) & (m <= 0.2))


def test_paper_p_exp_threshold_is_d():
    import dataclasses

    cfg = dataclasses.replace(CFG, te_in_band=False)
    poses = jnp.array([[0.0, 0.8, 0.0], [0.0, 0.55, 0.0]])  # clearance 0.5 and 0.25 < d = 0.3
    tr = Transition(pose=poses, next_pose=poses, context=_ctx(2), obs=jnp.zeros((2, 1)),
                    action=jnp.zeros((2, 2)), u_rl=jnp.zeros((2, 2)))
    data = init_safety_data(cfg, jax.tree_util.tree_map(lambda a: a[0], tr), n_features=2)
    data, _ = update_datasets(data, jax.random.PRNGKey(0), tr, features_fn=clearance_features, cfg=cfg)
    assert int(data.p_exp.size) == 1


def test_synthetic_pretrain_data_labels():
    def sample(key):
        return jax.random.uniform(key, (3,), minval=-1.5, maxval=1.5), _ctx()

    data = synthetic_pretrain_data(jax.random.PRNGKey(0), clearance_features, sample, 512, cfg=CFG)
    m = np.asarray(data.x.min(-1))
    np.testing.assert_array_equal(np.asarray(data.safe), m >= CFG.d)
    mu = np.asarray(data.x_unsafe.min(-1))[np.asarray(data.unsafe_valid)]
    assert mu.size > 256 and np.all((mu >= 0.1) & (mu <= 0.2))
