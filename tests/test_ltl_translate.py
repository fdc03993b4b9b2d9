"""Translation of LTL formulas to automata: the paper's tasks, distances, the Automaton API."""

from __future__ import annotations

import importlib
import json
import warnings

import jax.numpy as jnp
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from d2spo.errors import LTLSyntaxError, UserError
from d2spo.ltl import (
    TASKS,
    UNREACHABLE,
    Automaton,
    AutomatonArrays,
    AutomatonTooLarge,
    NeverCompletedWarning,
    parse,
    task_automaton,
    task_formula,
    to_dba,
    translate,
)
from d2spo.ltl.automaton import letters_to_guard
from d2spo.ltl.formula import FormulaTooLarge
from d2spo.ltl.tasks import BUCHI_SUITE, SUITE

# The package exports the function ``translate``, which hides the module of the same name.
translate_module = importlib.import_module("d2spo.ltl.translate")


def statuses(aut: Automaton, word: list[set[str]]) -> list[str]:
    """Status after each non-empty prefix of a word given as sets of true propositions."""
    return [aut.status(q) for q in aut.run(aut.letter(s) for s in word)[1:]]


def singletons(aut: Automaton, names: list[str]) -> set[int]:
    """Letters with no proposition or exactly one of ``names`` (disjoint areas)."""
    return {0} | {aut.letter([n]) for n in names}


# --- The paper's tasks ---------------------------------------------------------------------------

# Minimal state counts derived by hand (docs/ltl.md draws each automaton):
#   phi1:         A1 not yet / A1 seen / A1, A2 seen, + accepting + rejecting        = 5
#   phi1-printed: A1 not yet / A1 seen, + accepting + rejecting                      = 4
#   phi2:         start / need A3 / need A1 / need A1 or A3 (both read) / need A4 / need A2,
#                 + accepting + rejecting                                             = 8
#   relaxed:      A1 not yet / A1 seen, + accepting + rejecting                      = 4
EXPECTED_STATES = {"phi1": 5, "phi1-printed": 4, "phi2": 8, "relaxed": 4}


PAPER_TASKS = sorted(set(TASKS) - set(SUITE) - set(BUCHI_SUITE))  # the suites: test_state_fields.py, test_ltl_buchi.py


@pytest.mark.parametrize("name", PAPER_TASKS)
def test_paper_task_state_counts(name):
    aut = translate(task_formula(name))
    assert aut.n_states == EXPECTED_STATES[name]
    assert len(aut.accepting) == 1 and len(aut.rejecting) == 1
    assert aut.initial == 0 and aut.status(0) == "undecided"


def test_every_task_is_listed():
    assert set(PAPER_TASKS) == set(EXPECTED_STATES)


def test_phi1_words():
    aut = translate(TASKS["phi1"])
    assert statuses(aut, [{"A1"}, {"A2"}, {"A3"}]) == ["undecided", "undecided", "accepting"]
    assert statuses(aut, [set(), {"A1"}, set(), {"A2"}, set(), {"A3"}])[-1] == "accepting"
    assert statuses(aut, [{"A2"}]) == ["rejecting"]
    assert statuses(aut, [{"A3"}]) == ["rejecting"]
    assert statuses(aut, [{"A1"}, {"A3"}]) == ["undecided", "rejecting"]
    assert statuses(aut, [{"A1"}, {"A2"}, {"A1"}, {"A2"}]) == ["undecided"] * 4  # A3 still needed
    assert statuses(aut, [{"A1", "A2", "A3"}]) == ["accepting"]  # overlapping areas: at once


def test_phi1_as_printed_never_needs_a3():
    aut = translate(TASKS["phi1-printed"])
    assert statuses(aut, [{"A1"}, {"A2"}]) == ["undecided", "accepting"]
    assert statuses(aut, [{"A3"}]) == ["rejecting"]
    assert statuses(aut, [{"A1"}, {"A3"}]) == ["undecided", "rejecting"]


def test_phi2_words():
    aut = translate(TASKS["phi2"])
    assert statuses(aut, [{"A1"}, {"A3"}, {"A4"}, {"A2"}])[-1] == "accepting"
    assert statuses(aut, [{"A3"}, {"A1"}, set(), {"A4"}, set(), {"A2"}])[-1] == "accepting"
    assert statuses(aut, [{"A1"}, {"A4"}]) == ["undecided", "rejecting"]  # A3 must come right after
    assert statuses(aut, [{"A2"}]) == ["rejecting"]
    # A2 before A4 does not count, nor A2 together with A4: A2 must come strictly after A4.
    assert statuses(aut, [{"A1"}, {"A3"}, {"A2"}, {"A4", "A2"}]) == ["undecided"] * 4
    assert statuses(aut, [{"A1"}, {"A3"}, {"A2"}, {"A4", "A2"}, {"A2"}])[-1] == "accepting"


