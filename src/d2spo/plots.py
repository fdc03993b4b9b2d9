"""Every figure of d2spo, drawn from data: run directories, their episode curves and snapshots.

* the policy figure of ``d2spo demo``: trajectories on the layout and the learned CBF;
* ``d2spo eval --plot``'s trajectories per layout (``evaluation_figure``);
* Figs. 2–3 (``reward_figure``): moving-average return per method, mean and ± 1 std over seeds;
* Fig. 4 (``cbf_figure``): the learned h as a surface and as level sets, one run per layout;
* Fig. 5 (``snapshot_figure``): the executed policy's trajectories at the run's policy snapshots;
* maps over one layout (``d2spo certify``'s picture, ``d2spo ltl --plot``'s shaping fields) are in
  ``d2spo.map_plots``.

Each thing is drawn by one function (``draw_trajectories``, in ``d2spo.plot_outcomes`` with the
outcomes' colours and names; ``draw_cbf``, ``draw_reward_curves``) that the figures share. ``d2spo.reproduce`` only chooses which run directories go into which
figure. Colours, colour maps and the file writer come from ``d2spo.plotstyle`` (Okabe–Ito colours,
one colour scale per figure, PNG at 300 dpi or PDF/SVG by the suffix). Matplotlib only, with
Figure objects (no pyplot global state), so it is safe in tests and servers.
"""

from __future__ import annotations

import textwrap
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.gridspec import GridSpec
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from d2spo.envs import geometry
from d2spo.envs.render import add_legend, draw_layout
from d2spo.errors import RunDirError
from d2spo.plot_outcomes import draw_trajectories, outcome_handles
from d2spo.plotstyle import (
    BLACK,
    BLUISH_GREEN,
    ORANGE,
    REDDISH_PURPLE,
    SIGNED_CMAP,
    SKY_BLUE,
    VERMILLION,
    save_figure,
)
from d2spo.rollout import make_rollout
from d2spo.run import load_policy, load_run_config, load_snapshot
from d2spo.runio import read_episodes


def policy_trajectories(learner, policy, env, params, episodes: int, seed: int, rollout=None):
    """Poses [E, T+1, 3] (NaN after each episode's end) and per-episode (collided, completed).
    ``rollout``: a ``rollout.make_rollout`` of the same learner and size, to reuse its compilation
    (e.g. for several snapshots of one run)."""
    if rollout is None:
        rollout = make_rollout(learner, env, episodes, int(params.max_steps))
    collided, completed, _, _, poses, *_ = rollout(params, policy, jax.random.PRNGKey(seed))
    return np.asarray(poses), np.asarray(collided), np.asarray(completed)


def cbf_grid(learner, safety, heading: float = 0.0, resolution: int = 80):
    """h(b(z, O)) on a grid of positions at a fixed heading, with every obstacle sensed.

    Returns (xs, ys, H [res, res], inside [res, res]) where ``inside`` marks positions whose
    robot disk overlaps an obstacle or a wall.
    """
    params = learner.params
    lo, hi = np.asarray(params.geom.arena_lo), np.asarray(params.geom.arena_hi)
    xs = np.linspace(lo[0], hi[0], resolution)
    ys = np.linspace(lo[1], hi[1], resolution)
    gx, gy = np.meshgrid(xs, ys)
    poses = jnp.stack([gx.ravel(), gy.ravel(), jnp.full(gx.size, heading)], axis=-1).astype(jnp.float32)

    # one compiled program: op by op, vmap dispatches (and compiles) every primitive of the lidar
    # on its own, 2.4 s for one grid in a fresh process against well under a second jitted
    @jax.jit
    def grid(cbf, poses):
        ctx = learner.sensed(jnp.ones((poses.shape[0], learner.n_obstacles), bool))
        h = learner.safety_nets.cbf.apply(cbf, jax.vmap(learner.features)(poses, ctx))
        return h, jax.vmap(lambda p: geometry.collides(p[:2], params.geom, params.robot_radius))(poses)

    h, inside = grid(safety.cbf, poses)
    return xs, ys, np.asarray(h).reshape(gx.shape), np.asarray(inside).reshape(gx.shape)


def signed_norm(*hs) -> Normalize:
    """One colour scale, symmetric about h = 0, for every grid of h in ``hs``."""
    lim = max((float(np.nanmax(np.abs(h))) for h in hs), default=0.0) or 1.0
    return Normalize(-lim, lim)


