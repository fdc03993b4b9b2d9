"""LTL formula -> deterministic Büchi automaton (DBA), for tasks that no finite run completes.

``translate`` builds a monitor of good and bad prefixes, which is all a task needs when some finite
run completes it. Formulas such as ``G F a``, ``G (a -> F b)`` or ``G !c & F a`` have no good
prefix; they hold on an infinite run when it passes through accepting transitions infinitely
often. ``to_dba`` builds that automaton (docs/ltl.md, "Büchi automata"):

1. negation normal form (``nnf.nnf``), then a tableau NBA (``nba.py``);
2. Safra-Piterman determinisation to a parity automaton (``determinise.py``);
3. the Büchi-type test and relabelling of that parity automaton (``determinise.buchi_marks``);
   a formula that fails it has no DBA and is refused with ``NoDeterministicBuchi``, which carries
   a witness (words that refute every DBA);
4. reduction (``buchi_reduce.py``): one rejecting sink, one accepting sink, partition refinement,
   merges of language-equivalent states; states renumbered breadth-first from the initial state 0.

A conjunction or disjunction whose operands all have a DBA is built instead as the product of
their automata (``buchi_reduce.product``), each made by steps 1-4, then reduced.

Acceptance is on transitions: a run is accepted iff it takes accepting transitions infinitely often.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass
from functools import cached_property

from d2spo.errors import UserError
from d2spo.ltl.automaton import (
    UNREACHABLE,
    AutomatonTooLarge,
    Words,
    _dot_escape,
    backward_distances,
    letters_to_guard,
)
from d2spo.ltl.buchi_reduce import dead_states, product, reduce, universal_states
from d2spo.ltl.determinise import buchi_marks, determinise
from d2spo.ltl.formula import And, Formula, Or, check_size
from d2spo.ltl.nba import to_nba
from d2spo.ltl.nnf import nnf
from d2spo.ltl.parser import parse
from d2spo.ltl.progression import DNF_TRUE, Dnf, Progression, clause_order, dnf_to_formula, negate_dnf, to_dnf
from d2spo.ltl.tableau import Tableau
from d2spo.ltl.translate import MAX_APS, MAX_TABLEAU_NODES

MAX_NBA_STEPS = 1_000_000
"""Most work (as ``translate.MAX_TABLEAU_STEPS`` counts it) spent expanding the nodes of the NBAs of
one ``to_dba`` call (step 1), beyond which it raises ``AutomatonTooLarge``: a node can have
exponentially many branches (``G F G F … a``, a chain ``a R b R c …``). The suite's tasks need at
most 300, a patrol of twelve areas 72, ``G (a -> X X X X X X X X b)`` 14000; ``G F`` nested 12 deep
1.1 million (10 s on a 2-core CPU), 14 deep 4.7 million (54 s), 16 deep ran for minutes."""
MAX_NAME_STEPS = 200_000
"""Most tableau work (as ``translate.MAX_TABLEAU_STEPS`` counts it) spent on simplifying the
state names; beyond it the names keep their unsatisfiable and redundant clauses."""


class NoDeterministicBuchi(UserError):
    """The formula's language is not recognised by any deterministic Büchi automaton (``F G a``)."""

    def __init__(self, message: str, witness: tuple[list[int], list[int], list[int]] | None = None):
        super().__init__(message)
        self.witness = witness
        """Words u, x, y (lists of letters): u·x^ω and every u·z·x^ω with z a word over {x, y}
        satisfy the formula, no u·x^k1·y·x^k2·y··· does: an automaton that must accept the former
        after finitely many x's would accept the latter (Landweber's argument)."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True, eq=False)
class BuchiAutomaton(Words):
    """A complete deterministic Büchi automaton with accepting transitions, over the letters
    0 .. 2**len(aps) - 1 (bit i <=> aps[i] holds). A run is accepted iff it takes accepting
    transitions infinitely often."""

    aps: tuple[str, ...]
    """Atomic propositions, sorted; bit i of a letter is set iff aps[i] holds."""
    initial: int
    """Initial state."""
    delta: tuple[tuple[int, ...], ...]
    """delta[q][letter]: the next state."""
    accepting: tuple[tuple[bool, ...], ...]
    """accepting[q][letter]: the transition delta[q][letter] is accepting."""
    rejecting: frozenset[int]
    """Rejecting sinks: the states from which no run is accepted (computed exactly, and checked)."""
    state_formulas: tuple[str, ...] = ()
    """Per state, a residual of the formula (the formula progressed along a shortest word to it)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "aps", tuple(self.aps))
        object.__setattr__(self, "initial", int(self.initial))
        object.__setattr__(self, "delta", tuple(tuple(int(t) for t in row) for row in self.delta))
        object.__setattr__(self, "accepting", tuple(tuple(bool(x) for x in row) for row in self.accepting))
        object.__setattr__(self, "rejecting", frozenset(int(q) for q in self.rejecting))
        object.__setattr__(self, "state_formulas", tuple(self.state_formulas))
        n, width = len(self.delta), 1 << len(self.aps)
        if list(self.aps) != sorted(set(self.aps)):
            raise ValueError(f"aps must be sorted and distinct, got {self.aps}")
        if not 0 <= self.initial < n:
            raise ValueError(f"initial state {self.initial} out of range [0, {n})")
        if any(len(row) != width or not all(0 <= t < n for t in row) for row in self.delta):
            raise ValueError(f"delta must be {n} rows of {width} states in [0, {n})")
        if len(self.accepting) != n or any(len(row) != width for row in self.accepting):
            raise ValueError(f"accepting must be {n} rows of {width} booleans")
        if self.rejecting != dead_states(self.delta, self.accepting):
            raise ValueError("rejecting must be exactly the states from which no run is accepted")
        if not self.state_formulas:
            object.__setattr__(self, "state_formulas", tuple(f"q{q}" for q in range(n)))
        elif len(self.state_formulas) != n:
            raise ValueError("state_formulas must have one entry per state")

    @property
    def n_states(self) -> int:
        return len(self.delta)

    @property
    def n_letters(self) -> int:
        return 1 << len(self.aps)

    @cached_property
    def accepting_sinks(self) -> frozenset[int]:
        """The states from which every run is accepted (reached exactly after good prefixes)."""
        return frozenset(universal_states(self.delta, self.accepting))

    def completed_states(self, feasible_letters: Collection[int] | None = None) -> frozenset[int]:
        """The states where what is left of the task is a "never" part only: every run from them
        on ``feasible_letters`` (every letter when None) that stays out of the rejecting sinks is
        accepted. An episode may end there as completed (``G !A4 & F A1`` once A1 is reached, A4
        never entered; a co-safe task in its accepting sink). Exactly the live states from which
        no cycle of non-accepting transitions between live states can be reached."""
        letters = range(self.n_letters) if feasible_letters is None else sorted({int(a) for a in feasible_letters})
        # ``universal_states`` on the automaton over ``letters`` with each rejecting sink made an
        # accepting self-loop: a run that enters one no longer counts against a state
        rej = self.rejecting
        delta = [[q if q in rej else self.delta[q][a] for a in letters] for q in range(self.n_states)]
        accepting = [[q in rej or self.accepting[q][a] for a in letters] for q in range(self.n_states)]
        return frozenset(universal_states(delta, accepting) - rej)

    def is_accepting_sink(self, q: int) -> bool:
        """Every continuation from q is accepted: the task is done (a co-safe task may end here)."""
        return q in self.accepting_sinks

    def status(self, q: int) -> str:
        """'accepting sink', 'rejecting sink' or 'live'."""
        return "accepting sink" if q in self.accepting_sinks else "rejecting sink" if q in self.rejecting else "live"

    def accepts_lasso(self, prefix: Sequence[int], loop: Sequence[int]) -> bool:
        """Whether the word prefix·loop^ω is accepted (``loop`` must not be empty)."""
        if not loop:
            raise ValueError("the loop of a lasso word must not be empty")
        q = self.run(prefix)[-1]
        loop = [self._letter(a) for a in loop]
        first_seen: dict[int, int] = {}
        hits: list[bool] = []  # per pass through the loop: an accepting transition was taken
        while q not in first_seen:
            first_seen[q] = len(hits)
            hit = False
            for letter in loop:
                hit = hit or self.accepting[q][letter]
                q = self.delta[q][letter]
            hits.append(hit)
        return any(hits[first_seen[q]:])

    def distances(self, feasible_letters: Collection[int] | None = None) -> list[int]:
        """Per state, the fewest letters, all from ``feasible_letters`` (every letter when None),
        after which the run has taken an accepting transition (the next accepting visit: at least
        1); ``UNREACHABLE`` when no such path exists. Breadth-first search backwards."""
        letters = range(self.n_letters) if feasible_letters is None else sorted({int(a) for a in feasible_letters})
        if any(not 0 <= a < self.n_letters for a in letters):
            raise ValueError(f"feasible letters must be in [0, {self.n_letters})")
        return [UNREACHABLE if d is None else d for d in letters_to_marked(self.delta, self.accepting, letters)]

    def edges(self) -> list[tuple[int, int, bool, str]]:
        """(source, target, accepting, guard) per group of letters with the same target and
        acceptance; the guard holds exactly for those letters."""
        return marked_edges(self.delta, self.accepting, self.aps)

    def to_dot(self) -> str:
        """Graphviz source: doublecircle = accepting sink, grey = rejecting sink, accepting
        transitions bold and marked with a dot."""
        lines = ["digraph buchi {", "  rankdir=LR;", '  init [shape=point, label=""];']
        for q in range(self.n_states):
            shape = "doublecircle" if q in self.accepting_sinks else "circle"
            style = ", style=filled, fillcolor=lightgrey" if q in self.rejecting else ""
            lines.append(f'  {q} [shape={shape}{style}, label="{q}\\n{_dot_escape(self.state_formulas[q])}"];')
        lines.append(f"  init -> {self.initial};")
        for q, t, acc, guard in self.edges():
            extra = ", style=bold" if acc else ""
            lines.append(f'  {q} -> {t} [label="{_dot_escape(guard)}{" ●" if acc else ""}"{extra}];')
        lines.append("}")
        return "\n".join(lines) + "\n"

    def pretty(self, feasible_letters: Collection[int] | None = None) -> str:
        """A text table (state, status, distance to the next accepting transition, residual
        formula) and the transitions, accepting ones marked ``(accepting)``."""
        dist = self.distances(feasible_letters)
        lines = [f"aps: {', '.join(self.aps) or '(none)'}; initial state {self.initial}; acceptance on transitions"]
        rows = [("state", "status", "distance", "formula")]
        for q in range(self.n_states):
            rows.append((str(q), self.status(q), "-" if dist[q] == UNREACHABLE else str(dist[q]), self.state_formulas[q]))
        widths = [max(len(r[i]) for r in rows) for i in range(3)]
        for r in rows:
            lines.append("  ".join(c.ljust(w) for c, w in zip(r[:3], widths, strict=True)) + "  " + r[3])
        lines.append("transitions:")
        for q, t, acc, guard in self.edges():
            lines.append(f"  {q} -> {t}: {guard}{' (accepting)' if acc else ''}")
        return "\n".join(lines)


