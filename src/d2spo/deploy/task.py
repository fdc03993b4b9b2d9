"""The task's automaton on the robot: the letter of a position, its transitions, and a tracker that
keeps the automaton state q the policy observes (``envs.nav.Env._letters``, ``ltl.labelling``).

A letter is a bit set: bit i holds while the robot centre is inside an area labelled with the
automaton's proposition ``aps[i]``. The state the policy observes is the *relaxed* one, read with
each area's labelling radius (the area's own radius unless the run set ``--label-radius``); the
task counts as done when the state read with the true radii accepts. Under ``event`` labelling
the automaton reads a letter only when it differs from the last one and is not empty.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from d2spo.deploy.dual import F32


@dataclass(frozen=True)
class Automaton:
    """The manifest's ``automaton`` and the areas' labelling data."""

    aps: tuple[str, ...]
    """Propositions; bit i of a letter is aps[i]."""
    delta: np.ndarray
    """int32 [Q, 2**len(aps)]: the next state for each letter."""
    initial: int
    accepting: np.ndarray
    """bool [Q]."""
    rejecting: np.ndarray
    """bool [Q]."""
    event: bool
    """Event labelling (True) or step labelling."""
    area_center: np.ndarray
    """float32 [N, 2]."""
    area_radius: np.ndarray
    """float32 [N]: true radii (``q_true``, completion)."""
    label_radius: np.ndarray
    """float32 [N]: labelling radii (the observed q)."""
    area_bits: np.ndarray
    """int32 [N]: the letter bit each area sets (0: its label is no proposition of the task)."""
    visit: np.ndarray | None = None
    """bool [Q, 2**len(aps)]: the accepting transitions of a Büchi task (a recurrence such as a patrol
    is scored by how often it takes one); None for a task with a finite goal."""

    @classmethod
    def of_manifest(cls, manifest: dict) -> Automaton:
        """The automaton of an export's manifest (its ``automaton`` and ``layout.areas``)."""
        aut, areas = manifest["automaton"], manifest["layout"]["areas"]
        return cls(tuple(aut["aps"]), np.array(aut["delta"], np.int32), int(aut["initial"]),
                   np.array(aut["accepting"], bool), np.array(aut["rejecting"], bool), aut["label_mode"] == "event",
                   np.array([a["center"] for a in areas], F32).reshape(-1, 2),
                   np.array([a["radius"] for a in areas], F32), np.array([a["label_radius"] for a in areas], F32),
                   np.array([a["bit"] for a in areas], np.int32),
                   None if aut.get("visit") is None else np.array(aut["visit"], bool))  # absent before 2026-12-02

    @property
    def n_states(self) -> int:
        return int(self.delta.shape[0])

    def letter(self, x: float, y: float, true: bool = False) -> int:
        """The letter at (x, y): the bits of the areas holding it, by labelling radius (or true radius)."""
        dx = self.area_center[:, 0] - F32(x)
        dy = self.area_center[:, 1] - F32(y)
        radius = self.area_radius if true else self.label_radius
        inside = dx * dx + dy * dy <= radius * radius
        return int(np.bitwise_or.reduce(np.where(inside, self.area_bits, 0), initial=0))

    def _checked(self, q, letter, prev_letter) -> tuple[int, int, int]:
        """(q, letter, prev_letter) as ints, or a ValueError: a state outside 0..Q-1 or a letter outside
        0..2**len(aps)-1 (numpy would wrap a negative one to another state's transition silently)."""
        out = []
        for name, v, n in (("q", q, self.n_states), ("letter", letter, self.delta.shape[1]),
                           ("prev_letter", prev_letter, self.delta.shape[1])):
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not 0 <= v < n:
                raise ValueError(f"Automaton: {name} must be an integer in 0..{n - 1}; got {v!r:.40}")
            out.append(int(v))
        return out[0], out[1], out[2]

    def is_visit(self, q: int, letter: int, prev_letter: int) -> bool:
        """Whether the step that ``advance`` takes from q reads an accepting transition
        (``ltl.labelling.accepting_visit``); always False for a task without them."""
        q, letter, prev_letter = self._checked(q, letter, prev_letter)
        if self.visit is None or (self.event and (letter == prev_letter or letter == 0)):
            return False
        return bool(self.visit[q, letter])

    def advance(self, q: int, letter: int, prev_letter: int) -> int:
        """The state after reading ``letter`` at q, the previous step's letter being ``prev_letter``.
        ValueError for a state or letter the automaton does not have."""
        q, letter, prev_letter = self._checked(q, letter, prev_letter)
        if self.event and (letter == prev_letter or letter == 0):
            return int(q)
        return int(self.delta[q, letter])


