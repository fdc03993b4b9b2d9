"""The shaping potential's geodesic distance and the annealed labelling radius."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from d2spo.envs import EnvConfig, geodesic, layouts, make_env
from d2spo.ltl.anneal import AnnealConfig, annealed_params, label_radius, separation_cap
from d2spo.ltl.reward import RewardConfig


def _fields(layout_name: str, robot_radius: float = 0.15):
    lay = layouts.load(layout_name)
    f = geodesic.distance_fields(lay.arena, [o.lo for o in lay.obstacles], [o.hi for o in lay.obstacles],
                                 [a.center for a in lay.areas], [a.radius for a in lay.areas], robot_radius)
    return lay, jnp.asarray(f)


def test_open_arena_geodesic_is_close_to_straight_line():
    lay, f = _fields("open")
    rng = np.random.default_rng(0)
    for xy in rng.uniform(0.4, 4.6, size=(50, 2)):
        d = np.asarray(geodesic.lookup(f, jnp.asarray(xy, jnp.float32)))
        euclid = np.array([math.dist(xy, a.center) for a in lay.areas])
        # 8-connected grid paths are at most 1/cos(22.5°) ≈ 1.083 times the straight line
        assert np.all(d >= euclid - 0.05) and np.all(d <= 1.09 * euclid + 0.05)


def test_paper_geodesic_goes_round_the_obstacle_on_the_line_to_a1():
    lay, f = _fields("paper")
    a1 = [a.name for a in lay.areas].index("A1")
    west = np.asarray(geodesic.lookup(f, jnp.array([1.9, 0.5])))[a1]
    straight = math.dist((1.9, 0.5), lay.areas[a1].center)
    assert west > straight + 0.2  # O1 blocks the segment: the path bends round it
    # stepping up out of O1's shadow shortens the path although the straight line gets no shorter
    above = np.asarray(geodesic.lookup(f, jnp.array([1.9, 1.05])))[a1]
    assert above < west
    assert math.dist((1.9, 1.05), lay.areas[a1].center) > straight - 0.05


def test_lookup_is_exact_on_nodes_and_linear_between():
    f = jnp.asarray(np.arange(2 * 3 * 4, dtype=np.float32).reshape(2, 3, 4))
    s = geodesic.SPACING
    assert np.allclose(geodesic.lookup(f, jnp.array([2 * s, 1 * s])), f[:, 1, 2])
    mid = geodesic.lookup(f, jnp.array([2.5 * s, 1 * s]))
    assert np.allclose(mid, 0.5 * (f[:, 1, 2] + f[:, 1, 3]))


def test_geodesic_shaping_rewards_the_detour_and_euclidean_does_not():
    """Moving from O1's west side up (round the obstacle) earns shaping only with the geodesic metric."""
    out = {}
    for metric in ("geodesic", "euclidean"):
        env, params = make_env(EnvConfig(layout="paper", preset="ideal", start_jitter_xy=0.0, start_jitter_theta=0.0,
                                         reward=RewardConfig(shaping_metric=metric)), task="F A1")
        d0 = env._center_distance(jnp.array([1.9, 0.5]), params)
        d1 = env._center_distance(jnp.array([1.9, 1.05]), params)
        out[metric] = float(d0[0] - d1[0])
    assert out["geodesic"] > 0.15 and out["euclidean"] < 0.05


def test_bad_shaping_metric_is_a_config_error():
    from d2spo.errors import ConfigError

    with pytest.raises(ConfigError, match="shaping_metric"):
        make_env(EnvConfig(layout="paper", reward=RewardConfig(shaping_metric="manhattan")))


def test_shaping_clearance_makes_the_band_near_an_obstacle_costly():
    """With a clearance of 0.3 m, a point 0.2 m from `relaxed`'s obstacle lies in the penalised
    band (outside it with None, the robot radius 0.15 m): leaving the band costs extra, and a point
    well clear of every obstacle keeps (nearly) the same distance. 0.3 is the default."""
    lay = layouts.load("relaxed")
    a2 = [a.name for a in lay.areas].index("A2")
    near, clear = jnp.array([3.5, 2.5]), jnp.array([2.0, 2.5])  # obstacle face at x = 3.7
    by_clearance = {}
    for c in (0.15, 0.3):
        _, f = _fields("relaxed", robot_radius=c)
        by_clearance[c] = (float(geodesic.lookup(f, near)[a2]), float(geodesic.lookup(f, clear)[a2]))
    assert by_clearance[0.3][0] > by_clearance[0.15][0] + 0.5
    assert by_clearance[0.3][1] == pytest.approx(by_clearance[0.15][1], abs=0.15)
    geo = RewardConfig(shaping_metric="geodesic")
    for reward, c in ((geo, 0.3), (dataclasses.replace(geo, shaping_clearance=None), 0.15)):
        env, params = make_env(EnvConfig(layout="relaxed", reward=reward), task="relaxed")
        assert float(env._center_distance(near, params)[a2]) == pytest.approx(by_clearance[c][0], rel=1e-5)


