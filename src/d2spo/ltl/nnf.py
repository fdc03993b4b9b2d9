"""Negation normal form of an LTL formula (step 1 of ``translate`` and of ``buchi.to_dba``):
negations only on propositions, ``->`` and ``<->`` expanded, constants folded, each sub-formula
converted once per polarity; ``FormulaTooLarge`` when the form as printed grows too large."""

from __future__ import annotations

from collections.abc import Callable

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
)

MAX_NNF_SIZE = 4000
"""Most operators and propositions in the negation normal form of a formula (or of its negation),
counted as printed. ``a <-> b`` is ``(a & b) | (!a & !b)``, so a chain of n ``<->`` is about 2**n
as printed (and so is a chain of ``W`` under a negation: ``!(a W b)`` is ``!b U (!a & !b)``);
every later pass (satisfiability, state names) works on that printed form. The 10-long chain of
``<->`` has about 3800; an 11-long one is refused. The named tasks have at most 30."""

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
