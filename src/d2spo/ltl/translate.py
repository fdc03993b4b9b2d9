"""LTL formula -> minimal deterministic automaton that tracks task progress (paper Sec. II-B).

The construction, in four steps (docs/ltl.md has the details and the argument for exactness):

1. Negation normal form (NNF): negations only on propositions; ``->``, ``<->`` expanded.
2. Formula progression. A state is a progressed formula kept in disjunctive normal form (DNF)
   over "atoms", the non-boolean sub-formulas of the NNF formula (literals, ``X``, ``U``, ``R``,
   ``W``, ``F``, ``G`` nodes). Reading a letter rewrites every atom by the one-step expansion laws
   (``a U b`` -> ``prog(b) | (prog(a) & a U b)``, ...). DNFs over a finite set of atoms, kept
   sorted, deduplicated and free of subsumed clauses, are finitely many, so progression stops.
3. Exact status. Each new state is checked with a tableau satisfiability test (``ltl/tableau.py``:
   an on-the-fly generalised Büchi automaton and an emptiness check): unsatisfiable clauses, and clauses that
   imply another clause, are dropped; if nothing is left the state is the rejecting state
   ``false``; if its negation is unsatisfiable it is the accepting state ``true``. This makes
   accepting/rejecting exact for every LTL formula, not only for the co-safe and safety fragments.
4. Minimisation of the resulting Moore machine (output = accepting / rejecting / undecided) by
   partition refinement, so the state count is the minimum for the status semantics.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable

from d2spo.ltl.automaton import Automaton, AutomatonTooLarge
from d2spo.ltl.formula import (
    FALSE,
    TRUE,
    Always,
    And,
    Const,
    Eventually,
    Formula,
    FormulaTooLarge,
    Iff,
    Implies,
    Next,
    Not,
    Or,
    Prop,
    Release,
    Until,
    WeakUntil,
    check_size,
    conjunction,
    disjunction,
)
from d2spo.ltl.parser import parse
from d2spo.ltl.tableau import Tableau

MAX_APS = 12
"""Most atomic propositions a formula may use (the transition table has 2**len(aps) columns)."""
MAX_TABLEAU_NODES = 200_000
"""Most tableau nodes the satisfiability checks of one translation may build."""
MAX_TABLEAU_STEPS = 10_000_000
"""Most work the tableau may do in one translation: each formula it expands counts one step plus
the formulas its branch has already processed (what that step copies). A bound on the time (1 to
4 s on a 2-core CPU, by the formula: 0.8 s for the ordered visit of 12 areas, 3.3 s for
``a W b W ... W h``), so a formula whose check grows exponentially is refused instead of running
for minutes: an ordered visit of 11 areas ``F(a & X F(b & X F(...))`` needs 8 million steps
(0.5 s), 12 areas are refused (15 took 184 s before this bound). The named tasks need at most
1100."""
MAX_NNF_SIZE = 4000
"""Most operators and propositions in the negation normal form of a formula (or of its negation),
counted as printed. ``a <-> b`` is ``(a & b) | (!a & !b)``, so a chain of n ``<->`` is about 2**n
as printed (and so is a chain of ``W`` under a negation: ``!(a W b)`` is ``!b U (!a & !b)``);
every later pass (satisfiability, state names) works on that printed form. The 10-long chain of
``<->`` has about 3800; an 11-long one is refused. The named tasks have at most 30."""
MAX_DNF_CLAUSES = 64
"""Most clauses in the disjunctive normal form of a state of the automaton (``FormulaTooLarge``
beyond). A chain of n ``<->`` over propositions has 2**(n-1) clauses, and the checks of ``decide``
take time quadratic in the clauses: a 7-long chain (64 clauses) takes about 2 s (its monitor's
check gives up, its DBA is built), an 8-long one is refused at once (it took 50 s; a 10-long one
2 minutes). The named tasks have at most 4."""


class NeverCompletedWarning(UserWarning):
    """The formula has no good prefix: no finite run completes it (e.g. ``G F a``, ``G !obs``)."""


# --- 1. Negation normal form ---------------------------------------------------------------------


def _and(a: Formula, b: Formula) -> Formula:
    if a == FALSE or b == FALSE:
        return FALSE
    if a == TRUE:
        return b
    if b == TRUE or a == b:
        return a
    return And(a, b)


def _or(a: Formula, b: Formula) -> Formula:
    if a == TRUE or b == TRUE:
        return TRUE
    if a == FALSE:
        return b
    if b == FALSE or a == b:
        return a
    return Or(a, b)


def _next(a: Formula) -> Formula:
    return a if isinstance(a, Const) else Next(a)


def _eventually(a: Formula) -> Formula:
    return a if isinstance(a, (Const, Eventually)) else Eventually(a)


def _always(a: Formula) -> Formula:
    return a if isinstance(a, (Const, Always)) else Always(a)


def _until(a: Formula, b: Formula) -> Formula:
    if isinstance(b, Const) or a == FALSE:
        return b
    return _eventually(b) if a == TRUE else Until(a, b)


def _release(a: Formula, b: Formula) -> Formula:
    if isinstance(b, Const) or a == TRUE:
        return b
    return _always(b) if a == FALSE else Release(a, b)


def _weak_until(a: Formula, b: Formula) -> Formula:
    if b == TRUE or a == TRUE:
        return TRUE
    if a == FALSE:
        return b
    return _always(a) if b == FALSE else WeakUntil(a, b)


def nnf(f: Formula, negate: bool = False) -> Formula:
    """Negation normal form of ``f`` (of ``!f`` if ``negate``), with constants folded.

    The result uses only Const, Prop, Not(Prop), And, Or, Next, Eventually, Always, Until, Release
    and WeakUntil. Each sub-formula is converted once per polarity and the results are shared, so
    ``a <-> b <-> c <-> ...``, whose form as printed doubles with every ``<->``, is built in linear
    time; ``FormulaTooLarge`` when that printed form has more than ``MAX_NNF_SIZE`` nodes.
    """
    memo: dict[tuple[Formula, bool], Formula] = {}

    def shared(g: Formula, neg: bool) -> Formula:
        if (g, neg) not in memo:
            memo[g, neg] = _nnf_step(g, neg, shared)
        return memo[g, neg]

    out = shared(f, negate)
    if (size := printed_size(out)) > MAX_NNF_SIZE:
        raise FormulaTooLarge(
            f"the negation normal form of {'!' if negate else ''}({_abridged(f)}) has {size} operators and propositions, "
            f"more than MAX_NNF_SIZE={MAX_NNF_SIZE} (each <-> doubles its operands, and so does a W under a "
            "negation); simplify the formula, e.g. split a chain of <-> or W")
    return out


def _nnf_step(f: Formula, negate: bool, nnf: Callable[[Formula, bool], Formula]) -> Formula:
    """One step of ``nnf`` at the root of ``f``; ``nnf(g, negate)`` converts a sub-formula."""
    if isinstance(f, Const):
        return Const(f.value != negate)
    if isinstance(f, Prop):
        return Not(f) if negate else f
    if isinstance(f, Not):
        return nnf(f.arg, not negate)
    if isinstance(f, (And, Or)):
        left, right = nnf(f.left, negate), nnf(f.right, negate)
        return _and(left, right) if isinstance(f, And) != negate else _or(left, right)
    if isinstance(f, Implies):
        return nnf(Or(Not(f.left), f.right), negate)
    if isinstance(f, Iff):
        both = And(f.left, f.right)
        neither = And(Not(f.left), Not(f.right))
        exactly_one = Or(And(f.left, Not(f.right)), And(Not(f.left), f.right))
        return nnf(exactly_one if negate else Or(both, neither), False)
    if isinstance(f, Next):
        return _next(nnf(f.arg, negate))
    if isinstance(f, Eventually):
        return _always(nnf(f.arg, True)) if negate else _eventually(nnf(f.arg, False))
    if isinstance(f, Always):
        return _eventually(nnf(f.arg, True)) if negate else _always(nnf(f.arg, False))
    if isinstance(f, Until):  # !(a U b) == !a R !b
        if negate:
            return _release(nnf(f.left, True), nnf(f.right, True))
        return _until(nnf(f.left, False), nnf(f.right, False))
    if isinstance(f, Release):  # !(a R b) == !a U !b
        if negate:
            return _until(nnf(f.left, True), nnf(f.right, True))
        return _release(nnf(f.left, False), nnf(f.right, False))
    if isinstance(f, WeakUntil):  # !(a W b) == !b U (!a & !b)
        if negate:
            not_b = nnf(f.right, True)
            return _until(not_b, _and(nnf(f.left, True), not_b))
        return _weak_until(nnf(f.left, False), nnf(f.right, False))
    raise TypeError(f"not an LTL formula node: {f!r}")


def printed_size(f: Formula) -> int:
    """Nodes of ``f`` as printed: a sub-formula shared by two parents counts twice (one pass over
    the distinct nodes, iterative)."""
    size: dict[Formula, int] = {}
    stack = [f]
    while stack:
        todo = [c for c in stack[-1].children() if c not in size]
        if todo:
            stack.extend(todo)
        else:
            g = stack.pop()
            size[g] = 1 + sum(size[c] for c in g.children())
    return size[f]


def _abridged(f: Formula, width: int = 60) -> str:
    """``str(f)``, cut to ``width`` characters for an error message."""
    text = str(f)
    return text if len(text) <= width else text[:width - 3] + "..."


# --- 2. Progression over DNFs ------------------------------------------------------------------

Clause = frozenset  # of atoms (non-boolean NNF formulas), read as their conjunction
Dnf = frozenset  # of clauses, read as their disjunction

DNF_TRUE: Dnf = frozenset({frozenset()})
DNF_FALSE: Dnf = frozenset()


def _consistent(clause: Clause) -> bool:
    return not any(isinstance(a, Not) and a.arg in clause for a in clause)


def _drop_subsumed(clauses: Iterable[Clause]) -> Dnf:
    """Remove each clause that contains another one (``c | (c & d) == c``). ``FormulaTooLarge``
    when more than ``MAX_DNF_CLAUSES`` are left."""
    kept: list[Clause] = []
    for c in sorted(set(clauses), key=len):
        if not any(k <= c for k in kept):
            kept.append(c)
            if len(kept) > MAX_DNF_CLAUSES:
                raise FormulaTooLarge(
                    f"the formula's disjunctive normal form has more than MAX_DNF_CLAUSES={MAX_DNF_CLAUSES} clauses "
                    "(a chain a <-> b <-> ... of n propositions has 2**(n-1)); simplify the formula, e.g. split "
                    "a chain of <->")
    return frozenset(kept)


def dnf_or(x: Dnf, y: Dnf) -> Dnf:
    if not x or y == DNF_TRUE:
        return y
    if not y or x == DNF_TRUE:
        return x
    return _drop_subsumed(x | y)


def dnf_and(x: Dnf, y: Dnf) -> Dnf:
    if not x or y == DNF_TRUE:
        return x
    if not y or x == DNF_TRUE:
        return y
    return _drop_subsumed(c | d for c in x for d in y if _consistent(c | d))


def to_dnf(f: Formula) -> Dnf:
    """DNF of an NNF formula, over its non-boolean sub-formulas."""
    if isinstance(f, Const):
        return DNF_TRUE if f.value else DNF_FALSE
    if isinstance(f, And):
        return dnf_and(to_dnf(f.left), to_dnf(f.right))
    if isinstance(f, Or):
        return dnf_or(to_dnf(f.left), to_dnf(f.right))
    return frozenset({frozenset({f})})


def dnf_to_formula(d: Dnf) -> Formula:
    """The DNF as a formula, clauses and atoms in a fixed (sorted) order."""
    clauses = sorted((sorted(c, key=str) for c in d), key=lambda c: (len(c), [str(a) for a in c]))
    return disjunction([conjunction(c) for c in clauses])


class _Progression:
    """Progression of NNF formulas through letters (bit i of a letter <=> aps[i] holds)."""

    def __init__(self, aps: tuple[str, ...]):
        self.bit = {name: 1 << i for i, name in enumerate(aps)}
        self.memo: dict[tuple[Formula, int], Dnf] = {}

    def formula(self, f: Formula, letter: int) -> Dnf:
        key = (f, letter)
        if key not in self.memo:
            self.memo[key] = self._formula(f, letter)
        return self.memo[key]

    def _formula(self, f: Formula, letter: int) -> Dnf:
        if isinstance(f, Const):
            return DNF_TRUE if f.value else DNF_FALSE
        if isinstance(f, Prop):
            return DNF_TRUE if letter & self.bit[f.name] else DNF_FALSE
        if isinstance(f, Not):
            return DNF_FALSE if letter & self.bit[f.arg.name] else DNF_TRUE  # type: ignore[attr-defined]
        if isinstance(f, And):
            return dnf_and(self.formula(f.left, letter), self.formula(f.right, letter))
        if isinstance(f, Or):
            return dnf_or(self.formula(f.left, letter), self.formula(f.right, letter))
        if isinstance(f, Next):
            return to_dnf(f.arg)
        itself: Dnf = frozenset({frozenset({f})})
        if isinstance(f, Eventually):
            return dnf_or(self.formula(f.arg, letter), itself)
        if isinstance(f, Always):
            return dnf_and(self.formula(f.arg, letter), itself)
        if isinstance(f, (Until, WeakUntil)):  # b | (a & f)
            now_a, now_b = self.formula(f.left, letter), self.formula(f.right, letter)
            return dnf_or(now_b, dnf_and(now_a, itself))
        if isinstance(f, Release):  # b & (a | f)
            now_a, now_b = self.formula(f.left, letter), self.formula(f.right, letter)
            return dnf_and(now_b, dnf_or(now_a, itself))
        raise TypeError(f"not an NNF formula node: {f!r}")

    def dnf(self, d: Dnf, letter: int) -> Dnf:
        out = DNF_FALSE
        for clause in d:
            part = DNF_TRUE
            for atom in clause:
                part = dnf_and(part, self.formula(atom, letter))
                if not part:
                    break
            out = dnf_or(out, part)
        return out


# --- 3. Exact status (tableau.Tableau); 4. determinisation by progression, then minimisation -----------


def _clause_order(c: Clause) -> tuple[int, list[str]]:
    return len(c), sorted(map(str, c))


def _negate_dnf(d: Iterable[Clause]) -> frozenset:
    """A tableau node (set of formulas, all must hold) equivalent to ``!d``."""
    return frozenset(disjunction(sorted((nnf(a, True) for a in clause), key=str)) for clause in d)


def translate(formula: Formula | str, max_states: int = 1000) -> Automaton:
    """Minimal deterministic automaton of ``formula`` whose accepting (rejecting) states are
    exactly the good (bad) prefixes. Raises ``LTLSyntaxError`` for an unparsable string and
    ``AutomatonTooLarge`` when a size limit is hit (``max_states`` before minimisation,
    ``MAX_APS``, ``MAX_TABLEAU_NODES``). Warns ``NeverCompletedWarning`` when no prefix is good."""
    f = formula if isinstance(formula, Formula) else parse(formula)  # parse: a TypeError for None, a number
    check_size(f)
    aps = tuple(sorted(f.aps()))
    if len(aps) > MAX_APS:
        raise AutomatonTooLarge(f"the formula uses {len(aps)} propositions; at most {MAX_APS} are supported")
    prog = _Progression(aps)
    tableau = Tableau(MAX_TABLEAU_NODES, MAX_TABLEAU_STEPS)
    canonical: dict[Dnf, Dnf] = {}

    def decide(d: Dnf) -> Dnf:
        """DNF_FALSE / DNF_TRUE when ``d`` is unsatisfiable / valid; otherwise ``d`` without its
        unsatisfiable clauses and without each clause that implies another kept one."""
        if d not in canonical:
            clauses = [c for c in sorted(d, key=_clause_order) if tableau.satisfiable(c)]
            for c in list(clauses):
                if any(c2 != c and not tableau.satisfiable(c | _negate_dnf({c2})) for c2 in clauses):
                    clauses.remove(c)
            out = frozenset(clauses)
            if out and out != DNF_TRUE and not tableau.satisfiable(_negate_dnf(out)):
                out = DNF_TRUE
            canonical[d] = out
        return canonical[d]

    states = [decide(to_dnf(nnf(f)))]
    number = {states[0]: 0}
    delta: list[list[int]] = []
    for d in states:  # grows while we iterate: breadth-first exploration
        # Only the propositions that occur in d matter; letters equal on them share a target.
        names = {name for clause in d for atom in clause for name in atom.aps()}
        relevant = sum(prog.bit[name] for name in names)
        row: list[int] = []
        by_relevant: dict[int, int] = {}
        for letter in range(1 << len(aps)):
            key = letter & relevant
            if key not in by_relevant:
                target = decide(prog.dnf(d, key))
                if target not in number:
                    if len(states) >= max_states:
                        raise AutomatonTooLarge(
                            f"the automaton of {f} has more than max_states={max_states} states"
                        )
                    number[target] = len(states)
                    states.append(target)
                by_relevant[key] = number[target]
            row.append(by_relevant[key])
        delta.append(row)
    status = [1 if d == DNF_TRUE else 2 if d == DNF_FALSE else 0 for d in states]
    if 1 not in status:
        warnings.warn(
            f"{f} has no good prefix: no finite run completes this task, so its automaton has no "
            "accepting state and no distance to acceptance (see docs/ltl.md, 'Which formulas')",
            NeverCompletedWarning,
            stacklevel=2,
        )
    return _minimise(aps, delta, status, [str(dnf_to_formula(d)) for d in states])


def _minimise(aps: tuple[str, ...], delta: list[list[int]], status: list[int], names: list[str]) -> Automaton:
    """Moore's partition refinement (output = status), states renumbered breadth-first from 0.

    State 0 is initial. The label of a merged state is that of its first-discovered member.
    """
    block = list(status)
    n_blocks = len(set(block))
    while True:
        signatures = [(block[q], tuple(block[t] for t in row)) for q, row in enumerate(delta)]
        ids: dict[tuple, int] = {}
        block = [ids.setdefault(s, len(ids)) for s in signatures]
        if len(ids) == n_blocks:
            break
        n_blocks = len(ids)
    order = {block[0]: 0}  # block -> new state number, breadth-first
    rep = [0]  # new state -> representative old state
    for q in rep:
        for t in delta[q]:
            if block[t] not in order:
                order[block[t]] = len(rep)
                rep.append(t)
    first = {}
    for q in range(len(delta)):
        first.setdefault(block[q], q)
    return Automaton(
        aps=aps,
        initial=0,
        accepting=frozenset(i for i, q in enumerate(rep) if status[q] == 1),
        rejecting=frozenset(i for i, q in enumerate(rep) if status[q] == 2),
        delta=tuple(tuple(order[block[t]] for t in delta[q]) for q in rep),
        state_formulas=tuple(names[first[block[q]]] for q in rep),
    )
