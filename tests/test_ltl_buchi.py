"""Deterministic Büchi automata (``d2spo.ltl.to_dba``) against the semantics of LTL on lasso words:
the reference ``holds`` of tests/_ltl_reference.py, written from the definitions, shares no code with
``d2spo.ltl.buchi``."""

from __future__ import annotations

import itertools
import warnings

import pytest
from _ltl_reference import encode, formulas, holds, lassos, refutes_dba, syntactic_recurrence
from hypothesis import given, settings
from hypothesis import strategies as st

from d2spo.errors import UserError
from d2spo.ltl import UNREACHABLE, BuchiAutomaton, NeverCompletedWarning, NoDeterministicBuchi, to_dba, translate
from d2spo.ltl.parser import parse
from d2spo.ltl.tasks import BUCHI_SUITE, TASKS


def check_exact(text: str, count: int = 400) -> BuchiAutomaton:
    f = parse(text)
    dba = to_dba(f)
    for prefix, loop in lassos(dba.n_letters, count, seed=len(text)):
        assert dba.accepts_lasso(prefix, loop) == holds(f, dba.aps, prefix, loop), (text, prefix, loop)
    return dba


# --- Hand-written formulas ------------------------------------------------------------------------

STATES = {  # formula -> state count of the automaton that to_dba builds (* = known to be minimal)
    "G !A4 & F A1": 3,  # * need A1 / A1 seen, + rejecting sink
    "G F a & G F b": 2,  # * wait for a / wait for b
    "G F a & G F b & G !c": 3,  # * the same, + rejecting sink
    "G (a -> F b)": 2,  # * no request pending / request pending
    "G !c & F (a & F (b & F d))": 5,  # * need a / b / d, then G !c, + rejecting sink
    "a U b": 3,  # *
    "F a": 2,  # *
    "G a": 2,  # *
    "X a": 4,  # *
    "a R b": 3,  # *
    "a W b": 3,  # *
    "true": 1,  # *
    "false": 1,  # *
    "G F a": 1,  # *
    "F a & G F b": 2,  # *
    "G (a -> X b)": 3,  # * no demand / b needed now, + rejecting sink
    "G F a | G F b": 1,  # * accept on a or b
    "G F a | F G a": 1,  # * the same language as G F a
    "F G a & G a": 2,  # * the same language as G a
    "F G a & G F !a": 1,  # * unsatisfiable
    "a U (b & G F c)": 3,  # * a U b pending / G F c, + rejecting sink
    "F (a & G F b)": 2,  # *
    "G (a -> F b) & G (b -> F a)": 3,  # nothing pending / b pending / a pending
    "(G F a & G F b) | G c": 3,  # c so far / wait for a / wait for b
    "G (a -> (b U c))": 3,  # * no demand / b U c pending, + rejecting sink
    "X X a & G F b": 5,  # * steps 0, 1, 2 / G F b, + rejecting sink
}

NO_DBA = ["F G a", "F G a & G F b", "!(G F a)", "G F a -> G F b", "F (a & X G !b)", "F G a | G F b", "F G a | G b",
          "a U G b"]


@pytest.mark.parametrize("text", sorted(STATES))
def test_exact_on_lassos_and_state_counts(text):
    dba = check_exact(text)
    assert dba.n_states == STATES[text]
    assert dba.initial == 0


@pytest.mark.parametrize("text", NO_DBA)
def test_formulas_without_a_dba_are_refused_in_one_line(text):
    with pytest.raises(NoDeterministicBuchi) as caught:
        to_dba(text)
    message = str(caught.value)
    assert "\n" not in message and "no deterministic Büchi automaton" in message
    assert message.startswith(str(parse(text)))
    assert isinstance(caught.value, UserError)
    assert not syntactic_recurrence(parse(text))
    assert refutes_dba(parse(text), caught.value.witness)


