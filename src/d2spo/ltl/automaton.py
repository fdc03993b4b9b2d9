"""Deterministic automata for LTL tasks, and their array form for use under jit.

``Automaton`` is the python-level object that ``d2spo.ltl.translate`` returns: a transition table
over letters (int bitmasks, bit i <=> ``aps[i]`` holds) with absorbing accepting (a good prefix has
been read) and rejecting (a bad prefix has been read) states. ``Automaton.distances`` is the
paper's Prog(q) (Sec. IV-C): the fewest letters that lead from q to an accepting state.
``Automaton.arrays`` gives ``AutomatonArrays``, the pytree the environment steps inside jit.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from d2spo.errors import UserError

UNREACHABLE = 10**6
"""Distance of a state from which acceptance cannot be reached with feasible letters."""


class AutomatonTooLarge(UserError):
    """The automaton of a formula exceeds a size limit of the translator (``d2spo.ltl.translate``)."""


class AutomatonArrays(NamedTuple):
    """An automaton as arrays: a pytree that steps inside jit-compiled code."""

    delta: jnp.ndarray
    """int32 [Q, 2**n_aps]: next state for each letter (bit i of a letter <=> aps[i] holds)."""
    accepting: jnp.ndarray
    """bool [Q]: a good prefix has been read; the task is done."""
    rejecting: jnp.ndarray
    """bool [Q]: a bad prefix has been read; the task can no longer be satisfied."""
    distance: jnp.ndarray
    """int32 [Q]: fewest feasible letters to reach acceptance (UNREACHABLE if impossible)."""
    initial: jnp.ndarray
    """int32 []: initial state."""
    visit: jnp.ndarray | None = None
    """bool [Q, 2**n_aps]: reading the letter in the state takes an accepting transition of a
    deterministic Büchi automaton, an *accepting visit* (``ltl.buchi_task.BuchiTask``); None for a
    monitor (``translate``), whose episodes end at acceptance."""



def backward_distances(delta: Sequence[Sequence[int]], letters: Collection[int], seeds: Sequence[int],
                       start: int) -> list[int | None]:
    """Per state, ``start`` at the ``seeds`` and one more per letter (from ``letters``) a run needs to
    reach one of them; None where none can be reached. Breadth-first search backwards over ``delta``."""
    predecessors: list[set[int]] = [set() for _ in delta]
    for q, row in enumerate(delta):
        for a in letters:
            predecessors[row[a]].add(q)
    dist: list[int | None] = [None] * len(delta)
    frontier = deque(seeds)
    for q in frontier:
        dist[q] = start
    while frontier:
        t = frontier.popleft()
        for q in sorted(predecessors[t]):
            if dist[q] is None:
                dist[q] = dist[t] + 1  # type: ignore[operator]
                frontier.append(q)
    return dist


class Words:
    """Reading words of letters, for the monitor (``Automaton``) and the Büchi automaton
    (``buchi.BuchiAutomaton``): ``aps``, ``initial``, ``delta``, ``n_states`` and ``n_letters`` are
    theirs. A state or letter out of range is a ValueError, not a state read from the end."""

    def letter(self, true_aps: Iterable[str]) -> int:
        """The letter in which exactly ``true_aps`` hold (ValueError for an unknown name)."""
        if isinstance(true_aps, str):  # letter("A1") would read the names "A" and "1"
            raise TypeError(f"letter() takes a list of proposition names, got the string {true_aps!r}; "
                            f"write letter([{true_aps!r}])")
        letter = 0
        for name in true_aps:
            if name not in self.aps:
                raise ValueError(f"unknown atomic proposition {name!r}; the automaton has {self.aps}")
            letter |= 1 << self.aps.index(name)
        return letter

    def run(self, letters: Iterable[int], start: int | None = None) -> list[int]:
        """States visited while reading ``letters``, starting (and including) ``start``."""
        q = self.initial if start is None else self._state(start)
        visited = [q]
        for letter in letters:
            q = self.delta[q][self._letter(letter)]
            visited.append(q)
        return visited

    def _state(self, q) -> int:
        """``q`` if it is a state's number, else ValueError (a negative one once read a state from the end)."""
        if not _is_index(q, self.n_states):
            raise ValueError(f"no state {q!r}: the automaton's states are 0 .. {self.n_states - 1}")
        return int(q)

    def _letter(self, letter) -> int:
        """``letter`` if it is a letter's number (``letter(...)`` gives them), else ValueError."""
        if not _is_index(letter, self.n_letters):
            raise ValueError(f"no letter {letter!r}: the letters are 0 .. {self.n_letters - 1}, one bit per "
                             f"proposition of {self.aps} (letter([...]) gives one)")
        return int(letter)