def letters_to_marked(delta: Sequence[Sequence[int]], marked: Sequence[Sequence[bool]],
                      letters: Collection[int]) -> list[int | None]:
    """Per state, the fewest ``letters`` after which a run has taken a marked transition
    (``marked[q][a]``: at least 1); None when none can be. Breadth-first search backwards."""
    seeds = [q for q in range(len(delta)) if any(marked[q][a] for a in letters)]
    return backward_distances(delta, letters, seeds, 1)


def to_dba(formula: Formula | str, max_states: int = 1000) -> BuchiAutomaton:
    """Deterministic Büchi automaton (accepting transitions) of ``formula``, exact for every
    formula that has one. Raises ``NoDeterministicBuchi`` when it has none (e.g. ``F G a``),
    ``LTLSyntaxError`` for an unparsable string, ``AutomatonTooLarge`` beyond a size limit
    (``max_states`` states of a parity or product automaton before reduction, ``MAX_APS``,
    ``MAX_TABLEAU_NODES``)."""
    f = formula if isinstance(formula, Formula) else parse(formula)  # parse: a TypeError for None, a number
    check_size(f)
    aps = tuple(sorted(f.aps()))
    if len(aps) > MAX_APS:
        raise AutomatonTooLarge(f"the formula uses {len(aps)} propositions; at most {MAX_APS} are supported")
    g = nnf(f)
    start = to_dnf(g)  # the initial state's name; FormulaTooLarge (MAX_DNF_CLAUSES) before any automaton is built
    try:
        delta, accepting = _automaton(g, aps, max_states, [MAX_NBA_STEPS, MAX_NBA_STEPS])
    except _NoDba as e:
        raise NoDeterministicBuchi(
            f"{f} has no deterministic Büchi automaton: it can demand that something holds forever from some "
            "unknown time on (a persistence property, like F G a), which no deterministic Büchi automaton "
            "recognises; these are other properties that are trained: a recurrence (G F a: back to a again and "
            "again, leaving it between), a safety from the start (G a) or a reach (F a)",
            e.args[0]) from None
    dead, done = dead_states(delta, accepting), universal_states(delta, accepting)
    return BuchiAutomaton(aps, 0, delta, accepting, frozenset(dead), _names(start, aps, delta, dead, done))