def test_reference_recognises_the_classes():
    assert syntactic_recurrence(parse("G (a -> F b) & G !c"))
    assert syntactic_recurrence(parse("!(F G a)"))
    assert not syntactic_recurrence(parse("F G a"))
    assert not syntactic_recurrence(parse("!(a R G F b)"))
    assert holds(parse("G F a"), ("a",), [0, 0], [0, 1]) and not holds(parse("G F a"), ("a",), [1], [0])
    assert refutes_dba(parse("F G a"), ([], [1], [0])) and not refutes_dba(parse("G F a"), ([], [1], [0]))


@settings(max_examples=250, deadline=None)
@given(data=st.data(), aps=st.sampled_from([("p", "q"), ("p", "q", "r")]))
def test_random_formulas_exact_or_rightly_refused(data, aps):
    f = data.draw(formulas(aps, 3), label="formula")
    try:
        dba = to_dba(f)
    except NoDeterministicBuchi as refusal:
        assert not syntactic_recurrence(f)
        assert refutes_dba(f, refusal.witness)
        return
    letters = st.integers(0, (1 << len(aps)) - 1)
    for _ in range(8):
        prefix = data.draw(st.lists(letters, max_size=3), label="prefix")
        loop = data.draw(st.lists(letters, min_size=1, max_size=3), label="loop")
        read = [encode(a, aps, dba.aps) for a in prefix], [encode(a, aps, dba.aps) for a in loop]
        assert dba.accepts_lasso(*read) == holds(f, aps, prefix, loop)


@settings(max_examples=100, deadline=None)
@given(data=st.data(), aps=st.sampled_from([("p", "q"), ("p", "q", "r")]))
def test_sinks_are_the_monitors_good_and_bad_prefixes(data, aps):
    f = data.draw(formulas(aps, 3), label="formula")
    try:
        dba = to_dba(f)
    except NoDeterministicBuchi:
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NeverCompletedWarning)
        monitor = translate(f)
    assert monitor.aps == dba.aps
    word = data.draw(st.lists(st.integers(0, dba.n_letters - 1), max_size=6), label="word")
    for q, m in zip(dba.run(word), monitor.run(word), strict=True):
        assert dba.is_accepting_sink(q) == (m in monitor.accepting)
        assert (q in dba.rejecting) == (m in monitor.rejecting)


@pytest.mark.parametrize("text", ["F (a & F (b & F c))", "a U b", "(!c U a) & F b", "X (a | b)", "F a & F b"])
def test_co_safe_tasks_end_in_an_accepting_sink(text):
    dba, monitor = to_dba(text), translate(text)
    (sink,) = dba.accepting_sinks
    assert dba.delta[sink] == (sink,) * dba.n_letters and all(dba.accepting[sink])
    assert dba.status(sink) == "accepting sink" and dba.state_formulas[sink] == "true"
    for word in itertools.product(range(dba.n_letters), repeat=3):
        assert (dba.run(word)[-1] == sink) == (monitor.run(word)[-1] in monitor.accepting)


# --- Distances, the API, limits ---------------------------------------------------------------------


def test_distances_to_the_next_accepting_transition():
    dba = to_dba("G F a & G F b")
    none, a, b, both = 0, dba.letter(["a"]), dba.letter(["b"]), dba.letter(["a", "b"])
    singletons = [none, a, b]
    start = dba.initial
    assert dba.distances(singletons)[start] == 2  # a, then b
    assert dba.distances()[start] == 1  # {a, b} at once
    assert dba.distances([none, a])[start] == UNREACHABLE  # b never comes
    after_a = dba.delta[start][a]
    assert dba.distances(singletons)[after_a] == 1 and dba.accepting[after_a][b]
    for letters in ([none, a], singletons, [none, a, b, both]):  # the BFS satisfies its equation
        dist = dba.distances(letters)
        for q in range(dba.n_states):
            options = [1 if dba.accepting[q][x] else dist[dba.delta[q][x]] + 1 for x in letters]
            assert dist[q] == min(min(options), UNREACHABLE)

    task = to_dba("G !A4 & F A1")
    dist = task.distances([0, task.letter(["A1"]), task.letter(["A4"])])
    assert dist[task.initial] == 2  # A1, then one more step without A4
    assert dist[task.delta[task.initial][task.letter(["A1"])]] == 1
    assert [dist[q] for q in task.rejecting] == [UNREACHABLE]


