"""Layouts, presets and configuration errors; the built-in layouts are feasible as documented."""

from __future__ import annotations

import json
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _faults import paper_starting_in
from matplotlib.figure import Figure
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from d2spo.envs import EnvConfig, generator, layouts, make_env, render, workspace
from d2spo.envs.dynamics import PRESETS
from d2spo.envs.workspace import Area, Layout
from d2spo.errors import ConfigError

TINY = {
    "arena": [4.0, 3.0],
    "start": [0.5, 0.5, 0.0],
    "obstacles": [{"center": [2.0, 1.5], "half_extents": [0.3, 0.5]}],
    "areas": [{"name": "A1", "center": [3.5, 2.5], "radius": 0.3}, {"name": "A2", "center": [0.6, 2.4], "radius": 0.3}],
}


def write(tmp_path, data, name="layout.json"):
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return str(path)


def field_of(excinfo) -> str:
    return excinfo.value.field


# ----------------------------------------------------------------------------- configuration


@pytest.mark.parametrize(
    "change, field",
    [
        (lambda d: d.update(start=[2.0, 1.5, 0.0]), "layout.start"),  # inside the obstacle
        (lambda d: d.update(start=[9.0, 1.0, 0.0]), "layout.start"),  # outside the arena
        (lambda d: d["areas"][0].update(center=[3.9, 2.5]), "layout.areas[0]"),  # sticks out of the arena
        (lambda d: d["areas"][0].update(center=[7.0, 2.5]), "layout.areas[0]"),  # outside the workspace
        (lambda d: d["areas"][1].update(center=[1.8, 1.5]), "layout.areas[1]"),  # overlaps the obstacle
        (lambda d: d["areas"][1].update(radius=-0.2), "layout.areas[1].radius"),
        (lambda d: d["areas"][1].update(name="A1"), "layout.areas[1].name"),
        (lambda d: d["obstacles"][0].update(half_extents=[0.3, -1.0]), "layout.obstacles[0].half_extents[1]"),
        (lambda d: d["obstacles"][0].pop("center"), "layout.obstacles[0].center"),
        (lambda d: d.pop("areas"), "layout.areas"),
        (lambda d: d.update(arena=[4.0, 0.0]), "layout.arena[1]"),
        (lambda d: d.update(arena=[4.0]), "layout.arena"),
        (lambda d: d.update(start="home"), "layout.start"),
        (lambda d: d.update(colour="red"), "layout.colour"),  # named as inside an area (with the closest key)
        # a misspelt key inside an area or obstacle (it was dropped without a word, and a label with it)
        (lambda d: d["areas"][1].update(lable="dock"), "layout.areas[1].lable"),
        (lambda d: d["areas"][0].update(colour="red"), "layout.areas[0].colour"),
        (lambda d: d["obstacles"][0].update(height=1.0), "layout.obstacles[0].height"),
    ],
)
def test_bad_layout_json_names_the_field(tmp_path, change, field):
    data = json.loads(json.dumps(TINY))
    change(data)
    with pytest.raises(ConfigError) as e:
        layouts.load(write(tmp_path, data))
    assert field_of(e) == field


def test_an_area_no_formula_could_name_is_refused(tmp_path):
    """A name that is no proposition (``dock-west``) needs a label: without one the area could never be
    named in a task, and a task on its label would silently use the other areas of that label."""
    data = json.loads(json.dumps(TINY))
    data["areas"][0] = {k: v for k, v in data["areas"][0].items() if k != "label"} | {"name": "dock-west"}
    with pytest.raises(ConfigError, match=r'not a proposition name .* has no "label": add one') as e:
        layouts.load(write(tmp_path, data))
    assert field_of(e) == "layout.areas[0]"
    data["areas"][0]["label"] = "dock"
    assert layouts.load(write(tmp_path, data)).areas[0].label == "dock"


def test_a_misspelt_key_is_named_with_the_key_it_is_closest_to(tmp_path):
    data = json.loads(json.dumps(TINY))
    data["areas"][1]["lable"] = "dock"
    with pytest.raises(ConfigError, match=r"areas\[1\]\.lable: unknown key \(did you mean 'label'\?\); an area has "):
        layouts.load(write(tmp_path, data))
    data = json.loads(json.dumps(TINY))
    data["obstacles"][0] = {"center": data["obstacles"][0]["center"], "radious": 0.3}  # not "half_extents: missing"
    with pytest.raises(ConfigError, match=r"obstacles\[0\]\.radious: unknown key \(did you mean 'radius'\?\)"):
        layouts.load(write(tmp_path, data))
    # the message names the file, as a malformed file's does
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ConfigError, match=r"^layout: expected a JSON object, got list \(in .*list\.json\)$"):
        layouts.load(str(tmp_path / "list.json"))


