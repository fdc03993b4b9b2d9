"""GAE and discounted sums against hand-computed values and a plain-Python reference loop."""

import numpy as np
import pytest

from d2spo.algos.common.gae import gae


def reference_gae(rewards, values, dones, last_value, gamma, lam, truncated=None, bootstrap=None):
    """Direct per-env, per-step loop (float64)."""
    T, N = rewards.shape
    adv = np.zeros((T, N))
    for n in range(N):
        running = 0.0
        for t in reversed(range(T)):
            trunc = truncated is not None and truncated[t, n]
            if trunc:
                next_v = bootstrap[t, n]
            elif dones[t, n]:
                next_v = 0.0
            else:
                next_v = values[t + 1, n] if t + 1 < T else last_value[n]
            delta = rewards[t, n] + gamma * next_v - values[t, n]
            if dones[t, n] or trunc:
                running = 0.0
            running = delta + gamma * lam * running
            adv[t, n] = running
    return adv, adv + values


def test_gae_hand_computed_with_done_in_the_middle():
    # gamma = 0.9, lam = 0.8, so gamma * lam = 0.72.
    # delta = [1 + .9*1 - .5, 2 - 1 (done), 3 + .9*2 - 1.5, 4 + .9*3 - 2] = [1.4, 1.0, 3.3, 4.7]
    # A3 = 4.7; A2 = 3.3 + .72*4.7 = 6.684; A1 = 1.0 (trace cut); A0 = 1.4 + .72*1.0 = 2.12
    rewards = np.array([[1.0], [2.0], [3.0], [4.0]])
    values = np.array([[0.5], [1.0], [1.5], [2.0]])
    dones = np.array([[0], [1], [0], [0]])
    adv, ret = gae(rewards, values, dones, np.array([3.0]), gamma=0.9, lam=0.8)
    np.testing.assert_allclose(np.asarray(adv)[:, 0], [2.12, 1.0, 6.684, 4.7], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(ret)[:, 0], [2.62, 2.0, 8.184, 6.7], rtol=1e-6)


def test_gae_done_on_last_step_ignores_last_value():
    # gamma = lam = 1, zero values: returns are the undiscounted reward-to-go of the episode.
    adv, ret = gae(np.ones((3, 1)), np.zeros((3, 1)), np.array([[0], [0], [1]]), np.array([100.0]), 1.0, 1.0)
    np.testing.assert_allclose(np.asarray(ret)[:, 0], [3.0, 2.0, 1.0])
    np.testing.assert_allclose(np.asarray(adv), np.asarray(ret))


def test_gae_truncation_bootstraps_from_final_value_but_cuts_trace():
    # gamma = 0.5, lam = 1. Step 1 is truncated with V(final obs) = 10; last_value = 5.
    # delta = [1 + 0, 1 + .5*10, 1 + .5*5] = [1, 6, 3.5]; A = [1 + .5*6, 6, 3.5]
    adv, _ = gae(
        np.ones((3, 1)), np.zeros((3, 1)), np.array([[0], [1], [0]]), np.array([5.0]), 0.5, 1.0,
        truncated=np.array([[0], [1], [0]]), bootstrap_values=np.array([[0.0], [10.0], [0.0]]),
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(adv)[:, 0], [4.0, 6.0, 3.5])


def test_gae_truncated_needs_bootstrap_values():
    with pytest.raises(ValueError, match="bootstrap_values"):
        gae(np.ones((2, 1)), np.zeros((2, 1)), np.zeros((2, 1)), np.zeros(1), 0.9, 0.9, truncated=np.zeros((2, 1)))


@pytest.mark.parametrize("with_truncation", [False, True])
def test_gae_matches_reference_loop_on_random_data(with_truncation):
    rng = np.random.default_rng(0)
    T, N = 37, 5
    rewards = rng.normal(size=(T, N))
    values = rng.normal(size=(T, N))
    dones = rng.random((T, N)) < 0.15
    last_value = rng.normal(size=N)
    kwargs = {}
    truncated = bootstrap = None
    if with_truncation:
        truncated = (rng.random((T, N)) < 0.1) & ~dones
        bootstrap = rng.normal(size=(T, N))
        kwargs = {"truncated": truncated, "bootstrap_values": bootstrap}
    adv, ret = gae(rewards, values, dones, last_value, 0.97, 0.9, **kwargs)
    ref_adv, ref_ret = reference_gae(rewards, values, dones, last_value, 0.97, 0.9, truncated, bootstrap)
    np.testing.assert_allclose(np.asarray(adv), ref_adv, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(np.asarray(ret), ref_ret, rtol=1e-4, atol=1e-5)

