"""D²SPO over ``envs.generalist.GeneralistEnv``: one learner for a bank of layouts (``--generalist``).

``D2SPOLearner`` reads the layout through its ``layouts`` (``algos.d2spo.OneLayout``: from its
params). The CBF input of an observation needs the layout's obstacles (the nearest-obstacle
distance) and the datasets store the step's sensed set of the layout's boxes. Over a bank every
environment has its own layout, so the generalist is ``D2SPOLearner`` given ``LayoutBank``, which
reads both per environment instead:

* x of an observation is ``GeneralistEnv.cbf_input`` (the ranges and the clearance it carries);
* a step's O_s is ``info["box_lo"]``, ``info["box_hi"]`` and ``info["sensed"]`` (the layout's
  boxes and its four walls as boxes, ``envs.generalist.view``); the sensor model then needs no
  arena, so the learner's arena is one far larger than any layout's;
* the cautious start's synthetic samples are drawn in arenas of ``generator.SIDE`` with walls as
  boxes, as the bank's layouts are;
* the runtime filter keeps clear of the boxes of each environment's own layout
  (``filter_context``), in training and when acting.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from d2spo.algos.d2spo import D2SPOConfig, D2SPOLearner
from d2spo.envs import generator, geometry
from d2spo.envs.generalist import N_BOXES, make_generalist_env, view, wall_boxes
from d2spo.envs.geometry import Geometry
from d2spo.envs.sensors import Sensed
from d2spo.errors import ConfigError
from d2spo.ltl.tasks import reach_avoid_tasks

BEYOND = 1.0e3
"""Half-side (m) of the learner's arena: farther than any wall box, so walls are seen only as boxes."""


class LayoutBank:
    """Where the generalist reads the layout: per environment, from its bank (module docstring).
    Every method takes the learner's params (the bank), so they may be an argument of the program."""

    params_as_argument = True
    """The run loop passes the env params (the field bank) to ``init`` and ``chunk`` as an argument,
    not as constants (``train.learner_program``)."""

    def __init__(self, env, params, d2: D2SPOConfig):
        if int(params.geom.box_lo.shape[0]) != N_BOXES:
            raise ConfigError("env", "LayoutBank reads envs.generalist.GeneralistEnv")
        self.env = env
        self.H = float(env.config.sensing_radius)
        self.box_half = d2.synthetic_box_half

    def arena(self, params) -> tuple[jax.Array, jax.Array]:
        return jnp.full((2,), -BEYOND, jnp.float32), jnp.full((2,), BEYOND, jnp.float32)

    def x_of_obs(self, params, obs: jax.Array) -> jax.Array:
        return self.env.cbf_input(obs, params)

    def context(self, params, info: dict) -> Sensed:
        return Sensed(info["box_lo"], info["box_hi"], info["sensed"])

    def filter_context(self, params, env_state) -> Sensed:
        """Every box (obstacles and walls) of the layout of each environment of ``env_state``."""

        def one(b):
            g = view(params, b).geom
            return Sensed(g.box_lo, g.box_hi, jnp.ones(g.box_lo.shape[:1], bool))

        b = env_state.layout
        return jax.vmap(one)(b) if b.ndim else one(b)

    def synthetic_sample(self, params, key: jax.Array):
        """A hypothetical pose among random boxes in a random arena of the generator's sizes, its
        walls as the last four boxes (as in ``envs.generalist.view``)."""
        k_side, k_pose, k_theta, k_centre, k_half = jax.random.split(key, 5)
        side = jax.random.uniform(k_side, (), minval=generator.SIDE[0], maxval=generator.SIDE[1])
        pose_xy = jax.random.uniform(k_pose, (2,), minval=0.0, maxval=side)
        theta = jax.random.uniform(k_theta, (), minval=-jnp.pi, maxval=jnp.pi)
        m = N_BOXES - 4
        centre = jax.random.uniform(k_centre, (m, 2), minval=0.0, maxval=side)
        a, b = self.box_half
        half = jax.random.uniform(k_half, (m, 1), minval=a, maxval=b)
        w_lo, w_hi = wall_boxes(jnp.stack([side, side]))
        box_lo = jnp.concatenate([centre - half, w_lo])
        box_hi = jnp.concatenate([centre + half, w_hi])
        lo, hi = self.arena(params)
        mask = geometry.sensed_mask(pose_xy, Geometry(box_lo, box_hi, lo, hi), self.H)
        return jnp.concatenate([pose_xy, theta[None]]), Sensed(box_lo, box_hi, mask)


def build_generalist(cfg, bank, max_steps: int):
    """(env, params, learner) of a generalist config (``TrainConfig``, ``generalist`` set) on ``bank``
    for ``cfg.task`` and ``cfg.generalist_tasks`` random reach-avoid sequences, every episode at
    most ``max_steps`` long. The layouts' own radii label the areas (no annealing)."""
    tasks = [cfg.task, *reach_avoid_tasks(cfg.generalist_tasks)] if cfg.generalist_tasks else cfg.task
    env, params = make_generalist_env(cfg.env_config(), tasks, bank, max_steps)
    anneal = dataclasses.replace(cfg.anneal, enabled=False)
    learner = D2SPOLearner(env, params, cfg.td3, cfg.cbf, anneal, cfg.num_envs, cfg.chunk_steps, cfg.episodes,
                           cfg.d2spo, layouts=LayoutBank)
    return env, params, learner
