"""The exported policy at run time (``d2spo.deploy``): every call a robot's driver makes refuses
malformed input in one ValueError naming the argument, ``scan_error`` tells a scan the map predicts
from one it does not, the automaton refuses a state or letter it does not have, and the filter
returns an action that already meets its condition at once. tests/test_export_cli.py holds the
command, the example and the refused exports."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from d2spo.deploy import Policy


@pytest.fixture(scope="module")
def tiny(tiny_export):
    """``_tiny_run`` of ϕ1 on ``paper`` and its export: tests/conftest.py's ``tiny_export``, built once per worker."""
    return tiny_export


def _edited(policy, ranges, pose, part: str, k: int, value: float):
    """The observation at ``pose`` with entry ``k`` of its ``part`` set to ``value``."""
    obs = policy.observation(ranges, pose, 0)
    obs[policy.parts[part].start + k] = value
    return obs


@pytest.mark.parametrize("call, match", [
    (lambda p, r, pose: p.act(r, (0.6, 0.6, float("nan")), 0), r"pose must be .*entries \[2\] are not finite"),
    (lambda p, r, pose: p.act(r, (0.6, float("inf"), 0.0), 0), r"pose must be .*not finite"),
    (lambda p, r, pose: p.act(r, (0.6, 0.6), 0), "pose must be .*got 2 values"),
    (lambda p, r, pose: p.act(r, (50.0, 0.6, 0.0), 0), "outside the arena.*layout's frame, in metres"),
    (lambda p, r, pose: p.act(r[:3], pose, 0), "ranges must be 16 lidar ranges.*got 3 values"),
    (lambda p, r, pose: p.act(r.reshape(2, 8), pose, 0), "ranges must be 16 lidar ranges"),
    (lambda p, r, pose: p.act(["1.0"] * 16, pose, 0), "ranges must be 16 lidar ranges"),
    (lambda p, r, pose: p.act(None, pose, 0), "ranges must be 16 lidar ranges"),
    (lambda p, r, pose: p.act(np.where(np.arange(16) == 3, -0.5, r), pose, 0), r"lidar ranges \[3\] are negative"),
    (lambda p, r, pose: p.act(r, pose, 1.5), "q must be an integer automaton state"),
    (lambda p, r, pose: p.act(r, pose, True), "q must be an integer automaton state"),
    (lambda p, r, pose: p.act(r, pose, None), "q must be an integer automaton state"),
    (lambda p, r, pose: p.act(r, pose, 0, filter="yes"), "filter must be True, False or None"),
    (lambda p, r, pose: p.act_observation(np.full(p.observation_size, np.nan)), "obs must be .*not finite"),
    (lambda p, r, pose: p.act_observation(np.zeros(10)), "obs must be an observation of .*got 10 values"),
    # an observation of numbers that no env gives: refused by its part, never a NaN or an unchecked pose
    (lambda p, r, pose: p.act_observation(_edited(p, r, pose, "pose", 0, 1e10)), "outside the arena"),
    (lambda p, r, pose: p.act_observation(_edited(p, r, pose, "pose", 2, 5.0)), "pose part .*not a unit vector"),
    (lambda p, r, pose: p.act_observation(_edited(p, r, pose, "lidar", 3, 50.0)), r"lidar part .*outside \[0, 1\]"),
    (lambda p, r, pose: p.act_observation(_edited(p, r, pose, "automaton", 0, 0.5)), "automaton part .*not one-hot"),
    (lambda p, r, pose: p.act_observation(_edited(p, r, pose, "path", 0, 3e38)), "path part .*longer than a unit"),
    (lambda p, r, pose: p.x_of_observation(p.observation(r, pose, 0)[:5]), "obs must be an observation of .*got 5"),
    (lambda p, r, pose: p.filter(pose, [5.0, 5.0]), r"u0 must be .*in \[-1, 1\]; got \[5.0, 5.0\]"),
    (lambda p, r, pose: p.command([float("nan"), 0.0]), "action must be .*not finite"),
    (lambda p, r, pose: p.command(0.5), "action must be .*got 1 value$"),
    (lambda p, r, pose: p.filter(pose, [float("nan"), 0.0]), "u0 must be .*not finite"),
    (lambda p, r, pose: p.filter(pose, [0.1]), "u0 must be .*got 1 value"),
    (lambda p, r, pose: p.scan((float("nan"), 0.6, 0.0)), "pose must be"),
    (lambda p, r, pose: p.task_tracker().update(0.6, 0.6), "update before reset"),
    (lambda p, r, pose: p.task_tracker().reset(float("nan"), 0.6), "x must be a finite number"),
    (lambda p, r, pose: p.task_tracker().reset(0.6, None), "y must be a finite number"),
    (lambda p, r, pose: p.task_tracker().reset(1000.0, 1000.0), r"\(1000, 1000\) lies outside the arena"),
])
def test_every_runtime_call_refuses_malformed_input_in_one_value_error(tiny, call, match):
    """A robot's driver may hand the runtime a NaN pose, a scan of the wrong size or a float state:
    each is one ValueError naming the argument, never a NaN action (the first case returned
    [nan, nan] before) nor numpy's own message or warning (a path entry of 3e38 overflowed float32's
    norm with a RuntimeWarning before it was refused)."""
    policy = Policy.load(tiny[1])
    pose = (0.6, 0.6, 0.0)
    scan = policy.scan(pose)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=match):
            call(policy, scan, pose)


