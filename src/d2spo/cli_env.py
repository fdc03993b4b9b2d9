"""The ``d2spo env`` commands (``cli.commands`` lists them): draw a layout (``env show``) and check a
layout, and a task on it, as training would (``env check``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Union

import tyro

from d2spo.demo import random_rollout
from d2spo.envs import EnvConfig, layouts, make_env
from d2spo.envs.dynamics import load_dynamics
from d2spo.envs.layout_bank import check_fits
from d2spo.envs.nav import checked_layout
from d2spo.envs.preflight import preflight, start_state
from d2spo.errors import ConfigError
from d2spo.fields import check_choice, check_fields
from d2spo.ltl.buchi_task import is_recurrence
from d2spo.ltl.labelling import LABEL_MODES
from d2spo.plotstyle import check_picture_path
from d2spo.rollout import visit_optimum
from d2spo.safety.cbf import CBFConfig


@dataclasses.dataclass
class EnvShowCmd:
    """Draw a layout: obstacles, labelled areas, the start and the sensing radius."""

    layout: str = "paper"
    """Built-in layout name (paper, relaxed, open, physical-1..4), random[:SEED] (5-10 m, three styles),
    random5[:SEED] (the earlier 5 m generator), world[:SEED] (the generalist's world: 5-20 m, boxes and
    pillars, 4-12 areas), zones[:SEED] (a ZoneEnv-style layout) or a JSON file (docs/layouts.md)."""
    out: Path = Path("layout.png")
    """Where to write the picture: .png (300 dpi), .pdf or .svg."""
    rollout_steps: int = 0
    """If > 0, also draw a random-action rollout of this many steps."""
    seed: int = 0
    """Seed for the rollout."""
    task: str | None = None
    """The rollout's task (a name or a formula): the rollout ends where an episode of it would; default:
    reach the last area's label."""
    label_mode: str = "event"
    """The rollout's labelling, as `d2spo train --label-mode`: 'event' or 'step'; the task reads its letters."""

    def run(self) -> int:
        check_fields(self, natural=("rollout_steps",), seed=("seed",))  # as train's and eval's: -3 is no count
        check_choice(self, "label_mode", LABEL_MODES)
        check_picture_path(self.out, "out")
        lay = layouts.load(self.layout)
        trajs, title = None, None
        for name, given in (("task", self.task is not None), ("label_mode", self.label_mode != "event")):
            if given and self.rollout_steps <= 0:
                raise ConfigError(name, "applies to the random rollout only: give --rollout-steps N (N > 0) too")
        if self.rollout_steps > 0:
            task = self.task if self.task is not None else f"F {lay.areas[-1].label}"
            trajs = [random_rollout(self.layout, self.rollout_steps, self.seed, task=task, label_mode=self.label_mode)]
            labels = ", step labelling" if self.label_mode == "step" else ""
            title = f"layout {lay.name!r}: a random-action rollout, task {task!r} (seed {self.seed}{labels})"
        from d2spo.envs.render import save_layout_png  # matplotlib: imported only to draw

        save_layout_png(lay, self.out, trajectories=trajs, title=title, trajectory_label="random actions (x: end)")
        print(f"wrote {self.out}")
        return 0


