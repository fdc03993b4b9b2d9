"""The true robot dynamics (Example 1): a unicycle with unmodelled effects.

Learners never see this module: it is the black box f of Eq. (1). The nominal model f_n that
D²SPO fits (Eq. (5)) lives in ``d2spo.safety.nominal``.

State s = (x, y, theta). The agent's action a in [-1, 1]^2 is clipped to that box and scaled to the
commanded velocities (v, omega) = (a_0 * v_max, a_1 * omega_max); a robot that cannot reverse
(``EnvConfig.reverse`` False) maps a_0 onto [0, v_max] instead: v = (a_0 + 1) / 2 * v_max. Then,
per step of length dt:

1. actuator lag: the realised velocities follow the commands through a first-order lag with time
   constant ``actuator_tau`` (exact discretisation, alpha = 1 - exp(-dt / tau); tau = 0 means none);
2. gain mismatch and slip: v_eff = v * v_gain * (1 - slip * u_v), omega_eff likewise with
   omega_gain and its own u_omega, where u ~ U(0, 1) is drawn every step;
3. motion: midpoint integration, x += v_eff * cos(theta + omega_eff * dt / 2) * dt (y likewise with
   sin), theta += omega_eff * dt;
4. process noise: Gaussian with std ``noise_xy`` on x and on y, ``noise_theta`` on theta; then
   theta is wrapped to [-pi, pi).

Presets (``PRESETS``) bundle values for every dynamics field of ``EnvConfig`` plus the robot's
size and sensor, and a ``layout_scale`` applied to the layout's geometry.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
from flax import struct

from d2spo.errors import ConfigError, is_finite_number, json_trouble
from d2spo.inputs import read_regular


@dataclass(frozen=True)
class Preset:
    """Values a preset gives to the ``EnvConfig`` fields the user left unset (None)."""

    dt: float
    """Control period (s)."""
    v_max: float
    """Largest commanded linear speed (m/s)."""
    omega_max: float
    """Largest commanded angular speed (rad/s)."""
    robot_radius: float
    """Radius of the robot disk (m)."""
    sensing_radius: float
    """Sensing radius H (m)."""
    layout_scale: float
    """Factor applied to every length of the layout (arena, obstacles, areas, start)."""
    actuator_tau: float
    """Time constant of the first-order actuator lag (s); 0 = none."""
    v_gain: float
    """Realised / commanded linear speed."""
    omega_gain: float
    """Realised / commanded angular speed."""
    slip: float
    """Largest fraction of speed lost to wheel slip in one step (drawn uniformly in [0, slip])."""
    noise_xy: float
    """Std of the Gaussian process noise on x and on y, per step (m)."""
    noise_theta: float
    """Std of the Gaussian process noise on theta, per step (rad)."""


PRESETS: dict[str, Preset] = {
    # No unmodelled effect: the true dynamics is the textbook unicycle (midpoint-integrated).
    "ideal": Preset(
        dt=0.1, v_max=1.0, omega_max=2.5, robot_radius=0.15, sensing_radius=1.2, layout_scale=1.0,
        actuator_tau=0.0, v_gain=1.0, omega_gain=1.0, slip=0.0, noise_xy=0.0, noise_theta=0.0,
    ),
    # The paper's simulations: mild lag, ~5 % weaker actuation, a little slip and noise.
    "default": Preset(
        dt=0.1, v_max=1.0, omega_max=2.5, robot_radius=0.15, sensing_radius=1.2, layout_scale=1.0,
        actuator_tau=0.08, v_gain=0.95, omega_gain=0.95, slip=0.05, noise_xy=0.005, noise_theta=0.01,
    ),
    # TurtleBot3 Burger: 0.22 m/s, 2.84 rad/s, LDS lidar range 3.5 m, 0.105 m footprint radius.
    # Layouts are halved (5 m -> 2.5 m) and dt doubled to 0.2 s so that crossing the arena takes
    # ~57 steps at full speed, close to the 50 steps of the default preset (see docs/env.md).
    "turtlebot": Preset(
        dt=0.2, v_max=0.22, omega_max=2.84, robot_radius=0.105, sensing_radius=3.5, layout_scale=0.5,
        actuator_tau=0.15, v_gain=0.9, omega_gain=0.9, slip=0.1, noise_xy=0.003, noise_theta=0.02,
    ),
}


DYNAMICS_FIELDS = ("dt", "v_max", "omega_max", "actuator_tau", "v_gain", "omega_gain", "slip", "noise_xy",
                   "noise_theta")
"""The ``EnvConfig`` fields that make up the robot's motion: what a dynamics file gives (all of them)."""

