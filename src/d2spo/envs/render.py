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
    """Draw the arena, obstacles (black), labelled areas (green), start (blue) and the sensing disk.

    ``sensing_radius`` (H) is drawn as a dashed circle around the start when ``show_sensing``;
    ``robot_radius``, when given, draws the robot's footprint at the start.
    """
    w, h = layout.arena
    ax.add_patch(Rectangle((0, 0), w, h, fill=False, edgecolor="black", linewidth=1.5))
    for o in layout.obstacles:
        ax.add_patch(Rectangle(tuple(o.lo), 2 * o.half_extents[0], 2 * o.half_extents[1],
                               facecolor=OBSTACLE_COLOR, edgecolor=OBSTACLE_COLOR))
    for a in layout.areas:
        ax.add_patch(Circle(a.center, a.radius, facecolor=AREA_COLOR, alpha=0.35, edgecolor=AREA_COLOR))
        ax.annotate(a.name, a.center, ha="center", va="center", fontsize=9, weight="bold")
    sx, sy, st = layout.start
    ax.plot([sx], [sy], "o", color=START_COLOR, markersize=6, zorder=3)
    ax.annotate("", (sx + 0.25 * np.cos(st) * max(w, h) / 5, sy + 0.25 * np.sin(st) * max(w, h) / 5), (sx, sy),
                arrowprops={"arrowstyle": "->", "color": START_COLOR})
    if robot_radius is not None:
        ax.add_patch(Circle((sx, sy), robot_radius, fill=False, edgecolor=START_COLOR))
    if show_sensing:
        ax.add_patch(Circle((sx, sy), sensing_radius, fill=False, edgecolor=START_COLOR, linestyle="--", alpha=0.6))
    ax.set_xlim(-0.02 * w, 1.02 * w)
    ax.set_ylim(-0.02 * h, 1.02 * h)
    ax.set_aspect("equal")
    ax.set_title(layout.name)


def draw_trajectory(ax, xy, color: str = "tab:red", label: str | None = None) -> None:
    """Draw a path xy [T, 2] with a marker at its end."""
    xy = np.asarray(xy)
    ax.plot(xy[:, 0], xy[:, 1], "-", color=color, linewidth=1.2, label=label)
    ax.plot(xy[-1:, 0], xy[-1:, 1], "x", color=color)


def save_layout_png(
    layout: Layout, path: str | Path, trajectories=None, sensing_radius: float = 1.2, dpi: int = 100
) -> None:
    """Write a PNG of ``layout`` with optional trajectories (a list of [T, 2] arrays)."""
    fig = Figure(figsize=(5, 5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    draw_layout(layout, ax, sensing_radius=sensing_radius)
    for xy in trajectories or ():
        draw_trajectory(ax, xy)
    fig.savefig(str(path), dpi=dpi, bbox_inches="tight")


def save_state_fields_png(layout: Layout, aut, fields, path: str | Path, distance=None, dpi: int = 90) -> None:
    """One panel per automaton state that still has a target: the shaping distance field
    (``envs.state_fields.StateFields``) with its target nodes (green) and forbidden nodes (red).

    ``aut`` is the ``Automaton``; ``distance`` its distances on this layout (shown in the titles).
    """
    states = [q for q in range(aut.n_states) if fields.target_cells[q].any()]
    cols = min(len(states), 3) or 1
    rows = max(1, -(-len(states) // cols))
    fig = Figure(figsize=(4.2 * cols, 4.4 * rows))
    FigureCanvasAgg(fig)
    w, h = layout.arena
    for k, q in enumerate(states):
        ax = fig.add_subplot(rows, cols, k + 1)
        f = fields.field[q]
        vmax = float(np.percentile(f, 90))
        im = ax.imshow(f, origin="lower", extent=(0, w, 0, h), cmap="viridis", vmin=0.0, vmax=vmax)
        ax.contour(np.linspace(0, w, f.shape[1]), np.linspace(0, h, f.shape[0]), f,
                   levels=np.arange(0.5, vmax, 0.5), colors="white", linewidths=0.4, alpha=0.6)
        for mask, color in ((fields.target_cells[q], "tab:green"), (fields.forbidden_cells[q], "tab:red")):
            if mask.any():
                ax.contourf(np.linspace(0, w, mask.shape[1]), np.linspace(0, h, mask.shape[0]), mask.astype(float),
                            levels=[0.5, 1.5], colors=[color], alpha=0.75)
        for o in layout.obstacles:
            ax.add_patch(Rectangle(tuple(o.lo), 2 * o.half_extents[0], 2 * o.half_extents[1], color=OBSTACLE_COLOR))
        for a in layout.areas:
            ax.add_patch(Circle(a.center, a.radius, fill=False, edgecolor="white", linewidth=0.8))
            ax.annotate(a.name, a.center, ha="center", va="center", fontsize=8, weight="bold", color="white")
        ax.plot([layout.start[0]], [layout.start[1]], "o", color=START_COLOR, markersize=5)
        d = "" if distance is None else f", {distance[q]} to go"
        formula = aut.state_formulas[q]
        formula = formula if len(formula) <= 42 else formula[:40] + "…"
        ax.set_title(f"state {q}{d}: to {' '.join(fields.targets[q]) or '-'}, "
                     f"not {' '.join(fields.forbidden[q]) or '-'}\n{formula}", fontsize=8)
        ax.set_xlim(0, w)
        ax.set_ylim(0, h)
        ax.set_aspect("equal")
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, label="distance (m)")
    fig.suptitle(f"shaping distance per automaton state on {layout.name} (green: target, red: forbidden)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(str(path), dpi=dpi)