@dataclasses.dataclass
class EnvCheckCmd:
    """Validate a layout (built-in or JSON file) for the robot of a preset and print what it holds."""

    layout: str = "paper"
    """Built-in layout name or a JSON file."""
    task: str | None = None
    """Also check that this task (a name or a formula) can be completed on the layout; default: no task."""
    preset: str = "default"
    """Robot preset whose size and layout scale the layout is checked with: ideal, default or turtlebot."""
    robot_radius: float | None = None
    """The robot's radius (m), as `d2spo train --robot-radius`; default: the preset's."""
    dynamics: Path | None = None
    """A dynamics JSON file (docs/env.md), as `d2spo train --dynamics`: the task's time check uses its speed."""
    max_steps: int | None = None
    """The episode limit, as `d2spo train --max-steps`: the time check and a patrol's route-optimal count
    use it; default: the one training derives from the task (docs/ltl.md)."""
    label_mode: str = "event"
    """Labelling, as `d2spo train --label-mode`: 'event' (a letter when the set of areas changes to a
    non-empty one) or 'step' (a letter every step); the task's checks read the letters it gives."""

    def env_config(self) -> EnvConfig:
        motion = load_dynamics(self.dynamics) if self.dynamics is not None else {}
        return EnvConfig(layout=self.layout, preset=self.preset, robot_radius=self.robot_radius,
                         max_steps=self.max_steps, label_mode=self.label_mode, **motion)

    def run(self) -> int:
        env_cfg = self.env_config()
        cfg, lay = checked_layout(env_cfg)
        n_obs, n_disks = len(lay.obstacles), len(lay.disks)
        kinds = f" ({n_obs - n_disks} box{'es' * (n_obs - n_disks != 1)}, {n_disks} disk{'s' * (n_disks != 1)})" \
            if n_disks else ""
        print(f"layout {lay.name!r}: arena {lay.arena[0]:g} x {lay.arena[1]:g} m, "
              f"{n_obs} obstacle{'s' * (n_obs != 1)}{kinds}, areas {lay.describe_areas()}; "
              f"a robot of radius {cfg.robot_radius:g} m fits at the start and reaches every area")
        try:  # a layout of the user's own, for a generalist trained elsewhere (`eval` refuses it otherwise)
            check_fits(lay)
            print("a generalist can be evaluated on it (`d2spo eval GENERALIST --layout ... --task ...`)")
        except ConfigError as e:
            print(f"a generalist cannot be evaluated on it: {str(e).removeprefix(f'{e.field}: ')}")
        if self.task is None:
            print("no task checked (--task NAME_OR_FORMULA checks one)")
            return 0
        env, params = make_env(env_cfg, task=self.task)
        # what `d2spo train` checks before it starts, with D²SPO's barrier margin d (a warning where no route keeps it)
        preflight(env, params, repr(self.task), margin=CBFConfig().d)
        n = int(params.aut.distance[start_state(env.task)])  # after the start's letter, as an episode begins
        goal = " to its first accepting visit (a patrol: then again and again)" if is_recurrence(env.automaton) else ""
        derived = " (derived from the task; --max-steps sets it)" if self.max_steps is None else ""
        print(f"task {self.task!r}: needs {n} area visit{'s' * (n != 1)}{goal} on this layout; episode limit "
              f"{int(params.max_steps)} steps of {env.config.dt:g} s for this robot{derived}; "
              f"observation size {env.observation_size}")
        optimum = visit_optimum(env.task, int(params.max_steps), env.config, None, margin=CBFConfig().d)
        if optimum:  # what `d2spo eval` and training's summary divide a patrol's visits by
            keep = optimum.get("route_optimal_visits_margin")
            kept = f" ({keep} on routes that keep D²SPO's margin d = {optimum['margin']:g} m)" if keep is not None else ""
            print(f"route-optimal count: {optimum['route_optimal_visits']} accepting visits per episode of "
                  f"{int(params.max_steps)} steps{kept}; visits are reported as a fraction of it")
        return 0


ENV_SUBCOMMANDS = {"show": EnvShowCmd, "check": EnvCheckCmd}
EnvCommands = Union[tuple(Annotated[cmd, tyro.conf.subcommand(name, prefix_name=False)]
                          for name, cmd in ENV_SUBCOMMANDS.items())]


@dataclasses.dataclass
class EnvCmd:
    """Environment tools."""

    cmd: Annotated[tyro.conf.OmitSubcommandPrefixes[EnvCommands], tyro.conf.arg(name="")]

    def run(self) -> int:
        return self.cmd.run()