NOT_DYNAMICS = {
    "robot_radius": "the robot's size is --robot-radius",
    "radius": "the robot's size is --robot-radius",
    "sensing_radius": "the lidar's range is --sensing-radius",
    "n_rays": "the lidar's rays are --n-rays",
    "reverse": "a robot that cannot reverse is --no-reverse",
}
"""Keys a robot's description may hold that are not its motion: the flag each is given by."""

_POSITIVE = ("dt", "v_max", "omega_max", "v_gain", "omega_gain")
LARGEST = 1e6
"""The largest value a dynamics field takes: far beyond any robot, and far below float32's overflow."""


def check_value(name: str, value, where: str = "") -> float:
    """``value`` as a float if it is valid for the dynamics field ``name``; ConfigError naming the
    field otherwise (``where`` is added to the message, e.g. the file it came from)."""
    if not is_finite_number(value):
        raise ConfigError(name, f"expected a finite number, got {value!r}{where}")
    if name == "slip" and not 0 <= value < 1:
        raise ConfigError(name, f"must be in [0, 1), got {value}{where}")
    if value < 0 or (value == 0 and name in _POSITIVE):
        raise ConfigError(name, f"must be {'positive' if name in _POSITIVE else 'non-negative'}, got {value}{where}")
    if value > LARGEST:
        raise ConfigError(name, f"must be at most {LARGEST:g}, got {value:g}{where} (the float32 dynamics overflow "
                          "long before such values)")
    return float(value)


