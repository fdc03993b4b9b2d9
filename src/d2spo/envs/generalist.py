"""The generalist's environment: a new layout from a bank at every reset, and an observation that
names the subgoal instead of the layout or the automaton state.

``envs.nav.Env`` trains on one layout: its observation holds the robot's position in that arena,
the areas' positions and the automaton state's one-hot, so what a policy learns there is tied to
the layout and the formula. ``GeneralistEnv`` keeps nav's dynamics, sensing, labelling and reward,
and changes two things:

* **Layouts.** Every episode draws one of the B layouts of a ``layout_bank.LayoutBank`` (square
  arenas of 5-10 m, four areas A1..A4, ``envs.generator``); the state carries its index.
  ``view(params, b)`` writes layout b's arrays into the base fields (geometry, areas, start), so
  nav's step reads them as it reads its own. Unused obstacle slots become tiny boxes far outside the
  arena. The start is the layout's, with a uniform heading; the labelling radius is the true one
  (no annealing).
* **Observation** (float32 [K + 10]), all in the robot's frame, none of it the layout's coordinates
  or the automaton's state index:

  - ``lidar`` [K]: ranges / H, as nav's;
  - ``clearance`` [1]: the distance to the nearest obstacle or wall / H (the paper's b(z, O_s));
    with ``lidar`` it is the CBF's input x, read off the observation (``cbf_input``);
  - ``target`` [4]: the path length to the nearest area whose entry makes progress, round obstacles
    and round the areas whose entry would reject the task (``layout_bank.nearest``), / ``SCALE``;
    the direction of steepest descent of that path (forward, left); 1 if there is a target;
  - ``forbidden`` [4]: the distance from the robot to the edge of the nearest area whose entry would
    reject the task (or undo progress) / ``SCALE``; the direction to its centre (forward, left); 1
    if there is one;
  - ``progress`` [1]: the automaton's distance to acceptance (area visits still needed) / its
    largest finite value.

  The automaton state decides the target and forbidden areas (``area_roles``), the layout bank the
  distances: one network serves every formula over A1..A4 and every layout of the distribution.

The reward is nav's (Eq. (8) plus the shaping); its shaping distance is the same path length as the
observation's target distance, and its scale the drawn layout's diagonal. ``GeneralistEnv``
overrides nav's public hooks (``observation_parts``, ``observe``, ``reset_state``,
``shaping_distance``) and ``step``; ``make_generalist_env`` builds it from its ``EnvConfig`` (the
dynamics, the robot, the reward), the task(s) and the bank.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from d2spo.envs import generator, layout_bank, sensors, state_fields
from d2spo.envs.env_config import EnvConfig
from d2spo.envs.geometry import Geometry
from d2spo.envs.layout_bank import LayoutBank
from d2spo.envs.nav import Env, EnvState
from d2spo.envs.params import EnvParams, robot_fields
from d2spo.errors import ConfigError
from d2spo.ltl import task_automaton, task_formula
from d2spo.ltl.automaton import UNREACHABLE, Automaton, AutomatonArrays, union
from d2spo.ltl.buchi_task import BuchiTask

N_AREAS = layout_bank.N_AREAS
"""Areas per layout (A1 .. A4)."""
GENERALIST_MAX_STEPS = 400
"""The generalist's episode limit when ``max_steps`` is unset: routes in 10 m arenas are long."""
SCALE = 10.0
"""Metres per unit of the observation's distances (the largest arena's side)."""
FAR = -1.0e3
"""Where unused obstacle slots go: a tiny box this far outside every arena."""


@struct.dataclass(kw_only=True)
class GeneralState(EnvState):
    """nav's state plus the index of the episode's layout in the bank."""

    layout: jnp.ndarray
    """int32 []: the episode's layout (index into ``GeneralParams.bank``)."""


