"""D²SPO over ``envs.generalist.GeneralistEnv``: one learner for a bank of layouts (``--generalist``).

``D2SPOLearner`` reads the layout through its ``layouts`` (``algos.one_layout.OneLayout``: from its
params). The CBF input of an observation needs the layout's obstacles (the nearest-obstacle
distance) and the datasets store the step's sensed set of the layout's boxes. Over a bank every
environment has its own layout, so the generalist is ``D2SPOLearner`` given ``LayoutBank``, which
reads both per environment instead:

* x of an observation is ``GeneralistEnv.cbf_input`` (the ranges and the clearance it carries);
* a step's O_s is ``info["box_lo"]``, ``info["box_hi"]``, ``info["disk_center"]``,
  ``info["disk_radius"]`` and ``info["sensed"]`` (the layout's boxes, its four walls as boxes and
  its disks, ``envs.generalist.view``); the sensor model then needs no arena, so the learner's
  arena is one far larger than any layout's;
* the cautious start's synthetic samples are drawn among boxes and disks in arenas of
  ``SYNTHETIC_SIDE`` with walls as boxes, as the bank's layouts are;
* the runtime filter keeps clear of the obstacles of each environment's own layout
  (``filter_context``), in training and when acting.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from d2spo.algos.d2spo import D2SPOConfig, D2SPOLearner
from d2spo.envs import geometry
from d2spo.envs.generalist import N_BOXES, N_DISKS, make_generalist_env, view_geometry, wall_boxes
from d2spo.envs.geometry import Geometry
from d2spo.envs.sensors import Sensed
from d2spo.errors import ConfigError
from d2spo.ltl.tasks import patrol_tasks, reach_avoid_tasks

BEYOND = 1.0e3
SYNTHETIC_SIDE = (5.0, 20.0)
"""Range of the synthetic samples' arena side (m): the sides the generalist's layouts have."""
SYNTHETIC_DISK_RADIUS = (0.1, 0.4)
"""Range of the synthetic samples' disk radii (m)."""
"""Half-side (m) of the learner's arena: farther than any wall box, so walls are seen only as boxes."""


class LayoutBank:
    """Where the generalist reads the layout: per environment, from its bank (module docstring).
    Every method takes the learner's params (the bank), so they may be an argument of the program."""

    params_as_argument = True
    """The run loop passes the env params (the field bank) to ``init`` and ``chunk`` as an argument,
    not as constants (``train.learner_program``)."""

    def __init__(self, env, params, d2: D2SPOConfig):
        if int(params.geom.box_lo.shape[0]) != N_BOXES or params.geom.n_disks != N_DISKS:
            raise ConfigError("env", "LayoutBank reads envs.generalist.GeneralistEnv")
        self.env = env
        self.H = float(env.config.sensing_radius)
        self.box_half = d2.synthetic_box_half

    def arena(self, params) -> tuple[jax.Array, jax.Array]:
        return jnp.full((2,), -BEYOND, jnp.float32), jnp.full((2,), BEYOND, jnp.float32)

    def x_of_obs(self, params, obs: jax.Array) -> jax.Array:
        return self.env.cbf_input(obs, params)

    def context(self, params, info: dict) -> Sensed:
        return Sensed(info["box_lo"], info["box_hi"], info["sensed"], info["disk_center"], info["disk_radius"])

    def filter_context(self, params, env_state) -> Sensed:
        """Every obstacle (boxes, walls, disks) of the layout of each environment of ``env_state``."""

        def one(b):
            g = view_geometry(params.bank, b)
            return Sensed(g.box_lo, g.box_hi, jnp.ones((g.n_obstacles,), bool), g.disk_center, g.disk_radius)

        b = env_state.layout
        return jax.vmap(one)(b) if b.ndim else one(b)

    def synthetic_sample(self, params, key: jax.Array):
        """A hypothetical pose among random boxes and disks in a random square arena of
        ``SYNTHETIC_SIDE``, its walls as the last four boxes (as in ``envs.generalist.view``)."""
        k_side, k_pose, k_theta, k_centre, k_half, k_disk, k_radius = jax.random.split(key, 7)
        side = jax.random.uniform(k_side, (), minval=SYNTHETIC_SIDE[0], maxval=SYNTHETIC_SIDE[1])
        pose_xy = jax.random.uniform(k_pose, (2,), minval=0.0, maxval=side)
        theta = jax.random.uniform(k_theta, (), minval=-jnp.pi, maxval=jnp.pi)
        m = N_BOXES - 4
        centre = jax.random.uniform(k_centre, (m, 2), minval=0.0, maxval=side)
        a, b = self.box_half
        half = jax.random.uniform(k_half, (m, 1), minval=a, maxval=b)
        w_lo, w_hi = wall_boxes(jnp.stack([side, side]))
        box_lo = jnp.concatenate([centre - half, w_lo])
        box_hi = jnp.concatenate([centre + half, w_hi])
        disk_center = jax.random.uniform(k_disk, (N_DISKS, 2), minval=0.0, maxval=side)
        disk_radius = jax.random.uniform(k_radius, (N_DISKS,), minval=SYNTHETIC_DISK_RADIUS[0],
                                         maxval=SYNTHETIC_DISK_RADIUS[1])
        lo, hi = self.arena(params)
        mask = geometry.sensed_mask(pose_xy, Geometry(box_lo, box_hi, lo, hi, disk_center, disk_radius), self.H)
        return jnp.concatenate([pose_xy, theta[None]]), Sensed(box_lo, box_hi, mask, disk_center, disk_radius)


