"""The translator against the semantics of LTL, on random formulas and random words.

The translator claims that, for every LTL formula, the automaton is in an accepting state exactly
after good prefixes (every infinite continuation satisfies the formula) and in a rejecting state
exactly after bad prefixes (none does). Two references, written here from the definitions and
sharing no code with ``d2spo.ltl.translate``, check that claim:

* ``TypeGraph`` decides good/bad prefixes exactly for every formula (see its docstring).
* ``lasso_holds`` is the standard recursive semantics on ultimately periodic ("lasso") words
  u·w^ω. Enumerating bounded lasso continuations decides good/bad prefixes exactly for formulas of
  temporal depth at most 1 over two propositions (see ``lasso_status``); it cross-checks
  ``TypeGraph`` and the translator there, and checks on random lasso words for all formulas that
  an accepting (rejecting) state is only ever reached on words that satisfy (violate) the formula.
"""

from __future__ import annotations

import itertools
from functools import cache

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from d2spo.ltl import translate
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

# Random formulas often have no good prefix; the translator warns about those, which is expected.
pytestmark = pytest.mark.filterwarnings("ignore::d2spo.ltl.NeverCompletedWarning")

TEMPORAL = (Next, Eventually, Always, Until, Release, WeakUntil)
UNARY = (Not, Next, Eventually, Always)
BINARY = (And, Or, Implies, Iff, Until, Release, WeakUntil)


def subformulas(f: Formula) -> list[Formula]:
    """Distinct sub-formulas, children before parents."""
    out: list[Formula] = []
    seen: set[Formula] = set()

    def visit(g: Formula) -> None:
        for child in g.children():
            visit(child)
        if g not in seen:
            seen.add(g)
            out.append(g)

    visit(f)
    return out


def temporal_depth(f: Formula) -> int:
    inner = max((temporal_depth(c) for c in f.children()), default=0)
    return inner + isinstance(f, TEMPORAL)


def boolean(f: Formula, value: dict[Formula, np.ndarray]) -> np.ndarray:
    """Value of a non-temporal node from the values of its children."""
    if isinstance(f, Not):
        return ~value[f.arg]
    left, right = value[f.left], value[f.right]  # type: ignore[attr-defined]
    if isinstance(f, And):
        return left & right
    if isinstance(f, Or):
        return left | right
    if isinstance(f, Implies):
        return ~left | right
    assert isinstance(f, Iff)
    return left == right


# --- Reference 1: lasso semantics ----------------------------------------------------------------


def lasso_holds(f: Formula, aps: tuple[str, ...], words: np.ndarray, loop_start: int) -> np.ndarray:
    """Truth of ``f`` at position 0 of each lasso word ``words[j, :loop_start] · (words[j,
    loop_start:])^ω`` (letters are bitmasks over ``aps``). Positions 0..n-1 with successor
    i+1, and loop_start after n-1; U/F are least fixpoints, R/W/G greatest fixpoints, reached
    after n rounds of the one-step law."""
    n = words.shape[1]
    succ = np.array([*range(1, n), loop_start])
    value: dict[Formula, np.ndarray] = {}
    for g in subformulas(f):
        if isinstance(g, Const):
            value[g] = np.full(words.shape, g.value)
        elif isinstance(g, Prop):
            value[g] = (words >> aps.index(g.name) & 1).astype(bool)
        elif isinstance(g, Next):
            value[g] = value[g.arg][:, succ]
        elif isinstance(g, TEMPORAL):
            if isinstance(g, (Eventually, Always)):
                now, stay = value[g.arg], value[g.arg]
            else:
                now, stay = value[g.right], value[g.left]
            least = isinstance(g, (Eventually, Until))
            v = np.full(words.shape, not least)
            for _ in range(n):
                if isinstance(g, Eventually):
                    v = now | v[:, succ]
                elif isinstance(g, Always):
                    v = now & v[:, succ]
                elif isinstance(g, (Until, WeakUntil)):
                    v = now | (stay & v[:, succ])
                else:  # Release: right & (left | next)
                    v = now & (stay | v[:, succ])
            value[g] = v
        else:
            value[g] = boolean(g, value)
    return value[f][:, 0]


