"""Pictures of layouts and trajectories, with matplotlib only (Agg; no pyplot global state).

>>> fig = Figure(figsize=(5, 5)); ax = fig.add_subplot()
>>> draw_layout(layout, ax); draw_trajectory(ax, xy)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import is_color_like
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from d2spo.envs.workspace import DiskObstacle, Layout, Obstacle
from d2spo.plotstyle import BLACK, BLUE, PALETTE, SKY_BLUE, VERMILLION, save_figure

OBSTACLE_COLOR = BLACK
AREA_COLOR = SKY_BLUE
LABEL_COLORS = PALETTE[:-1]
"""Area colours by label, in order of first use, when some label is shared by several areas
(the Okabe–Ito colours but black, the obstacles' colour)."""
START_COLOR = BLUE
ROBOT_COLOR = VERMILLION


def obstacle_patch(o: Obstacle | DiskObstacle, **style):
    """A matplotlib patch of one obstacle: a rectangle for a box, a circle for a disk."""
    if isinstance(o, DiskObstacle):
        return Circle(o.center, o.radius, **style)
    return Rectangle(tuple(o.lo), 2 * o.half_extents[0], 2 * o.half_extents[1], **style)


def area_colors(layout: Layout) -> list[str]:
    """Each area's colour: ``AREA_COLOR`` when every label is one area's, else one colour per label:
    the label itself when every label names a colour (``zones:SEED``'s green, yellow, blue and
    magenta), else ``LABEL_COLORS`` in order of first use."""
    labels = layout.labels
    if len(labels) == len(layout.areas):
        return [AREA_COLOR] * len(layout.areas)
    if all(is_color_like(label) for label in labels):
        return [a.label for a in layout.areas]
    return [LABEL_COLORS[labels.index(a.label) % len(LABEL_COLORS)] for a in layout.areas]


def draw_layout(
    layout: Layout, ax, show_sensing: bool = True, sensing_radius: float = 1.2, robot_radius: float | None = None
) -> None:
    """Draw the arena, obstacles (black boxes and disks), named areas (sky blue; coloured by label when
    several areas share one, one legend entry per label, the label written beside each area whose
    label is not its name), start (blue) and the sensing disk, with axes in metres and the layout's
    name as the title.

    ``sensing_radius`` (H) is drawn as a dashed circle around the start when ``show_sensing``;
    ``robot_radius``, when given, draws the robot's footprint at the start. The artists carry
    legend labels: ``add_legend(ax)`` shows them.
    """
    w, h = layout.arena
    ax.add_patch(Rectangle((0, 0), w, h, fill=False, edgecolor="black", linewidth=1.5))
    for i, o in enumerate(layout.obstacles):
        ax.add_patch(obstacle_patch(o, facecolor=OBSTACLE_COLOR, edgecolor=OBSTACLE_COLOR,
                                    label="obstacle" if i == 0 else None))
    labelled = any(a.label != a.name for a in layout.areas)
    legend = f"area of interest (its {'label' if labelled else 'name'} is the LTL proposition)"
    colors = area_colors(layout)
    named = set()  # one legend entry per colour: each label's when areas share labels
    for a, color in zip(layout.areas, colors, strict=True):
        entry = legend if len(set(colors)) == 1 else f"area labelled {a.label!r}"
        ax.add_patch(Circle(a.center, a.radius, facecolor=color, alpha=0.35, edgecolor=color,
                            label=None if entry in named else entry))
        named.add(entry)
        ax.annotate(a.name, a.center, ha="center", va="center", fontsize=9, weight="bold")
        if a.label != a.name:  # the proposition, beside the area (on the side towards the arena's middle)
            left = a.center[0] > w / 2
            ax.annotate(a.label, (a.center[0] + (-a.radius if left else a.radius), a.center[1] + a.radius),
                        ha="right" if left else "left", va="bottom", fontsize=8, style="italic")
    sx, sy, st = layout.start
    ax.plot([sx], [sy], "o", color=START_COLOR, markersize=6, zorder=3, label="start; arrow: initial heading")
    ax.annotate("", (sx + 0.25 * np.cos(st) * max(w, h) / 5, sy + 0.25 * np.sin(st) * max(w, h) / 5), (sx, sy),
                arrowprops={"arrowstyle": "->", "color": START_COLOR})
    if robot_radius is not None:
        ax.add_patch(Circle((sx, sy), robot_radius, fill=False, edgecolor=START_COLOR,
                            label=f"robot footprint (radius {robot_radius:g} m)"))
    if show_sensing:
        ax.add_patch(Circle((sx, sy), sensing_radius, fill=False, edgecolor=START_COLOR, linestyle="--", alpha=0.6,
                            label=f"sensing radius H = {sensing_radius:g} m (around the start)"))
    ax.set_xlim(-0.02 * w, 1.02 * w)
    ax.set_ylim(-0.02 * h, 1.02 * h)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"layout {layout.name!r}")


