"""The look every figure shares (``d2spo.plotstyle``): 300 dpi PNG, or PDF/SVG by the suffix, any
other suffix refused in one line; one colour scale per figure, labelled axes, legends that name
every mark, no empty panel. Figures drawn from synthetic data: nothing is trained or compiled."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.colors import to_hex
from matplotlib.figure import Figure
from PIL import Image

from d2spo import cli, map_plots, plot_outcomes, plots, plotstyle
from d2spo.envs import layouts, render
from d2spo.envs.compiled_task import default_task
from d2spo.errors import ConfigError
from d2spo.ltl import task_automaton, task_formula


def _bare_figure() -> Figure:
    fig = Figure(figsize=(2.0, 1.5))
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1])
    ax.set_title("a title wider than the figure itself, which a tight box keeps whole")
    return fig


def test_save_figure_writes_300_dpi_png_or_vector_pdf_svg_by_the_suffix(tmp_path):
    png = plotstyle.save_figure(_bare_figure(), tmp_path / "f.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = Image.open(png)
    assert round(image.info["dpi"][0]) == 300
    assert image.size[0] > 2.0 * 300  # the long title is kept (bbox_inches="tight"), not cut at 2 in
    assert plotstyle.save_figure(_bare_figure(), tmp_path / "f.pdf").read_bytes()[:5] == b"%PDF-"
    svg = plotstyle.save_figure(_bare_figure(), tmp_path / "f.SVG").read_text()
    assert svg.startswith("<?xml") and "<svg" in svg


@pytest.mark.parametrize("name", ["f.jpg", "f.eps", "f.txt", "f"])
def test_save_figure_refuses_another_suffix_before_drawing(name, tmp_path):
    with pytest.raises(ConfigError, match=r"^out: .*not a picture format; end the name in one of \.png, \.pdf, \.svg$"):
        plotstyle.save_figure(_bare_figure(), tmp_path / name, "out")
    with pytest.raises(ConfigError, match="the folder .* does not exist"):
        plotstyle.save_figure(_bare_figure(), tmp_path / "no" / "f.png")
    assert not list(tmp_path.iterdir())


def test_env_show_writes_the_format_its_out_names_and_refuses_jpg_in_one_line(tmp_path, capsys):
    assert cli.main(["env", "show", "--out", str(tmp_path / "x.pdf")]) == 0
    assert (tmp_path / "x.pdf").read_bytes()[:5] == b"%PDF-"
    assert cli.main(["env", "show", "--out", str(tmp_path / "x.svg")]) == 0
    assert b"<svg" in (tmp_path / "x.svg").read_bytes()
    capsys.readouterr()
    assert cli.main(["env", "show", "--out", str(tmp_path / "x.jpg")]) == 2  # matplotlib could, d2spo does not
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"d2spo: error: --out: {tmp_path / 'x.jpg'}: not a picture format; end the name in one of "
                   ".png, .pdf, .svg"]


def _plot_axes(fig):
    return [ax for ax in fig.axes if not hasattr(ax, "_colorbar")]


def _legend_texts(fig) -> list[str]:
    return [t.get_text() for leg in fig.legends for t in leg.get_texts()]


def test_state_fields_share_one_colour_scale_that_leaves_out_contact_and_names_what_it_shows():
    task = default_task(task_automaton(task_formula("phi2")), "paper", "event")
    fig = map_plots.draw_state_fields_figure(task)
    bars = [ax for ax in fig.axes if hasattr(ax, "_colorbar")]
    panels = _plot_axes(fig)
    assert len(bars) == 1 and len(panels) == 6  # phi2 on paper: six states with a target, one colourbar
    label = bars[0].get_ylabel()
    assert label.startswith("d_q: path length to a target, weighted\n(m;") and "× 2 within" in label
    images = [ax.get_images()[0] for ax in panels]
    assert len({(im.norm.vmin, im.norm.vmax) for im in images}) == 1  # one scale for every panel
    # the scale is set by the nodes the robot can stand on: the contact band (× 100 per step, up to
    # ~49 m here) is drawn apart, so the open space is not squeezed into the bottom of the scale
    contact, penalty = map_plots.field_regions(task)
    top = images[0].norm.vmax
    field = task.fields.field
    assert top == pytest.approx(max(float(field[q][~contact].max()) for q in range(task.n_states)
                                    if task.fields.target_cells[q].any()))
    assert top < 15.0 < field.max() < penalty
    for ax in panels:
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("x (m)", "y (m)")
    legend = _legend_texts(fig)
    assert {"target: entering makes progress", "forbidden: entering rejects or sets back",
            "robot touches an obstacle or wall (step cost × 100)", "obstacle", "start"} <= set(legend)
    fig.canvas.draw()
    for ax in panels:  # titles fit their panel's width
        assert ax.title.get_window_extent().width <= 1.05 * ax.get_window_extent().width, ax.get_title()


def _paths(n: int):
    rng = np.random.default_rng(0)
    paths, rates = [], []
    for k in range(n):
        lay = layouts.load(f"random:{11 + k}")
        xy = rng.normal(0, 0.05, (3, 20, 2)).cumsum(1) + np.array(lay.start[:2])
        poses = np.concatenate([xy, np.zeros((3, 20, 1))], -1)
        paths.append((lay, poses, np.array([0, 1, 0], bool), np.array([1, 0, 0], bool)))
        rates.append({"completion_rate": 1 / 3, "safety_rate": 2 / 3, "episodes": 3})
    return paths, rates


@pytest.mark.parametrize("n,rows", [(1, 1), (4, 2), (5, 2), (7, 2)])
def test_evaluation_figure_has_one_panel_per_layout_and_no_empty_one(n, rows):
    fig = plots.draw_evaluation_figure(*_paths(n), "run")
    axes = fig.axes
    shown = min(n, plots.EVAL_PLOT_LAYOUTS)
    assert len(axes) == shown
    assert len({ax.get_subplotspec().rowspan.start for ax in axes}) == rows
    for ax in axes:
        assert len(ax.lines) >= 3 and ax.patches  # trajectories and the layout on every panel
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("x (m)", "y (m)")
    legend = _legend_texts(fig)
    assert {"obstacle", "trajectory: task completed (x: end)", "trajectory: collision (x: end)",
            "trajectory: out of time (x: end)"} <= set(legend)


def test_a_patrols_panels_give_its_visits_not_a_completion_no_episode_reaches():
    """A recurrence's per-layout rates carry ``route_optimal_visits``: its panels read as ``d2spo eval``
    prints them, and the legend names a patrol's normal end (the step limit), not "out of time"."""
    paths, rates = _paths(2)
    rates = [{**r, "completion_rate": 0.0, "accepting_visits_per_episode": 14.83, "route_optimal_visits": 26,
              "visit_fraction": 14.83 / 26} for r in rates]
    fig = plots.draw_evaluation_figure(paths, rates, "run")
    titles = [ax.get_title() for ax in fig.axes]
    assert all(": 66.7% safe\n14.8 of 26 route-optimal visits (57.0%)\n" in t for t in titles), titles
    assert not any("completed" in t for t in titles)
    legend = _legend_texts(fig)
    assert "trajectory: ran to the step limit, as a patrol does (x: end)" in legend
    assert "trajectory: out of time (x: end)" not in legend and "trajectory: task completed (x: end)" not in legend
    fig.canvas.draw()
    for ax in fig.axes:  # titles fit their panel's width
        assert ax.title.get_window_extent().width <= 1.05 * ax.get_window_extent().width, ax.get_title()
    # a co-safe task's panels are as before
    co = plots.draw_evaluation_figure(*_paths(1), "run")
    assert co.axes[0].get_title().startswith("random:11: 33.3% completed, 66.7% safe")


