"""Figures of trained policies: trajectories on the layout and the learned CBF over the workspace.

Matplotlib only, with Figure objects (no pyplot global state), so it is safe in tests and servers.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from d2spo.envs.render import add_legend, draw_layout, draw_trajectory

OUTCOME_COLORS = {"completed": "tab:purple", "collided": "tab:red", "neither": "tab:orange"}
"""Trajectory colours: the task completed (true labelling), a collision, or the episode ran out."""


def policy_trajectories(learner, policy, env, params, episodes: int, seed: int, rollout=None):
    """Poses [E, T+1, 3] (NaN after each episode's end) and per-episode (collided, completed).
    ``rollout``: a ``rollout.make_rollout`` of the same learner and size, to reuse its compilation
    (e.g. for several snapshots of one run)."""
    from d2spo.rollout import make_rollout

    if rollout is None:
        rollout = make_rollout(learner, env, episodes, int(params.max_steps))
    collided, completed, _, _, poses = rollout(params, policy, jax.random.PRNGKey(seed))
    return np.asarray(poses), np.asarray(collided), np.asarray(completed)


def cbf_grid(learner, safety, heading: float = 0.0, resolution: int = 80):
    """h(b(z, O)) on a grid of positions at a fixed heading, with every obstacle sensed.

    Returns (xs, ys, H [res, res], inside [res, res]) where ``inside`` marks positions whose
    robot disk overlaps an obstacle or a wall.
    """
    from d2spo.envs import geometry

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


def draw_cbf(ax, learner, safety, layout, heading: float = 0.0, levels: int = 15, colorbar_fig=None) -> None:
    """Filled contour of h over the workspace, its zero level set in white, obstacles on top."""
    xs, ys, h, _ = cbf_grid(learner, safety, heading)
    lim = float(np.nanmax(np.abs(h))) or 1.0
    cs = ax.contourf(xs, ys, h, levels=levels, cmap="RdYlGn", vmin=-lim, vmax=lim)
    ax.contour(xs, ys, h, levels=[0.0], colors="white", linewidths=1.5)
    draw_layout(layout, ax, show_sensing=False)
    ax.set_title(f"learned CBF h at heading {np.degrees(heading):.0f}° (white: h = 0)")
    if colorbar_fig is not None:
        cb = colorbar_fig.colorbar(cs, ax=ax, shrink=0.8)
        cb.set_label("h, the learned CBF (h ≥ 0: safe set)")


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
    from matplotlib.lines import Line2D

    poses, collided, completed = policy_trajectories(learner, policy, env, params, episodes, seed)
    has_cbf = hasattr(learner, "safety_nets")
    fig = Figure(figsize=(11 if has_cbf else 5.5, 6.2), layout="constrained")  # constrained: no title is clipped
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if has_cbf else 1, 1)
    draw_layout(env.layout, ax, sensing_radius=float(params.sensing_radius))
    for i in range(poses.shape[0]):
        xy = poses[i, :, :2]
        xy = xy[np.all(np.isfinite(xy), axis=-1)]
        outcome = "collided" if collided[i] else ("completed" if completed[i] else "neither")
        draw_trajectory(ax, xy, color=OUTCOME_COLORS[outcome])
    ax.set_title(title or f"{completed.mean():.0%} completed, {1 - collided.mean():.0%} safe "
                          f"({poses.shape[0]} episodes)")
    names = {"completed": "task completed", "collided": "collision", "neither": "out of time"}
    add_legend(ax, [Line2D([], [], color=c, label=f"trajectory: {names[k]} (x: end)")
                    for k, c in OUTCOME_COLORS.items()])
    if has_cbf:
        draw_cbf(fig.add_subplot(1, 2, 2), learner, policy[1], env.layout, heading=0.0, colorbar_fig=fig)
    fig.suptitle(suptitle or f"layout {env.layout.name!r}")
    return fig, {"safety_rate": float(1 - collided.mean()), "completion_rate": float(completed.mean())}
