"""The real bounds of the observation, for the Gymnasium and gymnax front ends.

Every component of the observation (see ``nav.Env``) is bounded:

* ``lidar``: ranges / H, in [0, 1];
* ``pose``: x and y scaled to [-1, 1] over the arena, widened by how far the robot centre can
  leave the arena in the one step that ends an episode by collision (below); cos and sin in [-1, 1];
* ``areas``: each area centre in the robot frame / the arena's longer side; both components are
  bounded by the distance from that centre to the farthest corner of the (widened) arena;
* ``automaton``: a one-hot vector, in [0, 1].

How far the centre can leave the arena: a step that starts with the robot disk inside the arena
moves the centre by at most v_max · v_gain · dt (the actuator lag only blends commands, slip only
slows) plus the process noise. The noise is drawn as sqrt(2) · erfinv(u) with u a float32 in
(-1, 1), so it never exceeds 5.5 standard deviations; we allow 6. A collision is declared as
soon as the centre is within one robot radius of a wall, so the centre ends at most
``v_max · v_gain · dt + 6 · noise_xy − robot_radius`` beyond it (and nowhere beyond it when
``collision_terminates`` is off: the robot is then held where it was).
"""

from __future__ import annotations

import numpy as np

from d2spo.envs.nav import Env

_NOISE_SIGMAS = 6.0
"""Bound on one standard-normal draw of the process noise (float32 erfinv reaches about 5.5)."""
_ROUNDING = 1e-5
"""Slack for float32 rounding in the scaled position and the area offsets."""


def outside_margin(env: Env) -> float:
    """How far (m) the robot centre can end beyond the arena wall, in the step that collides."""
    cfg = env.config
    if not cfg.collision_terminates:
        return 0.0
    return max(0.0, cfg.v_max * cfg.v_gain * cfg.dt + _NOISE_SIGMAS * cfg.noise_xy - cfg.robot_radius)


def observation_bounds(env: Env) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), float32 [observation_size]: bounds that every observation of ``env`` lies in."""
    low = np.zeros(env.observation_size, np.float32)
    high = np.ones(env.observation_size, np.float32)
    sl = env.observation_slices
    w, h = env.layout.arena
    m = outside_margin(env)

    pose_hi = np.array([1.0 + 2.0 * m / w, 1.0 + 2.0 * m / h, 1.0, 1.0]) + _ROUNDING
    low[sl["pose"]], high[sl["pose"]] = -pose_hi, pose_hi

    corners = np.array([[-m, -m], [w + m, -m], [-m, h + m], [w + m, h + m]])
    reach = [np.max(np.hypot(*(corners - np.asarray(a.center)).T)) for a in env.layout.areas]
    area_hi = np.repeat(np.asarray(reach) / max(w, h), 2) + _ROUNDING  # (forward, left) per area
    low[sl["areas"]], high[sl["areas"]] = -area_hi, area_hi
    if "path" in sl:
        low[sl["path"]], high[sl["path"]] = -1.0 - _ROUNDING, 1.0 + _ROUNDING
    return low, high