def test_a_buchi_tasks_json_and_dot_carry_its_accepting_visits():
    """`d2spo ltl patrol2 --json` once showed no accepting state and nothing else: a reader could not
    tell a patrol from a task nothing accepts. Its visits and whether it is a recurrence are in it,
    and round-trip; `--dot` draws the visits bold, as the DBA's accepting transitions."""
    import json

    from d2spo.ltl import task_automaton
    from d2spo.ltl.buchi_task import BuchiTask

    patrol = task_automaton("GF A1 & GF A3 & G !A4")
    data = json.loads(json.dumps(patrol.to_json()))
    assert data["accepting"] == [] and data["recurrence"] is True
    assert data["visits"] == [[a for a, v in enumerate(row) if v] for row in patrol.visits]
    assert data["visits"][patrol.initial] == [patrol.letter(["A1", "A3"])]  # both at once: a visit at once
    again = BuchiTask.from_json(data)
    assert again.visits == patrol.visits and again.to_json() == data
    never = task_automaton("G !A4 & F A3")  # completes, with no visit
    assert never.to_json()["recurrence"] is False and never.to_json()["accepting"]
    dot = patrol.to_dot()
    bold = [ln for ln in dot.splitlines() if "style=bold" in ln]
    assert len(bold) == 2 and all("●" in ln for ln in bold) and "1 -> 0" in bold[1]
    assert dot.count(" -> ") == 1 + sum(len({(t, v) for t, v in zip(row, vis)})
                                        for row, vis in zip(patrol.delta, patrol.visits))
    respond = task_automaton("G (A1 -> F A2) & G F A1")  # every state drawn, as Automaton.to_dot does
    assert all(f"  {q} [shape=" in respond.to_dot() for q in range(respond.n_states))


def test_api_and_rendering():
    dba = to_dba("G (A1 -> F A2)")
    assert dba.aps == ("A1", "A2") and dba.n_letters == 4 and not dba.rejecting and not dba.accepting_sinks
    assert dba.state_formulas == ("G (!A1 | F A2)", "F A2 & G (!A1 | F A2)")
    assert to_dba("G !A4 & F A1").state_formulas == ("F A1 & G !A4", "G !A4", "false")
    assert "acceptance on transitions" in dba.pretty() and "(accepting)" in dba.pretty()
    assert dba.to_dot().startswith("digraph") and "style=bold" in dba.to_dot()
    assert dba.accepts_lasso([], [dba.letter(["A1"]), dba.letter(["A2"])])
    assert not dba.accepts_lasso([dba.letter(["A1"])], [0])
    with pytest.raises(ValueError, match="loop"):
        dba.accepts_lasso([0], [])
    with pytest.raises(ValueError, match="rejecting"):
        BuchiAutomaton(dba.aps, 0, dba.delta, dba.accepting, frozenset({0}))
    with pytest.raises(ValueError, match="unknown atomic proposition"):
        dba.letter(["A3"])


NAMED = ["G !A4 & F A1", "G F A1 & G F A3 & G !A4", "G (A1 -> F A2)", "G !purple & F (red & F (green & F yellow))",
         "G F blue & G F green & G F yellow & G !magenta"]


@pytest.mark.parametrize("text", NAMED)
def test_named_tasks_translate_fast(text, monkeypatch):
    """Fast as a bound on the work, not a clock: each named task translates within the NBA budget
    ``buchi.MAX_NBA_STEPS`` documents for the suite's tasks (300 steps; the default is 1e6)."""
    import sys

    monkeypatch.setattr(sys.modules["d2spo.ltl.buchi"], "MAX_NBA_STEPS", 300)
    to_dba(text)
    dba = check_exact(text, count=300)
    assert not dba.accepting_sinks and len(dba.rejecting) == (1 if "!" in text else 0)