@struct.dataclass(kw_only=True)
class GeneralParams(EnvParams):
    """nav's params (dynamics, automaton, reward, ...) plus the bank and the roles of the areas.

    In a ``view`` the base fields (geometry, areas, start) hold layout ``layout``'s arrays.
    """

    bank: LayoutBank
    """The layouts and their fields."""
    target_areas: jnp.ndarray
    """bool [Q, 4]: in automaton state q, entering area i (alone) moves closer to acceptance."""
    forbidden_areas: jnp.ndarray
    """bool [Q, 4]: in automaton state q, entering area i (alone) rejects the task or moves away."""
    layout: jnp.ndarray
    """int32 []: the layout the base fields hold (``view``)."""
    initials: jnp.ndarray
    """int32 [T]: the initial state of each task of the mixture (one task: [1]); every episode
    starts in one of them, drawn uniformly (``ltl.automaton.union``)."""
    progress_scale: jnp.ndarray
    """float32 [Q]: per state, the largest finite distance to acceptance of its own task (the
    observation's ``progress`` divides by it)."""


N_BOXES = layout_bank.M_MAX + 4
"""Obstacle boxes of a view: the bank's slots, then the four walls as boxes (``view``)."""
WALL = 1.0
"""Thickness (m) of the wall boxes, more than the sensing radius reaches through."""


