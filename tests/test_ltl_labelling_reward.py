"""Labelling (which letters the automaton reads) and the reward of Eq. (8)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest

from d2spo.errors import ConfigError
from d2spo.ltl import TASKS, UNREACHABLE, translate
from d2spo.ltl.labelling import next_state
from d2spo.ltl.reward import RewardConfig, progress_reward, step_reward


def _run(aut_arrays, letters, event):
    """Automaton states after each per-time-step letter, under jit and scan."""

    @jax.jit
    def go(letters):
        def step(carry, letter):
            q, prev = carry
            q_next = next_state(aut_arrays, q, letter, prev, event)
            return (q_next, letter), q_next

        _, qs = jax.lax.scan(step, (aut_arrays.initial, jnp.int32(0)), letters)
        return qs

    return [int(q) for q in go(jnp.asarray(letters, dtype=jnp.int32))]


def test_event_and_step_labelling_differ_on_phi2():
    aut = translate(TASKS["phi2"])
    arr = aut.arrays()
    a1, a2, a3, a4 = (aut.letter([f"A{i}"]) for i in range(1, 5))
    # The robot stays in A1 for two steps, travels (empty letter), stays in A3, and so on.
    per_step = [a1, a1, 0, a3, a3, 0, 0, a4, 0, a2]
    event_states = _run(arr, per_step, event=True)
    step_states = _run(arr, per_step, event=False)
    # Event labelling reads A1 A3 A4 A2: the task is done at the last step, not before.
    assert [aut.status(q) for q in event_states] == ["undecided"] * 9 + ["accepting"]
    read = [[a1]] * 3 + [[a1, a3]] * 4 + [[a1, a3, a4]] * 2 + [[a1, a3, a4, a2]]  # after each step
    assert event_states == [aut.run(letters)[-1] for letters in read]
    # Step labelling reads A1 A1: "A1 & X A3" fails at the second step.
    assert aut.status(step_states[1]) == "rejecting"
    assert step_states == aut.run(per_step)[1:]


def test_event_labelling_ignores_repeats_and_empty_letters():
    aut = translate(TASKS["relaxed"])
    arr = aut.arrays()
    q0 = arr.initial
    a1 = aut.letter(["A1"])
    moved = int(aut.delta[int(q0)][a1])
    assert int(next_state(arr, q0, jnp.int32(a1), jnp.int32(0), True)) == moved
    assert int(next_state(arr, q0, jnp.int32(a1), jnp.int32(a1), True)) == int(q0)  # same letter
    assert int(next_state(arr, q0, jnp.int32(0), jnp.int32(a1), True)) == int(q0)  # left the area
    assert int(next_state(arr, q0, jnp.int32(a1), jnp.int32(a1), False)) == moved  # step mode


# --- Reward, Eq. (8) -------------------------------------------------------------------------------

CFG = RewardConfig(c_n=0.5, c_p=2.0, r_goal=10.0, c_regress=3.0, r_reject=7.0)


def _relaxed():
    aut = translate(TASKS["relaxed"])
    feasible = {0, aut.letter(["A1"]), aut.letter(["A2"])}
    arr = aut.arrays(feasible)
    q0 = aut.initial
    q1 = aut.delta[q0][aut.letter(["A1"])]
    (acc,) = aut.accepting
    (rej,) = aut.rejecting
    assert arr.distance.tolist()[q0] == 2 and arr.distance.tolist()[q1] == 1
    assert int(arr.distance[rej]) == UNREACHABLE
    return arr, q0, q1, acc, rej


def reward(arr, q, q_next, cfg=CFG) -> float:
    return float(progress_reward(arr, jnp.int32(q), jnp.int32(q_next), cfg))


def test_reward_cases():
    arr, q0, q1, acc, rej = _relaxed()
    assert reward(arr, q0, q0) == -0.5  # no progress: -c_n
    assert reward(arr, q1, q1) == -0.5
    assert reward(arr, q0, q1) == 2.0  # closer to acceptance: +c_p
    assert reward(arr, q1, acc) == 10.0  # task completed: r_goal
    assert reward(arr, q0, acc) == 10.0  # completed in one letter: r_goal, not c_p + r_goal
    assert reward(arr, q0, rej) == -7.0  # bad prefix: -r_reject
    assert reward(arr, acc, acc) == -0.5  # absorbing: completion is rewarded once


def test_reward_regress():
    # F (A1 & X A2): after A1 the automaton waits for A2; leaving A1 for neither area goes back.
    aut = translate("F (A1 & X A2)")
    arr = aut.arrays()
    q0 = aut.initial
    q1 = aut.delta[q0][aut.letter(["A1"])]
    assert aut.delta[q1][0] == q0 and int(arr.distance[q0]) > int(arr.distance[q1])
    assert reward(arr, q1, q0) == -3.0  # a change of state that is not closer: -c_regress
    assert reward(arr, q0, q1) == 2.0


def test_sparse_reward():
    arr, q0, q1, acc, rej = _relaxed()
    sparse = RewardConfig(r_goal=5.0, mode="sparse")
    assert [reward(arr, q, t, sparse) for q, t in [(q0, q0), (q0, q1), (q1, acc), (q0, rej), (acc, acc)]] == [
        0.0,
        0.0,
        5.0,
        0.0,
        0.0,
    ]


def test_reward_is_float32_and_vmaps():
    arr, q0, q1, acc, rej = _relaxed()
    qs = jnp.array([q0, q0, q1, q0], dtype=jnp.int32)
    nexts = jnp.array([q0, q1, acc, rej], dtype=jnp.int32)
    r = jax.jit(jax.vmap(lambda q, t: progress_reward(arr, q, t, CFG)))(qs, nexts)
    assert r.dtype == jnp.float32
    assert r.tolist() == [-0.5, 2.0, 10.0, -7.0]


def test_unknown_reward_mode_is_refused_by_the_config():
    with pytest.raises(ConfigError, match="reward.mode"):
        RewardConfig(mode="dense")


def test_step_reward_adds_the_shaping_by_hand():
    """Eq. (8) plus w (gamma Phi' - Phi), Phi = -(distance(q) scale + near) / scale, by hand."""
    arr, q0, q1, acc, rej = _relaxed()  # distance(q0) = 2, distance(q1) = 1
    cfg = RewardConfig(c_n=0.5, c_p=2.0, shaping=2.0, shaping_gamma=0.5)
    measured = lambda near, near_next: lambda: (jnp.float32(near), jnp.float32(near_next), jnp.float32(5.0))
    step = jax.jit(lambda q, t, hit, near, near_next: step_reward(arr, q, t, hit, cfg, measured(near, near_next)))
    # q0 -> q0, 1 m -> 0.5 m: -c_n + 2 (0.5 (-(10 + 0.5) / 5) - (-(10 + 1) / 5)) = -0.5 + 2 (-1.05 + 2.2)
    assert float(step(q0, q0, False, 1.0, 0.5)) == pytest.approx(-0.5 + 2.3, abs=1e-6)
    # q0 -> q1 (closer) with a collision: c_p - c_collision + 2 (0.5 (-(5 + 0.2) / 5) + 2.2)
    assert float(step(q0, q1, True, 1.0, 0.2)) == pytest.approx(2.0 - 10.0 + 2 * (-0.52 + 2.2), abs=1e-6)
    # accepting: Phi' = 0, and r_goal
    assert float(step(q1, acc, False, 0.3, 0.0)) == pytest.approx(10.0 + 2 * (0.0 + (5 + 0.3) / 5), abs=1e-6)


def test_step_reward_measures_nothing_unshaped():
    arr, q0, q1, acc, rej = _relaxed()

    def no_measuring():
        raise AssertionError("the shaping distances were measured")

    for cfg in (RewardConfig(shaping=0.0), RewardConfig(mode="sparse")):
        assert float(step_reward(arr, q0, q1, False, cfg, no_measuring)) == reward(arr, q0, q1, cfg)