@cache
def _lasso_continuations(n_letters: int, max_prefix: int) -> list[np.ndarray]:
    """All v·w with |v| <= max_prefix and |w| = 1, grouped by |v| (arrays [count, |v| + 1])."""
    return [np.array(list(itertools.product(range(n_letters), repeat=k + 1))) for k in range(max_prefix + 1)]


def lasso_status(f: Formula, aps: tuple[str, ...], word: list[int]) -> list[str]:
    """Status after each prefix of ``word`` (including the empty one), by enumerating the lasso
    continuations v·w^ω with |v| <= 2**len(aps) and |w| = 1.

    Exact when f has temporal depth <= 1 (temporal operators only over boolean combinations of
    propositions). Why: such an f is a boolean combination of propositions, ``X b`` and ``b U c``,
    ``b R c``, ``b W c``, ``F b``, ``G b`` with b, c boolean. On a word c_0 c_1 ..., those are
    determined by c_0, c_1 and the order in which distinct letters first occur (``b U c`` holds iff
    some letter satisfying c first occurs after only letters satisfying b have occurred). With the
    distinct letters l_1 = c_0, l_2, ..., l_m in order of first occurrence, the lasso
    c_0 c_1 l_3 ... l_{m-1} (l_m)^ω (c_0 c_0 l_2 ... (l_m)^ω when c_1 = c_0) has the same values, and
    its v has at most m <= 2**len(aps) letters. Prepending the same finite prefix to two words that
    agree on all formulas of temporal depth <= 1 keeps them in agreement (structural induction on
    the one-step laws), so these continuations reach every value f can take after any prefix.
    """
    assert temporal_depth(f) <= 1
    statuses = []
    for k in range(len(word) + 1):
        values = set()
        for tails in _lasso_continuations(1 << len(aps), 1 << len(aps)):
            words = np.concatenate([np.tile(np.array(word[:k], dtype=int), (len(tails), 1)), tails], axis=1)
            values |= set(lasso_holds(f, aps, words, words.shape[1] - 1).tolist())
        statuses.append(_status(values))
    return statuses


def _status(possible: set[bool]) -> str:
    """Status from the set of truth values the formula can still take."""
    assert possible, "every prefix has a continuation"
    if possible == {True}:
        return "accepting"
    return "rejecting" if possible == {False} else "undecided"


# --- Reference 2: the graph of truth-value types ---------------------------------------------------