def add_legend(ax, extra=()) -> None:
    """A legend under the axes for the labelled artists of ``draw_layout`` (and ``extra`` handles)."""
    handles, _ = ax.get_legend_handles_labels()
    handles = handles + list(extra)
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=7, frameon=False)


def draw_trajectory(ax, xy, color: str = VERMILLION, label: str | None = None) -> None:
    """Draw a path xy [T, 2] with a marker at its end."""
    xy = np.asarray(xy)
    ax.plot(xy[:, 0], xy[:, 1], "-", color=color, linewidth=1.2, label=label)
    ax.plot(xy[-1:, 0], xy[-1:, 1], "x", color=color)


def save_layout_png(
    layout: Layout, path: str | Path, trajectories=None, sensing_radius: float = 1.2,
    title: str | None = None, trajectory_label: str = "trajectory",
) -> Path:
    """Write a picture of ``layout`` (PNG at 300 dpi, or PDF/SVG by the suffix: ``plotstyle.save_figure``)
    with optional trajectories (a list of [T, 2] arrays), a legend, and ``title`` (default: the
    layout's name and size)."""
    fig = Figure(figsize=(5.5, 6.0), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    draw_layout(layout, ax, sensing_radius=sensing_radius)
    for i, xy in enumerate(trajectories or ()):
        draw_trajectory(ax, xy, label=trajectory_label if i == 0 else None)
    n = len(layout.obstacles)
    ax.set_title(title or f"layout {layout.name!r}: {layout.arena[0]:g} m x {layout.arena[1]:g} m, "
                          f"{n} obstacle{'s' * (n != 1)}, {len(layout.areas)} areas", fontsize=10)
    add_legend(ax)
    return save_figure(fig, path, "out")


class FrameRenderer:
    """RGB frames of the robot in a layout, for Gymnasium's ``render_mode="rgb_array"``.

    The layout is drawn once; each frame moves the robot disk, its heading and its sensing circle.
    """

    def __init__(self, layout: Layout, robot_radius: float, sensing_radius: float, pixels: int = 400):
        self.fig = Figure(figsize=(4, 4), dpi=pixels / 4)
        self.canvas = FigureCanvasAgg(self.fig)
        self.ax = self.fig.add_subplot()
        draw_layout(layout, self.ax, show_sensing=False)
        self.body = Circle((0.0, 0.0), robot_radius, facecolor=ROBOT_COLOR, edgecolor=ROBOT_COLOR, zorder=4)
        self.sensing = Circle((0.0, 0.0), sensing_radius, fill=False, edgecolor=ROBOT_COLOR, linestyle="--",
                              alpha=0.6, zorder=4)
        self.ax.add_patch(self.body)
        self.ax.add_patch(self.sensing)
        (self.heading,) = self.ax.plot([], [], "-", color="white", linewidth=1.5, zorder=5)
        self.robot_radius = robot_radius

    def __call__(self, pose, title: str = "") -> np.ndarray:
        """uint8 [height, width, 3]: the layout with the robot at ``pose`` = (x, y, theta)."""
        x, y, theta = (float(v) for v in pose)
        self.body.center = self.sensing.center = (x, y)
        r = self.robot_radius
        self.heading.set_data([x, x + r * np.cos(theta)], [y, y + r * np.sin(theta)])
        self.ax.set_title(title)
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()