def _is_index(value, n: int) -> bool:
    """Whether ``value`` is one of 0 .. n - 1 as an integer (not a bool, a float or a negative)."""
    return not isinstance(value, bool) and isinstance(value, (int, np.integer)) and 0 <= value < n


@dataclass(frozen=True, eq=False)
class Automaton(Words):
    """A complete deterministic automaton over the letters 0 .. 2**len(aps) - 1."""

    aps: tuple[str, ...]
    """Atomic propositions, sorted; bit i of a letter is set iff aps[i] holds."""
    initial: int
    """Initial state."""
    accepting: frozenset[int]
    """States reached exactly after good prefixes (every continuation satisfies the formula)."""
    rejecting: frozenset[int]
    """States reached exactly after bad prefixes (no continuation satisfies the formula)."""
    delta: tuple[tuple[int, ...], ...]
    """delta[q][letter]: the next state."""
    state_formulas: tuple[str, ...] = ()
    """Per state, the progressed formula it stands for ('true' accepting, 'false' rejecting)."""

    def __post_init__(self) -> None:
        # Accept any sequences/sets; store the documented immutable types.
        object.__setattr__(self, "aps", tuple(self.aps))
        object.__setattr__(self, "initial", int(self.initial))
        object.__setattr__(self, "delta", tuple(tuple(int(t) for t in row) for row in self.delta))
        object.__setattr__(self, "accepting", frozenset(int(q) for q in self.accepting))
        object.__setattr__(self, "rejecting", frozenset(int(q) for q in self.rejecting))
        object.__setattr__(self, "state_formulas", tuple(self.state_formulas))
        n, width = len(self.delta), 1 << len(self.aps)
        if list(self.aps) != sorted(set(self.aps)):
            raise ValueError(f"aps must be sorted and distinct, got {self.aps}")
        if not 0 <= self.initial < n:
            raise ValueError(f"initial state {self.initial} out of range [0, {n})")
        if any(len(row) != width or not all(0 <= t < n for t in row) for row in self.delta):
            raise ValueError(f"delta must be {n} rows of {width} states in [0, {n})")
        if not all(0 <= q < n for q in self.accepting | self.rejecting):
            raise ValueError(f"accepting/rejecting states must be in [0, {n})")
        if self.accepting & self.rejecting:
            raise ValueError("a state cannot be both accepting and rejecting")
        if any(self.delta[q] != (q,) * width for q in self.accepting | self.rejecting):
            raise ValueError("accepting and rejecting states must be absorbing")
        if not self.state_formulas:
            names = {q: "true" for q in self.accepting} | {q: "false" for q in self.rejecting}
            object.__setattr__(self, "state_formulas", tuple(names.get(q, f"q{q}") for q in range(n)))
        elif len(self.state_formulas) != n:
            raise ValueError("state_formulas must have one entry per state")

    @property
    def n_states(self) -> int:
        return len(self.delta)

    @property
    def n_letters(self) -> int:
        return 1 << len(self.aps)

    def letter_aps(self, letter: int) -> tuple[str, ...]:
        """The propositions that hold in ``letter``."""
        return tuple(name for i, name in enumerate(self.aps) if letter >> i & 1)

    def status(self, q: int) -> str:
        """'accepting', 'rejecting' or 'undecided'."""
        q = self._state(q)
        return "accepting" if q in self.accepting else "rejecting" if q in self.rejecting else "undecided"

    def _letters(self, feasible_letters: Collection[int] | None) -> list[int]:
        if feasible_letters is None:
            return list(range(self.n_letters))
        letters = sorted({int(a) for a in feasible_letters})
        bad = [a for a in letters if not 0 <= a < self.n_letters]
        if bad:
            raise ValueError(f"feasible letters {bad} out of range [0, {self.n_letters})")
        return letters

    def distances(self, feasible_letters: Collection[int] | None = None) -> list[int | None]:
        """Prog(q) of Sec. IV-C as a number: per state, the fewest letters, all taken from
        ``feasible_letters`` (all letters when None), that lead to an accepting state; None when
        no such path exists. Breadth-first search backwards from the accepting states."""
        return backward_distances(self.delta, self._letters(feasible_letters), sorted(self.accepting), 0)

    def to_json(self, feasible_letters: Collection[int] | None = None) -> dict:
        """A JSON-serialisable dict: aps, initial, accepting, rejecting, delta, distance."""
        return {
            "aps": list(self.aps),
            "initial": self.initial,
            "accepting": sorted(self.accepting),
            "rejecting": sorted(self.rejecting),
            "delta": [list(row) for row in self.delta],
            "distance": self.distances(feasible_letters),
        }

    @classmethod
    def from_json(cls, data: dict) -> Automaton:
        """Inverse of ``to_json`` (the distances are recomputed on demand, state names are lost)."""
        keys = ("aps", "initial", "accepting", "rejecting", "delta")
        return cls(*(data[k] for k in keys))

    def arrays(self, feasible_letters: Collection[int] | None = None,
               distance: list[int | None] | None = None) -> AutomatonArrays:
        """The automaton as jnp arrays; distance uses ``UNREACHABLE`` for None. ``distance``: what
        ``distances(feasible_letters)`` returns, when the caller has it already."""
        if distance is None:
            distance = self.distances(feasible_letters)
        dist = [UNREACHABLE if d is None else d for d in distance]
        return AutomatonArrays(
            delta=jnp.asarray(self.delta, dtype=jnp.int32).reshape(self.n_states, self.n_letters),
            accepting=jnp.asarray([q in self.accepting for q in range(self.n_states)], dtype=jnp.bool_),
            rejecting=jnp.asarray([q in self.rejecting for q in range(self.n_states)], dtype=jnp.bool_),
            distance=jnp.asarray(dist, dtype=jnp.int32),
            initial=jnp.asarray(self.initial, dtype=jnp.int32),
        )

    def edges(self) -> list[tuple[int, int, str]]:
        """(source, target, guard) per pair of states with a transition; the guard is a boolean
        formula over the aps that holds exactly for the letters of the transitions."""
        out = []
        for q, row in enumerate(self.delta):
            targets: dict[int, list[int]] = {}
            for letter, t in enumerate(row):
                targets.setdefault(t, []).append(letter)
            for t, letters in targets.items():
                out.append((q, t, letters_to_guard(letters, self.aps)))
        return out

    def to_dot(self) -> str:
        """Graphviz source: doublecircle = accepting, grey = rejecting, each state labelled with
        its number and progressed formula."""
        lines = ["digraph automaton {", "  rankdir=LR;", '  init [shape=point, label=""];']
        for q in range(self.n_states):
            shape = "doublecircle" if q in self.accepting else "circle"
            style = ", style=filled, fillcolor=lightgrey" if q in self.rejecting else ""
            label = f"{q}\\n{_dot_escape(self.state_formulas[q])}"
            lines.append(f'  {q} [shape={shape}{style}, label="{label}"];')
        lines.append(f"  init -> {self.initial};")
        lines += self._dot_edges()
        lines.append("}")
        return "\n".join(lines) + "\n"

    def _dot_edges(self) -> list[str]:
        """``to_dot``'s edges: one per pair of states with a transition, labelled with its guard."""
        return [f'  {q} -> {t} [label="{_dot_escape(guard)}"];' for q, t, guard in self.edges()]

    def pretty(self, feasible_letters: Collection[int] | None = None) -> str:
        """A text table: state, status, distance (with ``feasible_letters``), formula, and the
        transitions grouped by target."""
        dist = self.distances(feasible_letters)
        lines = [f"aps: {', '.join(self.aps) or '(none)'}; initial state {self.initial}"]
        rows = [("state", "status", "distance", "formula")]
        for q in range(self.n_states):
            d = "-" if dist[q] is None else str(dist[q])
            rows.append((str(q), self.status(q), d, self.state_formulas[q]))
        widths = [max(len(r[i]) for r in rows) for i in range(3)]
        for r in rows:
            lines.append("  ".join(c.ljust(w) for c, w in zip(r[:3], widths, strict=True)) + "  " + r[3])
        lines.append("transitions:")
        for q, t, guard in self.edges():
            if q != t or q not in self.accepting | self.rejecting:
                lines.append(f"  {q} -> {t}: {guard}")
        return "\n".join(lines)