def draw_cbf(ax, xs, ys, h, layout, norm: Normalize | None = None, levels: int = 15):
    """Filled contours of h (a ``cbf_grid``) over the workspace on ``norm`` (default: this grid's
    ``signed_norm``), its zero level set as a black line, the layout on top; returns the filled
    contours (for a colourbar). The caller titles the axes."""
    norm = norm or signed_norm(h)
    cs = ax.contourf(xs, ys, h, levels=np.linspace(norm.vmin, norm.vmax, levels + 1), cmap=SIGNED_CMAP, norm=norm)
    ax.contour(xs, ys, h, levels=[0.0], colors=BLACK, linewidths=1.5)
    draw_layout(layout, ax, show_sensing=False)
    return cs


CBF_LABEL = "h, the learned CBF (h ≥ 0: safe set)"
"""The colourbar label of every picture of h."""
ZERO_LINE = Line2D([], [], color=BLACK, linewidth=1.5, label="h = 0 (edge of the safe set)")
"""The legend entry of ``draw_cbf``'s zero level set."""


def rates_title(rates: Mapping) -> str:
    """A panel's outcome in words: "C% completed, S% safe", or for a recurrence (``rates`` with
    ``route_optimal_visits``) "S% safe" and, on a second line, "V of N route-optimal visits (F%)".
    Rates to 0.1%: whole percents would draw 99.5% safe as "100% safe"."""
    safe = f"{rates['safety_rate']:.1%} safe"
    best = rates.get("route_optimal_visits")
    if best is None:
        return f"{rates['completion_rate']:.1%} completed, {safe}"
    frac = rates.get("visit_fraction")
    share = "" if frac is None else f" ({frac:.1%})"
    return f"{safe}\n{rates['accepting_visits_per_episode']:.1f} of {best} route-optimal visits{share}"


def policy_figure(path: Path, learner, policy, env, params, episodes: int = 8, seed: int = 0,
                  title: str = "", suptitle: str = "") -> dict:
    """Write ``draw_policy_figure`` to ``path``; returns the safety and completion rates it shows."""
    fig, rates = draw_policy_figure(learner, policy, env, params, episodes, seed, title, suptitle)
    save_figure(fig, path)
    return rates


def draw_policy_figure(learner, policy, env, params, episodes: int = 8, seed: int = 0, title: str = "",
                       suptitle: str = "") -> tuple[Figure, dict]:
    """Layout with the policy's trajectories (left) and, for D²SPO, the learned CBF (right), under
    ``suptitle`` (default: the layout's name); and the safety and completion rates of the episodes."""
    poses, collided, completed = policy_trajectories(learner, policy, env, params, episodes, seed)
    has_cbf = hasattr(learner, "safety_nets")
    fig = Figure(figsize=(11 if has_cbf else 5.5, 6.2), layout="constrained")  # constrained: no title is clipped
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if has_cbf else 1, 1)
    draw_layout(env.layout, ax, sensing_radius=float(params.sensing_radius))
    drawn = draw_trajectories(ax, poses, collided, completed)
    ax.set_title(title or f"{completed.mean():.0%} completed, {1 - collided.mean():.0%} safe "
                          f"({poses.shape[0]} episodes)")
    add_legend(ax, outcome_handles(drawn=drawn))
    if has_cbf:
        ax = fig.add_subplot(1, 2, 2)
        xs, ys, h, _ = cbf_grid(learner, policy[1], heading=0.0)
        filled = draw_cbf(ax, xs, ys, h, env.layout)
        ax.set_title("learned CBF h at heading 0°")
        cb = fig.colorbar(filled, ax=ax, shrink=0.8, ticks=MaxNLocator(8))
        cb.set_label(CBF_LABEL)
        add_legend(ax, [ZERO_LINE])
    fig.suptitle(suptitle or f"layout {env.layout.name!r}")
    return fig, {"safety_rate": float(1 - collided.mean()), "completion_rate": float(completed.mean())}


EVAL_PLOT_LAYOUTS = 6
"""``d2spo eval --plot`` draws at most this many layouts (the first ones of ``--layout-seeds``)."""