class TypeGraph:
    """Exact good/bad-prefix decisions for any formula, from the definition of the semantics.

    A *type* assigns a letter and a truth value to each temporal sub-formula; the values of the
    other sub-formulas follow from those. A type t may be followed by t' when the one-step laws hold
    (``X b`` at t is b at t'; ``b U c`` at t is ``c | (b & (b U c at t'))`` at t; likewise F, G, R,
    W). A path is *fair* when no eventuality stays pending forever (``b U c``/``F c`` true without
    c; ``b R c``/``G c`` false while c holds; ``b W c`` false while b or c holds).

    The truth values of all sub-formulas along any infinite word form a fair path whose letters are
    that word. Conversely, along a fair path the assigned values are the true ones (induction on
    the sub-formula: X by the step law; for U, F the fairness gives a witness, and a false U with a
    true witness would contradict the step law backwards from the witness; R, G, W dually). So a
    word extending prefix u can satisfy (violate) f iff a fair path reads u from a type where f is
    true (false). Fair-path starts are the greatest fixpoint of the Emerson-Lei characterisation.
    """

    def __init__(self, f: Formula, aps: tuple[str, ...]):
        self.f = f
        subs = subformulas(f)
        temporal = [g for g in subs if isinstance(g, TEMPORAL)]
        n_nodes = 1 << (len(aps) + len(temporal))
        ids = np.arange(n_nodes)
        self.letter = ids & ((1 << len(aps)) - 1)
        value: dict[Formula, np.ndarray] = {}
        for g in subs:
            if isinstance(g, Const):
                value[g] = np.full(n_nodes, g.value)
            elif isinstance(g, Prop):
                value[g] = (self.letter >> aps.index(g.name) & 1).astype(bool)
            elif isinstance(g, TEMPORAL):
                value[g] = (ids >> (len(aps) + temporal.index(g)) & 1).astype(bool)
            else:
                value[g] = boolean(g, value)
        self.holds = value[f]

        edges = np.ones((n_nodes, n_nodes), dtype=bool)  # edges[t, t'] : t' may follow t
        fulfilled = [np.ones(n_nodes, dtype=bool)]  # per eventuality: not pending at the node
        for g in temporal:
            here, there = value[g][:, None], value[g][None, :]
            if isinstance(g, Next):
                edges &= here == value[g.arg][None, :]
                continue
            if isinstance(g, (Eventually, Always)):
                now, stay = value[g.arg][:, None], value[g.arg][:, None]
            else:
                now, stay = value[g.right][:, None], value[g.left][:, None]
            if isinstance(g, Eventually):
                edges &= here == (now | there)
                fulfilled.append(~value[g] | value[g.arg])
            elif isinstance(g, Always):
                edges &= here == (now & there)
                fulfilled.append(value[g] | ~value[g.arg])
            elif isinstance(g, Until):
                edges &= here == (now | (stay & there))
                fulfilled.append(~value[g] | value[g.right])
            elif isinstance(g, WeakUntil):
                edges &= here == (now | (stay & there))
                fulfilled.append(value[g] | (~value[g.left] & ~value[g.right]))
            else:  # Release
                edges &= here == (now & (stay | there))
                fulfilled.append(value[g] | ~value[g.right])
        self.edges = edges

        def pre(target: np.ndarray) -> np.ndarray:
            return edges[:, target].any(axis=1)

        fair = np.ones(n_nodes, dtype=bool)
        while True:  # nu Z. AND_e EX E[true U (Z & fulfilled_e)]
            new = fair.copy()
            for ok in fulfilled:
                reach = fair & ok
                while True:
                    grown = reach | pre(reach)
                    if (grown == reach).all():
                        break
                    reach = grown
                new &= pre(reach)
            if (new == fair).all():
                break
            fair = new
        self.fair = fair

    def status(self, word: list[int]) -> list[str]:
        """Status after each prefix of ``word``, including the empty one."""
        # frontier[v]: the types position i can have on a fair path that reads word[:i] from a
        # type where f has value v (every fair type has a fair successor).
        frontier = {v: self.fair & (self.holds == v) for v in (True, False)}
        statuses = [_status({v for v in (True, False) if frontier[v].any()})]
        for letter in word:
            possible = set()
            for v in (True, False):
                here = frontier[v] & (self.letter == letter)
                possible |= {v} if here.any() else set()
                frontier[v] = self.edges[here].any(axis=0) & self.fair
            statuses.append(_status(possible))
        return statuses


# --- Strategies ------------------------------------------------------------------------------------


def formulas(aps: tuple[str, ...], depth: int, temporal: bool = True) -> st.SearchStrategy[Formula]:
    """Formulas of nesting depth <= depth (every operator counts) over aps, true and false."""
    leaves = st.sampled_from([Prop(a) for a in aps] * 2 + [TRUE, FALSE])
    if depth == 0:
        return leaves
    sub = formulas(aps, depth - 1, temporal)
    unary = [op for op in UNARY if temporal or op is Not]
    binary = [op for op in BINARY if temporal or op not in TEMPORAL]
    return st.one_of(
        leaves,
        st.sampled_from(unary).flatmap(lambda op: st.builds(op, sub)),
        st.sampled_from(binary).flatmap(lambda op: st.builds(op, sub, sub)),
    )


