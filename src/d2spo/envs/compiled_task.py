"""A task compiled onto a layout, once: the value the environment, its reward and observation, and
the pre-flight checks read.

``compile_task(automaton, layout, label_mode, robot_radius, field_costs)`` computes the letters the
layout can produce, the automaton's distances to acceptance over them (Prog(q), Sec. IV-C), its
arrays, which areas carry each automaton proposition (their label) and the role of each letter in
each state (target, forbidden, neutral). The grid computations run on first use, at most once: with
``field_costs`` the per-state shaping fields (``fields``, ``envs.state_fields``), the shortest
route (``route_length``) and the automaton states the robot can reach (``reached``, ``envs.routes``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax.numpy as jnp
import numpy as np

from d2spo.envs import layouts, routes
from d2spo.envs.env_config import EnvConfig
from d2spo.envs.state_fields import StateFields, letter_roles, state_fields
from d2spo.envs.workspace import Layout
from d2spo.ltl.automaton import Automaton, AutomatonArrays
from d2spo.ltl.buchi_task import is_recurrence


@dataclass(frozen=True, eq=False)
class CompiledTask:
    """A task on a layout, for a robot: everything computed from the pair that does not change while training."""

    automaton: Any
    """The ``Automaton``, or an object with ``aps`` and ``arrays(feasible_letters)`` only (then
    ``distance``, the roles and ``fields`` are None and there are no routes)."""
    layout: Layout
    """The (scaled) layout."""
    label_mode: str
    """'event' or 'step' labelling."""
    robot_radius: float
    """The robot's radius (m): what ``route_length`` and ``reached`` drive."""
    feasible_letters: tuple[int, ...]
    """The letters labelling can produce on the layout (``layouts.feasible_letters``)."""
    distance: tuple[int | None, ...] | None
    """Per automaton state, the fewest feasible letters to acceptance (None: unreachable)."""
    arrays: AutomatonArrays
    """The automaton as arrays, its ``distance`` over the feasible letters."""
    area_bits: np.ndarray
    """int32 [N]: the letter bit each area sets, its label's (0 for an area whose label is no proposition)."""
    roles: np.ndarray | None
    """int8 [Q, 2**n_aps]: the role (``state_fields.NEUTRAL``, ``TARGET``, ``FORBIDDEN``) of reading each
    letter in each state (``state_fields.letter_roles``; the areas: ``state_fields.named_areas``)."""
    field_costs: dict[str, float] | None
    """``state_fields``'s clearance, robot radius and step costs (``RewardConfig.field_costs``), or
    None: no per-state shaping fields."""

    @property
    def n_states(self) -> int:
        """Q, the automaton's states."""
        return int(self.arrays.delta.shape[0])

    @cached_property
    def fields(self) -> StateFields | None:
        """The per-state shaping fields (``state_fields.state_fields``), or None without ``field_costs``."""
        if self.field_costs is None:
            return None
        return state_fields(self.automaton, self.layout, self.roles, self.label_mode, **self.field_costs)

    @property
    def recurrence(self) -> bool:
        """Whether the task is a recurrence (``ltl.buchi_task``): no state completes it, it is scored by
        its accepting visits."""
        return is_recurrence(self.automaton)

    @cached_property
    def route_length(self) -> float:
        """Length (m) of the shortest route that completes the task (``routes.route_length``), or for a
        recurrence that makes its first accepting visit (``routes.visit_lengths``); inf: none."""
        if self.recurrence:
            return self.visits_length(1)
        return routes.route_length(self.automaton, self.layout, self.label_mode, self.robot_radius)

    def visits_length(self, visits: int) -> float:
        """A recurrence's shortest route (m) that makes ``visits`` accepting visits (``routes.visit_lengths``;
        inf: none)."""
        lengths = routes.visit_lengths(self.automaton, self.layout, self.label_mode, self.robot_radius, math.inf,
                                       visits)
        return lengths[-1] if len(lengths) == visits else math.inf

    def optimal_visits(self, max_steps: int, dt: float, v_max: float, radius: float | None = None) -> int:
        """A recurrence's route-optimal visit count: the accepting visits of the shortest routes that fit
        in ``max_steps`` steps of ``dt`` at ``v_max`` (``routes.visit_lengths``; turning and braking
        ignored, and the grid's 8 directions allowed for: an upper bound on what a robot can score).
        ``radius``: routes that keep this far from every obstacle and wall (default: the robot's radius;
        the barrier's margin d gives what a robot that keeps d can make)."""
        reach = max_steps * dt * v_max * routes.OCTILE_EXCESS
        r = self.robot_radius if radius is None else radius
        return len(routes.visit_lengths(self.automaton, self.layout, self.label_mode, r, reach))

    @cached_property
    def reached(self) -> tuple[bool, ...]:
        """Per automaton state, whether the robot can drive into it (``routes.reachable_states``)."""
        return tuple(routes.reachable_states(self.automaton, self.layout, self.label_mode, self.robot_radius))


def compile_task(automaton: Any, layout: Layout, label_mode: str, robot_radius: float,
                 field_costs: dict[str, float] | None = None) -> CompiledTask:
    """``automaton`` on ``layout`` for a robot of ``robot_radius`` (module docstring); with
    ``field_costs`` (``RewardConfig.field_costs``: clearance, robot radius and step costs) the
    per-state shaping fields too. Raises nothing about the task's feasibility: that is
    ``preflight.check_feasible``'s."""
    aps = tuple(automaton.aps)
    feasible = tuple(layouts.feasible_letters(layout, aps, label_mode))
    bits = np.array([1 << aps.index(a.label) if a.label in aps else 0 for a in layout.areas], np.int32)
    if not isinstance(automaton, Automaton):  # arrays() only
        arrays = AutomatonArrays(*(None if a is None else jnp.asarray(a) for a in automaton.arrays(list(feasible))))
        return CompiledTask(automaton, layout, label_mode, robot_radius, feasible, None, arrays, bits, None, None)
    distance = automaton.distances(feasible)
    arrays = automaton.arrays(feasible, distance)
    roles = letter_roles(automaton, distance, label_mode == "event")
    return CompiledTask(automaton, layout, label_mode, robot_radius, feasible, tuple(distance), arrays, bits, roles,
                        field_costs)


def default_task(automaton: Automaton, layout_name: str, label_mode: str) -> CompiledTask:
    """``automaton`` compiled on a layout as the default environment config compiles it (robot
    radius, layout scale, shaping clearance and costs), its fields included: what ``d2spo ltl
    --plot`` draws (``map_plots.state_fields_figure``) before it checks the task."""
    cfg = EnvConfig(layout=layout_name, label_mode=label_mode).resolved()
    layout = layouts.load(layout_name).scaled(cfg.layout_scale)
    return compile_task(automaton, layout, label_mode, cfg.robot_radius, cfg.reward.field_costs(cfg.robot_radius))
