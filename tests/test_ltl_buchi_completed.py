"""Where an episode of a Büchi task may end (``BuchiAutomaton.completed_states``: only a "never"
part is left), checked both ways against tests/_ltl_reference.py's independent lasso evaluator."""

from __future__ import annotations

import pytest
from _ltl_reference import formulas, holds, lassos
from hypothesis import given, settings
from hypothesis import strategies as st

from d2spo.ltl import BuchiAutomaton, NoDeterministicBuchi, to_dba
from d2spo.ltl.formula import Formula
from d2spo.ltl.parser import parse


def _words_to(dba: BuchiAutomaton, start: int, allowed) -> dict[int, list[int]]:
    """Breadth-first from ``start``: a shortest word to each state, over the transitions (q, a) that
    ``allowed(q, a)`` admits."""
    words, queue = {start: []}, [start]
    for q in queue:
        for a in range(dba.n_letters):
            t = dba.delta[q][a]
            if allowed(q, a) and t not in words:
                words[t] = words[q] + [a]
                queue.append(t)
    return words


def check_completed_states(f: Formula, dba: BuchiAutomaton, aps: tuple[str, ...]) -> None:
    """Against the evaluator: from a completed state every lasso that stays out of the rejecting
    sink satisfies the formula; from any other live state a lasso that stays out of it and ends in
    a cycle of non-accepting transitions does not."""
    done, reach = dba.completed_states(), _words_to(dba, dba.initial, lambda q, a: True)
    assert dba.accepting_sinks <= done and not done & dba.rejecting
    live = lambda q, a: q not in dba.rejecting and dba.delta[q][a] not in dba.rejecting  # noqa: E731
    for q, u0 in reach.items():
        if q in dba.rejecting:
            continue
        if q in done:
            for u, v in lassos(dba.n_letters, 60, seed=q):
                states = dba.run(u + v * (dba.n_states + 1), start=q)
                if not set(states) & dba.rejecting:
                    assert holds(f, aps, u0 + u, v), (str(f), q, u, v)
            continue
        # a non-accepting cycle reachable from q through live states: the lasso that runs it forever
        plain = lambda p, a: live(p, a) and not dba.accepting[p][a]  # noqa: E731
        witness = None
        for b, path in _words_to(dba, q, live).items():
            back = {dba.delta[b][a]: a for a in range(dba.n_letters) if plain(b, a)}
            for t, a in back.items():
                loop = _words_to(dba, t, plain).get(b)
                if loop is not None:
                    witness = (u0 + path, [a] + loop)
                    break
            if witness:
                break
        assert witness is not None, (str(f), q)
        assert not set(dba.run(witness[0] + witness[1] * 2)) & dba.rejecting
        assert not holds(f, aps, *witness), (str(f), q, witness)


@pytest.mark.parametrize("text, done", [("G !A4 & F A1", 1), ("G F A1 & G F A3 & G !A4", 0), ("G (A1 -> F A2)", 0),
                                        ("F (A1 & F A2)", 1), ("G !A4", 1), ("a U b", 1), ("G F a | F b", 1)])
def test_completed_states_leave_only_a_never_part(text, done):
    f = parse(text)
    dba = to_dba(f)
    assert len(dba.completed_states()) == done
    check_completed_states(f, dba, dba.aps)


@settings(max_examples=80, deadline=None)
@given(data=st.data(), aps=st.sampled_from([("p", "q"), ("p", "q", "r")]))
def test_completed_states_on_random_formulas(data, aps):
    f = data.draw(formulas(aps, 3), label="formula")
    try:
        dba = to_dba(f)
    except NoDeterministicBuchi:
        return
    check_completed_states(f, dba, dba.aps)


# --- A task that completes, satisfied by a run that never completes it (``endless_branch``) ---------


def completes_on(monitor, u: list[int], v: list[int]) -> bool:
    """Whether the monitor reaches an accepting state on u·v^ω (within |u| + n·|v| letters: by then
    the state at the loop's start has repeated)."""
    return any(q in monitor.accepting for q in monitor.run(u + v * (monitor.n_states + 1)))


def check_endless_branch(f: Formula) -> None:
    """Against the reference evaluator: not flagged, every short or random lasso word that satisfies
    ``f`` completes it; flagged, some word does not (searched among the same words)."""
    import warnings

    from d2spo.ltl import translate
    from d2spo.ltl.buchi_task import endless_branch
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        monitor = translate(f)
    if not monitor.accepting:
        assert not endless_branch(str(f))
        return
    aps = monitor.aps
    endless = [(u, v) for u, v in lassos(monitor.n_letters, 300, seed=7)
               if holds(f, aps, u, v) and not completes_on(monitor, u, v)]
    if endless_branch(str(f)):
        assert endless, str(f)
    else:
        assert not endless, (str(f), endless[:3])


@pytest.mark.parametrize("text, flagged", [("G F A1 & G F A3 | F A2", True), ("F A1 | G !A2", True),
                                           ("F A1 | G A2", True), ("F (A1 & F A2)", False), ("A1 U A2", False),
                                           ("(!A3 U A2) & (!A2 U A1) & F A1 & F A3", False), ("F A1 | G F A2", True),
                                           ("F (A1 | G A2)", True)])
def test_endless_branch_on_named_formulas(text, flagged):
    from d2spo.ltl.buchi_task import endless_branch

    assert endless_branch(text) == flagged
    check_endless_branch(parse(text))


@settings(max_examples=80, deadline=None)
@given(data=st.data(), aps=st.sampled_from([("p", "q"), ("p", "q", "r")]))
def test_endless_branch_on_random_formulas(data, aps):
    check_endless_branch(data.draw(formulas(aps, 3), label="formula"))
