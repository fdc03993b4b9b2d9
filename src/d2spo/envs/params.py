"""What ``reset`` and ``step`` read besides the state (``EnvParams``), and how an environment config
and a compiled task fill it (``env_params``; ``robot_fields``, the part that needs no layout, which
the generalist's env shares).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from d2spo.envs import geodesic
from d2spo.envs.compiled_task import CompiledTask
from d2spo.envs.dynamics import DynamicsParams
from d2spo.envs.env_config import EnvConfig
from d2spo.envs.geometry import Geometry
from d2spo.ltl.automaton import AutomatonArrays
from d2spo.ltl.reward import RewardConfig, progress_areas


@struct.dataclass
class EnvParams:
    """Everything ``reset``/``step`` need besides the state: a pytree, so it can change under jit."""

    geom: Geometry
    """Arena and obstacles (M boxes, D disks)."""
    area_center: jnp.ndarray
    """float32 [N, 2]: area centres."""
    area_radius: jnp.ndarray
    """float32 [N]: true area radii; drive ``q_true`` and ``completed``."""
    label_radius: jnp.ndarray
    """float32 [N]: relaxed labelling radii; drive ``q``, the reward and termination (annealed)."""
    relax_mask: jnp.ndarray
    """bool [Q, N]: in automaton state q, area i is labelled with its relaxed radius (else the true
    one). All true, unless ``AnnealConfig.relax == "targets"`` (``ltl.anneal.annealed_params``)."""
    area_bits: jnp.ndarray
    """int32 [N]: the letter bit each area sets (bit i <=> automaton proposition aps[i], the area's
    label; areas of one label set the same bit)."""
    advance: jnp.ndarray
    """bool [Q, N]: entering area i from automaton state q makes progress (for reward shaping)."""
    aut: AutomatonArrays
    """The task automaton."""
    start: jnp.ndarray
    """float32 [3]: start pose before jitter."""
    start_jitter: jnp.ndarray
    """float32 [3]: half-widths of the uniform start noise on x, y, theta."""
    dyn: DynamicsParams
    """True dynamics."""
    robot_radius: jnp.ndarray
    """float32 []: robot disk radius."""
    sensing_radius: jnp.ndarray
    """float32 []: sensing radius H."""
    max_steps: jnp.ndarray
    """int32 []: episode length limit."""
    geodesic: jnp.ndarray
    """float32 [N, ny, nx]: path length through free space from each grid node to each area's centre
    (``envs.geodesic``; the shaping potential's distance; [N, 1, 1] zeros unless the metric is 'geodesic')."""
    state_field: jnp.ndarray
    """float32 [Q, ny, nx]: per automaton state, path length to the areas that make progress round
    those that reject the task (``envs.state_fields``; [Q, 1, 1] zeros unless the metric is
    'geodesic-per-state')."""
    n_rays: int = struct.field(pytree_node=False, default=16)
    """Number of lidar rays K (static: it sets the observation size)."""
    event: bool = struct.field(pytree_node=False, default=True)
    """Event labelling (True) or step labelling (False)."""
    collision_terminates: bool = struct.field(pytree_node=False, default=True)
    """Collision ends the episode."""
    reward: RewardConfig = struct.field(pytree_node=False, default=RewardConfig())
    """Reward constants of Eq. (8)."""

    @property
    def max_steps_in_episode(self) -> jnp.ndarray:
        """``max_steps`` under gymnax's name for it (gymnax's ``EnvParams`` field)."""
        return self.max_steps


def _f32(v) -> jnp.ndarray:
    return jnp.asarray(v, jnp.float32)


def robot_fields(cfg: EnvConfig, max_steps: int) -> dict:
    """The fields of ``EnvParams`` a resolved config sets for any layout: dynamics, start jitter, radii,
    the step limit ``max_steps``, the lidar, the labelling, collisions and the reward."""
    return dict(
        start_jitter=_f32([cfg.start_jitter_xy, cfg.start_jitter_xy, cfg.start_jitter_theta]),
        dyn=DynamicsParams.create(
            dt=cfg.dt, v_max=cfg.v_max, omega_max=cfg.omega_max, actuator_tau=cfg.actuator_tau, v_gain=cfg.v_gain,
            omega_gain=cfg.omega_gain, slip=cfg.slip, noise_xy=cfg.noise_xy, noise_theta=cfg.noise_theta,
            reverse=cfg.reverse,
        ),
        robot_radius=_f32(cfg.robot_radius),
        sensing_radius=_f32(cfg.sensing_radius),
        max_steps=jnp.asarray(max_steps, jnp.int32),
        n_rays=cfg.n_rays,
        event=cfg.label_mode == "event",
        collision_terminates=cfg.collision_terminates,
        reward=cfg.reward,
    )


def env_params(cfg: EnvConfig, task: CompiledTask, max_steps: int) -> EnvParams:
    """The params of ``task``'s layout and automaton under the resolved config ``cfg``: the layout's
    geometry, areas and start, the labelling radii (``cfg.label_radius`` for the reward's, else the
    true ones), the shaping distances of ``cfg.reward.shaping_metric`` and ``robot_fields``."""
    layout, arrays = task.layout, task.arrays
    n_areas = len(layout.areas)
    area_radius = np.array([a.radius for a in layout.areas], np.float32).reshape(n_areas)
    label_radius = area_radius if cfg.label_radius is None else np.full(n_areas, cfg.label_radius, np.float32)
    metric = cfg.reward.shaping_metric
    if metric == "geodesic":
        centre_fields = geodesic.distance_fields(
            layout.arena, [o.lo for o in layout.boxes], [o.hi for o in layout.boxes],
            [a.center for a in layout.areas], area_radius, cfg.reward.clearance(cfg.robot_radius),
            disks=[(*d.center, d.radius) for d in layout.disks])
    else:
        centre_fields = np.zeros((n_areas, 1, 1), np.float32)
    field = np.zeros((task.n_states, 1, 1), np.float32) if task.fields is None else task.fields.field
    return EnvParams(
        geom=Geometry(
            box_lo=_f32(np.array([o.lo for o in layout.boxes]).reshape(-1, 2)),
            box_hi=_f32(np.array([o.hi for o in layout.boxes]).reshape(-1, 2)),
            arena_lo=_f32([0.0, 0.0]),
            arena_hi=_f32(layout.arena),
            disk_center=_f32([d.center for d in layout.disks]) if layout.disks else None,
            disk_radius=_f32([d.radius for d in layout.disks]) if layout.disks else None,
        ),
        area_center=_f32(np.array([a.center for a in layout.areas]).reshape(n_areas, 2)),
        area_radius=_f32(area_radius),
        label_radius=_f32(label_radius),
        relax_mask=jnp.ones((task.n_states, n_areas), bool),
        area_bits=jnp.asarray(task.area_bits),
        advance=progress_areas(arrays, task.area_bits),
        aut=arrays,
        start=_f32(layout.start),
        geodesic=_f32(centre_fields),
        state_field=_f32(field),
        **robot_fields(cfg, max_steps),
    )