@pytest.mark.parametrize("n, layout", [(1, None), (2, None), (3, None), (4, None), (1, "rooms-12x8.json"),
                                       (2, "handmade/warehouse-16.json"), (3, "handmade/corridor-12.json")])
def test_evaluation_figure_text_does_not_overlap(n, layout):
    """Two panels once drew the figure's title over the panels' titles and the legend over the x
    labels (the figure too short for square panels and their text); so did one panel of a 12 x 8 m
    lab with eight areas (a user's, tests/data/layouts/rooms-12x8.json: a long legend)."""
    paths, rates = _paths(n)
    if layout is not None:
        lay = layouts.load(str(Path(__file__).parent / "data" / "layouts" / layout))
        paths = [(lay, np.zeros_like(poses) + np.array([*lay.start[:2], 0.0]), *rest) for _, poses, *rest in paths]
    fig = plots.draw_evaluation_figure(paths, rates, "gen: phi2 / default, runtime filter on")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    top = fig._suptitle.get_window_extent(renderer)
    legend = fig.legends[0].get_window_extent(renderer)
    for ax in fig.axes:
        assert ax.title.get_window_extent(renderer).y1 <= top.y0, ax.get_title()
        assert ax.xaxis.label.get_window_extent(renderer).y0 >= legend.y1 or \
            ax.get_subplotspec().rowspan.stop < ax.get_gridspec().nrows, ax.get_title()


