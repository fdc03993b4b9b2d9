"""Maps over one layout: ``d2spo certify``'s picture (``certify_figure``) from its status maps, and
``d2spo ltl TASK --layout L --plot``'s shaping field per automaton state (``state_fields_figure``).
The shared pieces (layout drawing, legends, the file writer) come from ``d2spo.plots``,
``d2spo.envs.render`` and ``d2spo.plotstyle``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Patch

from d2spo.envs import geodesic
from d2spo.envs.render import OBSTACLE_COLOR, START_COLOR, draw_layout, obstacle_patch
from d2spo.plots import layout_handles, panel_grid
from d2spo.plotstyle import (
    BLACK,
    BLUISH_GREEN,
    FIELD_CMAP,
    GREY,
    ORANGE,
    SKY_BLUE,
    VERMILLION,
    save_figure,
)

CERTIFY_COLORS = {"outside the set": "white", "certified": BLUISH_GREEN, "not certified": ORANGE,
                  "violated": VERMILLION}
"""``certify_figure``'s colours of the status maps' values -1, 0, 1, 2, named as its legend names them."""


def certify_figure(layout, maps: list[np.ndarray], extent: tuple, summary: dict, eps_unsafe: float,
                   eps_safe: float, path: str | Path) -> None:
    """``d2spo certify``'s picture (RUN/certify.png) from its status maps (``certify.status_maps``):
    where Proposition 1 (ℒ and contact) and Proposition 2 (the grid's explored part; then the whole
    free space, if checked) are certified, not certified or violated, worst over θ and states; the
    search's worst points as x. One legend names every colour and mark."""
    cmap = ListedColormap(list(CERTIFY_COLORS.values()))
    rho = summary["residual"]["rho_h"]
    titles = (f"Prop. 1: h < 0 in the ring and contact (ε̄ = {eps_unsafe:g} m)",
              f"Prop. 2: e ≥ 0 on explored cells (D; ε = {eps_safe:g} m, ρ_h = {rho:.3g})",
              "Prop. 2 beyond D: every free pose, every live state")
    fig = Figure(figsize=(5.5 * len(maps), 5.6), layout="constrained")
    FigureCanvasAgg(fig)
    for i, m in enumerate(maps):
        ax = fig.add_subplot(1, len(maps), i + 1)
        ax.imshow(m + 1, origin="lower", extent=extent, cmap=cmap, vmin=-0.5, vmax=3.5, interpolation="nearest")
        draw_layout(layout, ax, show_sensing=False)
        key = "L" if i == 0 else "D"
        if i < 2:
            for c in summary["counterexamples"][key]:
                ax.plot(c["pose"][0], c["pose"][1], "x", color=BLACK if c["counterexample"] else GREY, markersize=7)
        ax.set_title(titles[i], fontsize=9)
    marks = [Patch(facecolor=c, edgecolor=GREY, label=f"{k} (worst over θ and automaton state)" if k == "violated" else k)
             for k, c in CERTIFY_COLORS.items()]
    marks += [Line2D([], [], color=c, marker="x", linestyle="", label=lab) for c, lab in
              ((BLACK, "worst point found by the search: a counterexample"), (GREY, "worst point found: no counterexample"))]
    fig.legend(handles=layout_handles(fig.axes) + marks, loc="outside lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle(str(summary["run"]), fontsize=10)
    save_figure(fig, path)


# ------------------------------------------------ d2spo ltl --plot: the shaping field per state
def field_regions(task) -> tuple[np.ndarray, float]:
    """Where ``task``'s fields (``envs.state_fields``) leave the useful range: bool [ny, nx] of the
    nodes where the robot would touch an obstacle or a wall (step cost × ``collide_cost``), and the
    penalty of a forbidden read (``BLOCKED_COST`` arena diagonals): a node whose d_q reaches it
    has no route to a target without one."""
    f, layout = task.fields.field, task.layout
    xs, ys = np.linspace(0.0, layout.arena[0], f.shape[2]), np.linspace(0.0, layout.arena[1], f.shape[1])
    box_lo = np.array([o.lo for o in layout.boxes], float).reshape(-1, 2)
    box_hi = np.array([o.hi for o in layout.boxes], float).reshape(-1, 2)
    clear = geodesic.clearance(xs, ys, box_lo, box_hi, layout.arena, [(*d.center, d.radius) for d in layout.disks])
    return clear < task.field_costs["robot_radius"], geodesic.BLOCKED_COST * float(np.hypot(*layout.arena))


def state_fields_figure(task, path: str | Path) -> Path:
    """``d2spo ltl TASK --layout L --plot``: write ``draw_state_fields_figure`` to ``path``
    (``plotstyle.save_figure``: PNG at 300 dpi, or PDF/SVG by the suffix)."""
    return save_figure(draw_state_fields_figure(task), path, "plot")


def draw_state_fields_figure(task) -> Figure:
    """One panel per automaton state of ``task`` (an ``envs.compiled_task.CompiledTask`` with
    fields) that still has a target: its shaping field d_q on one colour scale with one colourbar,
    its target and forbidden nodes; the nodes where the robot would touch an obstacle or wall, and
    those past the forbidden-read penalty, are drawn apart (grey, hatched) so that they do not
    stretch the scale."""
    aut, fields, layout, costs = task.automaton, task.fields, task.layout, task.field_costs
    states = [q for q in range(aut.n_states) if fields.target_cells[q].any()]
    contact, penalty = field_regions(task)
    apart = {q: contact | (fields.field[q] >= penalty) for q in states}
    top = max((float(fields.field[q][~apart[q]].max(initial=0.0)) for q in states), default=0.0)
    norm = Normalize(0.0, top or 1.0)
    cols = min(len(states), 3) or 1
    rows = max(1, -(-len(states) // cols))
    fig = Figure(figsize=(4.0 * cols + 1.2, 4.3 * rows + 1.3), layout="constrained")
    FigureCanvasAgg(fig)
    w, h = layout.arena
    axes = panel_grid(fig, len(states), cols) if states else [fig.add_subplot()]
    step = 0.5 if top <= 10 else 1.0
    past_penalty = False
    for ax, q in zip(axes, states):
        f = fields.field[q]
        gx, gy = np.linspace(0, w, f.shape[1]), np.linspace(0, h, f.shape[0])
        shown = np.ma.masked_where(apart[q], f)
        im = ax.imshow(shown, origin="lower", extent=(0, w, 0, h), cmap=FIELD_CMAP, norm=norm, interpolation="nearest")
        ax.contour(gx, gy, shown, levels=np.arange(step, top, step), colors="white", linewidths=0.4, alpha=0.6)
        past_penalty |= bool((f[~contact] >= penalty).any())
        for mask, style in ((apart[q], {"colors": [GREY], "hatches": ["//"]}),
                            (fields.target_cells[q], {"colors": [SKY_BLUE], "hatches": [None]}),
                            (fields.forbidden_cells[q], {"colors": [VERMILLION], "hatches": ["xx"]})):
            if mask.any():
                ax.contourf(gx, gy, mask.astype(float), levels=[0.5, 1.5], alpha=0.9, **style)
        for o in layout.obstacles:
            ax.add_patch(obstacle_patch(o, color=OBSTACLE_COLOR))
        for a in layout.areas:
            ax.add_patch(Circle(a.center, a.radius, fill=False, edgecolor="white", linewidth=0.8))
            ax.annotate(a.name, a.center, ha="center", va="center", fontsize=8, weight="bold", color="white")
        ax.plot([layout.start[0]], [layout.start[1]], "o", color=START_COLOR, markeredgecolor="white", markersize=6)
        d = "" if task.distance is None else f", {task.distance[q]} to go"
        formula = aut.state_formulas[q]
        formula = formula if len(formula) <= 38 else formula[:36] + "…"
        ax.set_title(f"state {q}{d}: to {' '.join(fields.targets[q]) or '-'}, "
                     f"not {' '.join(fields.forbidden[q]) or '-'}\n{formula}", fontsize=8)
        ax.set_xlim(0, w)
        ax.set_ylim(0, h)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    if not states:  # no state has a target: say so rather than leave the panel empty
        axes[0].text(0.5, 0.5, "no automaton state has a target on this layout", ha="center",
                     transform=axes[0].transAxes)
        axes[0].set_xlabel("x (m)")
        axes[0].set_ylabel("y (m)")
    else:
        fig.colorbar(im, ax=axes, shrink=0.8,
                     label=f"d_q: path length to a target, weighted\n(m; × {costs['clearance_cost']:g} "
                           f"within {costs['clearance']:g} m of an obstacle or wall)")  # two lines: fits a 2-panel figure
    apart_name = f"robot touches an obstacle or wall (step cost × {costs['collide_cost']:g})"
    if past_penalty:
        apart_name += f", or every route enters a forbidden area (d_q ≥ {penalty:.0f} m)"
    marks = [Patch(facecolor=SKY_BLUE, label="target: entering makes progress"),
             Patch(facecolor=VERMILLION, hatch="xx", label="forbidden: entering rejects or sets back"),
             Patch(facecolor=GREY, hatch="//", label=apart_name),
             Patch(facecolor=OBSTACLE_COLOR, label="obstacle"),
             Line2D([], [], marker="o", markerfacecolor="none", markeredgecolor=GREY, linestyle="", markersize=9,
                    label="area (white outline)"),
             Line2D([], [], color=START_COLOR, marker="o", linestyle="", label="start"),
             Line2D([], [], color=GREY, linewidth=0.8, label=f"white lines: d_q every {step:g} m")]
    fig.legend(handles=marks, loc="outside lower center", ncol=3, fontsize=7, frameon=False)
    fig.suptitle(f"shaping field d_q per automaton state on layout {layout.name!r}", fontsize=10)
    return fig