def test_negative_shaping_clearance_is_a_config_error():
    from d2spo.errors import ConfigError

    with pytest.raises(ConfigError, match="shaping_clearance"):
        make_env(EnvConfig(layout="relaxed", reward=RewardConfig(shaping_clearance=-0.1)), task="relaxed")


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.floats(0.5, 4.5), st.floats(0.5, 4.5)), min_size=2, max_size=5, unique=True),
       st.integers(0, 20_000))
def test_separated_relaxed_disks_never_overlap(centres, episode):
    c = jnp.asarray(centres, jnp.float32)
    n = len(centres)
    dist = np.linalg.norm(np.asarray(centres)[:, None] - np.asarray(centres)[None], axis=-1)
    r = float(np.min(dist[~np.eye(n, dtype=bool)])) / 2.5  # true disks well apart
    radius = jnp.full((n,), r, jnp.float32)
    cfg = AnnealConfig()
    lr = np.asarray(label_radius(radius, jnp.int32(episode), cfg, cfg.rate(20_000), separation_cap(c, radius)))
    assert np.all(lr >= r - 1e-6)
    for i in range(n):
        for j in range(i + 1, n):
            assert lr[i] + lr[j] <= dist[i, j] + 1e-4


def test_paper_relaxed_disks_start_wide_and_end_true():
    env, params = make_env(EnvConfig(layout="paper"), task="phi1")
    cfg = AnnealConfig()
    k2 = cfg.rate(20_000)
    start = np.asarray(annealed_params(params, jnp.int32(0), cfg, k2).label_radius)
    end = np.asarray(annealed_params(params, jnp.int32(10_000), cfg, k2).label_radius)
    assert np.all(start > 1.0) and np.all(start < 1.4)  # capped by the nearest area (A4), not 3.5 m
    assert np.allclose(end, np.asarray(params.area_radius), atol=1e-3)
    uncapped = AnnealConfig(separate=False)
    assert np.allclose(np.asarray(annealed_params(params, jnp.int32(0), uncapped, k2).label_radius), 3.5, atol=1e-3)


def test_relax_targets_keeps_forbidden_areas_at_their_true_radius():
    # "!A2 U A1": in the initial state A1 is the target and entering A2 rejects the task.
    env, params = make_env(EnvConfig(layout="paper"), "!A2 U A1")
    aps = env.aps
    bit = {a: 1 << aps.index(a) for a in aps}
    k2 = AnnealConfig().rate(20000)
    relaxed_all = annealed_params(params, jnp.int32(0), AnnealConfig(relax="all"), k2)
    relaxed_targets = annealed_params(params, jnp.int32(0), AnnealConfig(relax="targets"), k2)
    q0 = params.aut.initial
    centre = {a.name: np.asarray(a.center, np.float32) for a in env.layout.areas}
    off = np.array([0.0, -0.8], np.float32)  # 0.8 m from the centre: outside the true disk, inside the relaxed
    near_a2, near_a1 = jnp.asarray(centre["A2"] + off), jnp.asarray(centre["A1"] + np.array([-0.8, 0], np.float32))
    assert int(env._letters(near_a2, q0, relaxed_all)[0]) == bit["A2"]  # the paper's rule: A2 "entered"
    assert int(env._letters(near_a2, q0, relaxed_targets)[0]) == 0  # forbidden A2 keeps its true radius
    assert int(env._letters(near_a1, q0, relaxed_targets)[0]) == bit["A1"]  # the target A1 is relaxed
    assert int(env._letters(near_a1, q0, relaxed_targets)[1]) == 0  # true labelling unchanged
    with pytest.raises(Exception, match="anneal.relax"):
        AnnealConfig(relax="forbidden")