def panel_grid(fig: Figure, n: int, ncols: int) -> list:
    """``n`` axes in rows of ``ncols`` (fewer when ``n`` is smaller), the last row centred: no empty
    panel and no hole."""
    ncols = max(1, min(ncols, n))
    nrows = -(-n // ncols)
    grid = GridSpec(nrows, 2 * ncols, figure=fig)
    axes = []
    for k in range(n):
        row, col = divmod(k, ncols)
        shift = ncols - (n - row * ncols) if row == nrows - 1 else 0  # half-panels the last row is moved right
        axes.append(fig.add_subplot(grid[row, 2 * col + shift:2 * col + shift + 2]))
    return axes


def evaluation_figure(path: Path, paths: Sequence[tuple], per_layout: Sequence[dict], suptitle: str) -> Path:
    """``d2spo eval --plot``: write ``draw_evaluation_figure`` to ``path`` (``plotstyle.save_figure``)."""
    return save_figure(draw_evaluation_figure(paths, per_layout, suptitle), path, "plot")


def draw_evaluation_figure(paths: Sequence[tuple], per_layout: Sequence[dict], suptitle: str) -> Figure:
    """For each of the first ``EVAL_PLOT_LAYOUTS`` layouts, the layout and the trajectories of its
    first episodes (``paths``: (Layout, poses, collided, completed) per layout, from
    ``evaluate_run(keep_paths=k)``), titled with that layout's rates over all its episodes; one
    panel per layout (``panel_grid``) and one legend under the panels that names every mark. A
    recurrence's panels give its accepting visits per episode against the route-optimal count
    (``rates_title``), as ``d2spo eval`` prints them, instead of a completion no episode reaches."""
    shown = list(zip(paths, per_layout, strict=True))[:EVAL_PLOT_LAYOUTS]
    ncols = 2 if len(shown) == 4 else 3
    nrows = -(-len(shown) // min(ncols, len(shown)))
    labels = {f"area labelled {a.label!r}" for (lay, *_), _ in shown for a in lay.areas}
    legend_rows = -(-(len(labels) + 6) // 2)  # the areas' labels, obstacle, start and the outcomes (two columns)
    height = 4.6 * nrows + 1.6 + 0.25 * max(0, legend_rows - 5)
    # constrained layout neither sees the panels' equal aspect nor says when it gives up: a figure it
    # cannot fit draws the titles over each other (a 12 x 8 m lab's long legend did), so it is drawn
    # taller until nothing overlaps
    for _ in range(8):
        fig = _evaluation_panels(shown, ncols, (max(4.6 * min(ncols, len(shown)), 7.0), height), suptitle)
        if not text_overlaps(fig):
            break
        height += 0.4
    return fig


def _evaluation_panels(shown, ncols: int, size: tuple[float, float], suptitle: str) -> Figure:
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    handles, drawn = {}, set()
    for ax, ((layout, poses, collided, completed), rates) in zip(panel_grid(fig, len(shown), ncols), shown):
        draw_layout(layout, ax, show_sensing=False)
        drawn |= draw_trajectories(ax, poses, collided, completed)
        ax.set_title(f"{panel_name(layout, rates.get('layout'))}: {rates_title(rates)}\n"
                     f"({rates['episodes']} episodes; {poses.shape[0]} drawn)", fontsize=9)
        handles.update(zip(*reversed(ax.get_legend_handles_labels())))
    recurrence = any("route_optimal_visits" in rates for _, rates in shown)
    handles.update({h.get_label(): h for h in outcome_handles(recurrence, drawn)})
    fig.legend(handles=list(handles.values()), loc="outside lower center", ncol=2, fontsize=8, frameon=False)
    # a long formula (a user's patrol of six rooms) ran off both sides of the figure: wrapped at the
    # figure's width, about 11 characters an inch at 11 points
    fig.suptitle(textwrap.fill(suptitle, max(40, int(11 * size[0])), break_long_words=False), fontsize=11)
    return fig


def panel_name(layout, spec: str | None) -> str:
    """A panel's layout: its name, and the file it was read from where the file is named otherwise
    (two copies of one lab file, both ``"name": "lab"``, were two panels titled alike)."""
    if isinstance(spec, str) and spec.endswith(".json") and Path(spec).stem != layout.name:
        return f"{layout.name} ({Path(spec).name})"
    return layout.name


def text_overlaps(fig: Figure) -> bool:
    """Whether a panel's title reaches into the figure's title, or a bottom panel's x label into the
    legend under the panels (``draw_evaluation_figure``'s layout)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    top = fig._suptitle.get_window_extent(renderer).y0 if fig._suptitle is not None else np.inf
    bottom = fig.legends[0].get_window_extent(renderer).y1 if fig.legends else -np.inf
    for ax in fig.axes:
        if ax.title.get_window_extent(renderer).y1 > top:
            return True
        last_row = ax.get_subplotspec().rowspan.stop == ax.get_gridspec().nrows
        if last_row and ax.xaxis.label.get_window_extent(renderer).y0 < bottom:
            return True
    return False


# ---------------------------------------------------------------------- Figs. 2-3: reward curves
def smoothing_window(n_episodes: int, smooth: int = 200) -> int:
    """Episodes per moving-average point: ``smooth``, but at most a fifth of a short run, so that a
    quick run still draws a curve of a few points rather than a single one."""
    return max(1, min(smooth, n_episodes // 5))


def reward_curves(runs: Mapping[str, Iterable[Path]], smooth: int = 200) -> dict[str, tuple]:
    """Per label (its run directories, one per seed): (episode index, mean return over seeds, std,
    seeds) of the moving-average return over ``smoothing_window`` episodes (seeds cut to the
    shortest); the index is the episode count at the end of each window. Runs without episodes
    are skipped, and so is a label without any."""
    result = {}
    for label, dirs in runs.items():
        rs = []
        for d in dirs:
            p = Path(d) / "episodes.csv"
            ret = np.array([r[1] for r in read_episodes(p)], float) if p.is_file() else np.zeros(0)
            if len(ret) > 0:
                rs.append(ret)
        if not rs:
            continue
        n = min(len(r) for r in rs)
        k = smoothing_window(n, smooth)
        a = np.stack([np.convolve(r[:n], np.ones(k) / k, mode="valid") for r in rs])
        result[label] = (np.arange(a.shape[1]) + k, a.mean(0), a.std(0), len(rs))
    return result


def draw_reward_curves(ax, curves: Mapping[str, tuple], title: str) -> None:
    """``reward_curves`` as lines in the palette's order, each with its ± 1 std band over two or more
    seeds, both named in the legend (with the number of seeds); 'no runs' when there is no curve."""
    for label, (x, mean, std, seeds) in curves.items():
        line = ax.plot(x, mean, label=f"{label}: mean over {seeds} seed{'s' * (seeds != 1)}",
                       marker="o" if len(x) == 1 else None)[0]
        if seeds > 1:  # one seed has no spread: no band, and no legend entry for one
            ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.2, label=f"{label}: ± 1 std")
    ax.set_xlabel("training episodes")
    ax.xaxis.set_major_locator(MaxNLocator(5, integer=True))  # 20000-episode labels do not run together
    widths = sorted({int(x[0]) for x, *_ in curves.values()})  # a curve's first point ends its first window
    ax.set_ylabel(f"episode return (moving average over {'/'.join(map(str, widths))} episodes)" if widths
                  else "episode return (moving average)")
    ax.set_title(title)
    if curves:
        ax.legend(fontsize=7)
    else:
        ax.text(0.5, 0.5, "no runs", ha="center", transform=ax.transAxes)


CURVE_COLOURS = [SKY_BLUE, ORANGE, BLUISH_GREEN, REDDISH_PURPLE, VERMILLION, BLACK]
"""The order learners' curves take their colours in (Figs. 2-3, ``d2spo compare``)."""


def reward_figure(path: Path, panels: Sequence[tuple[str, Mapping[str, Iterable[Path]]]], smooth: int = 200) -> Path:
    """Figs. 2–3: one panel per (title, {label: run directories}), side by side."""
    fig = _figure(len(panels))
    for i, (title, runs) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        ax.set_prop_cycle(color=CURVE_COLOURS)
        draw_reward_curves(ax, reward_curves(runs, smooth), title)
    return save_figure(fig, path)


# ------------------------------------------------------------------ Fig. 4: the CBF on each layout
def cbf_figure(path: Path, runs: Sequence[tuple[str, Path]], heading: float = 0.0) -> Path:
    """Fig. 4: per (name, run directory), the learned h at a fixed heading as a surface (top row)
    and as level sets with h = 0 in black (bottom row), on one colour scale with one colourbar; a
    run without a checkpoint is 'not run' in both rows."""
    grids = {}
    for name, d in runs:
        if (Path(d) / "checkpoint.json").is_file():
            _, learner, policy, _ = load_policy(d)
            grids[name] = (*cbf_grid(learner, policy[1], heading, resolution=60)[:3], learner.env.layout)
    norm = signed_norm(*(g[2] for g in grids.values()))
    n = len(runs)
    fig = _figure(n, 2, size=4.0)
    filled = None
    for i, (name, _) in enumerate(runs):
        ax3 = fig.add_subplot(2, n, i + 1, projection="3d")
        ax2 = fig.add_subplot(2, n, i + n + 1)
        ax3.set_title(f"({chr(ord('a') + i)}) {name}")
        ax3.set_xlabel("x (m)")
        ax3.set_ylabel("y (m)")
        ax3.set_zlabel("h")
        level_title = f"({chr(ord('a') + n + i)}) {name}: level sets"
        if name not in grids:  # said in words on both panels
            ax2.set_title(level_title)
            ax2.set_xlabel("x (m)")
            ax2.set_ylabel("y (m)")
            ax2.text(0.5, 0.5, "not run", ha="center", transform=ax2.transAxes)
            ax3.text2D(0.5, 0.5, "not run", ha="center", transform=ax3.transAxes)
            continue
        xs, ys, h, layout = grids[name]
        gx, gy = np.meshgrid(xs, ys)
        ax3.plot_surface(gx, gy, h, cmap=SIGNED_CMAP, norm=norm, linewidth=0, antialiased=False)
        filled = draw_cbf(ax2, xs, ys, h, layout, norm)
        ax2.set_title(level_title)  # after draw_layout, which titles the axes with the layout's name
    if filled is not None:
        fig.colorbar(filled, ax=fig.axes, shrink=0.6, label=CBF_LABEL, ticks=MaxNLocator(8))
        fig.legend(handles=[ZERO_LINE, *layout_handles(fig.axes)], loc="outside lower center", ncol=4,
                   fontsize=8, frameon=False)
    return save_figure(fig, path)


def layout_handles(axes) -> list:
    """The legend entries ``draw_layout`` left on ``axes``, each label once."""
    handles = {}
    for ax in axes:
        handles.update(zip(*reversed(ax.get_legend_handles_labels())))
    return list(handles.values())


# ------------------------------------------------------- Fig. 5: trajectories during training
def snapshot_figure(path: Path, run_dir: Path, trajectories: int = 8) -> Path:
    """Fig. 5: the layout, then the executed policy's trajectories at each of the run's policy
    snapshots (``TrainConfig.snapshots``), ``trajectories`` episodes each (seed: the panel's index);
    one legend under the panels names every mark."""
    cfg = load_run_config(run_dir)
    if not cfg.snapshots:  # a figure of the layout alone, under a legend of marks it does not draw
        raise RunDirError(f"{run_dir}: trained without policy snapshots (TrainConfig.snapshots, "
                          "`d2spo reproduce fig5` trains with them); nothing to draw")
    cfg, learner, _, _ = load_policy(run_dir)
    snapshots = tuple(cfg.snapshots)
    env, params = learner.env, learner.params
    fig = _figure(1 + len(snapshots), size=4.0)
    ax = fig.add_subplot(1, 1 + len(snapshots), 1)
    draw_layout(env.layout, ax, sensing_radius=float(params.sensing_radius))
    ax.set_title("(a) layout, start and sensing radius")
    rollout = make_rollout(learner, env, trajectories, int(params.max_steps))  # one compilation for every snapshot
    drawn = set()
    for i, n in enumerate(snapshots):
        policy = load_snapshot(run_dir, n, learner)
        poses, collided, completed = policy_trajectories(learner, policy, env, params, trajectories, seed=i,
                                                         rollout=rollout)
        ax = fig.add_subplot(1, 1 + len(snapshots), i + 2)
        draw_layout(env.layout, ax, show_sensing=False)
        drawn |= draw_trajectories(ax, poses, collided, completed)
        ax.set_title(f"({chr(ord('b') + i)}) after {n} episodes\n{completed.mean():.0%} complete, "
                     f"{1 - collided.mean():.0%} safe ({poses.shape[0]} runs)")
    fig.legend(handles=layout_handles(fig.axes) + outcome_handles(drawn=drawn), loc="outside lower center", ncol=3,
               fontsize=8, frameon=False)
    return save_figure(fig, path)


def _figure(ncols: int, nrows: int = 1, size: float = 4.5) -> Figure:
    """A figure of ``ncols`` x ``nrows`` panels of ``size`` inches, laid out by the constrained engine
    (``tight_layout`` clips two-line titles over equal-aspect axes)."""
    fig = Figure(figsize=(size * ncols, size * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    return fig
