"""Formula progression over disjunctive normal forms (step 2 of ``translate``; ``buchi.to_dba``
names its states with it): a state is a progressed formula kept in DNF over atoms, the non-boolean
sub-formulas of the NNF formula; reading a letter rewrites every atom by the one-step expansion
laws. DNFs are kept sorted, deduplicated and free of subsumed clauses, so progression stops."""

from __future__ import annotations

from collections.abc import Iterable

from d2spo.ltl.formula import (
    Always,
    And,
    Const,
    Eventually,
    Formula,
    FormulaTooLarge,
    Next,
    Not,
    Or,
    Prop,
    Release,
    Until,
    WeakUntil,
    conjunction,
    disjunction,
)
from d2spo.ltl.nnf import nnf

MAX_DNF_CLAUSES = 64
"""Most clauses in the disjunctive normal form of a state of the automaton (``FormulaTooLarge``
beyond). A chain of n ``<->`` over propositions has 2**(n-1) clauses, and the checks of ``decide``
take time quadratic in the clauses: a 7-long chain (64 clauses) takes about 2 s (its monitor's
check gives up, its DBA is built), an 8-long one is refused at once (it took 50 s; a 10-long one
2 minutes). The named tasks have at most 4."""



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


class Progression:
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


def clause_order(c: Clause) -> tuple[int, list[str]]:
    return len(c), sorted(map(str, c))


def negate_dnf(d: Iterable[Clause]) -> frozenset:
    """A tableau node (set of formulas, all must hold) equivalent to ``!d``."""
    return frozenset(disjunction(sorted((nnf(a, True) for a in clause), key=str)) for clause in d)
