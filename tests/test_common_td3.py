"""TD3 losses on hand-made numbers with mocked apply functions; smoothing noise; Polyak update."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.algos.common.td3_losses import (
    cost_critic_loss,
    soft_update,
    target_policy_action,
    td3_actor_loss,
    td3_critic_loss,
)
from d2spo.replay import Transition


def actor_apply(p, s):  # pi(s) = p * s, 1-D actions
    return p * s


def critic_apply(p, s, a):  # Q1 = p0 * s + a, Q2 = p1 * s + 2 a  -> [2, B]
    return jnp.stack([p[0] * s[:, 0] + a[:, 0], p[1] * s[:, 0] + 2.0 * a[:, 0]])


def make_batch(action, reward, done, cost=(0.0, 0.0)):
    return Transition(
        obs=jnp.array([[1.0], [1.0]]),
        action=jnp.array(action)[:, None],
        reward=jnp.array(reward),
        cost=jnp.array(cost),
        next_obs=jnp.array([[0.5], [2.0]]),
        done=jnp.array(done, jnp.float32),
    )


ONLINE = jnp.array([0.0, 1.0])
TARGET = jnp.array([0.75, 0.0])
# Target actor p = 1: pi'(s') = [0.5, 2.0] -> clipped to [0.5, 1.0] (noise off).
# Target critics: Q'1 = .75 s' + a = [0.875, 2.5]; Q'2 = 0 s' + 2 a = [1.0, 2.0]; min = [0.875, 2.0].


def _critic_loss(batch, **kw):
    return td3_critic_loss(
        ONLINE, TARGET, 1.0, batch, jax.random.PRNGKey(0), 0.9, 0.0, 0.5, actor_apply, critic_apply, **kw
    )


def test_td3_critic_loss_hand_computed():
    # y = r + .9 min = [1 + .7875, -1 + 1.8] = [1.7875, 0.8]
    # Q1(s, a) = a = [0.2, -0.4]; Q2 = 1 + 2a = [1.4, 0.2]
    # loss = mean(1.5875^2, 1.2^2) + mean(0.3875^2, 0.6^2) = 1.980078125 + 0.255078125
    loss, metrics = _critic_loss(make_batch([0.2, -0.4], [1.0, -1.0], [0, 0]))
    assert float(loss) == pytest.approx(2.23515625, rel=1e-6)
    assert float(metrics["values/q_target"]) == pytest.approx((1.7875 + 0.8) / 2, rel=1e-6)


def test_td3_critic_loss_does_not_bootstrap_on_done():
    # y = [1.7875, -1]; Q1 = [0.2, 0.3], Q2 = [1.4, 1.6]
    # loss = mean(1.5875^2, 1.3^2) + mean(0.3875^2, 2.6^2) = 2.105078125 + 3.455078125
    loss, _ = _critic_loss(make_batch([0.2, 0.3], [1.0, -1.0], [0, 1]))
    assert float(loss) == pytest.approx(5.56015625, rel=1e-6)


def test_td3_critic_gradient_does_not_reach_target():
    batch = make_batch([0.2, -0.4], [1.0, -1.0], [0, 0])
    def loss(online, target):
        key = jax.random.PRNGKey(0)
        return td3_critic_loss(online, target, 1.0, batch, key, 0.9, 0.0, 0.5, actor_apply, critic_apply)[0]

    g_online, g_target = jax.grad(loss, argnums=(0, 1))(ONLINE, TARGET)
    assert np.all(np.asarray(g_target) == 0.0) and np.any(np.asarray(g_online) != 0.0)


def test_cost_critic_loss_uses_cost_and_pessimistic_max():
    # y_c = c + .9 max(Q'1, Q'2) = [0.5 + .9*1.0, 0 + .9*2.5] = [1.4, 2.25]
    # Q1 = [0.2, -0.4], Q2 = [1.4, 0.2]: loss = mean(1.2^2, 2.65^2) + mean(0, 2.05^2) = 4.23125 + 2.10125
    batch = make_batch([0.2, -0.4], [100.0, 100.0], [0, 0], cost=[0.5, 0.0])
    args = (ONLINE, TARGET, 1.0, batch, jax.random.PRNGKey(0), 0.9, 0.0, 0.5, actor_apply, critic_apply)
    loss, metrics = cost_critic_loss(*args)
    assert float(loss) == pytest.approx(6.3325, rel=1e-6)
    assert float(metrics["values/qc_target"]) == pytest.approx((1.4 + 2.25) / 2, rel=1e-6)
    # 'min' gives y_c = [0.5 + .7875, 1.8]
    _, metrics_min = cost_critic_loss(*args, reduce="min")
    assert float(metrics_min["values/qc_target"]) == pytest.approx((1.2875 + 1.8) / 2, rel=1e-6)


def test_target_smoothing_noise_is_clipped():
    next_obs = jnp.zeros((4000, 2))
    key = jax.random.PRNGKey(3)
    # Huge noise around pi'(s') = 0: every coordinate lands within [-c, c] and almost all on the bound.
    a = target_policy_action(key, 0.0, next_obs, actor_apply, policy_noise=100.0, noise_clip=0.3)
    assert float(jnp.max(jnp.abs(a))) <= 0.3 + 1e-7
    assert float(jnp.mean(jnp.isclose(jnp.abs(a), 0.3))) > 0.95
    # Moderate noise is applied with roughly the requested scale (clipping at 2.5 sigma trims a little).
    a = target_policy_action(key, 0.0, next_obs, actor_apply, policy_noise=0.2, noise_clip=0.5)
    assert 0.18 < float(jnp.std(a)) < 0.21
    # The smoothed action is clipped to the action box.
    a = target_policy_action(key, 1.0, jnp.full((4000, 2), 0.9), actor_apply, policy_noise=0.2, noise_clip=0.5)
    assert float(jnp.max(a)) == 1.0 and float(jnp.min(a)) >= 0.4 - 1e-6


def test_td3_actor_loss_and_penalty_hook():
    obs = jnp.array([[1.0], [2.0]])
    critic = jnp.array([1.0, 5.0])
    # pi(s) = .5 s = [.5, 1]; Q1 = s + a = [1.5, 3]; loss = -2.25
    loss, metrics = td3_actor_loss(0.5, critic, obs, actor_apply, critic_apply)
    assert float(loss) == pytest.approx(-2.25)
    # TD3-Lag style penalty 2 * a: mean = 1.5 -> loss = -0.75
    penalty = lambda s, a: 2.0 * a[:, 0]
    loss, metrics = td3_actor_loss(0.5, critic, obs, actor_apply, critic_apply, penalty_fn=penalty)
    assert float(loss) == pytest.approx(-0.75) and float(metrics["values/actor_penalty"]) == pytest.approx(1.5)
    # d/dp mean(-(s + p s) + 2 p s) = mean(s) = 1.5: the gradient flows through pi into Q1 only.
    grad = jax.grad(lambda p: td3_actor_loss(p, critic, obs, actor_apply, critic_apply, penalty_fn=penalty)[0])(0.5)
    assert float(grad) == pytest.approx(1.5)


def test_soft_update_is_exact_polyak():
    target = {"a": jnp.array([1.0, 2.0]), "b": jnp.float32(3.0)}
    online = {"a": jnp.array([3.0, 6.0]), "b": jnp.float32(-1.0)}
    out = soft_update(target, online, 0.25)
    np.testing.assert_array_equal(np.asarray(out["a"]), [1.5, 3.0])
    assert float(out["b"]) == 2.0
    np.testing.assert_array_equal(np.asarray(soft_update(target, online, 1.0)["a"]), [3.0, 6.0])
    np.testing.assert_array_equal(np.asarray(soft_update(target, online, 0.0)["a"]), [1.0, 2.0])



def test_actor_loss_through_a_safety_layer():
    """With execute_fn the critic sees the executed action and the gradient flows through the layer;
    the proposal penalty pulls the proposal toward what the layer lets through."""
    obs = jnp.array([[1.0], [2.0]])
    critic = jnp.array([0.0, 0.0])  # Q1 = a
    # identity layer, no penalty: the plain loss
    plain, _ = td3_actor_loss(0.3, critic, obs, actor_apply, critic_apply)
    same, _ = td3_actor_loss(0.3, critic, obs, actor_apply, critic_apply, None, lambda s, u: u, 1.0)
    assert float(plain) == pytest.approx(float(same))
    # a layer that halves the action: Q1 = 0.5 p s, override = (0.5 p s)^2
    halve = lambda s, u: 0.5 * u
    loss, m = td3_actor_loss(0.3, critic, obs, actor_apply, critic_apply, None, halve, 2.0)
    s = np.array([1.0, 2.0])
    expected = np.mean(-0.5 * 0.3 * s + 2.0 * (0.5 * 0.3 * s) ** 2)
    assert float(loss) == pytest.approx(expected, rel=1e-6)
    assert float(m["values/actor_override"]) == pytest.approx(np.mean((0.15 * s) ** 2), rel=1e-6)
    grad = jax.grad(lambda p: td3_actor_loss(p, critic, obs, actor_apply, critic_apply, None, halve, 2.0)[0])(0.2)
    expected_grad = np.mean(-0.5 * s + 2.0 * 2 * 0.25 * 0.2 * s**2)
    assert float(grad) == pytest.approx(expected_grad, rel=1e-5)
    # a layer that ignores the proposal: only the penalty moves the actor, toward the executed action
    block = lambda s, u: jnp.zeros_like(u)
    g = jax.grad(lambda p: td3_actor_loss(p, critic, obs, actor_apply, critic_apply, None, block, 1.0)[0])(0.3)
    assert float(g) > 0  # shrinking p moves pi(s) = p s toward 0


def test_the_smoothness_term_penalises_the_proposals_change_to_the_next_observation():
    """``smoothness * ||pi(s') - pi(s)||²``, hand-computed: with pi(s) = p s the term is
    smoothness * p² (s' - s)², and its gradient pulls p toward 0; off (0) the loss is the plain one."""
    obs, nxt = jnp.array([[1.0], [2.0]]), jnp.array([[2.0], [2.0]])
    critic = jnp.array([0.0, 0.0])  # Q1 = a
    plain, _ = td3_actor_loss(0.5, critic, obs, actor_apply, critic_apply)
    off, m_off = td3_actor_loss(0.5, critic, obs, actor_apply, critic_apply, next_obs=nxt, smoothness=0.0)
    assert float(off) == float(plain) and "values/actor_jerk" not in m_off
    loss, m = td3_actor_loss(0.5, critic, obs, actor_apply, critic_apply, next_obs=nxt, smoothness=3.0)
    s, s2 = np.array([1.0, 2.0]), np.array([2.0, 2.0])
    jerk = (0.5 * (s2 - s)) ** 2  # [0.25, 0]
    assert float(m["values/actor_jerk"]) == pytest.approx(jerk.mean())
    assert float(loss) == pytest.approx(np.mean(-0.5 * s + 3.0 * jerk))
    grad = jax.grad(lambda p: td3_actor_loss(p, critic, obs, actor_apply, critic_apply, next_obs=nxt,
                                             smoothness=3.0)[0])(0.5)
    assert float(grad) == pytest.approx(np.mean(-s + 3.0 * 2 * 0.5 * (s2 - s) ** 2))
    # ``smoothness_dims``: only those action dimensions count (2-D actions pi(s) = p s)
    obs2, nxt2 = jnp.array([[1.0, 1.0]]), jnp.array([[2.0, 3.0]])  # changes p * [1, 2]
    both = td3_actor_loss(1.0, critic, obs2, actor_apply, critic_apply, next_obs=nxt2, smoothness=1.0)[1]
    turn = td3_actor_loss(1.0, critic, obs2, actor_apply, critic_apply, next_obs=nxt2, smoothness=1.0,
                          smoothness_dims=(1,))[1]
    assert float(both["values/actor_jerk"]) == 5.0 and float(turn["values/actor_jerk"]) == 4.0


def test_target_smoothing_stays_in_the_actors_box():
    """A forward-only actor's target action is clipped at its own low bound, not at -1."""
    obs = jnp.full((256, 1), -0.2)  # pi'(s') = -0.2 with p = 1: below the box [0, 1]
    a = target_policy_action(jax.random.PRNGKey(3), 1.0, obs, actor_apply, 0.3, 0.5, low=0.0)
    assert float(jnp.min(a)) == 0.0 and float(jnp.max(a)) > 0.0
    b = target_policy_action(jax.random.PRNGKey(3), 1.0, obs, actor_apply, 0.3, 0.5)
    assert float(jnp.min(b)) < -0.3


def test_the_saturation_term_pulls_a_pinned_actor_back_to_where_the_tanh_has_a_slope():
    """``saturation * ||max(|z| - bound, 0)||²`` on the actor's output z before its tanh: 0 when off or
    within the bound; beyond it, its gradient moves z back even when the critic is flat."""
    from d2spo.algos.common.networks import DeterministicActor

    actor = DeterministicActor(2, (8,))
    params = actor.init(jax.random.PRNGKey(0), jnp.zeros((1, 3)))
    obs = jax.random.normal(jax.random.PRNGKey(1), (5, 3))
    bias = params["params"]["MLP_0"]["Dense_1"]["bias"]
    pinned = jax.tree_util.tree_map(lambda x: x, params)
    pinned["params"]["MLP_0"]["Dense_1"]["bias"] = bias + jnp.array([-9.0, 0.0])  # speed at -1, turn free
    z = actor.apply(pinned, obs, pre_tanh=True)
    np.testing.assert_allclose(np.tanh(np.asarray(z)), np.asarray(actor.apply(pinned, obs)), rtol=1e-6)
    flat = lambda c, s, a: jnp.zeros((2, a.shape[0]))  # Q1 = Q2 = 0: no gradient from the critic
    plain, m_plain = td3_actor_loss(pinned, None, obs, actor.apply, flat)
    off, m_off = td3_actor_loss(pinned, None, obs, actor.apply, flat, saturation=0.0)
    assert float(off) == float(plain) == 0.0 and "values/actor_saturation" not in m_off
    loss, m = td3_actor_loss(pinned, None, obs, actor.apply, flat, saturation=2.0, saturation_bound=2.5)
    excess = np.maximum(np.abs(np.asarray(z)) - 2.5, 0.0)
    assert excess[:, 0].min() > 0  # every sample's speed is beyond the bound
    assert float(m["values/actor_saturation"]) == pytest.approx(np.mean(np.sum(excess**2, axis=-1)), rel=1e-5)
    assert float(loss) == pytest.approx(2.0 * np.mean(np.sum(excess**2, axis=-1)), rel=1e-5)
    grad = jax.grad(lambda p: td3_actor_loss(p, None, obs, actor.apply, flat, saturation=2.0)[0])(pinned)
    g_bias = np.asarray(grad["params"]["MLP_0"]["Dense_1"]["bias"])
    assert g_bias[0] < 0  # descending the loss raises the speed's z from -9 toward -2.5
    # within the bound the term is exactly 0
    inside, m_in = td3_actor_loss(params, None, obs, actor.apply, flat, saturation=2.0, saturation_bound=50.0)
    assert float(inside) == 0.0 and float(m_in["values/actor_saturation"]) == 0.0


def test_the_speed_search_pulls_a_stalled_actor_to_the_speed_the_critic_prefers():
    """``speed_search``: a forward-only actor stalled deep in its tanh (speed 0) under a critic that
    values speed gets almost no policy gradient, and the search term gives it one towards speed 1;
    where the proposal is already the critic's best, is not a near stall, or no candidate beats it by
    the margin, the term is 0."""
    from d2spo.algos.common.networks import DeterministicActor
    from d2spo.algos.common.td3_losses import SPEED_SEARCH_MARGIN

    actor = DeterministicActor(2, (8,), low=(0.0, -1.0))
    params = actor.init(jax.random.PRNGKey(0), jnp.zeros((1, 3)))
    obs = jax.random.normal(jax.random.PRNGKey(1), (5, 3))
    stalled = jax.tree_util.tree_map(lambda x: x, params)
    bias = params["params"]["MLP_0"]["Dense_1"]["bias"]
    stalled["params"]["MLP_0"]["Dense_1"]["bias"] = bias + jnp.array([-9.0, 0.0])
    assert float(jnp.max(actor.apply(stalled, obs)[:, 0])) < 1e-6  # speed 0
    rising = lambda c, s, a: jnp.stack([a[:, 0], a[:, 0]])  # Q1 = Q2 = the speed

    def bias_grad(p, weight):
        g = jax.grad(lambda q: td3_actor_loss(q, None, obs, actor.apply, rising, speed_search=weight, speed_low=0.0)[0])(p)
        return np.asarray(g["params"]["MLP_0"]["Dense_1"]["bias"])

    assert abs(bias_grad(stalled, 0.0)[0]) < 1e-6  # the plain policy gradient is lost in the tanh
    assert bias_grad(stalled, 1.0)[0] < -1.0  # the search raises the speed's z
    loss, m = td3_actor_loss(stalled, None, obs, actor.apply, rising, speed_search=1.0, speed_low=0.0)
    assert float(m["values/actor_speed_search"]) == 1.0  # every sample pulled
    # an actor already at full speed: no candidate beats it, the term is 0
    fast = jax.tree_util.tree_map(lambda x: x, params)
    fast["params"]["MLP_0"]["Dense_1"]["bias"] = bias + jnp.array([9.0, 0.0])
    plain, _ = td3_actor_loss(fast, None, obs, actor.apply, rising)
    searched, m_fast = td3_actor_loss(fast, None, obs, actor.apply, rising, speed_search=1.0, speed_low=0.0)
    assert float(searched) == pytest.approx(float(plain)) and float(m_fast["values/actor_speed_search"]) == 0.0
    # an actor at half speed is not stalled: the critic's policy gradient moves it, the search does not
    half = jax.tree_util.tree_map(lambda x: x, params)
    half["params"]["MLP_0"]["Dense_1"]["bias"] = bias - actor.apply(params, obs, pre_tanh=True)[0] * jnp.array([1.0, 0.0])
    assert float(jnp.min(actor.apply(half, obs[:1])[:, 0])) == pytest.approx(0.5, abs=1e-5)
    _, m_half = td3_actor_loss(half, None, obs[:1], actor.apply, rising, speed_search=1.0, speed_low=0.0)
    assert float(m_half["values/actor_speed_search"]) == 0.0
    # an actor that may reverse: its stall is speed 0 (the middle of its range), not -1
    both = DeterministicActor(2, (8,))
    p2 = both.init(jax.random.PRNGKey(0), jnp.zeros((1, 3)))
    b2 = p2["params"]["MLP_0"]["Dense_1"]["bias"]
    for shift, pulled in ((-9.0, 0.0), (0.0, 1.0)):  # full astern: a choice; speed 0: a stall
        q2 = jax.tree_util.tree_map(lambda x: x, p2)
        q2["params"]["MLP_0"]["Dense_1"]["bias"] = b2 - both.apply(p2, obs, pre_tanh=True)[0] * jnp.array([1.0, 0.0]) \
            + jnp.array([shift, 0.0])
        _, m2 = td3_actor_loss(q2, None, obs[:1], both.apply, rising, speed_search=1.0, speed_low=-1.0)
        assert float(m2["values/actor_speed_search"]) == pulled, shift
    # a critic flatter than the margin across the speeds pulls nothing either
    gentle = lambda c, s, a: jnp.stack([a[:, 0], a[:, 0]]) * (SPEED_SEARCH_MARGIN / 2)
    _, m_gentle = td3_actor_loss(stalled, None, obs, actor.apply, gentle, speed_search=1.0, speed_low=0.0)
    assert float(m_gentle["values/actor_speed_search"]) == 0.0
