"""Configuration of the navigation environment (``envs.nav``): layout, robot, dynamics and reward."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields, replace

from d2spo.envs import dynamics
from d2spo.errors import ConfigError
from d2spo.fields import check_choice, check_fields
from d2spo.ltl.labelling import LABEL_MODES
from d2spo.ltl.reward import PER_STATE, RewardConfig

DISTANCE_OBS = ("ratio", "capped")
"""How a generalist observes a distance (``EnvConfig.distance_obs``; ``envs.generalist.observed_distance``)."""


@dataclass(frozen=True)
class EnvConfig:
    """Configuration of the navigation environment. Fields left at None take the preset's value."""

    layout: str = "paper"
    """Workspace: paper, relaxed, open, physical-1..4, random[:SEED], random5[:SEED], world[:SEED],
    zones[:SEED] or a .json path (docs/layouts.md)."""
    preset: str = "default"
    """Preset of unset fields: ideal, default, turtlebot."""
    max_steps: int | None = None
    """Episode step limit (truncation). None: base_max_steps, or more for a long route (docs/ltl.md)."""
    base_max_steps: int = 300
    """Step limit of an unset max_steps when the task's shortest route needs at most 60% of it."""
    recurrence_max_steps: int = 1000
    """Least step limit of an unset max_steps for a recurrence (scored by accepting visits per
    episode): 1000, ZoneEnv's and DeepLTL's episodes; 0: the route rule alone (docs/ltl.md)."""
    n_rays: int = 16
    """Lidar rays K, evenly spaced, ray 0 straight ahead."""
    label_mode: str = "event"
    """Labelling: 'event' (a letter when the set of areas changes to a non-empty one) or 'step'."""
    observe_path: bool | None = None
    """Observe the shaping path's direction. None: on with the geodesic-per-state metric."""
    distance_obs: str = "ratio"
    """A generalist's observed distances d (to the target, to the forbidden area): 'ratio',
    d / (d + 10 m), distinct at every distance; 'capped', min(d / 10 m, 2), alike beyond 20 m."""
    forbidden_range: float | None = None
    """A generalist observes the nearest area whose entry would reject the task only within this
    distance (m) of its edge, beyond it as no forbidden area; None: at any distance (the default)."""
    label_radius: float | None = None
    """Initial labelling radius (m); None: each area's own."""
    collision_terminates: bool = True
    """A collision ends the episode (False: the robot stops)."""
    start_jitter_xy: float = 0.05
    """Start position noise (m), uniform in [-j, j] on x, y."""
    start_jitter_theta: float = 0.1
    """Start heading noise (rad), uniform in [-j, j]."""
    dt: float | None = None
    """Control period (s). Preset: 0.1, turtlebot 0.2."""
    v_max: float | None = None
    """Top linear speed (m/s). Preset: 1.0, turtlebot 0.22."""
    reverse: bool = True
    """The robot may drive backwards: a[0] spans [-v_max, v_max]; False: [0, v_max] (forward only)."""
    omega_max: float | None = None
    """Top turn rate (rad/s). Preset: 2.5, turtlebot 2.84."""
    robot_radius: float | None = None
    """Robot disk radius (m). Preset: 0.15, turtlebot 0.105."""
    sensing_radius: float | None = None
    """Sensing radius H (m). Preset: 1.2, turtlebot 3.5."""
    layout_scale: float | None = None
    """Layout length factor. Preset: 1.0, turtlebot 0.5."""
    actuator_tau: float | None = None
    """Actuator lag (s); 0 = none. Preset: 0, 0.08, 0.15."""
    v_gain: float | None = None
    """Realised / commanded v. Preset: 1.0, 0.95, 0.9."""
    omega_gain: float | None = None
    """Realised / commanded omega. Preset: 1.0, 0.95, 0.9."""
    slip: float | None = None
    """Max slip (fraction of speed). Preset: 0, 0.05, 0.1."""
    noise_xy: float | None = None
    """x, y noise std per step (m). Preset: 0, 0.005, 0.003."""
    noise_theta: float | None = None
    """theta noise std per step (rad). Preset: 0, 0.01, 0.02."""
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
        check_fields(self, nullable=preset_fields + ("label_radius", "max_steps", "observe_path", "forbidden_range"),
                     positive=("dt", "v_max", "omega_max", "robot_radius", "sensing_radius", "layout_scale",
                               "v_gain", "omega_gain", "label_radius", "forbidden_range"),
                     non_negative=("actuator_tau", "noise_xy", "noise_theta", "start_jitter_xy", "start_jitter_theta"),
                     count=("max_steps", "base_max_steps", "n_rays"), natural=("recurrence_max_steps",),
                     flag=("collision_terminates", "observe_path", "reverse"))
        if self.slip is not None and not (isinstance(self.slip, (int, float)) and 0 <= self.slip < 1):
            raise ConfigError("slip", f"must be in [0, 1), got {self.slip!r}")
        for name in dynamics.DYNAMICS_FIELDS:  # the motion's range as a dynamics file's (at most LARGEST)
            if getattr(self, name) is not None:
                dynamics.check_value(name, getattr(self, name))
        check_choice(self, "label_mode", LABEL_MODES)
        check_choice(self, "distance_obs", DISTANCE_OBS)
        if self.observe_path and self.reward.shaping_metric != PER_STATE:
            raise ConfigError("observe_path", f"needs --shaping-metric {PER_STATE} (the path is its field), got "
                              f"{self.reward.shaping_metric!r}")
        if not isinstance(self.layout, str):  # a config.json holds the string
            hint = f"; give it as a string, str({self.layout!r})" if isinstance(self.layout, os.PathLike) else ""
            raise ConfigError("layout", f"expected a layout name or a JSON path, got {self.layout!r}{hint}")