class _NoDba(Exception):
    """A (sub-)formula has no deterministic Büchi automaton."""


def _operands(g: Formula, kind: type) -> list[Formula]:
    """The operands of a chain of ``kind`` (And or Or) nodes."""
    return [h for c in g.children() for h in (_operands(c, kind) if isinstance(c, kind) else [c])]


def _automaton(g: Formula, aps: tuple[str, ...], max_states: int,
               budget: list[int]) -> tuple[list[list[int]], list[list[bool]]]:
    """Reduced DBA (delta, accepting; initial state 0) of the NNF formula ``g`` over the letters of
    ``aps``. A conjunction or disjunction whose operands all have a DBA is built as the product
    of theirs (smaller than determinising the whole: the NBA of ``G F a | G F b`` guesses a
    disjunct, which Safra's trees remember in every order); otherwise the whole formula goes
    through steps 1-3 over its own propositions. Raises ``_NoDba``. ``budget``: [NBA steps left,
    ``MAX_NBA_STEPS``], shared by the operands."""
    if isinstance(g, (And, Or)):
        try:
            parts = [_automaton(h, aps, max_states, budget) for h in _operands(g, type(g))]
        except _NoDba:
            pass  # the whole may still have one: F G a & G a is G a
        else:
            return reduce(*product(parts, isinstance(g, And), max_states, str(g)))[:2]
    own = tuple(sorted(g.aps()))
    dpa = determinise(to_nba(g, own, MAX_TABLEAU_NODES, budget), 1 << len(own), max_states, str(g))
    marks, witness = buchi_marks(dpa)
    if marks is None:
        assert witness is not None
        # A letter class of g's propositions -> a letter over aps (the others false).
        letter = [sum(1 << aps.index(own[i]) for i in range(len(own)) if dpa.letter_class.index(c) >> i & 1)
                  for c in range(len(dpa.delta[0]))]
        raise _NoDba(tuple([letter[c] for c in word] for word in witness))
    # A letter over aps is read through the propositions of g.
    read = [dpa.letter_class[sum(1 << i for i, name in enumerate(own) if letter >> aps.index(name) & 1)]
            for letter in range(1 << len(aps))]
    delta = [[dpa.delta[q][c] for c in read] for q in range(len(dpa.delta))]
    accepting = [[marks[q][c] for c in read] for q in range(len(dpa.delta))]
    return reduce(delta, accepting)[:2]


