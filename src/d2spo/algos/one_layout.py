"""Where ``D2SPOLearner`` reads the layout when it trains on one (``--algo d2spo``, ``sl``).

The learner asks its layout reader (``layouts=``) for the arena, the CBF input x of an observation,
a step's sensed obstacles O_s, the runtime filter's obstacles and the cautious start's synthetic
samples. ``OneLayout`` reads them from the env params; ``algos.generalist.LayoutBank`` reads them
per environment of a bank of layouts.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from d2spo.envs import geometry, sensors
from d2spo.envs.geometry import Geometry
from d2spo.envs.sensors import Sensed

if TYPE_CHECKING:
    from d2spo.algos.d2spo import D2SPOConfig


class OneLayout:
    """Where D²SPO reads the layout when it trains on one (``--algo d2spo``, ``sl``): its env params.
    ``algos.generalist.LayoutBank`` reads it per environment instead. Every method takes the
    learner's params, so a learner acting on other params (``rollout.acting_on``) follows them."""

    params_as_argument = False
    """The run loop passes the env params to ``init`` and ``chunk`` as constants."""

    def __init__(self, env, params, d2: D2SPOConfig):
        self.lidar = env.observation_slices["lidar"]
        self.pose_slice = env.observation_slices.get("pose")
        self.H = float(env.config.sensing_radius)
        self.box_half = d2.synthetic_box_half

    def arena(self, params) -> tuple[jax.Array, jax.Array]:
        return params.geom.arena_lo, params.geom.arena_hi

    def x_of_obs(self, params, obs: jax.Array) -> jax.Array:
        return sensors.cbf_input_from_obs(obs, params.geom, self.lidar, self.pose_slice, self.H)

    def context(self, params, info: dict) -> Sensed:
        return sensors.sensed_obstacles(params.geom, info["sensed"])

    def filter_context(self, params, env_state) -> Sensed | None:
        return None

    def synthetic_sample(self, params, key: jax.Array):
        """A hypothetical pose among random boxes in this arena, as many as the layout has obstacles
        (pre-training data, not the layout)."""
        n = int(params.geom.n_obstacles)
        m = max(n, 1)
        k1, k2, k3, k4 = jax.random.split(key, 4)
        lo, hi = self.arena(params)
        pose_xy = jax.random.uniform(k1, (2,), minval=lo, maxval=hi)
        theta = jax.random.uniform(k2, (), minval=-jnp.pi, maxval=jnp.pi)
        centre = jax.random.uniform(k3, (m, 2), minval=lo, maxval=hi)
        a, b = self.box_half
        half = jax.random.uniform(k4, (m, 1), minval=a, maxval=b)
        box_lo, box_hi = centre - half, centre + half
        mask = geometry.sensed_mask(pose_xy, Geometry(box_lo, box_hi, lo, hi), self.H)
        if n == 0:
            mask = jnp.zeros((0,), bool)
            box_lo, box_hi = box_lo[:0], box_hi[:0]
        return jnp.concatenate([pose_xy, theta[None]]), Sensed(box_lo, box_hi, mask)
