"""The zones layout family (envs/zones.py): ZoneEnv's eight coloured zones, two per colour."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from d2spo.envs import EnvConfig, layouts, make_env
from d2spo.envs.zones import ARENA, CENTRAL, COLOURS, ROBOT_KEEPOUT, ZONE_KEEPOUT, ZONE_RADIUS, zones_layout
from d2spo.errors import ConfigError


@pytest.mark.parametrize("seed", range(12))
def test_zones_follow_zoneenvs_placement(seed):
    lay = layouts.load(f"zones:{seed}")
    assert lay == zones_layout(seed) and lay.name == f"zones:{seed}"
    assert lay.arena == (ARENA, ARENA) == (6.6, 6.6) and lay.obstacles == ()
    assert sorted(a.label for a in lay.areas) == sorted(COLOURS * 2)
    assert all(a.radius == ZONE_RADIUS == 0.4 for a in lay.areas)
    lo, hi = (ARENA - CENTRAL) / 2, (ARENA + CENTRAL) / 2
    centres = np.array([a.center for a in lay.areas])
    assert np.all((centres >= lo) & (centres <= hi))
    assert min(np.linalg.norm(a - b) for a, b in itertools.combinations(centres, 2)) >= 2 * ZONE_KEEPOUT
    start = np.array(lay.start[:2])
    assert np.all((start >= lo) & (start <= hi))
    assert np.linalg.norm(centres - start, axis=1).min() >= ZONE_KEEPOUT + ROBOT_KEEPOUT


def test_seeds_draw_other_layouts_and_bad_seeds_are_one_line():
    assert len({zones_layout(s).areas for s in range(20)}) == 20
    assert layouts.load("zones") == zones_layout(0)
    for bad in ("zones:-1", "zones:x"):
        with pytest.raises(ConfigError, match="seed"):
            layouts.load(bad)


def test_a_deepltl_task_compiles_onto_a_zones_layout():
    """The first of DeepLTL's finite ZoneEnv tasks: its letters are sets of colours, and either zone
    of a colour is a target."""
    env, params = make_env(EnvConfig(layout="zones:1"), task="F (green & (!blue U yellow)) & F magenta")
    assert set(env.aps) == {"green", "blue", "yellow", "magenta"}
    assert env.task.route_length < float("inf")


@pytest.mark.parametrize("name", ["zones:abc", "zones:3.5", "zones:-1"])
def test_a_bad_zones_seed_names_the_kind(name):
    """It said "random layout seed must be an integer" of a zones layout."""
    from d2spo.envs import layouts
    from d2spo.errors import ConfigError

    with pytest.raises(ConfigError, match=r"a zones:SEED layout's seed must be a whole number >= 0"):
        layouts.load(name)