def wall_boxes(arena: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(lo [4, 2], hi [4, 2]): the arena's walls as boxes just outside it (left, right, bottom, top)."""
    w, h, t = arena[0], arena[1], WALL
    lo = jnp.stack([jnp.stack([-t, -t]), jnp.stack([w, -t]), jnp.stack([-t, -t]), jnp.stack([-t, h])])
    hi = jnp.stack([jnp.stack([0.0 * w, h + t]), jnp.stack([w + t, h + t]), jnp.stack([w + t, 0.0 * h]),
                    jnp.stack([w + t, h + t])])
    return lo, hi


def view(params: GeneralParams, b: jnp.ndarray) -> GeneralParams:
    """``params`` with layout b's geometry, areas and start in the base fields. The geometry's boxes
    are the layout's (unused slots far away) and its four walls (``wall_boxes``), so a set of sensed
    boxes (``info["box_lo"]``, ``info["box_hi"]``, ``info["sensed"]``) describes everything the
    robot senses without the arena: the learner's CBF input needs no per-layout arena."""
    return params.replace(**_layout_fields(params.bank, b))


def _layout_fields(bank: LayoutBank, b: jnp.ndarray) -> dict:
    """The fields of ``GeneralParams`` that hold layout b of ``bank`` (``view``)."""
    mask = bank.box_mask[b][:, None]
    arena = bank.arena[b]
    w_lo, w_hi = wall_boxes(arena)
    lo = jnp.concatenate([jnp.where(mask, bank.box_lo[b], FAR), w_lo])
    hi = jnp.concatenate([jnp.where(mask, bank.box_hi[b], FAR + 0.01), w_hi])
    geom = Geometry(lo, hi, jnp.zeros_like(arena), arena)
    radius = bank.area_radius[b]
    return dict(geom=geom, area_center=bank.area_center[b], area_radius=radius, label_radius=radius,
                start=bank.start[b], layout=jnp.asarray(b, jnp.int32))


def subgoal(params: GeneralParams, q: jnp.ndarray, xy: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """(distance, direction [2], any) to the nearest target of state q in the view's layout, along
    the path round obstacles and q's forbidden areas (``layout_bank.nearest``); 0, 0, False when q
    has no target."""
    target = params.target_areas[q]
    dist, direction = layout_bank.nearest(params.bank, params.layout, target, params.forbidden_areas[q], xy)
    return dist, direction, jnp.any(target)


class GeneralistEnv(Env):
    """nav's environment over a bank of layouts, with the subgoal observation (module docstring)."""

    def __init__(self, config: EnvConfig, automaton: Automaton, bank_size: int):
        super().__init__(config, automaton, automaton.n_states, N_BOXES, N_AREAS)  # no task: the layout is the bank's
        self.bank_size = bank_size
        """Layouts in the bank (``GeneralParams.bank``)."""

    def observation_parts(self) -> list[tuple[str, int]]:
        """The subgoal observation's parts, in order, with their sizes (module docstring)."""
        return [("lidar", self.n_rays), ("clearance", 1), ("target", 4), ("forbidden", 4), ("progress", 1)]

    # -- the layout of the state ------------------------------------------------------------
    def step(self, key: jax.Array, state: GeneralState, action: jnp.ndarray, params: GeneralParams):
        """nav's step in the state's layout; an episode that ends restarts in a newly drawn layout.
        ``info`` also holds the step's boxes (``box_lo``, ``box_hi`` [N_BOXES, 2]; ``sensed`` masks them)."""
        v = view(params, state.layout)
        out = super().step(key, state, action, v)
        out[-1].update(box_lo=v.geom.box_lo, box_hi=v.geom.box_hi)
        return out

    def reset_state(self, u: jnp.ndarray, params: GeneralParams) -> GeneralState:
        """A fresh episode (``reset``, and nav's step when one ends) from three uniforms in [-1, 1]:
        u[0] draws the layout uniformly from the bank, u[1] the heading, u[2] the task of the mixture."""

        def pick(x, n):
            return jnp.clip(jnp.floor((x + 1.0) * 0.5 * n).astype(jnp.int32), 0, n - 1)

        b = pick(u[0], params.bank.arena.shape[0])
        v = view(params, b)
        start = jnp.stack([v.start[0], v.start[1], jnp.pi * u[1]])
        aut = v.aut._replace(initial=params.initials[pick(u[2], params.initials.shape[0])])
        base = super().reset_state(jnp.zeros(3), v.replace(start=start, start_jitter=jnp.zeros(3), aut=aut))
        return GeneralState(**{f.name: getattr(base, f.name) for f in dataclasses.fields(EnvState)}, layout=b)

    # -- reward shaping and observation ------------------------------------------------------
    def shaping_distance(self, xy: jnp.ndarray, q: jnp.ndarray, params: GeneralParams) -> jnp.ndarray:
        """The shaping's distance: the path length to q's nearest target (``subgoal``)."""
        return subgoal(params, q, xy)[0]

    def observe(self, state: GeneralState, params: GeneralParams) -> jnp.ndarray:
        """The subgoal observation of ``state`` in its own layout (module docstring)."""
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
        target = jnp.concatenate([jnp.minimum(dist / SCALE, 2.0)[None], frame(direction), found[None]])
        rel = v.area_center - xy  # [4, 2]
        centre = jnp.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1])
        edge = jnp.where(v.forbidden_areas[state.q], jnp.maximum(centre - v.area_radius, 0.0), jnp.inf)
        j = jnp.argmin(edge)
        has = jnp.isfinite(edge[j])
        toward = jnp.where(has, rel[j] / jnp.maximum(centre[j], 1e-6), 0.0)
        forbidden = jnp.concatenate([jnp.where(has, jnp.minimum(edge[j] / SCALE, 2.0), 0.0)[None], frame(toward),
                                     has[None]])
        aut = v.aut
        finite = aut.distance[state.q] < UNREACHABLE
        progress = jnp.where(finite, aut.distance[state.q] / v.progress_scale[state.q], 1.0)
        return jnp.concatenate([scan, clearance[None], target, forbidden, progress[None]]).astype(jnp.float32)

    def cbf_input(self, obs: jnp.ndarray, params: GeneralParams) -> jnp.ndarray:
        """x = b(z, O_s) [..., K + 1] read off observations: ranges and clearance times H."""
        sl = self.observation_slices
        return jnp.concatenate([obs[..., sl["lidar"]], obs[..., sl["clearance"]]], axis=-1) * params.sensing_radius


