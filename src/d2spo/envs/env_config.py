"""Configuration of the navigation environment (``envs.nav``): layout, robot, dynamics and reward."""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from d2spo.envs import dynamics
from d2spo.errors import ConfigError
from d2spo.fields import check_choice, check_fields
from d2spo.ltl.labelling import LABEL_MODES
from d2spo.ltl.reward import PER_STATE, RewardConfig


@dataclass(frozen=True)
class EnvConfig:
    """Configuration of the navigation environment. Fields left at None take the preset's value."""

    layout: str = "paper"
    """Workspace: paper, relaxed, open, physical-1..physical-4, random[:SEED], random5[:SEED], or a .json path."""
    preset: str = "default"
    """Robot and dynamics preset filling every field left unset: ideal, default or turtlebot."""
    max_steps: int | None = None
    """Episode length limit (steps); reaching it truncates the episode. None: ``base_max_steps``, or
    twice the task's shortest route at full speed (rounded up to 50) when that route needs over 60%
    of them (``envs.state_fields.default_max_steps``)."""
    base_max_steps: int = 300
    """The step limit an unset ``max_steps`` gives a task whose shortest route fits in 60% of it
    (every task on ``paper``). It was 200 before issue 15: ``paper``'s 0.75 m passages slow the
    robot, and avoid-until and next-chain, at 46% of 200 steps, timed out in them (docs/ltl.md, "Time")."""
    n_rays: int = 16
    """Number K of lidar rays, evenly spaced over 360 degrees, ray 0 straight ahead."""
    label_mode: str = "event"
    """Labelling: 'event' (read a letter when the set of areas changes to a non-empty one) or 'step'."""
    observe_path: bool | None = None
    """Append to the observation the direction in which the shaping path leaves the robot's
    position (unit vector of steepest descent of the current automaton state's field, in the robot's
    frame: forward, left; 0 where the field is flat), as the generalist's observation has. The
    field is the layout's map, never the dynamics. None (the default): on with
    ``reward.shaping_metric="geodesic-per-state"`` (the default metric), off with the others; True
    requires that metric. Off until 2026-11-25 (docs/env.md, "Observation")."""
    label_radius: float | None = None
    """Initial relaxed labelling radius (m) of every area for the reward; None = the true radius."""
    collision_terminates: bool = True
    """End the episode on collision; if False the robot is stopped at its last free position."""
    start_jitter_xy: float = 0.05
    """Start position noise: uniform in [-j, j] on x and on y (m, after layout scaling)."""
    start_jitter_theta: float = 0.1
    """Start heading noise: uniform in [-j, j] (rad)."""
    dt: float | None = None
    """Control period (s). Preset: 0.1 (ideal, default), 0.2 (turtlebot)."""
    v_max: float | None = None
    """Largest linear speed (m/s); action[0] = 1 commands v_max. Preset: 1.0, turtlebot 0.22."""
    omega_max: float | None = None
    """Largest angular speed (rad/s); action[1] = 1 commands omega_max. Preset: 2.5, turtlebot 2.84."""
    robot_radius: float | None = None
    """Radius of the robot disk (m). Preset: 0.15, turtlebot 0.105."""
    sensing_radius: float | None = None
    """Sensing radius H (m): lidar range and the radius defining O_s. Preset: 1.2, turtlebot 3.5."""
    layout_scale: float | None = None
    """Factor applied to every length of the layout. Preset: 1.0, turtlebot 0.5."""
    actuator_tau: float | None = None
    """Time constant of the first-order actuator lag (s); 0 = none. Preset: 0, 0.08, 0.15."""
    v_gain: float | None = None
    """Realised / commanded linear speed (gain mismatch). Preset: 1.0, 0.95, 0.9."""
    omega_gain: float | None = None
    """Realised / commanded angular speed (gain mismatch). Preset: 1.0, 0.95, 0.9."""
    slip: float | None = None
    """Largest fraction of speed lost to wheel slip per step, drawn in [0, slip]. Preset: 0, 0.05, 0.1."""
    noise_xy: float | None = None
    """Std of the Gaussian process noise on x and on y per step (m). Preset: 0, 0.005, 0.003."""
    noise_theta: float | None = None
    """Std of the Gaussian process noise on theta per step (rad). Preset: 0, 0.01, 0.02."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """Constants of the TLGRL reward, Eq. (8)."""

    def resolved(self) -> EnvConfig:
        """This config with every None filled from the preset, checked; ConfigError names the field."""
        preset = dynamics.get_preset(self.preset)
        filled = {
            f.name: getattr(preset, f.name)
            for f in fields(dynamics.Preset)
            if getattr(self, f.name) is None
        }
        if self.observe_path is None:
            filled["observe_path"] = self.reward.shaping_metric == PER_STATE
        return replace(self, **filled)  # checked again by __post_init__, now with no field unset

    def __post_init__(self) -> None:
        """Every field that is set; the preset's (None here) are checked once ``resolved`` fills them."""
        dynamics.get_preset(self.preset)
        preset_fields = ("dt", "v_max", "omega_max", "robot_radius", "sensing_radius", "layout_scale", "v_gain",
                         "omega_gain", "actuator_tau", "noise_xy", "noise_theta", "slip")
        check_fields(self, nullable=preset_fields + ("label_radius", "max_steps", "observe_path"),
                     positive=("dt", "v_max", "omega_max", "robot_radius", "sensing_radius", "layout_scale",
                               "v_gain", "omega_gain", "label_radius"),
                     non_negative=("actuator_tau", "noise_xy", "noise_theta", "start_jitter_xy", "start_jitter_theta"),
                     count=("max_steps", "base_max_steps", "n_rays"), flag=("collision_terminates", "observe_path"))
        if self.slip is not None and not (isinstance(self.slip, (int, float)) and 0 <= self.slip < 1):
            raise ConfigError("slip", f"must be in [0, 1), got {self.slip!r}")
        check_choice(self, "label_mode", LABEL_MODES)
        if self.observe_path and self.reward.shaping_metric != PER_STATE:
            raise ConfigError("observe_path", f"needs --shaping-metric {PER_STATE} (the path is its field), got "
                              f"{self.reward.shaping_metric!r}")
        if not isinstance(self.layout, str):
            raise ConfigError("layout", f"expected a layout name or a JSON path, got {self.layout!r}")