def test_limits():
    with pytest.raises(UserError, match="max_states"):
        to_dba("G F a & G F b & G F c & F G d | G F e", max_states=3)
    with pytest.raises(UserError, match="propositions"):
        to_dba(" & ".join(f"G F p{i}" for i in range(13)))


def test_the_nba_work_is_bounded(monkeypatch):
    """A tableau node can have exponentially many branches: ``a R b R c …`` of 16 operands took 18 s
    (``G F`` nested 16 deep ran for minutes, with no limit to stop it); ``MAX_NBA_STEPS`` refuses them
    in one line. The operands of a product share the bound (the default's refusals take seconds:
    a smaller bound here)."""
    import sys

    buchi = sys.modules["d2spo.ltl.buchi"]
    monkeypatch.setattr(buchi, "MAX_NBA_STEPS", 100)  # one ordered visit of three needs 75
    assert to_dba("F (a & F (b & F c))").n_states == 4
    with pytest.raises(UserError, match="MAX_NBA_STEPS=100"):
        to_dba("F (a & F (b & F c)) & F (d & F (e & F f))")


@pytest.mark.parametrize("name", BUCHI_SUITE)
def test_the_buchi_suite_is_exact_or_refused(name):
    """Each task of ``tasks.BUCHI_SUITE`` is exact on lassos, or (``persist``, F G) refused in one line."""
    text = TASKS[name]
    if name == "persist":
        with pytest.raises(NoDeterministicBuchi):
            to_dba(text)
        return
    check_exact(text, count=400)


def test_a_patrol_too_large_for_the_monitor_is_built_as_a_dba(monkeypatch):
    """The monitor's satisfiability check gives up on patrols of 9 or more areas (MAX_TABLEAU_STEPS),
    where ``to_dba`` still builds one state per area; ``task_automaton`` then takes the DBA. Here the
    bound is made tiny so that a 3-area patrol stands in for a 9-area one. A formula neither can
    build is still refused with the monitor's reason."""
    import sys

    from d2spo.ltl.automaton import AutomatonTooLarge
    from d2spo.ltl.buchi_task import is_recurrence, task_automaton

    tr = sys.modules["d2spo.ltl.translate"]  # the module (d2spo.ltl.translate is also the function's name)

    monkeypatch.setattr(tr, "MAX_TABLEAU_STEPS", 50)
    with pytest.raises(AutomatonTooLarge):
        tr.translate("GF a & GF b & GF c")
    task = task_automaton("GF a & GF b & GF c")
    assert task.n_states == 3 and is_recurrence(task)
    with pytest.raises(AutomatonTooLarge, match="MAX_TABLEAU_STEPS=50"):
        task_automaton("F (a & F (b & F c)) & F G a")  # no DBA either: the monitor's reason is kept


def test_the_co_safe_form_docs_give_a_never_part_is_equivalent_where_areas_overlap():
    """docs/ltl.md said `G !A4 & F A1` runs as `!A4 U A1`, which accepts entering A1 inside A4 (the
    letter {A1, A4}); the form it gives now completes and rejects after exactly the same prefixes,
    over every letter."""
    import re
    from pathlib import Path

    from d2spo.ltl import task_automaton

    text = (Path(__file__).resolve().parents[1] / "docs" / "ltl.md").read_text()
    forms = re.findall(r"`G !A4 & F A1`, has none, and runs exactly as its co-safe form `([^`]+)`", text)
    assert forms == ["!A4 U (A1 & !A4)"]

    def same_status(form: str) -> bool:
        never, monitor = task_automaton("G !A4 & F A1"), translate(form)
        assert never.aps == monitor.aps == ("A1", "A4")
        seen, todo = set(), [(never.initial, monitor.initial)]
        while todo:  # the product, from the start, over every letter
            q, m = todo.pop()
            if (never.status(q) == "completed") != (m in monitor.accepting) or \
                    (q in never.rejecting) != (m in monitor.rejecting):
                return False
            seen.add((q, m))
            todo.extend(t for a in range(4) if (t := (never.delta[q][a], monitor.delta[m][a])) not in seen)
        return True

    assert same_status(forms[0]) and not same_status("!A4 U A1")
