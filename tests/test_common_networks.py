"""Networks and Gaussian maths: closed forms, the tanh change of variables, output ranges."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.algos.common.networks import (
    DeterministicActor,
    GaussianActor,
    GaussianPolicy,
    QNetwork,
    TwinQ,
    ValueNetwork,
    first_critic,
    gaussian_entropy,
    gaussian_kl,
    gaussian_log_prob,
    init_params,
    tanh_gaussian_log_prob,
    tanh_gaussian_sample,
)

RNG = np.random.default_rng(0)


def _full_cov(log_std):
    return np.diag(np.exp(2.0 * np.asarray(log_std, np.float64)))


def test_gaussian_log_prob_matches_full_covariance_formula():
    mean, log_std, x = RNG.normal(size=3), RNG.normal(size=3) * 0.5, RNG.normal(size=3)
    cov = _full_cov(log_std)
    d = x - mean
    expected = -0.5 * d @ np.linalg.inv(cov) @ d - 0.5 * np.log(np.linalg.det(2 * np.pi * cov))
    got = gaussian_log_prob(jnp.array(mean), jnp.array(log_std), jnp.array(x))
    assert float(got) == pytest.approx(expected, rel=1e-5)
    assert float(gaussian_entropy(jnp.array(log_std))) == pytest.approx(
        0.5 * np.log(np.linalg.det(2 * np.pi * np.e * cov)), rel=1e-5
    )


def test_gaussian_kl_zero_on_itself_and_matches_closed_form_in_the_right_direction():
    mp, lp, mq, lq = (RNG.normal(size=4) * s for s in (1.0, 0.5, 1.0, 0.5))
    self_kl = gaussian_kl(jnp.array(mp), jnp.array(lp), jnp.array(mp), jnp.array(lp))
    assert float(self_kl) == pytest.approx(0.0, abs=1e-6)
    cp, cq = _full_cov(lp), _full_cov(lq)
    iq = np.linalg.inv(cq)
    d = mq - mp
    kl_pq = 0.5 * (np.trace(iq @ cp) + d @ iq @ d - 4 + np.log(np.linalg.det(cq) / np.linalg.det(cp)))
    got = float(gaussian_kl(jnp.array(mp), jnp.array(lp), jnp.array(mq), jnp.array(lq)))
    assert got == pytest.approx(kl_pq, rel=1e-5)
    reverse = float(gaussian_kl(jnp.array(mq), jnp.array(lq), jnp.array(mp), jnp.array(lp)))
    assert abs(reverse - got) > 1e-3  # KL is asymmetric, so the argument order is being tested


def test_tanh_gaussian_log_prob_matches_numeric_change_of_variables():
    mean, log_std = np.array([0.3, -0.7]), np.array([-0.2, 0.4])
    u = RNG.normal(size=(50, 2)) * 1.5
    # p_a(a) = p_u(u) / |da/du| with the Jacobian of tanh taken by central differences.
    h = 1e-5
    jac = (np.tanh(u + h) - np.tanh(u - h)) / (2 * h)
    z = (u - mean) / np.exp(log_std)
    log_pu = np.sum(-0.5 * z**2 - log_std - 0.5 * np.log(2 * np.pi), axis=-1)
    expected = log_pu - np.sum(np.log(jac), axis=-1)
    got = tanh_gaussian_log_prob(jnp.array(mean), jnp.array(log_std), jnp.array(u))
    np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-4, atol=1e-4)


def test_tanh_gaussian_density_integrates_to_one_and_is_stable_at_the_edges():
    u = np.linspace(-12.0, 12.0, 200_001)
    a = np.tanh(u)
    logp = np.asarray(tanh_gaussian_log_prob(jnp.array([0.5]), jnp.array([0.3]), jnp.array(u[:, None])), np.float64)
    assert np.trapezoid(np.exp(logp), a) == pytest.approx(1.0, abs=2e-3)
    # Far in the tail the correction is log 4 - 2|u|, finite where naive log(1 - tanh^2) is -inf.
    far = tanh_gaussian_log_prob(jnp.zeros(1), jnp.zeros(1), jnp.array([[30.0]]))
    assert float(far[0]) == pytest.approx(-0.5 * 900 - 0.5 * np.log(2 * np.pi) - (np.log(4.0) - 60.0), rel=1e-5)


def test_tanh_gaussian_sample_in_box():
    a, logp = tanh_gaussian_sample(jax.random.PRNGKey(0), jnp.full((1000, 3), 4.0), jnp.zeros((1000, 3)))
    assert a.shape == (1000, 3) and logp.shape == (1000,)
    assert float(jnp.max(jnp.abs(a))) <= 1.0 and bool(jnp.all(jnp.isfinite(logp)))


def test_modules_shapes_ranges_and_independence():
    key = jax.random.PRNGKey(0)
    obs, act = jnp.zeros((5, 4)), jnp.zeros((5, 2))
    big = 1e3 * jax.random.normal(key, (5, 4))

    actor = DeterministicActor(2, hidden=(16, 16))
    p = init_params(actor, key, obs)
    out = actor.apply(p, big)
    assert out.shape == (5, 2) and float(jnp.max(jnp.abs(out))) <= 1.0
    assert float(jnp.max(jnp.abs(out))) > 0.5  # squashed, not zeroed

    assert QNetwork((16,)).apply(init_params(QNetwork((16,)), key, obs, act), obs, act).shape == (5,)
    twin = TwinQ((16,), n_critics=3)
    q = twin.apply(init_params(twin, key, obs, act), big, act)
    assert q.shape == (3, 5) and not np.allclose(np.asarray(q[0]), np.asarray(q[1]))  # independent heads

    value = ValueNetwork((16,))
    assert value.apply(init_params(value, key, obs), obs).shape == (5,)

    pol = GaussianPolicy(2, hidden=(16,), log_std_init=-0.5)
    pp = init_params(pol, key, obs)
    mean, log_std = pol.apply(pp, big)
    assert mean.shape == log_std.shape == (5, 2)
    np.testing.assert_allclose(np.asarray(log_std), -0.5)  # state independent

    sac = GaussianActor(2, hidden=(16,), log_std_min=-5.0, log_std_max=2.0)
    sp = init_params(sac, key, obs)
    _, ls = sac.apply(sp, big)
    assert float(jnp.min(ls)) >= -5.0 and float(jnp.max(ls)) <= 2.0
    assert float(jnp.max(ls) - jnp.min(ls)) > 0.1  # state dependent


@pytest.mark.parametrize("layer_norm", [False, True])
def test_the_first_critic_alone_is_the_twins_first_row(layer_norm):
    """TD3's actor loss reads Q1 through ``first_critic``: its value and its gradient in the action
    (what the actor's gradient goes through) equal the twin's row 0, to float32 rounding: one critic's
    matrix products may round differently from the two's batched ones (bit for bit in the default
    phi1 run at XLA's default level: bench/RESULTS.md, 2026-12-04), and it is one critic."""
    twin = TwinQ((32, 32), layer_norm=layer_norm)
    obs, act = jax.random.normal(jax.random.PRNGKey(1), (64, 7)), jax.random.uniform(jax.random.PRNGKey(2), (64, 2))
    params = twin.init(jax.random.PRNGKey(0), obs, act)
    q1 = first_critic(twin)
    assert q1(params, obs, act).shape == (1, 64)

    def through(apply):
        return jax.jit(jax.value_and_grad(lambda a: jnp.sum(jnp.tanh(apply(params, obs, a)[0]))))(act)

    (v_twin, g_twin), (v_one, g_one) = through(twin.apply), through(q1)
    np.testing.assert_allclose(np.asarray(v_one), np.asarray(v_twin), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(g_one), np.asarray(g_twin), rtol=1e-5, atol=1e-7)
    # the second critic is not the first's: the test above can tell the rows apart
    assert not np.array_equal(np.asarray(twin.apply(params, obs, act)[1]), np.asarray(q1(params, obs, act)[0]))


def test_critic_layer_norm_adds_a_norm_per_hidden_layer_and_is_off_by_default():
    """``--td3.critic-layer-norm``: a LayerNorm after each hidden Dense of both critics; off, the
    parameters (and so old checkpoints) are those of before."""
    from d2spo.algos.td3 import TD3Config, make_nets

    obs, act = jnp.ones((3, 5)), jnp.zeros((3, 2))
    plain = make_nets(2, TD3Config(hidden=(8, 8))).critic
    normed = make_nets(2, TD3Config(hidden=(8, 8), critic_layer_norm=True)).critic
    p_plain = plain.init(jax.random.PRNGKey(0), obs, act)
    p_normed = normed.init(jax.random.PRNGKey(0), obs, act)
    names = lambda p: sorted(jax.tree_util.keystr(k) for k, _ in jax.tree_util.tree_leaves_with_path(p))  # noqa: E731
    assert not any("LayerNorm" in n for n in names(p_plain))
    assert sum("LayerNorm_0']['scale" in n or "LayerNorm_1']['scale" in n for n in names(p_normed)) == 2
    q = normed.apply(p_normed, obs, act)
    assert q.shape == (2, 3) and bool(jnp.all(jnp.isfinite(q)))
    assert not np.allclose(np.asarray(plain.apply(p_plain, obs, act)), np.asarray(q))
    with pytest.raises(Exception, match="critic_layer_norm"):
        TD3Config(critic_layer_norm="yes")


def test_a_forward_only_actor_proposes_in_its_box_and_explores_there():
    """``--td3.forward-only``: a[0] = (1 + tanh) / 2 in [0, 1], a[1] = tanh in [-1, 1], from the same
    parameters as the plain actor; warm-up and noisy behaviour actions stay in that box too."""
    from d2spo.algos.td3 import TD3Config, explore, init_agent, make_nets

    key = jax.random.PRNGKey(0)
    big = 1e3 * jax.random.normal(key, (64, 4))
    plain_nets, fwd_nets = make_nets(2, TD3Config(hidden=(16,))), make_nets(2, TD3Config(hidden=(16,), forward_only=True))
    assert plain_nets.actor.low is None and fwd_nets.actor.low == (0.0, -1.0)
    agent = init_agent(key, fwd_nets, 4, 2)
    plain = np.asarray(plain_nets.actor.apply(agent.actor, big))
    fwd = np.asarray(fwd_nets.actor.apply(agent.actor, big))
    np.testing.assert_allclose(fwd[:, 0], (1.0 + plain[:, 0]) / 2.0, atol=1e-6)
    np.testing.assert_array_equal(fwd[:, 1], plain[:, 1])
    assert fwd[:, 0].min() >= 0.0 and fwd[:, 0].max() > 0.9 and plain[:, 0].min() < -0.5
    for random_phase in (True, False):
        a = np.asarray(explore(fwd_nets, agent, big, jax.random.PRNGKey(1), jnp.asarray(random_phase), 0.5))
        assert a[:, 0].min() >= 0.0 and a[:, 1].min() < -0.2 and np.abs(a).max() <= 1.0
        b = np.asarray(explore(plain_nets, agent, big, jax.random.PRNGKey(1), jnp.asarray(random_phase), 0.5))
        assert b[:, 0].min() < -0.2


@pytest.mark.parametrize("forward_only", [False, True])
def test_pre_tanh_exploration_keeps_a_saturated_action_and_spreads_a_central_one(forward_only):
    """``--td3.exploration-noise-space pre-tanh``: an actor at a bound of its box stays there (the
    clipped "action" noise slows an actor at full speed by about 0.4 noise on average), and at the
    box's centre the spread is the "action" noise's."""
    from flax.core import unfreeze

    from d2spo.algos.td3 import TD3Config, explore, init_agent, make_nets
    from d2spo.errors import ConfigError

    nets = make_nets(2, TD3Config(hidden=(8,), forward_only=forward_only))
    agent = init_agent(jax.random.PRNGKey(0), nets, 3, 2)
    obs = jnp.zeros((4096, 3))
    c0, c1 = (0.5, 0.5) if forward_only else (0.0, 1.0)

    def with_output_bias(b):  # the actor's last layer outputs b whatever the observation
        params = unfreeze(agent.actor)
        last = sorted(params["params"]["MLP_0"])[-1]
        params["params"]["MLP_0"][last]["kernel"] = jnp.zeros_like(params["params"]["MLP_0"][last]["kernel"])
        params["params"]["MLP_0"][last]["bias"] = jnp.asarray(b, jnp.float32)
        return agent.replace(actor=params)

    def act(a, space, noise=0.2):
        return np.asarray(explore(nets, a, obs, jax.random.PRNGKey(1), jnp.asarray(False), noise, space))

    full = with_output_bias([20.0, 0.0])  # full speed ahead, straight on
    plain, pre = act(full, "action"), act(full, "pre-tanh")
    assert plain[:, 0].mean() == pytest.approx(1.0 - 0.2 * 0.3989, abs=0.01)  # E[min(0, N(0, 0.2^2))]
    assert pre[:, 0].min() > 1.0 - 1e-3
    np.testing.assert_allclose(pre[:, 1].std(), plain[:, 1].std(), rtol=0.05)  # a[1] at 0: both spreads alike
    centre = with_output_bias([0.0, 0.0])  # the middle of the box
    plain, pre = act(centre, "action"), act(centre, "pre-tanh", noise=0.05)
    assert plain[:, 0].mean() == pytest.approx(c0, abs=0.02)
    assert pre[:, 0].std() == pytest.approx(0.05, rel=0.06)
    with pytest.raises(ConfigError, match="exploration_noise_space"):
        TD3Config(exploration_noise_space="params")