def _position(x, y) -> tuple[float, float]:
    """(x, y) as floats, or a ValueError: each a finite real number (m, the layout's frame)."""
    for name, v in (("x", x), ("y", y)):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)) \
                or not np.isfinite(v):
            raise ValueError(f"TaskTracker: {name} must be a finite number (m, the layout's frame); got {v!r:.40}")
    return float(x), float(y)


class TaskTracker:
    """The automaton state along one run of the robot: ``reset`` at the start pose, then ``update``
    after every control step with the pose reached. ``q`` is what the policy observes."""

    def __init__(self, automaton: Automaton, bounds: tuple[np.ndarray, np.ndarray] | None = None):
        self.automaton = automaton
        self.bounds = bounds
        """(lo, hi) a position must lie within (m, the layout's frame), or None: unchecked."""
        self.q = self.q_true = automaton.initial
        self.letter = self.letter_true = 0
        self.started = False
        self.visits = 0
        """Accepting visits since ``reset`` (read with the true radii, as the env's ``accepting_visit``):
        a patrol's laps. Stays 0 for a task with a finite goal."""
        self.visited = False
        """Whether the last ``update`` took an accepting transition."""

    def reset(self, x: float, y: float) -> int:
        """A new run from (x, y): the automaton reads the start's letter (as the env's reset does)."""
        x, y = self._inside(*_position(x, y))
        self.started = True
        aut = self.automaton
        self.letter, self.letter_true = aut.letter(x, y), aut.letter(x, y, true=True)
        self.q = aut.advance(aut.initial, self.letter, 0)
        self.q_true = aut.advance(aut.initial, self.letter_true, 0)
        self.visits, self.visited = 0, False
        return self.q

    def update(self, x: float, y: float) -> int:
        """After a step to (x, y): the new state q."""
        x, y = self._inside(*_position(x, y))
        if not self.started:
            raise ValueError("TaskTracker.update before reset: call reset(x, y) at the start pose first")
        aut = self.automaton
        letter, letter_true = aut.letter(x, y), aut.letter(x, y, true=True)
        self.q = aut.advance(self.q, letter, self.letter)
        self.visited = aut.is_visit(self.q_true, letter_true, self.letter_true)
        self.visits += self.visited
        self.q_true = aut.advance(self.q_true, letter_true, self.letter_true)
        self.letter, self.letter_true = letter, letter_true
        return self.q

    def _inside(self, x: float, y: float) -> tuple[float, float]:
        if self.bounds is not None:
            lo, hi = self.bounds
            if not (lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]):
                raise ValueError(f"TaskTracker: ({x:g}, {y:g}) lies outside the arena (with its slack: x {lo[0]:g}..."
                                 f"{hi[0]:g}, y {lo[1]:g}...{hi[1]:g} m); is it in the layout's frame, in metres?")
        return x, y

    @property
    def completed(self) -> bool:
        """The task is done (the state read with the true radii accepts)."""
        return bool(self.automaton.accepting[self.q_true])

    @property
    def finished(self) -> bool:
        """The episode would end here: q accepts or rejects (the env's termination)."""
        return bool(self.automaton.accepting[self.q] or self.automaton.rejecting[self.q])
