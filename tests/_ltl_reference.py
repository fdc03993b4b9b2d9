"""The tests' reference for LTL on lasso words, independent of ``d2spo.ltl.buchi``, and random formulas.

``holds`` is written from the definitions and shares no code with ``d2spo.ltl.buchi``: on a lasso
word u·v^ω the positions are those of u and v, the successor of the last one is the first of v, and
each sub-formula gets a truth value per position; ``U`` and ``F`` are the least fixpoints of their
one-step laws, ``R``, ``W`` and ``G`` the greatest (exact on a lasso: every position has one
successor, so the fixpoints of the finite system of equations are the truth values of the infinite
word). ``syntactic_recurrence`` is the syntactic recurrence class of Chang, Manna and Pnueli, whose
formulas all have a deterministic Büchi automaton. Used by tests/test_ltl_buchi.py,
tests/test_ltl_buchi_completed.py and bench/buchi_exactness.py.
"""

from __future__ import annotations

import itertools
import random

from hypothesis import strategies as st

from d2spo.ltl.formula import (
    FALSE,
    TRUE,
    Always,
    And,
    Const,
    Eventually,
    Formula,
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

# --- The reference: LTL on lasso words --------------------------------------------------------------


def holds(f: Formula, aps: tuple[str, ...], prefix: list[int], loop: list[int]) -> bool:
    """Whether prefix·loop^ω satisfies f (letters: bit i <=> aps[i] holds)."""
    word = prefix + loop
    n = len(word)
    nxt = [i + 1 for i in range(n - 1)] + [len(prefix)]

    def fixpoint(start: bool, law) -> list[bool]:
        value = [start] * n
        while True:
            new = [law(i, value[nxt[i]]) for i in range(n)]
            if new == value:
                return value
            value = new

    def ev(g: Formula) -> list[bool]:
        if isinstance(g, Const):
            return [g.value] * n
        if isinstance(g, Prop):
            return [bool(letter >> aps.index(g.name) & 1) for letter in word]
        if isinstance(g, Not):
            return [not x for x in ev(g.arg)]
        if isinstance(g, Next):
            inner = ev(g.arg)
            return [inner[nxt[i]] for i in range(n)]
        if isinstance(g, Eventually):
            inner = ev(g.arg)
            return fixpoint(False, lambda i, later: inner[i] or later)
        if isinstance(g, Always):
            inner = ev(g.arg)
            return fixpoint(True, lambda i, later: inner[i] and later)
        left, right = ev(g.left), ev(g.right)  # type: ignore[attr-defined]
        if isinstance(g, And):
            return [x and y for x, y in zip(left, right, strict=True)]
        if isinstance(g, Or):
            return [x or y for x, y in zip(left, right, strict=True)]
        if isinstance(g, Implies):
            return [not x or y for x, y in zip(left, right, strict=True)]
        if isinstance(g, Iff):
            return [x == y for x, y in zip(left, right, strict=True)]
        if isinstance(g, Until):
            return fixpoint(False, lambda i, later: right[i] or (left[i] and later))
        if isinstance(g, WeakUntil):
            return fixpoint(True, lambda i, later: right[i] or (left[i] and later))
        assert isinstance(g, Release)
        return fixpoint(True, lambda i, later: right[i] and (left[i] or later))

    return ev(f)[0]


def classes(f: Formula, positive: bool = True) -> tuple[bool, bool, bool]:
    """(guarantee, safety, recurrence) membership of f (of !f if not positive), by syntax."""
    if isinstance(f, (Const, Prop)):
        return True, True, True
    if isinstance(f, Not):
        return classes(f.arg, not positive)
    if isinstance(f, (And, Or, Next)):
        parts = [classes(c, positive) for c in f.children()]
        return tuple(all(p[k] for p in parts) for k in range(3))  # type: ignore[return-value]
    if isinstance(f, Implies):
        return classes(Or(Not(f.left), f.right), positive)
    if isinstance(f, Iff):
        g = Or(And(f.left, f.right), And(Not(f.left), Not(f.right)))
        return classes(g if positive else Not(g), True)
    if isinstance(f, (Eventually, Always)):
        guarantee, safety, recurrence = classes(f.arg, positive)
        if isinstance(f, Eventually) == positive:  # F, or G under a negation (!G a == F !a)
            return guarantee, False, guarantee
        return False, safety, recurrence
    left, right = classes(f.left, positive), classes(f.right, positive)  # type: ignore[attr-defined]
    if isinstance(f, WeakUntil) and not positive:  # !(a W b) == !b U (!a & !b)
        return classes(Until(Not(f.right), And(Not(f.left), Not(f.right))), True)
    least = isinstance(f, Until) == positive  # U, or R under a negation (!(a R b) == !a U !b)
    if least:
        return left[0] and right[0], False, left[2] and right[0]
    return False, left[1] and right[1], left[2] and right[2]


def syntactic_recurrence(f: Formula) -> bool:
    """Every class above lies in the recurrence class (each rule keeps recurrence >= the others)."""
    return classes(f)[2]


def refutes_dba(f: Formula, witness: tuple[list[int], list[int], list[int]]) -> bool:
    """Whether words u, x, y (lists of letters over f's sorted propositions) show, on short words,
    that no deterministic Büchi automaton accepts exactly f's words: every u·z·x^ω with z a word
    over {x, y} satisfies f while no u·(x^k y)^ω does. Landweber's argument: reading u and then x
    repeatedly, such an automaton D must take an accepting transition after a finite z (u·z·x^ω is
    accepted); insert y there and repeat: the word u·x^k1·y·x^k2·y··· makes D accept infinitely
    often but, like u·(x^k y)^ω, does not satisfy f."""
    aps = tuple(sorted(f.aps()))
    u, x, y = witness
    tails = [[]] + [sum(z, []) for k in range(1, 4) for z in itertools.product((x, y), repeat=k)]
    return all(holds(f, aps, u + z, x) for z in tails) and not any(holds(f, aps, u, x * k + y) for k in range(1, 6))


def lassos(n_letters: int, count: int, seed: int) -> list[tuple[list[int], list[int]]]:
    """Every lasso with |u| <= 2 and 1 <= |v| <= 2 when that is at most ``count`` of them, else
    ``count`` random ones with |u| <= 3 and 1 <= |v| <= 4."""
    letters = range(n_letters)
    every = [(list(u), list(v)) for k in range(3) for u in itertools.product(letters, repeat=k)
             for m in (1, 2) for v in itertools.product(letters, repeat=m)]
    if len(every) <= count:
        return every
    rng = random.Random(seed)
    return [([rng.randrange(n_letters) for _ in range(rng.randint(0, 3))],
             [rng.randrange(n_letters) for _ in range(rng.randint(1, 4))]) for _ in range(count)]


# --- Random formulas --------------------------------------------------------------------------------

UNARY = (Not, Next, Eventually, Always)
BINARY = (And, Or, Implies, Iff, Until, Release, WeakUntil)


def formulas(aps: tuple[str, ...], depth: int) -> st.SearchStrategy[Formula]:
    leaves = st.sampled_from([Prop(a) for a in aps] * 2 + [TRUE, FALSE])
    if depth == 0:
        return leaves
    sub = formulas(aps, depth - 1)
    return st.one_of(leaves, st.sampled_from(UNARY).flatmap(lambda op: st.builds(op, sub)),
                     st.sampled_from(BINARY).flatmap(lambda op: st.builds(op, sub, sub)))


def encode(letter: int, aps: tuple[str, ...], dba_aps: tuple[str, ...]) -> int:
    """A letter over ``aps`` read over ``dba_aps`` (the propositions that occur in the formula)."""
    return sum(1 << dba_aps.index(name) for i, name in enumerate(aps) if letter >> i & 1 and name in dba_aps)