def depth_one_formulas(aps: tuple[str, ...]) -> st.SearchStrategy[Formula]:
    """Boolean combinations (depth <= 2) of temporal operators over boolean formulas (depth <= 1)."""
    inner = formulas(aps, 1, temporal=False)
    temporal = st.one_of(
        st.sampled_from([Next, Eventually, Always]).flatmap(lambda op: st.builds(op, inner)),
        st.sampled_from([Until, Release, WeakUntil]).flatmap(lambda op: st.builds(op, inner, inner)),
    )
    top = st.one_of(temporal, st.builds(Not, temporal))
    ops = st.sampled_from([And, Or, Implies, Iff])
    return st.one_of(top, ops.flatmap(lambda op: st.builds(op, top, top)))


aps_choice = st.sampled_from([("p", "q"), ("p", "q", "r")])


def words(aps: tuple[str, ...], max_len: int = 6) -> st.SearchStrategy[list[int]]:
    return st.lists(st.integers(0, (1 << len(aps)) - 1), max_size=max_len)


def automaton_status(f: Formula, aps: tuple[str, ...], word: list[int]) -> list[str]:
    """Status after each prefix, by the translator (letters re-encoded over the automaton's aps)."""
    aut = translate(str(f))
    encode = [aut.letter(name for i, name in enumerate(aps) if a >> i & 1 and name in aut.aps) for a in word]
    return [aut.status(q) for q in aut.run(encode)]


# --- Properties ------------------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(data=st.data(), aps=aps_choice)
def test_status_after_every_prefix_is_exact(data, aps):
    f = data.draw(formulas(aps, 4), label="formula")
    # The reference enumerates 2**(|aps| + #temporal sub-formulas) types; keep that small.
    assume(sum(isinstance(g, TEMPORAL) for g in subformulas(f)) <= 6)
    word = data.draw(words(aps), label="word")
    assert automaton_status(f, aps, word) == TypeGraph(f, aps).status(word)


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_status_matches_lasso_enumeration_at_temporal_depth_one(data):
    aps = ("p", "q")
    f = data.draw(depth_one_formulas(aps), label="formula")
    word = data.draw(words(aps, max_len=4), label="word")
    expected = lasso_status(f, aps, word)
    assert TypeGraph(f, aps).status(word) == expected  # the two references agree
    assert automaton_status(f, aps, word) == expected


@settings(max_examples=200, deadline=None)
@given(data=st.data(), aps=aps_choice)
def test_decided_states_agree_with_lasso_semantics(data, aps):
    f = data.draw(formulas(aps, 4), label="formula")
    letters = st.integers(0, (1 << len(aps)) - 1)
    prefix = data.draw(st.lists(letters, max_size=4), label="prefix")
    loop = data.draw(st.lists(letters, min_size=1, max_size=4), label="loop")
    holds = bool(lasso_holds(f, aps, np.array([prefix + loop]), len(prefix))[0])
    unrolled = prefix + loop * 6
    statuses = automaton_status(f, aps, unrolled)
    assert "rejecting" not in statuses if holds else "accepting" not in statuses


@settings(max_examples=100, deadline=None)
@given(data=st.data(), aps=aps_choice)
def test_automaton_is_minimal_and_reachable(data, aps):
    aut = translate(str(data.draw(formulas(aps, 4), label="formula")))
    reached = set(aut.run([]))
    frontier = list(reached)
    while frontier:
        q = frontier.pop()
        for t in aut.delta[q]:
            if t not in reached:
                reached.add(t)
                frontier.append(t)
    assert reached == set(range(aut.n_states))
    # Two states are distinguishable iff some word leads them to different statuses.
    pairs = list(itertools.product(range(aut.n_states), repeat=2))
    distinct = {(p, q) for p, q in pairs if aut.status(p) != aut.status(q)}
    changed = True
    while changed:
        changed = False
        for p, q in pairs:
            successors = ((aut.delta[p][a], aut.delta[q][a]) for a in range(aut.n_letters))
            if (p, q) not in distinct and any(s in distinct for s in successors):
                distinct.add((p, q))
                changed = True
    assert all((p, q) in distinct for p, q in pairs if p != q)