def _names(start: Dnf, aps: tuple[str, ...], delta: list[list[int]], dead: set[int], done: set[int]) -> list[str]:
    """Per state, the formula (``start``: the DNF of its NNF) progressed along the first word that
    reaches it breadth-first, without its unsatisfiable clauses and those that imply another (kept
    when the satisfiability checks exceed their limits); 'true' for the accepting sink, 'false' for
    the rejecting one; a repeated residual gets ' #k' (the automaton needs several states to track it)."""
    prog = Progression(aps)
    tableau = Tableau(MAX_TABLEAU_NODES, MAX_NAME_STEPS)
    residual = {0: start}
    frontier = [0]
    for q in frontier:  # grows while we iterate
        for a, t in enumerate(delta[q]):
            if t not in residual:
                residual[t] = prog.dnf(residual[q], a)
                try:
                    clauses = sorted((c for c in residual[t] if tableau.satisfiable(c)), key=clause_order)
                    for c in list(clauses):  # drop each clause that implies another one
                        if any(d != c and not tableau.satisfiable(c | negate_dnf({d})) for d in clauses):
                            clauses.remove(c)
                    residual[t] = frozenset(clauses)
                except AutomatonTooLarge:
                    pass
                frontier.append(t)
    names, seen = [], {}
    for q in range(len(delta)):
        if q in done or q in dead:
            names.append("true" if q in done else "false")
            continue
        text = "true" if residual[q] == DNF_TRUE else str(dnf_to_formula(residual[q]))
        seen[text] = seen.get(text, 0) + 1
        names.append(text if seen[text] == 1 else f"{text} #{seen[text]}")
    return names


def marked_edges(delta, marks, aps: tuple[str, ...]) -> list[tuple[int, int, bool, str]]:
    """(source, target, mark, guard) per group of letters of a state with the same target and mark
    (``marks[q][letter]``: a transition's acceptance, or a Büchi task's visits); the guard holds
    exactly for those letters."""
    out = []
    for q, row in enumerate(delta):
        groups: dict[tuple[int, bool], list[int]] = {}
        for a, t in enumerate(row):
            groups.setdefault((t, bool(marks[q][a])), []).append(a)
        for (t, mark), letters in groups.items():
            out.append((q, t, mark, letters_to_guard(letters, aps)))
    return out
