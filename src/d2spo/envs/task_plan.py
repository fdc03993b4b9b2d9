"""The task side of the generalist's bank: which tasks a mixture holds over one union automaton
(``TaskPlan``, ``task_plan``), what pairing a layout with one of them means (each area's role in each
state of the task, by its label), and a slot's episode limit (``slot_max_steps``). ``TaskPlan.bank``
packs layouts into a ``layout_bank.LayoutBank`` with their roles, limits and fields;
``envs.generalist`` runs it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from d2spo.envs import layout_bank, state_fields
from d2spo.envs.layout_bank import LayoutBank
from d2spo.envs.workspace import Layout
from d2spo.errors import ConfigError
from d2spo.ltl import task_automaton, task_formula
from d2spo.ltl.automaton import Automaton, union
from d2spo.ltl.buchi_task import is_recurrence

N_AREAS = layout_bank.N_AREAS
"""Area slots per layout."""
GENERALIST_MAX_STEPS = 400
"""The least episode limit of a slot when ``max_steps`` is unset (``slot_max_steps``)."""
STEPS_PER_METRE = 20
"""A slot's episode limit when ``max_steps`` is unset: this many steps per metre of the arena's
width plus height (400 for 10 m x 10 m, 800 for 20 m x 20 m), and at least ``GENERALIST_MAX_STEPS``.
A task of the training mixture visits at most four areas; at the default robot's 0.1 m per step
these are about 2.4 half-perimeters of the arena, room for detours round walls."""
AUTO_NUMPY_FIELDS = 48
"""``TaskPlan.bank``'s "auto" computes up to this many fields with numpy (0.1 s each), more with JAX."""

def slot_max_steps(layout: Layout) -> int:
    """A slot's episode limit when none is given (``STEPS_PER_METRE``)."""
    return max(GENERALIST_MAX_STEPS, int(np.ceil(STEPS_PER_METRE * (layout.arena[0] + layout.arena[1]))))


@dataclasses.dataclass(frozen=True)
class TaskPlan:
    """The tasks of a generalist's mixture over one union automaton, and what pairing a layout with
    one of them needs: each task's first state and size, and every letter's role in every state."""

    automaton: Automaton
    """The union of the tasks' automata (one task: its own)."""
    automata: tuple[Automaton, ...]
    """Each task's own automaton (``ltl.task_automaton``), in order."""
    names: tuple[str, ...]
    """The tasks, as given (names or formulas; ``"a task"`` for an automaton object)."""
    initials: tuple[int, ...]
    """Task t's initial state in ``automaton``."""
    singles: tuple[int, ...]
    """The letters of one area entered alone (and the empty letter): a bank's areas never overlap."""
    distance: tuple[int | None, ...]
    """Per state of ``automaton``, its distance to acceptance over ``singles`` (None: unreachable)."""
    roles: np.ndarray
    """int [Q, letters]: ``state_fields.letter_roles`` of the union."""

    @property
    def offsets(self) -> tuple[int, ...]:
        """Task t's states are offsets[t] .. offsets[t + 1] - 1 of ``automaton`` (T + 1 entries)."""
        return tuple(int(x) for x in np.cumsum([0] + [a.n_states for a in self.automata]))

    @property
    def needs(self) -> tuple[frozenset, ...]:
        """Per task, the propositions a layout paired with it must carry."""
        return tuple(frozenset(a.aps) for a in self.automata)

    @property
    def recurrent(self) -> tuple[bool, ...]:
        """Per task, whether it is a recurrence (a patrol: no episode completes it, it runs to its
        slot's limit and is scored by its accepting visits; ``ltl.buchi_task.is_recurrence``)."""
        return tuple(is_recurrence(a) for a in self.automata)

    @property
    def states(self) -> int:
        """S: the most states of one task (the bank's per-slot axis)."""
        return max(b - a for a, b in zip(self.offsets[:-1], self.offsets[1:]))

    def slot_roles(self, layout: Layout, task: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(area_bits [N_AREAS], target [S, N_AREAS], forbidden [S, N_AREAS]) of ``layout`` paired with
        task ``task``: an area's bit is its label's letter (0 for a label no task names), its role in
        each state of the task that of entering it alone. Raises ConfigError when the layout lacks a
        label the task names."""
        aps = self.automaton.aps
        labels = [a.label for a in layout.areas]
        missing = sorted(self.needs[task] - set(labels))
        if missing:
            raise ConfigError("task", f"{self.names[task]} names {', '.join(missing)}, which no area of layout "
                              f"{layout.name!r} carries (its labels: {', '.join(layout.labels) or 'none'})")
        bits = np.zeros(N_AREAS, np.int32)
        target = np.zeros((self.states, N_AREAS), bool)
        forbidden = np.zeros_like(target)
        lo, hi = self.offsets[task], self.offsets[task + 1]
        for k, label in enumerate(labels):
            if label in aps:
                letter = self.automaton.letter([label])
                bits[k] = letter
                target[:hi - lo, k] = self.roles[lo:hi, letter] == state_fields.TARGET
                forbidden[:hi - lo, k] = self.roles[lo:hi, letter] == state_fields.FORBIDDEN
        return bits, target, forbidden

    def bank(self, layouts: Sequence[Layout], tasks: Sequence[int] | None = None, max_steps: int | None = None,
             method: str = "auto") -> LayoutBank:
        """A bank of ``layouts``, slot k paired with task tasks[k] (default k modulo the number of
        tasks), its roles, its episode limits (``max_steps`` for every slot; None: each its
        ``slot_max_steps``) and its fields (``layout_bank.with_fields``; method "auto": numpy for a
        handful of fields, where JAX's compilation would cost more than it saves). Raises ConfigError."""
        n_tasks = len(self.names)
        tasks = [k % n_tasks for k in range(len(layouts))] if tasks is None else [int(t) for t in tasks]
        packed = layout_bank.pack(layouts, tasks)
        roles = [self.slot_roles(lay, t) for lay, t in zip(layouts, tasks, strict=True)]
        limits = [slot_max_steps(lay) if max_steps is None else int(max_steps) for lay in layouts]
        paired = layout_bank.pair(packed, *(np.stack(x) for x in zip(*roles)), np.asarray(limits))
        if method == "auto":
            method = "numpy" if len(layouts) * self.states <= AUTO_NUMPY_FIELDS else "jax"
        return layout_bank.with_fields(paired, method)


def task_plan(tasks: Sequence[Any], label_mode: str) -> TaskPlan:
    """The ``TaskPlan`` of a mixture of tasks (names, formulas or Automaton objects). Raises ConfigError."""
    automata, names = [], []
    for t in tasks:
        a = task_automaton(task_formula(t)) if isinstance(t, str) else t
        if not isinstance(a, Automaton):
            raise ConfigError("task", "the generalist needs task names, formulas or Automaton objects")
        automata.append(a)
        names.append(t if isinstance(t, str) else "a task")
    aut, initials = union(automata) if len(automata) > 1 else (automata[0], [automata[0].initial])
    singles = [0] + [aut.letter([a]) for a in aut.aps]  # a bank's areas never overlap
    distance = aut.distances(singles)
    for name, q0 in zip(names, initials, strict=True):
        if distance[q0] is None:
            raise ConfigError("task", f"{name} cannot be completed (nor a patrol's visit made) entering one area at "
                              "a time, as the generalist's layouts (areas that never overlap) need")
    roles = state_fields.letter_roles(aut, distance, label_mode == "event")
    return TaskPlan(aut, tuple(automata), tuple(names), tuple(int(q) for q in initials), tuple(singles),
                    tuple(distance), roles)
