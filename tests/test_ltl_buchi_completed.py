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
