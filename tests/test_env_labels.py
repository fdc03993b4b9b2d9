"""Labelled areas (several areas, one proposition) and disk obstacles (docs/layouts.md)."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization

from d2spo import cli
from d2spo.envs import EnvConfig, geometry, layout_bank, layouts, make_env, sensors, workspace
from d2spo.envs.compiled_task import compile_task
from d2spo.envs.spaces import observation_bounds
from d2spo.envs.workspace import Area, DiskObstacle
from d2spo.errors import ConfigError
from d2spo.ltl.labelling import next_state

OFFICE = Path(__file__).parent / "data" / "layouts" / "office.json"
"""Two areas labelled desk, one kitchen; a disk pillar at (2.5, 2.5), radius 0.4, and a box."""
TASK = "F (desk & F kitchen)"
PILLAR, PILLAR_R = np.array([2.5, 2.5]), 0.4


@functools.lru_cache(maxsize=None)
def office_env():
    """The office under ideal dynamics (no lag, slip or noise: a scripted robot drives where it steers)."""
    return make_env(EnvConfig(layout=str(OFFICE), preset="ideal"), task=TASK)


@functools.lru_cache(maxsize=None)
def jitted_step():
    env, _ = office_env()
    return jax.jit(env.step)


def office_json() -> dict:
    return json.loads(OFFICE.read_text())


# ------------------------------------------------------------------------------- schema


def test_round_trip_keeps_labels_and_disks():
    lay = layouts.load(str(OFFICE))
    assert lay.labels == ("desk", "kitchen")
    assert [a.label for a in lay.areas] == ["desk", "desk", "kitchen"]
    assert lay.disks == (DiskObstacle((2.5, 2.5), 0.4),) and len(lay.boxes) == 1
    written = lay.to_json()
    expected = office_json()
    del expected["description"]
    assert written == expected  # the label only where it differs from the name; the disk as center + radius
    assert layouts.from_json(json.loads(json.dumps(written))) == lay
    assert lay.describe_areas() == "desk-1 (desk), desk-2 (desk), kitchen"
    assert dataclasses.replace(lay, areas=()).describe_areas() == "none (no task can name an area here)"
    half = lay.scaled(0.5)
    assert half.disks == (DiskObstacle((1.25, 1.25), 0.2),) and [a.label for a in half.areas] == ["desk", "desk", "kitchen"]
    assert Area("A1", (1.0, 1.0), 0.3).label == "A1"  # no label: the name


@pytest.mark.parametrize("change, field", [
    (lambda d: d["areas"][0].update(label="desk 1"), "layout.areas[0].label"),
    (lambda d: d["areas"][0].update(label="F"), "layout.areas[0].label"),
    (lambda d: d["areas"][0].update(label="1desk"), "layout.areas[0].label"),
    (lambda d: d["areas"][0].update(label=3), "layout.areas[0].label"),
    (lambda d: d["areas"][2].update(center=[2.5, 3.2]), "layout.areas[2]"),  # touches the pillar
    (lambda d: d["obstacles"][0].update(center=[5.5, 2.5]), "layout.obstacles[0].center"),
    (lambda d: d["obstacles"][0].update(radius=0.0), "layout.obstacles[0].radius"),
    (lambda d: d["obstacles"][0].update(radius=-1.0), "layout.obstacles[0].radius"),
    (lambda d: d["obstacles"][0].update(half_extents=[0.2, 0.2]), "layout.obstacles[0]"),
    (lambda d: d["obstacles"][0].pop("radius"), "layout.obstacles[0].half_extents"),
    (lambda d: d.update(start=[2.5, 2.3, 0.0]), "layout.start"),  # inside the pillar
    (lambda d: d["areas"][1].update(name="desk-1"), "layout.areas[1].name"),  # names stay unique
])
def test_refusals_name_the_field(change, field):
    data = office_json()
    change(data)
    with pytest.raises(ConfigError) as e:
        layouts.from_json(data)
    assert e.value.field == field and "\n" not in str(e.value)


def test_validate_refuses_layouts_built_in_python():
    lay = layouts.load(str(OFFICE))
    with pytest.raises(ConfigError, match=r"layout.obstacles\[0\].radius"):
        workspace.validate(dataclasses.replace(lay, obstacles=(DiskObstacle((2.5, 2.5), -0.1),)))
    with pytest.raises(ConfigError, match=r"layout.areas\[0\].label: 'true' is not a proposition name"):
        workspace.validate(dataclasses.replace(lay, areas=(Area("a", (1.0, 4.0), 0.3, "true"),)))


# ----------------------------------------------------------------------------- labelling


def _drive(waypoints, env, params):
    """A scripted robot (ideal dynamics): steer at each waypoint in turn, through env.step, until the
    episode ends. Returns (info of the last step, the areas the path entered)."""
    step = jitted_step()
    state, _ = jax.jit(env.reset)(jax.random.PRNGKey(0), params)
    key, k = jax.random.PRNGKey(1), 0
    entered = set()
    for _ in range(int(params.max_steps)):
        x, y, theta = (float(v) for v in state.pose)
        while k < len(waypoints) - 1 and math.dist((x, y), waypoints[k]) < 0.1:
            k += 1
        err = math.remainder(math.atan2(waypoints[k][1] - y, waypoints[k][0] - x) - theta, 2 * math.pi)
        action = jnp.array([max(0.0, 1.0 - abs(err)), max(-1.0, min(1.0, 2.0 * err))])
        key, sub = jax.random.split(key)
        state, _, _, cost, done, info = step(sub, state, action, params)
        entered |= {a.name for a in env.layout.areas if math.dist(info["next_pose"][:2].tolist(), a.center) <= a.radius}
        assert float(cost) == 0.0
        if bool(done):
            return info, entered
    raise AssertionError("the episode did not end")


@pytest.mark.parametrize("waypoints, desk", [
    ([(0.8, 4.2), (4.2, 4.2)], "desk-2"),
    ([(1.6, 1.3), (4.2, 0.9), (4.2, 4.2)], "desk-1"),
])
def test_either_desk_completes_the_task(waypoints, desk):
    env, params = office_env()
    info, entered = _drive(waypoints, env, params)
    assert bool(info["completed"]) and bool(info["terminated"])
    assert entered == {desk, "kitchen"}


def test_kitchen_first_does_not_count_and_overlapping_areas_of_one_label_set_one_bit():
    env, params = office_env()
    aut = params.aut
    desk, kitchen = (1 << env.aps.index(p) for p in ("desk", "kitchen"))
    letter = lambda xy, p=params: env._letters(jnp.asarray(xy, jnp.float32), aut.initial, p)[1]  # noqa: E731
    assert [int(letter(xy)) for xy in [(4.2, 0.9), (0.8, 4.2), (4.2, 4.2), (1.0, 1.0)]] == [desk, desk, kitchen, 0]
    q = aut.initial
    for xy in [(4.2, 4.2), (2.0, 4.0), (4.2, 0.9)]:  # the kitchen, nothing, desk-1: desk read, kitchen to go
        q = next_state(aut, q, letter(xy), jnp.int32(0), False)
    assert not bool(aut.accepting[q])
    assert bool(aut.accepting[next_state(aut, q, letter((4.2, 4.2)), jnp.int32(0), False)])
    # two overlapping desks: their lens reads {desk}, not the two desks' bits added up
    lens = params.replace(area_center=jnp.array([[1.0, 4.0], [1.4, 4.0], [4.2, 4.2]]))
    assert int(letter((1.2, 4.0), lens)) == desk
    lay = env.layout
    lay = dataclasses.replace(lay, areas=(dataclasses.replace(lay.areas[0], center=(1.0, 4.0)),
                                          dataclasses.replace(lay.areas[1], center=(1.4, 4.0)), lay.areas[2]))
    assert layouts.feasible_letters(lay, env.aps, "event") == [desk, kitchen]


def test_targets_hold_every_area_of_the_label_and_routes_take_the_shorter_desk():
    env, params = office_env()
    task = env.task
    q0 = int(params.aut.initial)
    q1 = next(q for q in range(task.n_states) if task.fields.targets[q] == ("kitchen",))
    assert task.fields.targets[q0] == ("desk-1", "desk-2")
    assert np.asarray(params.advance)[q0].tolist() == [True, True, False]
    for a in env.layout.areas[:2]:  # the target cells cover both desks; 0.1 m off either, the field is ~0.1 m
        iy, ix = round(a.center[1] / 0.05), round(a.center[0] / 0.05)
        assert task.fields.target_cells[q0, iy, ix] and not task.fields.target_cells[q1, iy, ix]
        assert task.fields.field[q0, round((a.center[1] - a.radius - 0.1) / 0.05), ix] < 0.25
    lay = env.layout
    one_desk = [compile_task(env.automaton, dataclasses.replace(lay, areas=(lay.areas[k], lay.areas[2])), "event",
                             task.robot_radius).route_length for k in (0, 1)]
    assert task.route_length == pytest.approx(min(one_desk)) and one_desk[0] != pytest.approx(one_desk[1])


# ------------------------------------------------------------------------------ disk obstacles


def _ray_hits(xy, angles, centre, r, H):
    """Independent: march along each ray in 0.1 mm steps to the first point inside the disk."""
    t = np.arange(0.0, H, 1e-4)
    out = []
    for a in angles:
        pts = xy + t[:, None] * np.array([math.cos(a), math.sin(a)])
        inside = np.flatnonzero(np.hypot(*(pts - centre).T) <= r)
        out.append(t[inside[0]] if inside.size else H)
    return np.array(out)


def test_lidar_sees_the_pillar_at_its_range():
    env, params = office_env()
    H = float(params.sensing_radius)
    pose = np.array([1.6, 2.3, 0.2], np.float32)  # only the pillar within H; three rays hit it
    scan = np.asarray(sensors.lidar(jnp.asarray(pose), params.geom, jnp.ones(2, bool), env.n_rays, H))
    angles = pose[2] + 2 * np.pi * np.arange(env.n_rays) / env.n_rays
    expected = _ray_hits(pose[:2].astype(np.float64), angles, PILLAR, PILLAR_R, H)
    assert np.sum(expected < H) >= 3
    np.testing.assert_allclose(scan, expected, atol=1e-3)
    # invisible when not sensed; the observation's lidar block and the CBF's input read it too
    hidden = sensors.lidar(jnp.asarray(pose), params.geom, jnp.array([True, False]), env.n_rays, H)
    assert np.all(np.asarray(hidden) == H)
    state = env.reset(jax.random.PRNGKey(0), params)[0].replace(pose=jnp.asarray(pose))
    np.testing.assert_allclose(np.asarray(env.observe(state, params))[env.observation_slices["lidar"]] * H, scan,
                               atol=1e-6)
    mask = geometry.sensed_mask(jnp.asarray(pose[:2]), params.geom, H)
    assert np.asarray(mask).tolist() == [False, True]  # the box (far), the pillar (near)
    x = sensors.cbf_input(jnp.asarray(pose), sensors.sensed_obstacles(params.geom, mask), params.geom.arena_lo,
                          params.geom.arena_hi, env.n_rays, H)
    assert float(x[-1]) == pytest.approx(np.hypot(*(pose[:2] - PILLAR)) - PILLAR_R, abs=1e-5)


def test_sensed_obstacles_keep_their_checkpoint_record():
    """O_s with disks round-trips through flax bytes; without disks its record is the three fields it
    always had (checkpoints of layouts without disks stay byte for byte what they were)."""
    _, params = office_env()
    ctx = sensors.sensed_obstacles(params.geom, jnp.array([[True, False], [False, True]]))
    assert ctx.disk_center.shape == (2, 1, 2) and ctx.disk_radius.shape == (2, 1)
    blank = jax.tree.map(jnp.zeros_like, ctx)
    back = serialization.from_bytes(blank, serialization.to_bytes(ctx))
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), back, ctx))
    boxes = sensors.Sensed(ctx.box_lo, ctx.box_hi, ctx.mask[:, :1])
    assert list(serialization.to_state_dict(boxes)) == ["box_lo", "box_hi", "mask"]


def test_observation_bounds_hold_on_the_office():
    env, params = office_env()
    low, high = observation_bounds(env)
    _, obs = jax.jit(env.reset_batch, static_argnums=2)(jax.random.PRNGKey(3), params, 4)
    assert low.shape == (env.observation_size,) and np.all((low <= obs) & (obs <= high))


def test_driving_into_the_pillar_ends_the_episode_with_cost_one():
    env, params = office_env()
    gap = PILLAR_R + float(params.robot_radius) + 0.02  # 2 cm of clearance, facing the pillar
    state = env.reset(jax.random.PRNGKey(0), params)[0].replace(pose=jnp.array([2.5 - gap, 2.5, 0.0]))
    _, _, _, cost, done, info = jitted_step()(jax.random.PRNGKey(2), state, jnp.array([1.0, 0.0]), params)
    assert float(cost) == 1.0 and bool(done) and bool(info["collided"]) and bool(info["terminated"])
    assert float(info["ep_cost"]) == 1.0


def test_free_grid_and_clearance_exclude_the_pillar():
    lay = layouts.load(str(OFFICE))
    assert lay.clearance(PILLAR) == pytest.approx(-PILLAR_R)
    assert lay.clearance(PILLAR + [0.0, 0.6]) == pytest.approx(0.2)
    free, centres = workspace.free_grid(lay, 0.15, 0.05)
    d = np.hypot(*(centres - PILLAR).transpose(2, 0, 1))
    assert not free[d <= PILLAR_R + 0.15 + 0.025].any()
    assert free[(d > PILLAR_R + 0.15 + 0.03) & (d < 0.8)].all()


# ------------------------------------------------------------------------------------ the CLI


def test_env_check_and_show_accept_the_office(tmp_path, capsys):
    assert cli.main(["env", "check", "--layout", str(OFFICE), "--task", TASK]) == 0
    out = capsys.readouterr().out
    assert "2 obstacles (1 box, 1 disk), areas desk-1 (desk), desk-2 (desk), kitchen" in out and f"task {TASK!r}: needs 2" in out
    assert "a generalist can be evaluated on it" in out
    wide = tmp_path / "wide.json"  # what only `eval` of a generalist used to say
    wide.write_text(json.dumps({**office_json(), "arena": [21.0, 6.0]}))
    assert cli.main(["env", "check", "--layout", str(wide)]) == 0
    assert ("a generalist cannot be evaluated on it: layout 'office': arena 21 x 6 m; a generalist reads arenas of "
            "at most 20 m a side") in capsys.readouterr().out
    png = tmp_path / "office.png"
    assert cli.main(["env", "show", "--layout", str(OFFICE), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


@pytest.mark.parametrize("args, message", [
    (["--task", "F lounge"], "F lounge cannot be completed in layout 'office' (propositions with no area, always "
                             "false: ['lounge']; its labels: desk, kitchen)"),
    # a slip of case or spelling: the label it was likely meant to be
    (["--task", "F (Desk & F kitchen)"], "(propositions with no area, always false: ['Desk']; its labels: desk, "
                                         "kitchen; did you mean desk for Desk?)"),
    (["--task", "F (desk & F kitchn)"], "always false: ['kitchn']; its labels: desk, kitchen; did you mean kitchen "
                                        "for kitchn?)"),
    # no run satisfies it: not the layout's fault
    (["--task", "F desk & G !desk"], "F desk & G !desk is unsatisfiable: no run satisfies it, on any layout"),
    # an area's name written as a proposition: a formula names areas by label
    (["--task", "F desk_2 & F kitchen"], "always false: ['desk_2']; its labels: desk, kitchen; did you mean desk "
                                         "(area desk-2's label) for desk_2?)"),
    # operators run into a label: one proposition to the parser
    (["--task", "GFdesk"], "always false: ['GFdesk']; its labels: desk, kitchen; did you mean G F desk for GFdesk?)"),
    (["--task", "F desk | F lounge"], "proposition 'lounge' names no area of layout 'office' (no area has that label; "
                                      "its labels: desk, kitchen)"),
])
def test_a_task_naming_a_label_no_area_carries_is_one_line(args, message, capsys):
    assert cli.main(["env", "check", "--layout", str(OFFICE), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_a_bad_label_in_a_file_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    data = office_json()
    data["areas"][0]["label"] = "desk-1"
    bad.write_text(json.dumps(data))
    assert cli.main(["env", "check", "--layout", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "layout.areas[0].label: 'desk-1' is not a proposition name" in err[0]


def test_the_field_bank_holds_disks_and_shared_labels():
    office = layouts.load(str(OFFICE))
    bank = layout_bank.pack([office])
    assert np.asarray(bank.disk_mask)[0].tolist() == [True] + [False] * (layout_bank.D_MAX - 1)
    np.testing.assert_allclose(np.asarray(bank.disk_center)[0, 0], office.disks[0].center)
    assert np.asarray(bank.area_mask)[0].sum() == 3 and np.asarray(bank.box_mask)[0].sum() == 1
