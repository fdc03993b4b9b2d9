"""Mistakes in the files a user writes (found in a user trial, 2026-12-02). A JSON integer too
large for a float (``1`` and 400 zeros: Python's json reads it as an int) in a layout, a dynamics
file or a config.json is one line and exit status 2, as any other bad number, not an OverflowError
traceback from ``math.isfinite``; a layout's misspelt top-level key is named with the key it is
closest to, and a ``description`` must be a string; a start inside an area that completes the task
is a warning, and ``env check`` counts the visits from the state an episode starts in."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _faults import cli as run_cli
from _faults import one_error

from d2spo import cli
from d2spo.cli import main
from d2spo.config import TrainConfig, config_to_dict
from d2spo.envs import layouts
from d2spo.envs.dynamics import load_dynamics
from d2spo.errors import ConfigError

HUGE = 10**400


def test_is_finite_number():
    from d2spo.errors import is_finite_number

    assert is_finite_number(1) and is_finite_number(2.5) and is_finite_number(10**300)
    for v in (HUGE, -HUGE, float("nan"), float("inf"), True, "1", None):
        assert not is_finite_number(v), v


@pytest.mark.parametrize("where", ["arena", "start", "area radius", "obstacle centre"])
def test_a_huge_integer_in_a_layout_is_one_line(tmp_path, capsys, where):
    data = layouts.load("paper").to_json()
    if where == "arena":
        data["arena"][0] = HUGE
    elif where == "start":
        data["start"][2] = HUGE
    elif where == "area radius":
        data["areas"][0]["radius"] = HUGE
    else:
        data["obstacles"][0]["center"][1] = HUGE
    path = tmp_path / "lab.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match="expected a finite number"):
        layouts.load(str(path))
    line = one_error(capsys, "env", "check", "--layout", path)
    assert "expected a finite number" in line


def test_a_huge_integer_in_a_dynamics_file_is_one_line(tmp_path, capsys):
    robot = {"dt": 0.1, "v_max": HUGE, "omega_max": 1.0, "actuator_tau": 0.0, "v_gain": 1.0,
             "omega_gain": 1.0, "slip": 0.0, "noise_xy": 0.0, "noise_theta": 0.0}
    path = tmp_path / "robot.json"
    path.write_text(json.dumps(robot))
    with pytest.raises(ConfigError, match="dynamics.v_max: expected a finite number"):
        load_dynamics(path)
    line = one_error(capsys, "env", "check", "--layout", "open", "--dynamics", path)
    assert "dynamics.v_max" in line


def test_a_huge_integer_in_a_config_file_is_one_line(tmp_path):
    text = json.dumps(config_to_dict(TrainConfig(episodes=10)))
    assert '"d": 0.3' in text
    path = tmp_path / "config.json"
    path.write_text(text.replace('"d": 0.3', f'"d": {HUGE}', 1))
    with pytest.raises(ConfigError, match="cbf.d: must be a finite number"):
        cli.parse(["train", "--config", str(path)]).config()


def test_a_misspelt_top_level_key_is_named_with_the_key_it_is_closest_to(tmp_path, capsys):
    """docs/layouts.md: other keys are rejected at the top level as inside an area, with the key
    they are closest to; the top level once said only ``unknown keys ['obstacle']``."""
    data = layouts.load("paper").to_json()
    data["obstacle"] = data.pop("obstacles")
    with pytest.raises(ConfigError, match=r"^layout\.obstacle: unknown key \(did you mean 'obstacles'\?\); a layout has "):
        layouts.from_json(data)


def test_a_description_that_is_not_a_string_is_refused():
    """docs/layouts.md gives ``description`` as an optional string, as ``name``; a number was taken."""
    data = layouts.load("paper").to_json()
    data["description"] = 7
    with pytest.raises(ConfigError, match=r"^layout\.description: expected a string, got 7$"):
        layouts.from_json(data)
    data["description"] = "free text"
    assert layouts.from_json(data).areas == layouts.load("paper").areas


def test_an_arena_larger_than_float32_positions_allow_is_one_line_and_no_numpy_warning(tmp_path, capsys):
    """A 1e308 m arena passed every check and overflowed numpy in the reachability search (a
    RuntimeWarning on stderr before the error); arenas over ``MAX_ARENA`` are refused first, and
    the largest allowed one still loads."""
    import warnings

    from d2spo.envs.workspace import MAX_ARENA

    data = {"name": "big", "arena": [1e308, 1e308], "start": [1.0, 1.0, 0.0], "obstacles": [],
            "areas": [{"name": "A1", "center": [3.0, 3.0], "radius": 0.5}]}
    with pytest.raises(ConfigError, match=r"^layout\.arena: .* larger than the 1000 m a side"):
        layouts.from_json(data)
    path = tmp_path / "big.json"
    path.write_text(json.dumps(data))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        line = one_error(capsys, "env", "check", "--layout", path, "--task", "F A1")
    assert "is the layout in metres?" in line
    data["arena"] = [MAX_ARENA, 10.0]
    assert layouts.from_json(data).arena == (MAX_ARENA, 10.0)


def test_a_heading_in_degrees_is_a_warning(tmp_path, capsys):
    """``"start": [1.5, 1.0, 90]`` (degrees) was taken without a word as 90 rad; a heading is any
    angle, so it is accepted, with one warning line saying it is read in radians."""
    from d2spo.errors import D2SPOWarning

    data = layouts.load("paper").to_json()
    data["start"][2] = 90
    with pytest.warns(D2SPOWarning, match=r"layout\.start: the heading 90 is larger than 2π; it is read in radians"):
        assert layouts.from_json(data).start[2] == 90
    data["start"][2] = -3.1
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        layouts.from_json(data)  # a heading within a turn: no warning


def _office_starting_at(tmp_path, start):
    data = json.loads((Path(__file__).parent / "data" / "layouts" / "office.json").read_text())
    data["start"] = start
    path = tmp_path / "office.json"
    path.write_text(json.dumps(data))
    return path


def test_a_start_inside_a_target_area_is_a_warning_and_needs_no_visit(tmp_path, capsys):
    """A robot that starts on its dock: the env's reset reads the dock's letter, so `F desk` accepts
    before the first step and every episode completes at once. `env check` said the task "needs 1
    area visit" and nothing warned; `train` trained it to 100% completion."""
    path = _office_starting_at(tmp_path, [4.2, 0.9, 0.0])  # the centre of desk-1, labelled desk
    for task in ("F desk", "G !kitchen & F desk"):
        rc, lines = run_cli(capsys, "env", "check", "--layout", path, "--task", task)
        assert rc == 0
        warning = [ln for ln in lines if ln.startswith("d2spo: warning:")]
        assert len(warning) == 1 and "lies inside desk-1" in warning[0] and "completes on its first step" in warning[0]


def test_env_check_counts_the_visits_from_the_state_the_start_leaves(tmp_path, capsys):
    inside = _office_starting_at(tmp_path, [4.2, 0.9, 0.0])
    capsys.readouterr()
    assert main(["env", "check", "--layout", str(inside), "--task", "F desk"]) == 0
    assert "task 'F desk': needs 0 area visits" in capsys.readouterr().out
    assert main(["env", "check", "--layout", str(inside), "--task", "F (desk & F kitchen)"]) == 0
    captured = capsys.readouterr()
    assert "needs 1 area visit on" in captured.out and "warning" not in captured.err  # desk is done: kitchen left
    outside = _office_starting_at(tmp_path, [0.6, 0.6, 0.0])
    assert main(["env", "check", "--layout", str(outside), "--task", "F (desk & F kitchen)"]) == 0
    captured = capsys.readouterr()
    assert "needs 2 area visits on" in captured.out and "warning" not in captured.err
