"""The automaton a task formula trains with: the monitor when a finite run completes it, else its DBA.

``task_automaton(formula)`` keeps ``translate``'s monitor for every formula with a good prefix (an
accepting state). A formula without one (``G !A4 & F A1``, ``G F A1 & G F A3``) gets its
deterministic Büchi automaton (``to_dba``; a formula with none raises ``NoDeterministicBuchi``) as a
``BuchiTask``: an ``Automaton`` whose accepting states are the DBA's *completed* states (only a
"never" part left, ``BuchiAutomaton.completed_states``; made absorbing, as the episode ends there),
and whose ``visits`` are the DBA's accepting transitions out of the other live states. A recurrence
task, with no completed state, runs to the episode limit and is scored by its accepting visits
(docs/ltl.md, "Tasks no finite run completes").
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Collection
from dataclasses import dataclass

import jax.numpy as jnp

from d2spo.ltl.automaton import Automaton, AutomatonArrays, AutomatonTooLarge, _dot_escape, letters_to_guard
from d2spo.ltl.buchi import BuchiAutomaton, NoDeterministicBuchi, letters_to_marked, marked_edges, to_dba
from d2spo.ltl.formula import Formula
from d2spo.ltl.translate import NeverCompletedWarning, translate

COMPLETED_MEANS = ("completed: the goal is met with nothing violated and only a never part is left (the state's "
                   "formula); the episode ends there, so the automaton holds it (absorbing) and does not watch that "
                   "never part further. For an automaton that keeps watching it, and rejects a later violation, "
                   "see d2spo.ltl.to_dba (docs/ltl.md)")
"""What a ``BuchiTask``'s accepting (completed) state means, as ``d2spo ltl`` prints it."""


@dataclass(frozen=True, eq=False)
class BuchiTask(Automaton):
    """A DBA as the environment runs it: ``accepting`` = its completed states (absorbing),
    ``rejecting`` = its rejecting sink, ``visits`` = its accepting transitions between live states
    that are not completed."""

    visits: tuple[tuple[bool, ...], ...] = ()
    """visits[q][letter]: reading ``letter`` in ``q`` is an accepting visit."""

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "visits", tuple(tuple(bool(v) for v in row) for row in self.visits))
        if len(self.visits) != self.n_states or any(len(row) != self.n_letters for row in self.visits):
            raise ValueError(f"visits must be {self.n_states} rows of {self.n_letters} booleans")

    def distances(self, feasible_letters: Collection[int] | None = None) -> list[int | None]:
        """Per state, the fewest letters from ``feasible_letters`` to a completed state where one can
        be reached, else to the next accepting visit (at least 1); None when neither can."""
        letters = self._letters(feasible_letters)
        to_done = super().distances(feasible_letters)
        to_visit = letters_to_marked(self.delta, self.visits, letters)
        return [d if d is not None else v for d, v in zip(to_done, to_visit, strict=True)]

    def status(self, q: int) -> str:
        """'completed' (the DBA's completed state: the episode ends there), 'rejecting' or 'undecided'."""
        return "completed" if q in self.accepting else super().status(q)

    def pretty(self, feasible_letters: Collection[int] | None = None) -> str:
        """``Automaton.pretty`` (a completed state's status says so), then the accepting visits: per
        state, the guard of the letters whose reading is one (what a patrol is scored by)."""
        lines = [super().pretty(feasible_letters), "accepting visits:"]
        for q, row in enumerate(self.visits):
            letters = [a for a, v in enumerate(row) if v]
            if letters:
                lines.append(f"  in {q}: {letters_to_guard(letters, self.aps)}")
        lines = lines if len(lines) > 2 else lines[:1] + ["accepting visits: none"]
        if self.accepting:
            lines.append(COMPLETED_MEANS)
        return "\n".join(lines)

    def to_json(self, feasible_letters: Collection[int] | None = None) -> dict:
        """``Automaton.to_json`` (``accepting``: the completed states), with ``visits``: per state,
        the letters whose reading is an accepting visit, ``recurrence``: whether no episode can
        complete the task (``is_recurrence``: it is scored by those visits), and with completed states
        ``accepting_means`` (``COMPLETED_MEANS``)."""
        out = {**super().to_json(feasible_letters),
               "visits": [[a for a, v in enumerate(row) if v] for row in self.visits],
               "recurrence": is_recurrence(self)}
        return out | ({"accepting_means": COMPLETED_MEANS} if self.accepting else {})

    @classmethod
    def from_json(cls, data: dict) -> BuchiTask:
        """Inverse of ``to_json``."""
        width = 1 << len(data["aps"])
        visits = [[a in set(row) for a in range(width)] for row in data["visits"]]
        return cls(*(data[k] for k in ("aps", "initial", "accepting", "rejecting", "delta")), visits=visits)

    def _dot_edges(self) -> list[str]:
        """``Automaton.to_dot``'s edges, with the letters of an accepting visit on an edge of their own,
        drawn bold and marked with a dot (as ``BuchiAutomaton.to_dot`` draws accepting transitions)."""
        return [f'  {q} -> {t} [label="{_dot_escape(guard)} ●", style=bold];' if visit
                else f'  {q} -> {t} [label="{_dot_escape(guard)}"];'
                for q, t, visit, guard in marked_edges(self.delta, self.visits, self.aps)]

    def arrays(self, feasible_letters: Collection[int] | None = None,
               distance: list[int | None] | None = None) -> AutomatonArrays:
        """``Automaton.arrays`` with the accepting visits (``AutomatonArrays.visit``); None when the
        task has none (a never part only: it runs as a monitor does, and reports no visits)."""
        arrays = super().arrays(feasible_letters, distance)
        if not any(any(row) for row in self.visits):
            return arrays
        return arrays._replace(visit=jnp.asarray(self.visits, dtype=jnp.bool_).reshape(self.n_states, self.n_letters))