def test_good_json_layout_loads_and_round_trips(tmp_path):
    layout = layouts.load(write(tmp_path, TINY, "mine.json"))
    assert layout.name == "mine" and len(layout.obstacles) == 1 and layout.area_names == ("A1", "A2")
    again = layouts.load(write(tmp_path, layout.to_json(), "again.json"))
    assert again == layout
    bom = tmp_path / "bom.json"  # as a Windows editor saves it: UTF-8 with a byte order mark
    bom.write_bytes(b"\xef\xbb\xbf" + (tmp_path / "mine.json").read_bytes())
    assert layouts.load(bom).obstacles == layout.obstacles  # a pathlib.Path too


def test_malformed_json_missing_file_and_unknown_names(tmp_path):
    with pytest.raises(ConfigError, match="malformed JSON") as e:
        layouts.load(write(tmp_path, '{"arena": [5, 5],'))
    assert field_of(e) == "layout"
    for bad in ("nowhere.json", "labyrinth", "random:x", "random:-1", "random5:x", "random7:1", ""):
        with pytest.raises(ConfigError) as e:
            layouts.load(bad)
        assert field_of(e) == "layout"


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"preset": "roomba"}, "preset"),
        ({"layout": "labyrinth"}, "layout"),
        ({"v_max": -1.0}, "v_max"),
        ({"dt": 0.0}, "dt"),
        ({"slip": 1.0}, "slip"),
        ({"noise_xy": -0.1}, "noise_xy"),
        ({"n_rays": 0}, "n_rays"),
        ({"max_steps": 0}, "max_steps"),
        ({"label_mode": "sometimes"}, "label_mode"),
        ({"label_radius": 0.0}, "label_radius"),
        ({"robot_radius": 0.7}, "layout.start"),  # the robot no longer fits at the start
        ({"robot_radius": 0.45}, "layout.areas[0]"),  # too wide for the gaps on the way to A1
    ],
)
def test_bad_env_config_names_the_field(kwargs, field):
    with pytest.raises(ConfigError) as e:
        make_env(EnvConfig(**kwargs), "phi1")
    assert field_of(e) == field


def test_task_impossible_in_layout():
    with pytest.raises(ConfigError, match="A3") as e:
        make_env(EnvConfig(layout="relaxed"), "phi1")
    assert field_of(e) == "task"


