"""The generalist's environment: a new layout from a bank at every reset, and an observation that
names the subgoal instead of the layout, its labels or the automaton state.

``envs.nav.Env`` trains on one layout: its observation holds the robot's position in that arena,
the areas' positions and the automaton state's one-hot, so what a policy learns there is tied to
the layout and the formula. ``GeneralistEnv`` keeps nav's dynamics, sensing, labelling and reward,
and changes two things:

* **Layouts.** Every episode draws one of the B slots of a ``layout_bank.LayoutBank``: a layout
  of any world (a rectangular arena of at most 20 m a side, boxes and disks, up to 16 areas whose
  labels any number of areas may share) paired with one task of the mixture; the state carries the
  slot's index. ``view(params, b)`` writes slot b's arrays into the base fields (geometry, areas,
  their letter bits, start), so nav's step reads them as it reads its own. Unused obstacle and
  area slots become tiny shapes far outside the arena. The start is the layout's, with a uniform
  heading; the labelling radius is the true one (no annealing).
* **Observation** (float32 [K + 10]), all in the robot's frame, none of it the layout's coordinates,
  its label names, its number of areas or the automaton's state index:

  - ``lidar`` [K]: ranges / H, as nav's;
  - ``clearance`` [1]: the distance to the nearest obstacle or wall / H (the paper's b(z, O_s));
    with ``lidar`` it is the CBF's input x, read off the observation (``cbf_input``);
  - ``target`` [4]: the path length to the nearest area whose entry makes progress, round obstacles
    and round the areas whose entry would reject the task (``layout_bank.nearest``), as
    ``observed_distance`` encodes it (d / (d + ``SCALE``) by default);
    the direction of steepest descent of that path (forward, left); 1 if there is a target;
  - ``forbidden`` [4]: the distance from the robot to the edge of the nearest area whose entry would
    reject the task (or undo progress), encoded alike; the direction to its centre (forward, left); 1
    if there is one (within ``EnvConfig.forbidden_range`` of its edge, when that is set);
  - ``progress`` [1]: the automaton's distance to acceptance (area visits still needed) / its
    largest finite value.

  The automaton state and the slot decide the target and forbidden areas (every area of a label
  whose entry makes progress, every area of a label whose entry rejects: ``slot_roles``), the
  bank the distances: one network serves every formula and every layout the bank can hold.

The reward is nav's (Eq. (8) plus the shaping); its shaping distance is the same path length as the
observation's target distance, and its scale the drawn layout's diagonal. ``GeneralistEnv``
overrides nav's public hooks (``observation_parts``, ``observe``, ``reset_state``,
``shaping_distance``) and ``step``; ``make_generalist_env`` builds it from its ``EnvConfig`` (the
dynamics, the robot, the reward), the task(s) and the layouts; ``GeneralistEnv.bank`` pairs other
layouts with its tasks (a zero-shot evaluation, a bank drawn afresh).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from d2spo.envs import generator, layout_bank, sensors
from d2spo.envs.eager import compiled_when_eager
from d2spo.envs.env_config import EnvConfig
from d2spo.envs.geometry import Geometry
from d2spo.envs.layout_bank import LayoutBank
from d2spo.envs.nav import Env, EnvState
from d2spo.envs.params import EnvParams, robot_fields
from d2spo.envs.task_plan import TaskPlan, task_plan
from d2spo.envs.workspace import Layout
from d2spo.errors import ConfigError
from d2spo.ltl.automaton import UNREACHABLE, Automaton, AutomatonArrays

N_AREAS = layout_bank.N_AREAS
"""Area slots per layout."""
SCALE = 10.0
"""The observation's distance scale (m): ``observed_distance``."""
FAR = -1.0e3
"""Where unused obstacle and area slots go: far outside every arena."""


@struct.dataclass(kw_only=True)
class GeneralState(EnvState):
    """nav's state plus the index of the episode's slot in the bank."""

    layout: jnp.ndarray
    """int32 []: the episode's slot (index into ``GeneralParams.bank``)."""


@struct.dataclass(kw_only=True)
class GeneralParams(EnvParams):
    """nav's params (dynamics, automaton, reward, ...) plus the bank.

    In a ``view`` the base fields (geometry, areas, letter bits, start) hold slot ``layout``'s arrays.
    """

    bank: LayoutBank
    """The slots: layouts, their tasks, roles and fields."""
    layout: jnp.ndarray
    """int32 []: the slot the base fields hold (``view``)."""
    initials: jnp.ndarray
    """int32 [T]: the initial state of each task of the mixture (one task: [1]); an episode starts in
    its slot's task's (``ltl.automaton.union``)."""
    local_state: jnp.ndarray
    """int32 [Q]: the index of each state within its own task (the bank's roles and fields are per
    slot and local state)."""
    progress_scale: jnp.ndarray
    """float32 [Q]: per state, the largest finite distance to acceptance of its own task (the
    observation's ``progress`` divides by it)."""