def test_relaxed_words():
    aut = translate(TASKS["relaxed"])
    assert statuses(aut, [{"A1"}, {"A2"}]) == ["undecided", "accepting"]
    assert statuses(aut, [{"A2"}]) == ["rejecting"]
    assert statuses(aut, [{"A1", "A2"}]) == ["accepting"]


def test_state_formulas_are_progressed_formulas():
    aut = translate(TASKS["phi1"])
    assert aut.state_formulas[0] == "(!A2 U A1) & (!A3 U A2) & F A1 & F A3"
    after_a1 = aut.run([aut.letter(["A1"])])[-1]
    assert aut.state_formulas[after_a1] == "(!A3 U A2) & F A3"
    assert {aut.state_formulas[q] for q in aut.accepting} == {"true"}
    assert {aut.state_formulas[q] for q in aut.rejecting} == {"false"}
    for text in aut.state_formulas:
        parse(text)


def test_task_formula():
    assert task_formula("phi2") == TASKS["phi2"]
    assert task_formula("F goal") == "F goal"


# --- Distances (Prog(q), Sec. IV-C) ---------------------------------------------------------------


def test_phi1_distances_with_disjoint_areas():
    aut = translate(TASKS["phi1"])
    dist = aut.distances(singletons(aut, ["A1", "A2", "A3"]))
    assert dist[aut.initial] == 3
    q = aut.initial
    for name, expected in [("A1", 2), ("A2", 1), ("A3", 0)]:
        q = aut.delta[q][aut.letter([name])]
        assert dist[q] == expected
    assert all(dist[r] is None for r in aut.rejecting)


def test_distances_depend_on_feasible_letters():
    aut = translate(TASKS["phi1"])
    assert aut.distances()[aut.initial] == 1  # {A1, A2, A3} at once, if the areas overlapped
    with_overlap = singletons(aut, ["A1", "A2", "A3"]) | {aut.letter(["A1", "A2"])}
    assert aut.distances(with_overlap)[aut.initial] == 2
    without_a2 = singletons(aut, ["A1", "A3"])  # A2 cannot be visited: only A3 can finish
    after_a1 = aut.delta[aut.initial][aut.letter(["A1"])]
    after_a2 = aut.delta[after_a1][aut.letter(["A2"])]
    dist = aut.distances(without_a2)
    assert (dist[aut.initial], dist[after_a1], dist[after_a2]) == (None, None, 1)
    assert aut.distances([])[aut.initial] is None


def test_phi2_distances():
    aut = translate(TASKS["phi2"])
    assert aut.distances(singletons(aut, ["A1", "A2", "A3", "A4"]))[aut.initial] == 4
    assert aut.distances()[aut.initial] == 3  # {A1, A3}, {A3, A4}, {A2}


def test_distances_reject_out_of_range_letters():
    aut = translate(TASKS["relaxed"])
    with pytest.raises(ValueError, match="out of range"):
        aut.distances([4])


# --- Exactness beyond the co-safe and safety fragments ------------------------------------------


@pytest.mark.filterwarnings("ignore::d2spo.ltl.NeverCompletedWarning")
@pytest.mark.parametrize(
    "text, word, expected",
    [
        ("G F a | !G F a", [], "accepting"),  # valid, though no prefix "progresses" it to true
        ("G F a & F G !a", [], "rejecting"),  # unsatisfiable
        ("X G a & F !a", [{"a"}], "rejecting"),  # G a & F !a is left: unsatisfiable
        ("X G a & F !a", [set()], "undecided"),
        ("(a U b) | (!a R !b)", [], "accepting"),  # a formula or its dual negation
        ("G F a", [{"a"}, set(), {"a"}], "undecided"),  # liveness: never decided
        ("F G a", [set(), {"a"}], "undecided"),
        ("G (a -> X !a) & G F a & G (b <-> X a)", [{"a"}, {"b"}], "undecided"),
        ("G (a -> X !a) & X G a", [{"a"}], "rejecting"),
        ("F a & G !a", [], "rejecting"),
        ("G a | F !a", [], "accepting"),
    ],
)
def test_status_is_exact_for_all_ltl(text, word, expected):
    aut = translate(text)
    assert aut.status(aut.run(aut.letter(s & set(aut.aps)) for s in word)[-1]) == expected


@pytest.mark.parametrize("text", ["G F a", "F G a", "G F a -> G F b"])
def test_liveness_needs_one_state_and_warns(text):
    with pytest.warns(NeverCompletedWarning, match="no good prefix"):
        aut = translate(text)
    assert aut.n_states == 1 and aut.status(0) == "undecided"
    assert aut.distances() == [None]