def test_a_policy_without_a_filter_says_so_when_asked_to_filter(tiny):
    """``policy.filter`` of an export without one (not D²SPO) is a ValueError, not 'NoneType' is not callable."""
    from d2spo.deploy.policy import Policy as P

    policy = P.load(tiny[1])
    policy.runtime_filter = None
    with pytest.raises(ValueError, match="no runtime filter"):
        policy.filter((0.6, 0.6, 0.0), [0.1, 0.0])


def test_scan_error_tells_a_scan_the_map_predicts_from_one_it_does_not(tiny):
    """Ranges in millimetres clip to H and read as free space, and a scan of another place acts
    without complaint: ``scan_error`` is the check a robot's node can make against the map."""
    policy = Policy.load(tiny[1])
    pose = (0.6, 0.6, 0.0)
    ranges = policy.scan(pose)
    assert policy.scan_error(ranges, pose) == 0.0
    assert policy.scan_error(ranges * 1000, pose) > 0.3  # millimetres
    assert policy.scan_error(policy.scan((4.0, 4.0, 1.0)), pose) > 0.1  # another pose's scan
    with pytest.raises(ValueError, match="ranges must be"):
        policy.scan_error(ranges[:3], pose)


@pytest.mark.parametrize("pose", [(0.6, 0.6, 0.0), (2.5, 2.5, 0.0), (4.0, 4.0, 1.0)])
def test_scan_error_sees_a_pose_off_by_30_cm(tiny, pose):
    """The median over every ray read 0.000 for these poses 0.3 m off (at most 0.006): half the rays or
    more see nothing within H either way. Over the rays that see a surface, the error is 0.11 m or more."""
    policy = Policy.load(tiny[1])
    for dx, dy in ((0.3, 0.0), (0.0, 0.3), (-0.3, 0.0), (0.0, -0.3)):
        off = policy.scan((pose[0] + dx, pose[1] + dy, pose[2]))  # the scan where the robot is
        assert policy.scan_error(off, pose) > 0.1, (pose, dx, dy)  # at the pose the localisation gives
    assert policy.scan_error(np.full(policy.n_rays, np.inf), (2.5, 2.5, 0.0)) > 0.3  # nothing seen where the map has


def test_the_automaton_refuses_a_state_or_letter_it_does_not_have(tiny):
    """``Automaton.advance`` and ``is_visit`` took a negative state or letter as numpy's index from the
    end: another state's transition, silently."""
    aut = Policy.load(tiny[1]).automaton
    n_letters = aut.delta.shape[1]
    assert aut.advance(aut.initial, 0, 0) == aut.initial
    for q, letter, name in [(0, -1, "letter"), (0, n_letters, "letter"), (-1, 1, "q"), (aut.n_states, 1, "q"),
                            (0.0, 1, "q"), (0, True, "letter")]:
        with pytest.raises(ValueError, match=f"Automaton: {name} must be an integer in 0..") as e:
            aut.advance(q, letter, 0)
        with pytest.raises(ValueError, match=f"Automaton: {name} must be an integer in 0.."):
            aut.is_visit(q, letter, 0)
        assert str(e.value).count("\n") == 0


def test_the_filter_returns_an_action_that_meets_its_condition_without_iterating(tiny, monkeypatch):
    """The filter returns u0 unchanged when c(u0) >= 0; it ran its linearise-and-project iterations (two
    evaluations of h and a derivative through the ray casts each) before it looked: most of its time."""
    from d2spo.deploy.filter import Filter

    policy = Policy.load(tiny[1])
    calls = []
    h = Filter.h
    monkeypatch.setattr(Filter, "h", lambda self, x: calls.append(1) or h(self, x))
    pose = np.array([2.5, 2.5, 0.0], np.float32)
    u, ok, c = policy.filter(pose, [0.0, 0.0])  # standing still in the middle of the arena: c(0) >= 0
    assert ok and c >= 0 and np.array_equal(u, np.zeros(2, np.float32))
    assert len(calls) == 2  # h at the pose and at the predicted one, nothing more
