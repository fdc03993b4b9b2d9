"""Every figure of d2spo, drawn from data: run directories, their episode curves and snapshots.

* the policy figure of ``d2spo demo``: trajectories on the layout and the learned CBF;
* ``d2spo eval --plot``'s trajectories per layout (``evaluation_figure``);
* Figs. 2–3 (``reward_figure``): moving-average return per method, mean and ± 1 std over seeds;
* Fig. 4 (``cbf_figure``): the learned h as a surface and as level sets, one run per layout;
* Fig. 5 (``snapshot_figure``): the executed policy's trajectories at the run's policy snapshots;
* ``d2spo certify``'s picture (``certify_figure``) from its status maps;
* ``d2spo ltl TASK --layout L --plot``'s shaping fields per automaton state (``state_fields_figure``).

Each thing is drawn by one function (``draw_trajectories``, ``draw_cbf``, ``draw_reward_curves``)
that the figures share. ``d2spo.reproduce`` only chooses which run directories go into which
figure. Matplotlib only, with Figure objects (no pyplot global state), so it is safe in tests and
servers.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle

from d2spo.envs import geometry
from d2spo.envs.render import OBSTACLE_COLOR, START_COLOR, add_legend, draw_layout, draw_trajectory, obstacle_patch
from d2spo.errors import ConfigError
from d2spo.rollout import make_rollout
from d2spo.run import load_policy, load_snapshot
from d2spo.runio import read_episodes

OUTCOME_COLORS = {"completed": "tab:purple", "collided": "tab:red", "neither": "tab:orange"}
"""Trajectory colours: the task completed (true labelling), a collision, or the episode ran out."""
OUTCOME_NAMES = {"completed": "task completed", "collided": "collision", "neither": "out of time"}
"""How the legends name each outcome of ``OUTCOME_COLORS``."""


def check_picture_path(path: Path, field: str) -> None:
    """ConfigError unless matplotlib can write a picture to ``path`` (flag ``field``): a format it
    knows by the suffix, in a folder that exists. Checked before the work that draws it."""
    path = Path(path)
    formats = FigureCanvasAgg(Figure()).get_supported_filetypes()
    if path.suffix[1:].lower() not in formats:
        raise ConfigError(field, f"{path}: not a picture format; end the name in one of "
                          f"{', '.join('.' + f for f in sorted(formats))}")
    if not path.parent.is_dir():
        raise ConfigError(field, f"{path}: the folder {path.parent} does not exist")


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
    ctx = learner.sensed(jnp.ones((poses.shape[0], learner.n_obstacles), bool))
    x = jax.vmap(learner.features)(poses, ctx)
    h = learner.safety_nets.cbf.apply(safety.cbf, x)
    inside = jax.vmap(lambda p: geometry.collides(p[:2], params.geom, params.robot_radius))(poses)
    return xs, ys, np.asarray(h).reshape(gx.shape), np.asarray(inside).reshape(gx.shape)


def draw_cbf(ax, xs, ys, h, layout, levels: int = 15, zero_color: str = "white", zero_width: float = 1.5):
    """Filled contours of h (a ``cbf_grid``) over the workspace, its zero level set as a line, the
    layout on top; returns the filled contours (for a colorbar). The caller titles the axes."""
    lim = float(np.nanmax(np.abs(h))) or 1.0
    cs = ax.contourf(xs, ys, h, levels=levels, cmap="RdYlGn", vmin=-lim, vmax=lim)
    ax.contour(xs, ys, h, levels=[0.0], colors=zero_color, linewidths=zero_width)
    draw_layout(layout, ax, show_sensing=False)
    return cs


def draw_trajectories(ax, poses, collided, completed) -> None:
    """Each episode's path (poses [E, T+1, 3], NaN after its end) coloured by its outcome."""
    for i in range(poses.shape[0]):
        xy = poses[i, :, :2]
        xy = xy[np.all(np.isfinite(xy), axis=-1)]
        outcome = "collided" if collided[i] else ("completed" if completed[i] else "neither")
        draw_trajectory(ax, xy, color=OUTCOME_COLORS[outcome])


def policy_figure(path: Path, learner, policy, env, params, episodes: int = 8, seed: int = 0,
                  title: str = "", suptitle: str = "") -> dict:
    """Write ``draw_policy_figure`` to ``path``; returns the safety and completion rates it shows."""
    fig, rates = draw_policy_figure(learner, policy, env, params, episodes, seed, title, suptitle)
    fig.savefig(str(path), dpi=100)
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
    draw_trajectories(ax, poses, collided, completed)
    ax.set_title(title or f"{completed.mean():.0%} completed, {1 - collided.mean():.0%} safe "
                          f"({poses.shape[0]} episodes)")
    add_legend(ax, [Line2D([], [], color=c, label=f"trajectory: {OUTCOME_NAMES[k]} (x: end)")
                    for k, c in OUTCOME_COLORS.items()])
    if has_cbf:
        ax = fig.add_subplot(1, 2, 2)
        xs, ys, h, _ = cbf_grid(learner, policy[1], heading=0.0)
        filled = draw_cbf(ax, xs, ys, h, env.layout)
        ax.set_title("learned CBF h at heading 0° (white: h = 0)")
        cb = fig.colorbar(filled, ax=ax, shrink=0.8)
        cb.set_label("h, the learned CBF (h ≥ 0: safe set)")
    fig.suptitle(suptitle or f"layout {env.layout.name!r}")
    return fig, {"safety_rate": float(1 - collided.mean()), "completion_rate": float(completed.mean())}


