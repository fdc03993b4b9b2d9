"""Redrawing a generalist's bank while it trains (algos/generalist.py ``Redraw``, ``--generalist-redraw``)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from d2spo.algos.generalist import Redraw, build_generalist
from d2spo.config import REDRAW_SEED, TrainConfig
from d2spo.envs import EnvConfig, layout_bank, layouts
from d2spo.errors import ConfigError
from d2spo.safety.cbf import CBFConfig


def _cfg(**kw) -> TrainConfig:
    return TrainConfig(algo="d2spo", task="phi1", generalist=True, generalist_layouts=4, generalist_tasks=1,
                       num_envs=2, env=EnvConfig(preset="ideal"), cbf=CBFConfig(hidden=(8,)), **kw)


@pytest.fixture(scope="module")
def built():
    cfg = _cfg(generalist_redraw=2)
    env, params, _ = build_generalist(cfg, [layouts.load(f"world:{s}") for s in range(4)], None)
    return cfg, env, params


def test_a_redraw_skips_busy_slots_and_writes_the_fresh_layouts(built):
    cfg, env, params = built
    redraw = Redraw(cfg, env)
    new, meta = redraw.next(params, jnp.array([0, 2]), {})  # environments in slots 0 and 2
    assert meta == {"redrawn": {"1": REDRAW_SEED, "3": REDRAW_SEED + 1}, "redraw_next": 0, "redraw_count": 2}
    for slot, seed in ((1, REDRAW_SEED), (3, REDRAW_SEED + 1)):
        lay = layouts.load(f"world:{seed}")
        np.testing.assert_allclose(np.asarray(new.bank.arena[slot]), lay.arena, rtol=1e-6)
        assert int(new.bank.area_mask[slot].sum()) == len(lay.areas)
        assert int(new.bank.task[slot]) == int(params.bank.task[slot])  # a slot keeps its task
        assert np.asarray(new.bank.fields[slot]).any()
    for slot in (0, 2):  # busy: untouched
        for a, b in zip(jax.tree_util.tree_leaves(new.bank), jax.tree_util.tree_leaves(params.bank)):
            np.testing.assert_array_equal(np.asarray(a[slot]), np.asarray(b[slot]))
    # the next chunk goes on in turn from slot 0; every slot busy: nothing changes
    _, meta2 = redraw.next(new, jnp.array([1, 2]), meta)
    assert meta2["redrawn"] == {"1": REDRAW_SEED, "3": REDRAW_SEED + 3, "0": REDRAW_SEED + 2}
    same, meta3 = redraw.next(new, jnp.array([0, 1, 2, 3]), meta)
    assert same is new and meta3["redrawn"] == meta["redrawn"]


def test_a_resumed_run_rebuilds_the_same_bank_from_its_meta(built):
    cfg, env, params = built
    redraw = Redraw(cfg, env)
    p, meta = params, {}
    for in_use in ([0, 1], [2, 3], [0, 3]):
        p, updates = redraw.next(p, jnp.array(in_use), meta)
        meta = {**meta, **updates}
    rebuilt = redraw.apply(params, meta["redrawn"])
    for a, b in zip(jax.tree_util.tree_leaves(p.bank), jax.tree_util.tree_leaves(rebuilt.bank)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_the_redraw_count_is_checked():
    with pytest.raises(ConfigError, match="generalist_redraw: expected 0 .. the bank's slots"):
        _cfg(generalist_redraw=5)
    assert _cfg(generalist_redraw=8, generalist_pairings=2).generalist_redraw == 8  # 4 layouts x 2 slots
    assert dataclasses.replace(_cfg(), generalist_redraw=0).generalist_redraw == 0
    assert layout_bank.N_AREAS >= 12



def test_pairings_give_each_layout_consecutive_slots_with_the_next_tasks():
    from d2spo.run import build

    _, params, _ = build(_cfg(generalist_pairings=2))  # the mixture: phi1 and one random task
    bank = jax.device_get(params.bank)
    assert bank.arena.shape[0] == 8
    assert bank.task.tolist() == [0, 1] * 4
    for n in range(4):  # layout world:n in slots 2n and 2n+1
        lay = layouts.load(f"world:{n}")
        for slot in (2 * n, 2 * n + 1):
            np.testing.assert_allclose(bank.arena[slot], lay.arena, rtol=1e-6)
        assert not np.array_equal(bank.fields[2 * n], bank.fields[2 * n + 1])  # each its own task's fields


def test_more_pairings_than_tasks_is_refused():
    with pytest.raises(ConfigError, match="generalist_pairings: at most the mixture's 2 tasks"):
        _cfg(generalist_pairings=3)