def test_a_long_title_is_wrapped_within_the_figure():
    """``d2spo eval --plot``'s title holds the task's formula: a long one ran off the figure's sides."""
    task = " & ".join(f"G F room{i}" for i in range(12)) + " & G !stairs"
    suptitle = f"gen: {task} / default, runtime filter on"
    fig = plots.draw_evaluation_figure(*_paths(1), suptitle)
    fig.canvas.draw()
    box = fig._suptitle.get_window_extent(fig.canvas.get_renderer())
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width, (box, fig.bbox)
    assert fig._suptitle.get_text().replace("\n", " ") == suptitle  # wrapped between words, nothing lost


def test_a_panel_names_the_file_its_layout_came_from_where_the_names_differ():
    """Two copies of a lab file that both say ``"name": "lab"`` drew two panels titled alike."""
    paths, rates = _paths(3)
    rates = [{**rates[0], "layout": "labs/lab_v2.json"}, {**rates[1], "layout": "random:12"},
             {**rates[2], "layout": "labs/random:13.json"}]
    titles = [ax.get_title() for ax in plots.draw_evaluation_figure(paths, rates, "run").axes]
    assert titles[0].startswith("random:11 (lab_v2.json): "), titles[0]
    assert titles[1].startswith("random:12: ") and titles[2].startswith("random:13: "), titles


def test_reward_curves_name_every_line_and_band_with_units(tmp_path):
    ax = Figure().add_subplot()
    x = np.arange(5) + 10
    plots.draw_reward_curves(ax, {"LPPO": (x, x * 1.0, np.ones(5), 3), "D²SPO": (x, x * 2.0, np.ones(5), 1)}, "t")
    assert ax.get_xlabel() == "training episodes"
    assert ax.get_ylabel() == "episode return (moving average over 10 episodes)"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "LPPO: mean over 3 seeds", "LPPO: ± 1 std", "D²SPO: mean over 1 seed"]  # one seed: no band
    empty = Figure().add_subplot()
    plots.draw_reward_curves(empty, {}, "t")
    assert [t.get_text() for t in empty.texts] == ["no runs"]  # not a blank panel


def test_layout_colours_are_the_colour_blind_safe_palette_or_the_labels_own():
    palette = {to_hex(c) for c in plotstyle.PALETTE}
    assert to_hex(render.AREA_COLOR) in palette and {to_hex(c) for c in render.LABEL_COLORS} <= palette
    assert {to_hex(c) for c in plot_outcomes.OUTCOME_COLORS.values()} <= palette
    zones = layouts.load("zones:3")
    assert render.area_colors(zones) == [a.label for a in zones.areas]  # green, yellow, ...: the labels
    ax = Figure().add_subplot()
    render.draw_layout(zones, ax)
    names = set(ax.get_legend_handles_labels()[1])
    assert {f"area labelled {label!r}" for label in zones.labels} <= names  # one entry per colour


def test_certify_figure_is_a_300_dpi_png(tmp_path):
    lay = layouts.load("paper")
    maps = [np.array([[-1, 0], [1, 2]]), np.zeros((2, 2), int)]
    summary = {"residual": {"rho_h": 0.1}, "counterexamples": {"L": [], "D": [{"pose": [1.0, 1.0], "counterexample": True}]},
               "run": "runs/x"}
    path = tmp_path / "certify.png"
    map_plots.certify_figure(lay, maps, (0, 5, 0, 5), summary, 0.05, 0.05, path)
    assert round(Image.open(path).info["dpi"][0]) == 300


@pytest.mark.parametrize("task", ["phi2", "patrol2"])
def test_the_fields_figures_texts_lie_inside_it(task):
    """Six panels (phi2) or two (a patrol): the colourbar's label, the titles and the legend are
    inside the figure (a one-line label once ran off a two-panel figure's edge)."""
    fig = map_plots.draw_state_fields_figure(default_task(task_automaton(task_formula(task)), "paper", "event"))
    fig.canvas.draw()
    box = fig.bbox
    bar = next(ax for ax in fig.axes if hasattr(ax, "_colorbar"))
    texts = [bar.yaxis.label, fig._suptitle, *(ax.title for ax in _plot_axes(fig)), *fig.legends]
    for t in texts:
        ext = t.get_window_extent()
        assert box.x0 - 1 <= ext.x0 and ext.x1 <= box.x1 + 1 and box.y0 - 1 <= ext.y0 and ext.y1 <= box.y1 + 1, t
