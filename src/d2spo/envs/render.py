"""Pictures of layouts and trajectories, with matplotlib only (Agg; no pyplot global state).

>>> fig = Figure(figsize=(5, 5)); ax = fig.add_subplot()
>>> draw_layout(layout, ax); draw_trajectory(ax, xy)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from d2spo.envs.layouts import Layout

OBSTACLE_COLOR = "black"
AREA_COLOR = "tab:green"
START_COLOR = "tab:blue"


def draw_layout(
    layout: Layout, ax, show_sensing: bool = True, sensing_radius: float = 1.2, robot_radius: float | None = None
) -> None:
    """Draw the arena, obstacles (black), labelled areas (green), start (blue) and the sensing disk,
    with axes in metres and the layout's name as the title.

    ``sensing_radius`` (H) is drawn as a dashed circle around the start when ``show_sensing``;
    ``robot_radius``, when given, draws the robot's footprint at the start. The artists carry
    legend labels: ``add_legend(ax)`` shows them.
    """
    w, h = layout.arena
    ax.add_patch(Rectangle((0, 0), w, h, fill=False, edgecolor="black", linewidth=1.5))
    for i, o in enumerate(layout.obstacles):
        ax.add_patch(Rectangle(tuple(o.lo), 2 * o.half_extents[0], 2 * o.half_extents[1], facecolor=OBSTACLE_COLOR,
                               edgecolor=OBSTACLE_COLOR, label="obstacle" if i == 0 else None))
    for i, a in enumerate(layout.areas):
        ax.add_patch(Circle(a.center, a.radius, facecolor=AREA_COLOR, alpha=0.35, edgecolor=AREA_COLOR,
                            label="area of interest (its name is the LTL proposition)" if i == 0 else None))
        ax.annotate(a.name, a.center, ha="center", va="center", fontsize=9, weight="bold")
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


def draw_trajectory(ax, xy, color: str = "tab:red", label: str | None = None) -> None:
    """Draw a path xy [T, 2] with a marker at its end."""
    xy = np.asarray(xy)
    ax.plot(xy[:, 0], xy[:, 1], "-", color=color, linewidth=1.2, label=label)
    ax.plot(xy[-1:, 0], xy[-1:, 1], "x", color=color)


def save_layout_png(
    layout: Layout, path: str | Path, trajectories=None, sensing_radius: float = 1.2, dpi: int = 100,
    title: str | None = None, trajectory_label: str = "trajectory",
) -> None:
    """Write a PNG of ``layout`` with optional trajectories (a list of [T, 2] arrays), a legend, and
    ``title`` (default: the layout's name and size)."""
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
    fig.savefig(str(path), dpi=dpi)