N_BOXES = layout_bank.M_MAX + 4
"""Obstacle boxes of a view: the bank's slots, then the four walls as boxes (``view``)."""
N_DISKS = layout_bank.D_MAX
"""Disk obstacles of a view: the bank's slots."""
WALL = 1.0
"""Thickness (m) of the wall boxes, more than the sensing radius reaches through."""


def observed_distance(d: jnp.ndarray, mode: str = "ratio") -> jnp.ndarray:
    """A distance d (m) as the observation holds it (``EnvConfig.distance_obs``): 'ratio', d / (d +
    ``SCALE``) in [0, 1), which tells every two distances apart (a 20 m world's routes run to 40 m
    and more); 'capped', min(d / ``SCALE``, 2), the encoding until 2026-11-27, under which a robot
    40 m from its target saw what it saw at 20 m and could stall there."""
    if mode == "capped":
        return jnp.minimum(d / SCALE, 2.0)
    return d / (d + SCALE)


def wall_boxes(arena: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(lo [4, 2], hi [4, 2]): the arena's walls as boxes just outside it (left, right, bottom, top)."""
    w, h, t = arena[0], arena[1], WALL
    lo = jnp.stack([jnp.stack([-t, -t]), jnp.stack([w, -t]), jnp.stack([-t, -t]), jnp.stack([-t, h])])
    hi = jnp.stack([jnp.stack([0.0 * w, h + t]), jnp.stack([w + t, h + t]), jnp.stack([w + t, 0.0 * h]),
                    jnp.stack([w + t, h + t])])
    return lo, hi


def view(params: GeneralParams, b: jnp.ndarray) -> GeneralParams:
    """``params`` with slot b's geometry, areas and start in the base fields. The geometry's boxes
    are the layout's (unused slots far away) and its four walls (``wall_boxes``), its disks the
    layout's (unused slots far away), so a set of sensed obstacles (``info["box_lo"]``,
    ``info["box_hi"]``, ``info["disk_center"]``, ``info["disk_radius"]``, ``info["sensed"]``)
    describes everything the robot senses without the arena: the learner's CBF input needs no
    per-layout arena."""
    return params.replace(**_layout_fields(params.bank, b))


def view_geometry(bank: LayoutBank, b: jnp.ndarray) -> Geometry:
    """Slot b's obstacles as a ``Geometry``: boxes then walls as boxes, disks (``view``)."""
    mask = bank.box_mask[b][:, None]
    arena = bank.arena[b]
    w_lo, w_hi = wall_boxes(arena)
    lo = jnp.concatenate([jnp.where(mask, bank.box_lo[b], FAR), w_lo])
    hi = jnp.concatenate([jnp.where(mask, bank.box_hi[b], FAR + 0.01), w_hi])
    disk = bank.disk_mask[b]
    centre = jnp.where(disk[:, None], bank.disk_center[b], FAR)
    radius = jnp.where(disk, bank.disk_radius[b], 0.01)
    return Geometry(lo, hi, jnp.zeros_like(arena), arena, centre, radius)


def _layout_fields(bank: LayoutBank, b: jnp.ndarray) -> dict:
    """The fields of ``GeneralParams`` that hold slot b of ``bank`` (``view``)."""
    used = bank.area_mask[b]
    centre = jnp.where(used[:, None], bank.area_center[b], FAR)
    radius = jnp.where(used, bank.area_radius[b], 0.0)
    return dict(geom=view_geometry(bank, b), area_center=centre, area_radius=radius, label_radius=radius,
                area_bits=bank.area_bits[b], start=bank.start[b], max_steps=bank.max_steps[b],
                layout=jnp.asarray(b, jnp.int32))


def subgoal(params: GeneralParams, q: jnp.ndarray, xy: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """(distance, direction [2], any) to the nearest target of state q in the view's slot, along
    the path round obstacles and q's forbidden areas (``layout_bank.nearest``); 0, 0, False when q
    has no target."""
    return layout_bank.nearest(params.bank, params.layout, params.local_state[q], xy)


class GeneralistEnv(Env):
    """nav's environment over a bank of slots, with the subgoal observation (module docstring)."""

    def __init__(self, config: EnvConfig, automaton: Automaton, plan: TaskPlan):
        super().__init__(config, automaton, automaton.n_states, N_BOXES + N_DISKS, N_AREAS)  # the layout: the bank's
        self.plan = plan
        """The tasks of the mixture, their states and roles (``bank`` pairs layouts with them)."""

    def observation_parts(self) -> list[tuple[str, int]]:
        """The subgoal observation's parts, in order, with their sizes (module docstring)."""
        return [("lidar", self.n_rays), ("clearance", 1), ("target", 4), ("forbidden", 4), ("progress", 1)]

    def bank(self, layouts: Sequence[Layout], tasks: Sequence[int] | None = None, max_steps: int | None = None,
             method: str = "auto") -> LayoutBank:
        """A bank of ``layouts``, slot k paired with task tasks[k] of the mixture (default: k modulo
        the number of tasks), with its roles, episode limits and fields (``TaskPlan.bank``)."""
        return self.plan.bank(layouts, tasks, max_steps, method)

    # -- the layout of the state ------------------------------------------------------------
    @compiled_when_eager()
    def step(self, key: jax.Array, state: GeneralState, action: jnp.ndarray, params: GeneralParams):
        """nav's step in the state's slot; an episode that ends restarts in a newly drawn slot.
        ``info`` also holds the step's obstacles (``box_lo``, ``box_hi`` [N_BOXES, 2], ``disk_center``
        [N_DISKS, 2], ``disk_radius`` [N_DISKS]; ``sensed`` masks them, boxes first)."""
        v = view(params, state.layout)
        out = super().step(key, state, action, v)
        out[-1].update(box_lo=v.geom.box_lo, box_hi=v.geom.box_hi, disk_center=v.geom.disk_center,
                       disk_radius=v.geom.disk_radius)
        return out

    def reset_state(self, u: jnp.ndarray, params: GeneralParams) -> GeneralState:
        """A fresh episode (``reset``, and nav's step when one ends) from three uniforms in [-1, 1]:
        u[0] draws the slot uniformly from the bank (its layout and its task), u[1] the heading."""
        n = params.bank.arena.shape[0]
        return self._start_in(jnp.clip(jnp.floor((u[0] + 1.0) * 0.5 * n).astype(jnp.int32), 0, n - 1), u, params)

    @compiled_when_eager()
    def reset_in_slot(self, key: jax.Array, params: GeneralParams, b: jnp.ndarray) -> tuple[GeneralState, jnp.ndarray]:
        """``reset`` in slot b of the bank rather than a drawn one (an evaluation that gives every
        episode a layout of its own: ``rollout.make_rollout(..., slot_per_episode=True)``)."""
        state = self._start_in(jnp.asarray(b, jnp.int32), jax.random.uniform(key, (3,), minval=-1.0, maxval=1.0),
                               params)
        return state, self.observe(state, params)

    def _start_in(self, b: jnp.ndarray, u: jnp.ndarray, params: GeneralParams) -> GeneralState:
        v = view(params, b)
        start = jnp.stack([v.start[0], v.start[1], jnp.pi * u[1]])
        aut = v.aut._replace(initial=params.initials[params.bank.task[b]])
        base = super().reset_state(jnp.zeros(3), v.replace(start=start, start_jitter=jnp.zeros(3), aut=aut))
        return GeneralState(**{f.name: getattr(base, f.name) for f in dataclasses.fields(EnvState)}, layout=b)

    # -- reward shaping and observation ------------------------------------------------------
    def shaping_distance(self, xy: jnp.ndarray, q: jnp.ndarray, params: GeneralParams) -> jnp.ndarray:
        """The shaping's distance: the path length to q's nearest target (``subgoal``)."""
        return subgoal(params, q, xy)[0]

    def observe(self, state: GeneralState, params: GeneralParams) -> jnp.ndarray:
        """The subgoal observation of ``state`` in its own slot (module docstring)."""
        v = view(params, state.layout)
        pose = state.pose
        xy, c, s = pose[:2], jnp.cos(pose[2]), jnp.sin(pose[2])
        everything = jnp.ones((self.n_obstacles,), bool)
        H = v.sensing_radius
        scan = sensors.lidar_cs(xy, c, s, v.geom, everything, v.n_rays, H) / H
        clearance = sensors.nearest_obstacle(xy, v.geom, everything, H) / H

        def frame(d):  # a world vector in the robot's frame (forward, left)
            return jnp.stack([c * d[0] + s * d[1], c * d[1] - s * d[0]])

        dist, direction, found = subgoal(v, state.q, xy)
        seen = functools.partial(observed_distance, mode=self.config.distance_obs)
        target = jnp.concatenate([seen(dist)[None], frame(direction), found[None]])
        rel = v.area_center - xy  # [N, 2]
        centre = jnp.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1])
        bank, b = v.bank, state.layout
        forbids = bank.forbidden[b, v.local_state[state.q]] & bank.area_mask[b]
        edge = jnp.where(forbids, jnp.maximum(centre - v.area_radius, 0.0), jnp.inf)
        j = jnp.argmin(edge)
        has = jnp.isfinite(edge[j])
        if self.config.forbidden_range is not None:  # a far one as none (EnvConfig.forbidden_range)
            has = has & (edge[j] <= self.config.forbidden_range)
        toward = jnp.where(has, rel[j] / jnp.maximum(centre[j], 1e-6), 0.0)
        forbidden = jnp.concatenate([jnp.where(has, seen(edge[j]), 0.0)[None], frame(toward),
                                     has[None]])
        aut = v.aut
        finite = aut.distance[state.q] < UNREACHABLE
        progress = jnp.where(finite, aut.distance[state.q] / v.progress_scale[state.q], 1.0)
        return jnp.concatenate([scan, clearance[None], target, forbidden, progress[None]]).astype(jnp.float32)

    def cbf_input(self, obs: jnp.ndarray, params: GeneralParams) -> jnp.ndarray:
        """x = b(z, O_s) [..., K + 1] read off observations: ranges and clearance times H."""
        sl = self.observation_slices
        return jnp.concatenate([obs[..., sl["lidar"]], obs[..., sl["clearance"]]], axis=-1) * params.sensing_radius