EVAL_PLOT_LAYOUTS = 6
"""``d2spo eval --plot`` draws at most this many layouts (the first ones of ``--layout-seeds``)."""


def evaluation_figure(path: Path, paths: Sequence[tuple], per_layout: Sequence[dict], suptitle: str) -> Path:
    """``d2spo eval --plot``: for each of the first ``EVAL_PLOT_LAYOUTS`` layouts, the layout and the
    trajectories of its first episodes (``paths``: (Layout, poses, collided, completed) per layout,
    from ``evaluate_run(keep_paths=k)``), titled with that layout's rates over all its episodes."""
    shown = list(zip(paths, per_layout, strict=True))[:EVAL_PLOT_LAYOUTS]
    ncols = min(3, len(shown))
    nrows = -(-len(shown) // ncols)
    fig = _figure(ncols, nrows, size=4.6, min_width=7.0)  # one panel: room for the title
    for k, ((layout, poses, collided, completed), rates) in enumerate(shown):
        ax = fig.add_subplot(nrows, ncols, k + 1)
        draw_layout(layout, ax, show_sensing=False)
        draw_trajectories(ax, poses, collided, completed)
        ax.set_title(f"{layout.name}: {rates['completion_rate']:.0%} completed, {rates['safety_rate']:.0%} safe\n"
                     f"({rates['episodes']} episodes; {poses.shape[0]} drawn)", fontsize=9)
        if k == 0:
            add_legend(ax, [Line2D([], [], color=c, label=f"{OUTCOME_NAMES[o]} (x: end)") for o, c in OUTCOME_COLORS.items()])
    fig.suptitle(suptitle, fontsize=11)
    fig.tight_layout()
    fig.savefig(str(path), dpi=90)
    return Path(path)


# ---------------------------------------------------------------------- Figs. 2-3: reward curves
def smoothing_window(n_episodes: int, smooth: int = 200) -> int:
    """Episodes per moving-average point: ``smooth``, but at most a fifth of a short run, so that a
    quick run still draws a curve of a few points rather than a single one."""
    return max(1, min(smooth, n_episodes // 5))


def reward_curves(runs: Mapping[str, Iterable[Path]], smooth: int = 200) -> dict[str, tuple]:
    """Per label (its run directories, one per seed): (episode index, mean return over seeds, std)
    of the moving-average return over ``smoothing_window`` episodes (seeds cut to the shortest);
    the index is the episode count at the end of each window. Runs without episodes are skipped,
    and so is a label without any."""
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
        result[label] = (np.arange(a.shape[1]) + k, a.mean(0), a.std(0))
    return result


def draw_reward_curves(ax, curves: Mapping[str, tuple], title: str) -> None:
    """``reward_curves`` as lines with a ± 1 std band, labelled with their keys."""
    for label, (x, mean, std) in curves.items():
        line = ax.plot(x, mean, label=label, marker="o" if len(x) == 1 else None)[0]
        ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.2)
    ax.set_xlabel("episode")
    widths = sorted({int(x[0]) for x, _, _ in curves.values()})  # a curve's first point ends its first window
    ax.set_ylabel(f"return (moving average over {'/'.join(map(str, widths))} episodes)" if widths
                  else "return (moving average)")
    ax.set_title(title)
    if curves:
        ax.legend(fontsize=8)


def reward_figure(path: Path, panels: Sequence[tuple[str, Mapping[str, Iterable[Path]]]], smooth: int = 200) -> Path:
    """Figs. 2–3: one panel per (title, {label: run directories}), side by side."""
    fig = _figure(len(panels))
    for i, (title, runs) in enumerate(panels):
        draw_reward_curves(fig.add_subplot(1, len(panels), i + 1), reward_curves(runs, smooth), title)
    fig.tight_layout()
    fig.savefig(str(path), dpi=110)
    return Path(path)


# ------------------------------------------------------------------ Fig. 4: the CBF on each layout
def cbf_figure(path: Path, runs: Sequence[tuple[str, Path]], heading: float = 0.0) -> Path:
    """Fig. 4: per (name, run directory), the learned h at a fixed heading as a surface (top row)
    and as level sets with h = 0 in black (bottom row); a run without a checkpoint is 'not run'."""
    n = len(runs)
    fig = _figure(n, 2, size=4.0)
    for i, (name, d) in enumerate(runs):
        ax3 = fig.add_subplot(2, n, i + 1, projection="3d")
        ax2 = fig.add_subplot(2, n, i + n + 1)
        ax3.set_title(f"({chr(ord('a') + i)}) {name}")
        level_title = f"({chr(ord('a') + n + i)}) {name}: level sets, h = 0 in black"
        if not (Path(d) / "checkpoint.json").is_file():
            ax2.set_title(level_title)
            ax2.text(0.5, 0.5, "not run", ha="center", transform=ax2.transAxes)
            continue
        _, learner, policy, _ = load_policy(d)
        xs, ys, h, _ = cbf_grid(learner, policy[1], heading, resolution=60)
        gx, gy = np.meshgrid(xs, ys)
        ax3.plot_surface(gx, gy, h, cmap="RdYlGn", linewidth=0, antialiased=False)
        ax3.set_xlabel("x (m)")
        ax3.set_ylabel("y (m)")
        ax3.set_zlabel("h")
        draw_cbf(ax2, xs, ys, h, learner.env.layout, zero_color="black", zero_width=1.2)
        ax2.set_title(level_title)  # after draw_layout, which titles the axes with the layout's name
    fig.tight_layout()
    fig.savefig(str(path), dpi=100)
    return Path(path)


# ------------------------------------------------------- Fig. 5: trajectories during training
def snapshot_figure(path: Path, run_dir: Path, trajectories: int = 8) -> Path:
    """Fig. 5: the layout, then the executed policy's trajectories at each of the run's policy
    snapshots (``TrainConfig.snapshots``), ``trajectories`` episodes each (seed: the panel's index)."""
    cfg, learner, _, _ = load_policy(run_dir)
    snapshots = tuple(cfg.snapshots)
    env, params = learner.env, learner.params
    fig = _figure(1 + len(snapshots), size=4.0)
    ax = fig.add_subplot(1, 1 + len(snapshots), 1)
    draw_layout(env.layout, ax, sensing_radius=float(params.sensing_radius))
    ax.set_title("(a) layout, start and sensing radius")
    rollout = make_rollout(learner, env, trajectories, int(params.max_steps))  # one compilation for every snapshot
    for i, n in enumerate(snapshots):
        policy = load_snapshot(run_dir, n, learner)
        poses, collided, completed = policy_trajectories(learner, policy, env, params, trajectories, seed=i,
                                                         rollout=rollout)
        ax = fig.add_subplot(1, 1 + len(snapshots), i + 2)
        draw_layout(env.layout, ax, show_sensing=False)
        draw_trajectories(ax, poses, collided, completed)
        ax.set_title(f"({chr(ord('b') + i)}) after {n} episodes\n{completed.mean():.0%} complete, "
                     f"{1 - collided.mean():.0%} safe ({poses.shape[0]} runs)")
    fig.set_layout_engine("constrained")  # tight_layout clips two-line titles over equal-aspect axes
    fig.savefig(str(path), dpi=100)
    return Path(path)


def _figure(ncols: int, nrows: int = 1, size: float = 4.5, min_width: float = 0.0) -> Figure:
    fig = Figure(figsize=(max(size * ncols, min_width), size * nrows))
    FigureCanvasAgg(fig)
    return fig


def certify_figure(layout, maps: list[np.ndarray], extent: tuple, summary: dict, eps_unsafe: float,
                   eps_safe: float, path: str | Path) -> None:
    """``d2spo certify``'s picture (RUN/certify.png) from its status maps (``certify.status_maps``):
    where Proposition 1 (ℒ and contact) and Proposition 2 (the grid's explored part; then the whole
    free space, if checked) are certified (green), not certified (orange) or violated (red), worst
    over θ and states; the search's worst points as x."""
    cmap = ListedColormap(["white", "tab:green", "orange", "tab:red"])
    rho = summary["residual"]["rho_h"]
    titles = (f"Prop. 1: h < 0 in the ring and contact (ε̄ = {eps_unsafe:g} m)",
              f"Prop. 2: e ≥ 0 on explored cells (D; ε = {eps_safe:g} m, ρ_h = {rho:.3g})",
              "Prop. 2 beyond D: every free pose, every live state")
    fig = Figure(figsize=(5.5 * len(maps), 5.2))
    for i, m in enumerate(maps):
        ax = fig.add_subplot(1, len(maps), i + 1)
        ax.imshow(m + 1, origin="lower", extent=extent, cmap=cmap, vmin=0, vmax=3, interpolation="nearest")
        draw_layout(layout, ax, show_sensing=False)
        key = "L" if i == 0 else "D"
        if i < 2:
            for c in summary["counterexamples"][key]:
                ax.plot(c["pose"][0], c["pose"][1], "x", color="black" if c["counterexample"] else "grey", markersize=7)
        ax.set_title(titles[i], fontsize=9)
    fig.suptitle(f"{summary['run']}: green certified, orange not certified, red violated (worst over θ and "
                 "automaton state), white outside the set; x = worst found by the search (black: a counterexample)",
                 fontsize=8)
    FigureCanvasAgg(fig).print_png(str(path))


def state_fields_figure(layout, aut, fields, path: str | Path, distance=None, dpi: int = 90) -> None:
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
            ax.add_patch(obstacle_patch(o, color=OBSTACLE_COLOR))
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
