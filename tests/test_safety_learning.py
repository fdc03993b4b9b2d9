"""Learning with the CBF machinery on a toy lidar world: h's sign, gradient routing, cautious start."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax

from d2spo.safety.cbf import CBFConfig, TeBatch, barrier_terms, t_s, t_u
from d2spo.safety.datasets import (
    Transition,
    init_safety_data,
    synthetic_pretrain_data,
    update_datasets,
)
from d2spo.safety.joint_policy import (
    cautious_start,
    init_safety_state,
    make_nets,
    safe_action,
    update,
)
from d2spo.safety.nominal import unicycle_prior, wrap_angle

K, H, R_ROBOT, DT, M = 16, 1.0, 0.15, 0.1, 2
CFG = CBFConfig(hidden=(32, 32), policy_hidden=(32, 32), nominal_hidden=(32, 32), batch_size=128, synthetic_replay=1.0,
                pretrain_samples=4096, pretrain_steps=1500, prior_steps=300, updates_per_iter=5,
                nominal_updates_per_iter=5, transitions_capacity=512, p_exp_capacity=512, unsafe_capacity=512)


def lidar(pose, ctx):
    """Toy b(z, O_s): K rays against sensed disks, clipped at H; 0 from inside a disk."""
    centres, radii, sensed = ctx
    ang = pose[2] + jnp.arange(K) * (2 * jnp.pi / K)
    d = jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)
    q = pose[:2] - centres
    dq = d @ q.T
    disc = dq**2 - jnp.sum(q**2, -1) + radii**2
    t = -dq - jnp.sqrt(jnp.where(disc > 0, disc, 1.0))
    t = jnp.where((disc > 0) & (t > 0), t, H)
    t = jnp.where(jnp.sum(q**2, -1) < radii**2, 0.0, t)
    return jnp.min(jnp.where(sensed, t, H), -1).clip(0.0, H)


def sample_scene(key):
    """Up to M disks and a pose within about H of the first (always sensed) one, any heading."""
    k1, k2, k3, k4, k5, k6 = jax.random.split(key, 6)
    centres = jax.random.uniform(k1, (M, 2), minval=-1.0, maxval=1.0)
    radii = jax.random.uniform(k2, (M,), minval=0.1, maxval=0.4)
    sensed = jnp.array([True, False]) | (jax.random.uniform(k3, (M,)) < 0.5)
    ang = jax.random.uniform(k4, (), minval=-jnp.pi, maxval=jnp.pi)
    dist = radii[0] + jax.random.uniform(k5, (), minval=0.0, maxval=H)
    xy = centres[0] + dist * jnp.array([jnp.cos(ang), jnp.sin(ang)])
    pose = jnp.concatenate([xy, jax.random.uniform(k6, (1,), minval=-jnp.pi, maxval=jnp.pi)])
    return pose, (centres, radii, sensed)


def true_step(s, u):
    """The black box: a unicycle that is 20 % slower than the prior believes."""
    v, w = 0.8 * u[..., 0], 2.0 * u[..., 1]
    th = s[..., 2]
    return jnp.stack([s[..., 0] + v * jnp.cos(th) * DT, s[..., 1] + v * jnp.sin(th) * DT, wrap_angle(th + w * DT)], -1)


def surface_distance(pose, ctx):
    centres, radii, sensed = ctx
    return jnp.min(jnp.where(sensed, jnp.linalg.norm(pose[:2] - centres, axis=-1) - radii, jnp.inf))


@jax.jit
def synthetic(key):
    return synthetic_pretrain_data(key, lidar, sample_scene, CFG.pretrain_samples, cfg=CFG)


# The tests' set-up, jitted: eagerly, each operation inside would compile a program of its own.
initial_state = jax.jit(lambda key: init_safety_state(key, make_nets(CFG, H), CFG, K))
scenes = jax.jit(lambda key, n: jax.vmap(sample_scene)(jax.random.split(key, n)), static_argnums=1)
stepped = jax.jit(true_step)


def test_h_learns_the_sign_of_safety_on_synthetic_data():
    nets = make_nets(CFG, H)
    train, test = synthetic(jax.random.PRNGKey(0)), synthetic(jax.random.PRNGKey(1))
    params = nets.cbf.init(jax.random.PRNGKey(2), jnp.zeros((1, K)))
    tx = optax.adam(3e-3)

    @jax.jit
    def fit(params, key):
        def body(c, k):
            p, o = c
            k1, k2 = jax.random.split(k)
            i = jax.random.randint(k1, (256,), 0, 4096)
            j = jax.random.randint(k2, (256,), 0, 4096)
            safe_w, unsafe_w = train.safe[i].astype(jnp.float32), train.unsafe_valid[j].astype(jnp.float32)

            def loss(q):
                return (t_s(nets.cbf.apply(q, train.x[i]), CFG.gamma_s, safe_w)
                        + t_u(nets.cbf.apply(q, train.x_unsafe[j]), CFG.gamma_u, unsafe_w))

            g = jax.grad(loss)(p)
            u, o = tx.update(g, o, p)
            return (optax.apply_updates(p, u), o), None
        return jax.lax.scan(body, (params, tx.init(params)), jax.random.split(key, 300))[0][0]

    params = fit(params, jax.random.PRNGKey(3))
    h_safe = np.asarray(nets.cbf.apply(params, test.x))[np.asarray(test.safe)]
    h_unsafe = np.asarray(nets.cbf.apply(params, test.x_unsafe))[np.asarray(test.unsafe_valid)]
    assert h_safe.size > 500 and h_unsafe.size > 500
    assert (h_safe > 0).mean() >= 0.95, (h_safe > 0).mean()
    assert (h_unsafe < 0).mean() >= 0.95, (h_unsafe < 0).mean()


def test_t_e_reaches_theta_and_omega_but_not_the_nominal_model():
    nets = make_nets(CFG, H)
    st = initial_state(jax.random.PRNGKey(0))
    pose, ctx = scenes(jax.random.PRNGKey(1), 64)
    u_rl = jnp.tile(jnp.array([1.0, 0.0]), (64, 1))
    batch = TeBatch(pose, stepped(pose, u_rl), ctx, u_rl, jnp.ones(64), u_rl)
    # a large γ_exp makes every row's hinge active, so T_e has a gradient everywhere
    cfg = dataclasses.replace(CFG, gamma_exp=100.0)

    def te(c, p, n):
        return barrier_terms(c, p, n, batch, nets=nets, cfg=cfg, features_fn=lidar, dt=DT)[0]

    g_c, g_p, g_n = jax.jit(jax.grad(te, argnums=(0, 1, 2)))(st.cbf, st.policy, st.nominal)
    norm = lambda g: float(sum(np.sum(np.asarray(x) ** 2) for x in jax.tree_util.tree_leaves(g)))
    assert norm(g_c) > 0 and norm(g_p) > 0
    assert norm(g_n) == 0.0


def test_cautious_start_makes_the_executed_policy_safe_before_any_real_data():
    nets = make_nets(CFG, H)
    st = initial_state(jax.random.PRNGKey(0))
    data = synthetic(jax.random.PRNGKey(1))

    @jax.jit
    def start(st):
        return cautious_start(jax.random.PRNGKey(2), st, data, nets=nets, cfg=CFG, features_fn=lidar, dt=DT,
                              prior=unicycle_prior(1.0, 2.0))

    st, metrics = start(st)
    assert float(metrics["safety/unsafe_h_neg"]) > 0.8

    @jax.jit
    def collision_rate(st, use_filter):
        """An exploring policy that drives straight at full speed from random poses clear of obstacles."""
        pose, ctx = jax.vmap(sample_scene)(jax.random.split(jax.random.PRNGKey(3), 512))
        start_ok = jax.vmap(surface_distance)(pose, ctx) > CFG.d

        def body(c, k):
            pose, hit = c
            u_rl = jnp.stack([jnp.ones(512), 0.3 * jax.random.normal(k, (512,))], -1).clip(-1, 1)
            x = jax.vmap(lidar)(pose, ctx)
            u = jnp.where(use_filter, safe_action(nets, st, x, u_rl), u_rl)
            pose = true_step(pose, u)
            return (pose, hit | (jax.vmap(surface_distance)(pose, ctx) < R_ROBOT)), None

        (_, hit), _ = jax.lax.scan(body, (pose, jnp.zeros(512, bool)), jax.random.split(jax.random.PRNGKey(4), 40))
        return jnp.sum(hit & start_ok) / jnp.sum(start_ok)

    raw, safe = float(collision_rate(st, False)), float(collision_rate(st, True))
    assert raw > 0.1, raw
    assert safe < raw / 5, (raw, safe)

    # one online UPDATE on real transitions runs, keeps everything finite and refits f_n to them
    pose, ctx = scenes(jax.random.PRNGKey(5), 64)
    u = jnp.tile(jnp.array([0.5, 0.1]), (64, 1))
    tr = Transition(pose=pose, next_pose=stepped(pose, u), context=ctx, obs=jnp.zeros((64, 1)), action=u, u_rl=u)

    @jax.jit
    def online(st, tr):
        sd = init_safety_data(CFG, jax.tree_util.tree_map(lambda a: a[0], tr), K)
        sd, _ = update_datasets(sd, jax.random.PRNGKey(6), tr, features_fn=lidar, cfg=CFG)
        return update(jax.random.PRNGKey(7), st, sd, nets=nets, cfg=CFG, features_fn=lidar, dt=DT, pretrain=data)

    _, m = online(st, tr)
    assert all(np.isfinite(float(v)) for v in m.values())