def test_safety_task_warns_that_it_is_never_completed():
    with pytest.warns(NeverCompletedWarning):
        aut = translate("G !obs & F (A1 & F A2)")
    assert aut.n_states == 2 and not aut.accepting  # only "obs seen" is distinguished


def test_paper_tasks_do_not_warn():
    """Every named task with a good prefix translates without a warning (the Büchi suite's have none:
    ``task_automaton`` gives them their DBA, test_ltl_buchi.py)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name, text in TASKS.items():
            if name not in BUCHI_SUITE:
                translate(text)


def test_constant_formulas():
    assert translate("true").accepting == {0}
    with pytest.warns(NeverCompletedWarning):
        assert translate("false").rejecting == {0}
    assert translate("X X true").n_states == 1
    assert translate("true").aps == ()


def test_formula_objects_and_strings_give_the_same_automaton():
    a = translate(TASKS["phi2"])
    b = translate(parse(TASKS["phi2"]))
    assert a.to_json() == b.to_json()


# --- Errors and limits -------------------------------------------------------------------------------


def test_syntax_error_passes_through():
    with pytest.raises(LTLSyntaxError):
        translate("A1 & & A2")


def test_max_states_guard():
    text = "F a & F b & F c & F d"  # 2**4 states
    assert translate(text).n_states == 16
    with pytest.raises(AutomatonTooLarge, match="max_states=10"):
        translate(text, max_states=10)


def test_too_many_propositions():
    text = " & ".join(f"F p{i}" for i in range(translate_module.MAX_APS + 1))
    with pytest.raises(AutomatonTooLarge) as info:
        translate(text)
    assert isinstance(info.value, UserError)


def test_tableau_guard(monkeypatch):
    monkeypatch.setattr(translate_module, "MAX_TABLEAU_NODES", 2)
    with pytest.raises(AutomatonTooLarge, match="tableau"):
        translate("G F a | G F b | F G c")


def chain(op: str, n: int) -> str:
    """``a op b op c ...`` over n propositions."""
    return f" {op} ".join("abcdefghijklmnop"[:n])


def test_nnf_converts_each_subformula_once_per_polarity():
    """``a <-> b`` is ``(a & b) | (!a & !b)``: each <-> doubles its operands as printed. The NNF of a
    chain shares them, so it has a few nodes per <-> (it was built as a tree: 2**n objects)."""
    from d2spo.ltl import nnf as nnf_module

    f = nnf_module.nnf(parse(chain("<->", 10)))
    objects, todo = {}, [f]
    while todo:
        g = todo.pop()
        if id(g) not in objects:
            objects[id(g)] = g
            todo.extend(g.children())
    assert len(objects) < 100 < 3000 < nnf_module.printed_size(f) <= nnf_module.MAX_NNF_SIZE


@pytest.mark.parametrize("text, limit, builds", [
    (chain("<->", 8), "MAX_DNF_CLAUSES=64", (translate, to_dba, task_automaton)),  # 128 clauses: 50 s before
    (chain("<->", 11), "MAX_NNF_SIZE=4000", (translate, to_dba, task_automaton)),
    (f"X ({chain('<->', 8)})", "MAX_DNF_CLAUSES=64", (translate, task_automaton)),  # the next state's DNF
    (chain("W", 11), "MAX_NNF_SIZE=4000", (translate, task_automaton)),  # !(a W b) is !b U (!a & !b): 6140 nodes
])
def test_chains_of_iff_and_weak_until_beyond_the_limits_are_one_error(text, limit, builds):
    for build in builds:
        with pytest.raises(FormulaTooLarge, match=limit) as info:
            build(text)
        assert isinstance(info.value, UserError) and "simplify the formula" in str(info.value)


def test_chains_within_the_limits_translate():
    """The 7-long chain of <-> (64 clauses) is true where an odd number of its propositions are false."""
    dba = to_dba(chain("<->", 7))
    assert dba.delta[dba.initial][0] in dba.rejecting  # 7 false: odd
    assert dba.delta[dba.initial][1] not in dba.rejecting  # 6 false: even
    assert task_automaton(chain("<->", 7)).n_states == 3
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NeverCompletedWarning)
        assert translate(chain("W", 6)).n_states == 7


# --- The Automaton API -------------------------------------------------------------------------------


def test_arrays():
    aut = translate(TASKS["phi1"])
    feasible = singletons(aut, ["A1", "A2", "A3"])
    arr = aut.arrays(feasible)
    assert isinstance(arr, AutomatonArrays)
    assert arr.delta.dtype == jnp.int32 and arr.delta.shape == (5, 8)
    assert arr.accepting.dtype == jnp.bool_ and arr.rejecting.dtype == jnp.bool_
    assert arr.distance.dtype == jnp.int32 and arr.initial.dtype == jnp.int32 and arr.initial.shape == ()
    assert arr.distance.tolist() == [UNREACHABLE if d is None else d for d in aut.distances(feasible)]
    (reject,) = aut.rejecting
    assert int(arr.distance[reject]) == UNREACHABLE
    assert arr.delta.tolist() == [list(row) for row in aut.delta]


def test_to_json_and_back():
    aut = translate(TASKS["phi2"])
    data = json.loads(json.dumps(aut.to_json()))
    assert set(data) == {"aps", "initial", "accepting", "rejecting", "delta", "distance"}
    assert data["aps"] == ["A1", "A2", "A3", "A4"]
    assert data["accepting"] == sorted(aut.accepting) and data["rejecting"] == sorted(aut.rejecting)
    assert len(data["delta"]) == aut.n_states and all(len(row) == 16 for row in data["delta"])
    assert data["distance"] == aut.distances()
    again = Automaton.from_json(data)
    assert again.to_json() == data


def test_to_dot_and_pretty():
    aut = translate(TASKS["relaxed"])
    dot = aut.to_dot()
    assert dot.startswith("digraph") and dot.rstrip().endswith("}")
    (acc,) = aut.accepting
    assert f"{acc} [shape=doublecircle" in dot
    assert '0 -> 1 [label="A1 & !A2"]' in dot
    text = aut.pretty()
    assert "(!A2 U A1) & F A2" in text and "rejecting" in text and "accepting" in text
    assert "0 -> 1: A1 & !A2" in text


def test_letters_and_guards():
    aut = translate(TASKS["relaxed"])
    assert aut.aps == ("A1", "A2")
    assert aut.letter(["A2"]) == 2 and aut.letter_aps(3) == ("A1", "A2")
    with pytest.raises(ValueError, match="unknown atomic proposition"):
        aut.letter(["A3"])
    assert letters_to_guard([1, 3], ("a", "b")) == "a"
    assert letters_to_guard([0, 1, 2, 3], ("a", "b")) == "true"
    assert letters_to_guard([], ("a", "b")) == "false"
    assert letters_to_guard([1, 2], ("a", "b")) == "(!a & b) | (a & !b)"


@settings(max_examples=40, deadline=None)
@given(st.integers(9, 11), st.data())
def test_guards_over_many_propositions_are_exact(n, data):
    """Beyond EXACT_GUARD_APS propositions the guard's cubes are grown greedily: their union is exactly
    the letters asked for, whatever they are."""
    from d2spo.ltl.automaton import _greedy_cubes

    want = set(data.draw(st.lists(st.integers(0, (1 << n) - 1), min_size=1, max_size=300)))
    if data.draw(st.booleans()):  # a guard of one proposition's letters and a few more, as patrols have
        want |= {a for a in range(1 << n) if a & 1}
    cubes = _greedy_cubes(want, n)
    covered = {a for a in range(1 << n) for care, value in cubes if a & care == value}
    assert covered == want


def test_automaton_checks_its_invariants():
    with pytest.raises(ValueError, match="absorbing"):
        Automaton(
            aps=("a",), initial=0, accepting=frozenset({1}), rejecting=frozenset(), delta=((0, 1), (0, 1))
        )
    with pytest.raises(ValueError, match="rows"):
        Automaton(aps=("a",), initial=0, accepting=frozenset(), rejecting=frozenset(), delta=((0,),))
    with pytest.raises(ValueError, match="sorted"):
        Automaton(aps=("b", "a"), initial=0, accepting=frozenset(), rejecting=frozenset(), delta=((0,) * 4,))


def test_reading_a_word_checks_its_states_and_letters():
    """`aut.status(42)` said 'undecided', `aut.run([-1])` read the letter from the end (every
    proposition true) and accepted, `aut.run([99])` was a bare IndexError."""
    from d2spo.ltl import to_dba, translate

    aut = translate("F (A1 & F A2)")
    dba = to_dba("GF A1 & GF A2")
    for bad in (42, -1, True):
        with pytest.raises(ValueError, match="no state"):
            aut.status(bad)
    for reader in (aut.run, dba.run, lambda w: dba.accepts_lasso([], w)):
        for bad in (-1, 99, 1.0):
            with pytest.raises(ValueError, match="no letter"):
                reader([bad])
    with pytest.raises(TypeError, match=r"write letter\(\['A1'\]\)"):
        aut.letter("A1")
    for build in (translate, to_dba):  # an AttributeError from deep inside, before
        with pytest.raises(TypeError, match="parse expects a str, got NoneType"):
            build(None)
    assert aut.run([aut.letter(["A1"]), aut.letter(["A2"])]) == [0, 1, 2] and aut.status(2) == "accepting"
    assert dba.accepts_lasso([], [dba.letter(["A1"]), dba.letter(["A2"])])