def is_recurrence(aut: Automaton) -> bool:
    """Whether ``aut`` is a recurrence (a patrol): a ``BuchiTask`` with accepting visits and no
    completed state, so no episode completes it; it runs to the step limit, scored by its visits."""
    return isinstance(aut, BuchiTask) and not aut.accepting and any(map(any, aut.visits))


def task_is_recurrence(task: str) -> bool | None:
    """Whether the task name or formula ``task`` translates to a recurrence (``is_recurrence``); None
    when it does not translate (its own error comes where the task is built, with its column)."""
    from d2spo.ltl.tasks import task_formula
    try:
        return is_recurrence(task_automaton(task_formula(task)))
    except Exception:  # noqa: BLE001 - any refusal of the task: the callers decide what it means
        return None


def buchi_task(dba: BuchiAutomaton) -> BuchiTask:
    """``dba`` as the environment runs it (``BuchiTask``); its completed states over every letter."""
    done = dba.completed_states()
    width = dba.n_letters
    delta = [(q,) * width if q in done else row for q, row in enumerate(dba.delta)]
    live = set(range(dba.n_states)) - done - dba.rejecting
    visits = [[bool(dba.accepting[q][a]) and q in live and delta[q][a] in live for a in range(width)]
              for q in range(dba.n_states)]
    return BuchiTask(dba.aps, dba.initial, done, dba.rejecting, delta, dba.state_formulas, visits)


PRODUCT_LIMIT = 200_000
"""``endless_branch`` gives up (False) beyond this many product transitions (states x letters)."""


@functools.cache
def endless_branch(formula: str) -> bool:
    """Whether ``formula`` completes (its monitor has an accepting state, so ``task_automaton``
    trains it as a task that completes) and yet some run satisfies it forever without completing it:
    a branch with no good prefix, such as the patrol in ``GF A1 & GF A3 | F A2``. A robot on that
    branch scores nothing. Exact: a cycle through an accepting transition of the formula's DBA, among
    the product states where the monitor is still undecided and reachable from the start; True where
    the formula has no DBA (``F A1 | F G A2``: every co-safe formula has one); False where an
    automaton or the product passes its size limit (``PRODUCT_LIMIT``)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NeverCompletedWarning)
        try:
            monitor = translate(formula)
            if not monitor.accepting:
                return False
            dba = to_dba(formula)
        except NoDeterministicBuchi:  # not a recurrence, so not co-safe: some run satisfies it with no good prefix
            return True
        except AutomatonTooLarge:
            return False
    if dba.aps != monitor.aps or monitor.n_states * dba.n_states * monitor.n_letters > PRODUCT_LIMIT:
        return False
    decided = monitor.accepting | monitor.rejecting
    start = (monitor.initial, dba.initial)
    if monitor.initial in decided:
        return False
    succ: dict[tuple[int, int], list[tuple[tuple[int, int], bool]]] = {}
    todo = [start]
    while todo:  # the undecided part of the product, from the start
        node = todo.pop()
        if node in succ:
            continue
        m, d = node
        succ[node] = [((monitor.delta[m][a], dba.delta[d][a]), dba.accepting[d][a]) for a in range(monitor.n_letters)
                      if monitor.delta[m][a] not in decided]
        todo.extend(t for t, _ in succ[node] if t not in succ)

    def reaches(src, dst) -> bool:
        seen, todo = {src}, [src]
        while todo:
            node = todo.pop()
            if node == dst:
                return True
            for t, _ in succ[node]:
                if t not in seen:
                    seen.add(t)
                    todo.append(t)
        return False

    return any(reaches(t, u) for u, edges in succ.items() for t, acc in set(edges) if acc)


def task_automaton(formula: Formula | str) -> Automaton:
    """``translate(formula)`` when it has an accepting state (a finite run completes the task), else
    ``buchi_task(to_dba(formula))``. Raises ``NoDeterministicBuchi`` for a formula with neither."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NeverCompletedWarning)
        try:
            monitor = translate(formula)
        except AutomatonTooLarge as too_large:  # the monitor's satisfiability check; a DBA may still be had
            try:  # (a patrol of 9 or more areas: GF of twelve takes about 2 s this way)
                return buchi_task(to_dba(formula))
            except (AutomatonTooLarge, NoDeterministicBuchi):
                raise too_large from None
    if monitor.accepting:
        return monitor
    return buchi_task(to_dba(formula))