def build_generalist(cfg, layouts, max_steps: int | None, tasks_of=None):
    """(env, params, learner) of a generalist config (``TrainConfig``, ``generalist`` set) on
    ``layouts`` (or a bank of this config's task mixture) for ``cfg.task`` and
    ``cfg.generalist_tasks`` random reach-avoid sequences and ``cfg.generalist_patrols`` random
    recurrences (slot k paired with task tasks_of[k],
    default k modulo their number), every episode at most ``max_steps`` long (None: each slot's
    ``envs.task_plan.slot_max_steps``). The layouts' own radii label the areas (no annealing)."""
    mixture = [*reach_avoid_tasks(cfg.generalist_tasks), *patrol_tasks(cfg.generalist_patrols)]
    tasks = [cfg.task, *mixture] if mixture else cfg.task
    env, params = make_generalist_env(cfg.env_config(), tasks, layouts, max_steps, tasks_of)
    anneal = dataclasses.replace(cfg.anneal, enabled=False)
    learner = D2SPOLearner(env, params, cfg.td3, cfg.cbf, anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes,
                           cfg.d2spo, layouts=LayoutBank)
    return env, params, learner


class Redraw:
    """Fresh layouts for a generalist's bank while it trains (``TrainConfig.generalist_redraw``).

    After chunk k the next ``generalist_redraw`` slots in turn that no environment is in get the
    layouts WORLD:REDRAW_SEED + n for the next n (a running count), each paired with its slot's own
    task, its roles, episode limit and fields computed then (``GeneralistEnv.bank``). The bank's
    state is the map slot -> seed, kept in the checkpoint's meta (``"redrawn"``), so a resumed run
    rebuilds the same bank. An environment keeps its slot to the end of its episode: the slots in
    use are skipped, so no episode changes layout under the robot."""

    def __init__(self, cfg, env):
        self.cfg, self.env = cfg, env
        self.per_chunk = int(cfg.generalist_redraw)
        self.size = int(cfg.generalist_layouts) * int(cfg.generalist_pairings)

    def apply(self, params, assigned: dict[str, int]) -> object:
        """``params`` with slot s holding layout WORLD:seed for every ("s", seed) of ``assigned``."""
        if not assigned:
            return params
        from d2spo.envs.layouts import load

        slots = sorted(int(s) for s in assigned)
        layouts = [load(f"{self.cfg.generalist_world}:{int(assigned[str(s)])}") for s in slots]
        tasks = [int(t) for t in jax.device_get(params.bank.task)[slots]]
        fresh = self.env.bank(layouts, tasks, self.cfg.env.max_steps, method="jax")  # fields independent of grouping
        index = jnp.asarray(slots, jnp.int32)
        bank = jax.tree_util.tree_map(lambda old, new: old.at[index].set(new), params.bank, fresh)
        return params.replace(bank=bank)

    def next(self, params, in_use, meta: dict) -> tuple[object, dict]:
        """(params, the run meta's updates) after one chunk's redraw: ``in_use`` [num_envs] the slots
        the environments are in; ``meta`` holds ``"redrawn"`` (slot -> seed), ``"redraw_next"`` (the
        next slot in turn) and ``"redraw_count"`` (layouts drawn so far)."""
        from d2spo.config import REDRAW_SEED

        busy = {int(s) for s in jax.device_get(in_use).ravel()}
        slot, count = int(meta.get("redraw_next", 0)), int(meta.get("redraw_count", 0))
        chosen: dict = {}
        for _ in range(self.size):
            if len(chosen) == self.per_chunk:
                break
            if slot not in busy:
                chosen[str(slot)] = REDRAW_SEED + count
                count += 1
            slot = (slot + 1) % self.size
        updates = {"redrawn": {**meta.get("redrawn", {}), **chosen}, "redraw_next": slot, "redraw_count": count}
        return self.apply(params, chosen), updates