def area_roles(automaton: Automaton, roles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(target [Q, 4], forbidden [Q, 4]): the role of entering area A(i+1) alone in each state, from
    the letters' ``roles`` (``state_fields.letter_roles``; areas whose name is no proposition are neutral)."""
    target = np.zeros((automaton.n_states, N_AREAS), bool)
    forbidden = np.zeros_like(target)
    for i in range(N_AREAS):
        name = f"A{i + 1}"
        if name in automaton.aps:
            letter = automaton.letter([name])
            target[:, i] = roles[:, letter] == state_fields.TARGET
            forbidden[:, i] = roles[:, letter] == state_fields.FORBIDDEN
    return target, forbidden


def make_generalist_env(cfg: EnvConfig, task: Any, bank: LayoutBank, max_steps: int = GENERALIST_MAX_STEPS
                        ) -> tuple[GeneralistEnv, GeneralParams]:
    """The generalist's env for a task (a name, a formula or an automaton over A1..A4), or a
    mixture of tasks (a list of them: each episode draws one, ``ltl.automaton.union``), and a bank.

    The dynamics, the robot and the reward are ``cfg``'s (``params.robot_fields``); ``max_steps``
    is one limit for every layout (the longest routes of 10 m arenas need it). The bank's areas
    never overlap, so a task must be doable entering one area at a time, and its layouts admit a
    robot of ``generator.RANDOM_RADIUS`` at most. Raises ConfigError.
    """
    n = int(bank.arena.shape[0])
    if n == 0 or bank.fields.ndim != 5:
        raise ConfigError("bank", "a layout bank with its fields is needed (layout_bank.build_bank)")
    tasks = list(task) if isinstance(task, (list, tuple)) else [task]
    if not tasks:
        raise ConfigError("task", "the generalist needs at least one task")
    automata = []
    for t in tasks:
        a = task_automaton(task_formula(t)) if isinstance(t, str) else t
        if not isinstance(a, Automaton):
            raise ConfigError("task", "the generalist needs task names, formulas or Automaton objects")
        if len(tasks) > 1 and isinstance(a, BuchiTask) and any(map(any, a.visits)):
            raise ConfigError("task", f"{t if isinstance(t, str) else 'a task'} is scored by accepting visits; "
                              "a task mixture holds tasks that complete only (train or evaluate it alone)")
        unknown = sorted(set(a.aps) - {f"A{i + 1}" for i in range(N_AREAS)})
        if unknown:
            raise ConfigError("task", f"the generalist's layouts have areas A1..A4; the task names {unknown}")
        automata.append(a)
    cfg = dataclasses.replace(cfg, max_steps=max_steps).resolved()
    if cfg.robot_radius > generator.RANDOM_RADIUS:
        raise ConfigError("robot_radius", f"the generalist's layouts admit a robot of radius at most "
                          f"{generator.RANDOM_RADIUS:g} m, got {cfg.robot_radius:g}")
    aut, initials = union(automata) if len(automata) > 1 else (automata[0], [automata[0].initial])
    singles = [0] + [aut.letter([a]) for a in aut.aps]  # bank layouts' areas never overlap
    distance = aut.distances(singles)
    for t, q0 in zip(tasks, initials, strict=True):
        if distance[q0] is None:
            what = t if isinstance(t, str) else "a task"
            raise ConfigError("task", f"{what} cannot be completed entering one area at a time, as the generalist's "
                              "layouts (areas that never overlap) need")
    target, forbidden = area_roles(aut, state_fields.letter_roles(aut, distance, cfg.label_mode == "event"))
    finite = np.array([UNREACHABLE if d is None else d for d in distance])
    scale = np.ones(aut.n_states, np.float32)  # per state, its own task's largest finite distance
    bounds = np.cumsum([0] + [a.n_states for a in automata])
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        own = finite[lo:hi][finite[lo:hi] < UNREACHABLE]
        scale[lo:hi] = max(int(own.max()) if own.size else 1, 1)
    bits = np.array([aut.letter([f"A{i + 1}"]) if f"A{i + 1}" in aut.aps else 0 for i in range(N_AREAS)], np.int32)
    params = GeneralParams(
        **robot_fields(cfg, max_steps), **_layout_fields(bank, jnp.zeros((), jnp.int32)),
        aut=AutomatonArrays(*(None if x is None else jnp.asarray(x) for x in aut.arrays(singles, distance))),
        area_bits=jnp.asarray(bits),
        advance=jnp.asarray(target), relax_mask=jnp.ones_like(jnp.asarray(target)),
        geodesic=jnp.zeros((N_AREAS, 1, 1), jnp.float32), state_field=jnp.zeros((aut.n_states, 1, 1), jnp.float32),
        bank=bank, target_areas=jnp.asarray(target), forbidden_areas=jnp.asarray(forbidden),
        initials=jnp.asarray(initials, jnp.int32), progress_scale=jnp.asarray(scale))
    return GeneralistEnv(cfg, aut, n), params