def test_presets_fill_only_unset_fields():
    cfg = EnvConfig(preset="turtlebot", v_max=0.3).resolved()
    tb = PRESETS["turtlebot"]
    assert cfg.v_max == 0.3 and cfg.omega_max == tb.omega_max == 2.84 and cfg.sensing_radius == 3.5
    assert cfg.robot_radius == 0.105 and cfg.layout_scale == 0.5 and cfg.dt == 0.2
    ideal = EnvConfig(preset="ideal").resolved()
    assert (ideal.actuator_tau, ideal.slip, ideal.noise_xy, ideal.v_gain) == (0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize("name", layouts.BUILTIN)
def test_builtin_layouts_validate_for_every_preset(name):
    layout = layouts.load(name)
    workspace.validate(layout)
    for preset in PRESETS.values():
        scaled = layout.scaled(preset.layout_scale)
        workspace.check_robot_fits(scaled, preset.robot_radius, 0.05 * preset.layout_scale)


def test_an_arena_searched_coarser_than_5_cm_says_so_when_an_area_is_unreached():
    """Over 50 m the reachability grid's cells grow past 0.05 m (1000 a side): a hand-made corridor
    written in millimetres (arena 1000 x 1000) then shows no passage, and the refusal says why."""
    import pathlib

    path = pathlib.Path(__file__).parent / "data" / "layouts" / "handmade" / "corridor-5.json"
    data = json.loads(path.read_text())
    workspace.check_robot_fits(layouts.from_json(data), 0.15)  # as drawn: reachable
    data["arena"] = [1000.0, 1000.0]
    with pytest.raises(ConfigError, match=r"cannot be reached .* grid of 1 m cells.* in metres\?"):
        workspace.check_robot_fits(layouts.from_json(data), 0.15)


def test_random5_layouts_are_feasible_and_deterministic():
    assert layouts.load("random5") == layouts.load("random5:0")
    assert layouts.load("random5:7") == generator.random_layout(7) != layouts.load("random5:8")
    for seed in range(40):
        layout = layouts.load(f"random5:{seed}")
        assert len(layout.obstacles) == 6 and layout.area_names == ("A1", "A2", "A3", "A4")
        workspace.validate(layout)
        workspace.check_robot_fits(layout, generator.RANDOM_RADIUS)
        for a in layout.areas:  # no area inside an obstacle; robot fits in every area
            assert layout.clearance(np.array(a.center)) > a.radius


def test_random5_layouts_share_shapes_so_params_batch():
    envs = [make_env(EnvConfig(layout=f"random5:{s}"), "phi2") for s in (1, 2)]
    (env, p1), (_, p2) = envs
    stacked = jax.tree.map(lambda a, b: jnp.stack([a, b]), p1, p2)  # vmap over layouts
    keys = jax.random.split(jax.random.key(0), 2)
    _, obs = jax.jit(jax.vmap(env.reset))(keys, stacked)
    assert obs.shape == (2, env.observation_size)


def test_feasible_letters():
    layout = layouts.load("paper")
    aps = ("A1", "A2", "A3", "A5")  # A5 has no area: always false; A4 is not a proposition
    assert layouts.feasible_letters(layout, aps, "event") == [1, 2, 4]
    assert layouts.feasible_letters(layout, aps, "step") == [0, 1, 2, 4]
    overlapping = Layout("o", (5.0, 5.0), (0.5, 0.5, 0.0), (), (
        Area("A1", (2.0, 2.0), 0.5), Area("A2", (2.8, 2.0), 0.5), Area("A3", (2.4, 2.6), 0.5),
        Area("A4", (4.0, 4.0), 0.4)))
    letters = layouts.feasible_letters(overlapping, ("A1", "A2", "A3", "A4"), "event")
    assert letters == [1, 2, 3, 4, 5, 6, 7, 8]  # A1, A2, A3 meet pairwise and all three together
    apart = Layout("o", (5.0, 5.0), (0.5, 0.5, 0.0), (), (
        Area("A1", (1.0, 1.0), 0.5), Area("A2", (1.9, 1.0), 0.5), Area("A3", (1.45, 1.9), 0.5)))
    assert layouts.feasible_letters(apart, ("A1", "A2", "A3"), "event") == [1, 2, 3, 4]  # no common point


def test_scaling_and_turtlebot_preset():
    env, params = make_env(EnvConfig(preset="turtlebot"), "phi1")
    assert env.layout.arena == (2.5, 2.5)
    np.testing.assert_allclose(params.area_radius, 0.175)
    assert float(params.dyn.v_max) == pytest.approx(0.22) and float(params.sensing_radius) == pytest.approx(3.5)
    crossing = 2.5 / (0.22 * 0.2)
    assert 50 <= crossing <= 60  # comparable to the default preset's 5 m / (1 m/s * 0.1 s) = 50 steps


def test_render_writes_png_without_pyplot(tmp_path):
    import sys

    layout = layouts.load("paper")
    path = tmp_path / "paper.png"
    render.save_layout_png(layout, path, trajectories=[np.array([[0.6, 0.6], [1.0, 1.2], [1.5, 1.3]])])
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fig = Figure()
    ax = fig.add_subplot()
    render.draw_layout(layout, ax, show_sensing=True)
    render.draw_trajectory(ax, np.zeros((3, 2)))
    assert len(ax.patches) >= 1 + 8 + 4 + 1
    # named, in metres, with a legend for the start arrow and the sensing circle
    render.add_legend(ax)
    assert ax.get_title() == "layout 'paper'" and ax.get_xlabel() == "x (m)" and ax.get_ylabel() == "y (m)"
    legend = {t.get_text() for t in ax.get_legend().get_texts()}
    assert {"start; arrow: initial heading", "sensing radius H = 1.2 m (around the start)", "obstacle"} <= legend
    if "matplotlib.pyplot" in sys.modules:
        assert sys.modules["matplotlib.pyplot"].get_fignums() == []


# ------------------------------------------------------------- the documented navigation claims


def shortest_path(layout, clearance, a, b, avoid=(), res=0.05):
    """Grid (8-connected) shortest path from a to the disk b, keeping ``clearance`` from obstacles
    and walls and staying out of the areas in ``avoid``. Returns waypoints [T, 2]."""
    free, centres = workspace.free_grid(layout, clearance, res)
    for area in avoid:
        free &= np.linalg.norm(centres - np.asarray(area.center), axis=-1) > area.radius + 0.1
    ny, nx = free.shape
    idx = -np.ones(free.shape, int)
    idx[free] = np.arange(free.sum())
    rows, cols, w = [], [], []
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        src = idx[: ny - dy, max(0, -dx): nx - max(0, dx)]
        dst = idx[dy:, max(0, dx): nx - max(0, -dx)]
        ok = (src >= 0) & (dst >= 0)
        rows += src[ok].tolist()
        cols += dst[ok].tolist()
        w += [math.hypot(dx, dy)] * int(ok.sum())
    graph = coo_matrix((w, (rows, cols)), shape=(free.sum(),) * 2).tocsr()
    start = idx[int(a[1] / res), int(a[0] / res)]
    dist, pred = dijkstra(graph, directed=False, indices=start, return_predecessors=True)
    flat = centres[free]
    inside = np.linalg.norm(flat - np.asarray(b.center), axis=-1) <= b.radius - 0.1
    node = int(np.argmin(np.where(inside, dist, np.inf)))
    path = [node]
    while path[-1] != start:
        path.append(pred[path[-1]])
    return flat[path[::-1]], dist[node] * res


def test_paper_layout_needs_navigation_and_fits_in_200_steps():
    """docs/layouts.md: each leg of A1 -> A2 -> A3 is blocked in a straight line, the whole route
    is about 10 m (~100 steps at 1 m/s), and phi2's route about 14 m."""
    layout = layouts.load("paper")
    area = {a.name: a for a in layout.areas}
    for route, most in ((("A1", "A2", "A3"), 11.0), (("A1", "A3", "A4", "A2"), 15.0)):
        pos, total = np.array(layout.start[:2]), 0.0
        for k, name in enumerate(route):
            avoid = [a for a in layout.areas if a.name not in (name, route[k - 1] if k else None)]
            path, length = shortest_path(layout, 0.15, pos, area[name], avoid)
            seg = pos + np.linspace(0, 1, 200)[:, None] * (path[-1] - pos)
            assert layout.clearance(seg).min() <= 0.15, f"leg to {name} is a straight line"
            total, pos = total + length, path[-1]
        assert total <= most


def test_pure_pursuit_completes_phi1_on_paper_within_200_steps():
    """A simple path follower, under the default preset's lag, slip and noise, completes phi1."""
    env, params = make_env(EnvConfig(layout="paper"), "phi1")
    layout = env.layout
    area = {a.name: a for a in layout.areas}
    waypoints, pos = [], np.array(layout.start[:2])
    for k, name in enumerate(("A1", "A2", "A3")):
        avoid = [a for a in layout.areas if a.name not in (name, ("A1", "A2")[k - 1] if k else None)]
        path, _ = shortest_path(layout, 0.15 + 0.1, pos, area[name], avoid)
        waypoints.append(path)
        pos = path[-1]
    step = jax.jit(env.step)
    state, _ = jax.jit(env.reset)(jax.random.key(0), params)
    leg, i = 0, 0
    for t in range(200):
        x, y, th = np.asarray(state.pose, np.float64)
        route = waypoints[leg]
        while i < len(route) - 1 and np.linalg.norm(route[i] - (x, y)) < 0.35:
            i += 1
        err = (math.atan2(route[i][1] - y, route[i][0] - x) - th + math.pi) % (2 * math.pi) - math.pi
        action = jnp.array([max(0.0, math.cos(err)) ** 2, np.clip(2.0 * err, -1, 1)], jnp.float32)
        state, _, _, cost, done, info = step(jax.random.key(t), state, action, params)
        assert float(cost) == 0.0
        if bool(done):
            break
        if int(info["q_next"]) != int(info["q"]):  # area reached: follow the next leg
            leg, i = leg + 1, 0
    assert bool(info["completed"]) and 60 < t + 1 < 200


def test_a_file_whose_robot_does_not_fit_is_named_in_the_refusal(tmp_path):
    """The schema's errors said "(in FILE)"; the robot's own checks (the start against the walls, an
    area it cannot reach) did not, though the file is what the user must fix."""
    from d2spo.envs.nav import checked_layout

    data = json.loads((pathlib.Path(__file__).parent / "data" / "layouts" / "handmade" / "corridor-5.json").read_text())
    near = tmp_path / "near.json"
    near.write_text(json.dumps({**data, "start": [0.1, data["start"][1], 0.0]}))  # 0.1 m from the wall
    with pytest.raises(ConfigError, match=rf"layout.start: .*would touch an obstacle or wall \(in {near}\)$"):
        checked_layout(EnvConfig(layout=str(near)))
    checked_layout(EnvConfig(layout="paper"))  # a built-in names no file


def test_a_start_inside_a_forbidden_area_is_named_in_the_refusal(tmp_path):
    """`G !A4 & F A1` from a start inside A4 was refused because "the first area the robot can enter
    from the start rejects it": the start itself is in the area, and the refusal now says so."""
    path = paper_starting_in(tmp_path / "start-in-a4.json", "A4")
    with pytest.raises(ConfigError, match=r"cannot be completed on layout 'paper': the start \(.*\) lies inside A4, and "
                                          r"the automaton reads that area at once, which fails the task before the "
                                          r"robot moves; move the start out of it$"):
        make_env(EnvConfig(layout=str(path)), "G !A4 & F A1")