def union(automata: Iterable[Automaton]) -> tuple[Automaton, list[int]]:
    """The disjoint union of automata over the union of their propositions, and each one's initial
    state in it. Component k's states are shifted by the states of the ones before it; a letter of
    the union is read by component k through the propositions it knows. An agent that starts in
    component k's initial state runs exactly automaton k (the generalist trains on a mixture of
    tasks this way: ``envs.generalist``). The union's own ``initial`` is the first component's.
    When a component is a Büchi task with accepting visits (``ltl.buchi_task.BuchiTask``), the union
    is one too: its visits are each component's, read through the same letters (none in a monitor's
    states), so that a mixture may hold patrols beside tasks that complete."""
    automata = list(automata)
    if not automata:
        raise ValueError("union of no automata")
    aps = tuple(sorted(set().union(*(a.aps for a in automata))))
    delta, accepting, rejecting, names, initials, visits = [], set(), set(), [], [], []
    offset = 0
    for a in automata:
        read = [a.letter([p for i, p in enumerate(aps) if letter >> i & 1 and p in a.aps]) for letter in range(1 << len(aps))]
        delta += [tuple(offset + a.delta[q][read[letter]] for letter in range(len(read))) for q in range(a.n_states)]
        marks = getattr(a, "visits", None) or [(False,) * a.n_letters] * a.n_states
        visits += [tuple(bool(marks[q][b]) for b in read) for q in range(a.n_states)]
        accepting |= {offset + q for q in a.accepting}
        rejecting |= {offset + q for q in a.rejecting}
        names += list(a.state_formulas)
        initials.append(offset + a.initial)
        offset += a.n_states
    parts = (aps, initials[0], frozenset(accepting), frozenset(rejecting), tuple(delta), tuple(names))
    if any(map(any, visits)):
        from d2spo.ltl.buchi_task import BuchiTask  # it builds on this module

        return BuchiTask(*parts, visits=tuple(visits)), initials
    return Automaton(*parts), initials