def make_generalist_env(cfg: EnvConfig, task: Any, layouts: Sequence[Layout] | LayoutBank,
                        max_steps: int | None = None, tasks_of: Sequence[int] | None = None
                        ) -> tuple[GeneralistEnv, GeneralParams]:
    """The generalist's env for a task (a name, a formula or an automaton), or a mixture of tasks (a
    list of them: each slot is paired with one, ``ltl.automaton.union``), over ``layouts`` (slot k
    paired with task tasks_of[k], default k modulo the number of tasks; or a bank this env's plan
    made, ``GeneralistEnv.bank``).

    The dynamics, the robot and the reward are ``cfg``'s (``params.robot_fields``); ``max_steps``
    is one limit for every slot (None: each slot's ``slot_max_steps``; the params' own
    ``max_steps`` is the largest, a rollout's length). A bank's areas never overlap, so a task must
    be doable entering one area at a time, and its layouts admit a robot of
    ``generator.RANDOM_RADIUS`` at most.
    Raises ConfigError.
    """
    tasks = list(task) if isinstance(task, (list, tuple)) else [task]
    if not tasks:
        raise ConfigError("task", "the generalist needs at least one task")
    resolved = cfg.resolved()
    if resolved.robot_radius > generator.RANDOM_RADIUS:  # before the fields are computed
        raise ConfigError("robot_radius", f"the generalist's layouts admit a robot of radius at most "
                          f"{generator.RANDOM_RADIUS:g} m, got {resolved.robot_radius:g}")
    plan = task_plan(tasks, resolved.label_mode)
    bank = layouts if isinstance(layouts, LayoutBank) else plan.bank(layouts, tasks_of, max_steps)
    if bank.size == 0 or bank.fields.ndim != 4 or bank.fields.shape[1] != plan.states:
        raise ConfigError("bank", "a bank of this task mixture, with its fields, is needed (GeneralistEnv.bank)")
    longest = int(np.max(np.asarray(bank.max_steps)))
    cfg = dataclasses.replace(cfg, max_steps=longest).resolved()
    aut, distance = plan.automaton, list(plan.distance)
    finite = np.array([UNREACHABLE if d is None else d for d in distance])
    scale = np.ones(aut.n_states, np.float32)  # per state, its own task's largest finite distance
    local = np.zeros(aut.n_states, np.int32)
    for lo, hi in zip(plan.offsets[:-1], plan.offsets[1:]):
        own = finite[lo:hi][finite[lo:hi] < UNREACHABLE]
        scale[lo:hi] = max(int(own.max()) if own.size else 1, 1)
        local[lo:hi] = np.arange(hi - lo)
    params = GeneralParams(
        **{**robot_fields(cfg, longest), **_layout_fields(bank, jnp.zeros((), jnp.int32)),
           "max_steps": jnp.asarray(longest, jnp.int32)},
        aut=AutomatonArrays(*(None if x is None else jnp.asarray(x) for x in aut.arrays(list(plan.singles), distance))),
        advance=jnp.zeros((aut.n_states, N_AREAS), bool), relax_mask=jnp.ones((aut.n_states, N_AREAS), bool),
        geodesic=jnp.zeros((N_AREAS, 1, 1), jnp.float32), state_field=jnp.zeros((aut.n_states, 1, 1), jnp.float32),
        bank=bank, initials=jnp.asarray(plan.initials, jnp.int32),
        local_state=jnp.asarray(local), progress_scale=jnp.asarray(scale))
    return GeneralistEnv(cfg, aut, plan), params