def load_dynamics(path: str | Path) -> dict[str, float]:
    """The dynamics in a JSON file: an object with every field of ``DYNAMICS_FIELDS`` (and optional
    ``name`` and ``description`` strings), as ``{field: value}``, ready for ``EnvConfig(**values)``.
    Every mistake (unreadable, not UTF-8, malformed JSON, unknown or missing key, wrong type,
    out-of-range value) raises ConfigError naming ``dynamics`` or ``dynamics.FIELD``."""
    path = Path(path)
    try:
        text = read_regular(path, lambda message: ConfigError("dynamics", message)).decode("utf-8-sig")  # a BOM too
    except UnicodeDecodeError as e:
        raise ConfigError("dynamics", f"{path}: not UTF-8 text (byte {e.start})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ConfigError("dynamics", f"{path}: malformed JSON: {e.msg} (line {e.lineno}, column {e.colno})") from None
    except (RecursionError, ValueError) as e:  # nested too deeply; a number too long to read
        raise ConfigError("dynamics", f"{path}: unreadable JSON ({json_trouble(e)})") from None
    if not isinstance(data, dict):
        raise ConfigError("dynamics", f"{path}: expected a JSON object, got {type(data).__name__}")
    unknown = sorted(set(data) - set(DYNAMICS_FIELDS) - {"name", "description"})
    if unknown:
        flags = [k for k in unknown if k in NOT_DYNAMICS]
        hint = (f"; {', '.join(flags)} {'is' if len(flags) == 1 else 'are'} not dynamics: "
                f"{', '.join(NOT_DYNAMICS[k] for k in flags)}" if flags else "")
        raise ConfigError("dynamics", f"{path}: unknown keys {unknown}; the fields are {list(DYNAMICS_FIELDS)}, "
                                      f"with 'name' and 'description'{hint}")
    for key in ("name", "description"):
        if key in data and not isinstance(data[key], str):
            raise ConfigError(f"dynamics.{key}", f"expected a string, got {data[key]!r} (in {path})")
    values = {}
    for name in DYNAMICS_FIELDS:
        if name not in data:
            raise ConfigError(f"dynamics.{name}", f"missing (in {path}); a dynamics file gives every field of "
                              f"{list(DYNAMICS_FIELDS)}")
        try:
            values[name] = check_value(name, data[name], f" (in {path})")
        except ConfigError as e:
            raise ConfigError(f"dynamics.{name}", str(e).split(": ", 1)[1]) from None
    return values


def get_preset(name: str) -> Preset:
    """The preset called ``name``; ConfigError naming ``preset`` otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError("preset", f"unknown preset {name!r}; choose one of {sorted(PRESETS)}") from None


@struct.dataclass
class DynamicsParams:
    """Parameters of the true dynamics, as arrays (traced under jit, so they can be changed)."""

    dt: jnp.ndarray
    """Control period (s)."""
    v_max: jnp.ndarray
    """Largest commanded linear speed (m/s)."""
    omega_max: jnp.ndarray
    """Largest commanded angular speed (rad/s)."""
    lag_alpha: jnp.ndarray
    """Per-step blending factor of the actuator lag, 1 - exp(-dt / tau) (1 when tau = 0)."""
    v_gain: jnp.ndarray
    """Realised / commanded linear speed."""
    omega_gain: jnp.ndarray
    """Realised / commanded angular speed."""
    slip: jnp.ndarray
    """Largest fraction of speed lost to slip per step."""
    noise_xy: jnp.ndarray
    """Std of the process noise on x and y (m)."""
    noise_theta: jnp.ndarray
    """Std of the process noise on theta (rad)."""
    v_mid: jnp.ndarray
    """Commanded linear speed at a_0 = 0: 0 for a robot that reverses, v_max / 2 for one that cannot."""

    @classmethod
    def create(cls, *, dt, v_max, omega_max, actuator_tau, v_gain, omega_gain, slip, noise_xy, noise_theta,
               reverse=True):
        alpha = 1.0 if actuator_tau == 0 else 1.0 - math.exp(-dt / actuator_tau)
        f = lambda v: jnp.asarray(v, jnp.float32)
        return cls(
            dt=f(dt), v_max=f(v_max), omega_max=f(omega_max), lag_alpha=f(alpha), v_gain=f(v_gain),
            omega_gain=f(omega_gain), slip=f(slip), noise_xy=f(noise_xy), noise_theta=f(noise_theta),
            v_mid=f(0.0 if reverse else 0.5 * v_max),
        )


def wrap_angle(theta: jnp.ndarray) -> jnp.ndarray:
    """theta mapped to [-pi, pi)."""
    two_pi = 2.0 * math.pi
    return theta - two_pi * jnp.floor((theta + math.pi) / two_pi)


def command(action: jnp.ndarray, dyn: DynamicsParams) -> jnp.ndarray:
    """Commanded (v, omega) [2] from an action in [-1, 1]^2 (out-of-range actions are clipped): v spans
    [-v_max, v_max], or [0, v_max] for a robot that cannot reverse (v_mid = v_max / 2)."""
    a = jnp.clip(action, -1.0, 1.0)
    return jnp.stack([a[0] * (dyn.v_max - dyn.v_mid) + dyn.v_mid, a[1] * dyn.omega_max])


def unicycle_step(
    pose: jnp.ndarray, vel: jnp.ndarray, action: jnp.ndarray, noise: jnp.ndarray, slip_u: jnp.ndarray,
    dyn: DynamicsParams,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """One step of the true dynamics.

    pose [3] = (x, y, theta); vel [2] = realised (v, omega) of the previous step (the actuator
    state); action [2] in [-1, 1]; noise [3] standard normal; slip_u [2] uniform in [0, 1].
    Returns (next pose [3], next actuator state [2]).
    """
    vel_next = vel + dyn.lag_alpha * (command(action, dyn) - vel)
    v = vel_next[0] * dyn.v_gain * (1.0 - dyn.slip * slip_u[0])
    w = vel_next[1] * dyn.omega_gain * (1.0 - dyn.slip * slip_u[1])
    heading = pose[2] + 0.5 * w * dyn.dt
    x = pose[0] + v * jnp.cos(heading) * dyn.dt + dyn.noise_xy * noise[0]
    y = pose[1] + v * jnp.sin(heading) * dyn.dt + dyn.noise_xy * noise[1]
    theta = wrap_angle(pose[2] + w * dyn.dt + dyn.noise_theta * noise[2])
    return jnp.stack([x, y, theta]), vel_next