def _dot_escape(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"')


def letters_to_guard(letters: Iterable[int], aps: tuple[str, ...]) -> str:
    """A short sum-of-products formula over ``aps`` true exactly on ``letters`` (prime implicants
    chosen greedily). ``true`` for all letters, ``false`` for none."""
    n = len(aps)
    want = set(letters)
    if not want:
        return "false"
    if len(want) == 1 << n:
        return "true"
    if n > EXACT_GUARD_APS:
        return _cubes_text(_greedy_cubes(want, n), aps)
    # A cube is (care mask, value): the letters a with a & care == value (Quine-McCluskey).
    primes: list[tuple[int, int]] = []
    level = {((1 << n) - 1, a) for a in want}
    while level:
        merged = set()
        covered = set()
        for care, value in level:
            for i in range(n):
                bit = 1 << i
                if care & bit:
                    other = (care, value ^ bit)
                    if other in level:
                        merged.add((care & ~bit, value & ~bit))
                        covered.add((care, value))
                        covered.add(other)
        primes.extend(sorted(level - covered))
        level = merged

    def members(cube: tuple[int, int]) -> set[int]:
        care, value = cube
        return {a for a in want if a & care == value}

    chosen: list[tuple[int, int]] = []
    left = set(want)
    while left:
        best = max(primes, key=lambda c: (len(members(c) & left), -bin(c[0]).count("1")))
        chosen.append(best)
        left -= members(best)

    return _cubes_text(chosen, aps)


EXACT_GUARD_APS = 8
"""Up to this many propositions ``letters_to_guard`` takes every prime implicant (Quine-McCluskey); beyond,
their number grows as 3^n (a patrol of twelve areas: about 40 s for its printout), and each cube is
grown greedily instead (``_greedy_cubes``): as exact, sometimes longer."""


def _greedy_cubes(want: set[int], n: int) -> list[tuple[int, int]]:
    """Cubes (care mask, value) whose union is exactly ``want``: from each letter not yet covered, a cube
    grown by freeing one proposition at a time while every letter it holds is wanted."""
    chosen: list[tuple[int, int]] = []
    left = set(want)
    while left:
        care, value = (1 << n) - 1, min(left)
        for i in range(n):
            bit = 1 << i
            free = care & ~bit
            # the cube with proposition i free holds value's letters with bit i either way
            if all(((value & free) | x) in want for x in _subsets(~free & ((1 << n) - 1))):
                care, value = free, value & free
        chosen.append((care, value))
        left -= {a for a in left if a & care == value}
    return chosen


def _subsets(mask: int):
    """Every submask of ``mask``."""
    sub = mask
    while True:
        yield sub
        if sub == 0:
            return
        sub = (sub - 1) & mask


def _cubes_text(cubes, aps: tuple[str, ...]) -> str:
    def cube_text(cube: tuple[int, int]) -> str:
        care, value = cube
        lits = [(name if value >> i & 1 else f"!{name}") for i, name in enumerate(aps) if care >> i & 1]
        return " & ".join(lits) if lits else "true"

    texts = sorted(cube_text(c) for c in cubes)
    if len(texts) == 1:
        return texts[0]
    return " | ".join(f"({t})" if " & " in t else t for t in texts)
