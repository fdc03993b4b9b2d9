"""Parser and printer of LTL formulas: precedence, associativity, round trip, errors."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from d2spo.errors import LTLSyntaxError, UserError
from d2spo.ltl import parse
from d2spo.ltl.formula import (
    FALSE,
    TRUE,
    Always,
    And,
    Eventually,
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
from d2spo.ltl.parser import run_together

a, b, c, d = Prop("a"), Prop("b"), Prop("c"), Prop("d")


@pytest.mark.parametrize(
    "text, tree",
    [
        ("a", a),
        ("true", TRUE),
        ("false", FALSE),
        ("A1", Prop("A1")),
        ("goal_2", Prop("goal_2")),
        ("XA1", Prop("XA1")),  # names are read greedily; "X A1" is next
        ("X A1", Next(Prop("A1"))),
        ("X(A1)", Next(Prop("A1"))),
        # a word of X, F and G only is that chain of operators, as LTL is usually written
        ("GF a", Always(Eventually(a))),
        ("FG(a)", Eventually(Always(a))),
        ("GFX a & XX b", And(Always(Eventually(Next(a))), Next(Next(b)))),
        ("GFa", Prop("GFa")),  # a name: it has other letters
        # unary binds tightest
        ("!a & b", And(Not(a), b)),
        ("F a U b", Until(Eventually(a), b)),
        ("G a R b", Release(Always(a), b)),
        ("X a W b", WeakUntil(Next(a), b)),
        ("!X F G a", Not(Next(Eventually(Always(a))))),
        # U/R/W bind tighter than &, and associate to the right (with each other too)
        ("a & b U c", And(a, Until(b, c))),
        ("a U b & c", And(Until(a, b), c)),
        ("a U b U c", Until(a, Until(b, c))),
        ("a U b R c", Until(a, Release(b, c))),
        ("a R b W c", Release(a, WeakUntil(b, c))),
        ("(a U b) U c", Until(Until(a, b), c)),
        # & tighter than |; both left-associative
        ("a | b & c", Or(a, And(b, c))),
        ("a & b | c", Or(And(a, b), c)),
        ("a & b & c", And(And(a, b), c)),
        ("a | b | c", Or(Or(a, b), c)),
        # | tighter than ->, which is right-associative
        ("a | b -> c", Implies(Or(a, b), c)),
        ("a -> b -> c", Implies(a, Implies(b, c))),
        ("(a -> b) -> c", Implies(Implies(a, b), c)),
        # -> tighter than <->, which is left-associative
        ("a -> b <-> c", Iff(Implies(a, b), c)),
        ("a <-> b -> c", Iff(a, Implies(b, c))),
        ("a <-> b <-> c", Iff(Iff(a, b), c)),
        # parentheses
        ("!(a & b)", Not(And(a, b))),
        ("F (a & X (F b))", Eventually(And(a, Next(Eventually(b))))),
        ("((a))", a),
        # alternates
        ("~a && b", And(Not(a), b)),
        ("a || b", Or(a, b)),
        ("[]<>a", Always(Eventually(a))),
        ("a => b", Implies(a, b)),
        ("a <=> b", Iff(a, b)),
        ("a<->b", Iff(a, b)),
        ("<>a|[]b", Or(Eventually(a), Always(b))),
        # the textbook's Unicode symbols
        ("□◇a ∧ □¬b", And(Always(Eventually(a)), Always(Not(b)))),
        ("◻◊a ∨ ○b", Or(Always(Eventually(a)), Next(b))),
        ("◯a→b⇒c", Implies(Next(a), Implies(b, c))),
        ("a ↔ b ⇔ c", Iff(Iff(a, b), c)),
        ("⊤ ∧ ¬⊥", And(TRUE, Not(FALSE))),
        ("¬a U b", Until(Not(a), b)),
        ("⋄a ⟶ b ⟹ c", Implies(Eventually(a), Implies(b, c))),
        ("a ⟷ b ⟺ c", Iff(Iff(a, b), c)),
    ],
)
def test_precedence_and_associativity(text, tree):
    assert parse(text) == tree


def test_paper_phi2_parses_as_intended():
    f = parse("((A1 & X A3) | (A3 & X A1)) & X(F(A4 & X(F A2)))")
    A1, A2, A3, A4 = (Prop(f"A{i}") for i in range(1, 5))
    assert f == And(
        Or(And(A1, Next(A3)), And(A3, Next(A1))),
        Next(Eventually(And(A4, Next(Eventually(A2))))),
    )
    assert f.aps() == {"A1", "A2", "A3", "A4"}


@pytest.mark.parametrize(
    "text, printed",
    [
        ("(!A3 U A2) & (!A2 U A1) & F A1", "(!A3 U A2) & (!A2 U A1) & F A1"),
        ("a&b|c&d", "(a & b) | (c & d)"),
        ("a U (b U c)", "a U b U c"),
        ("(a U b) U c", "(a U b) U c"),
        ("a -> (b -> c)", "a -> b -> c"),
        ("!(X a)", "!X a"),
        ("G(a -> F b)", "G (a -> F b)"),
        ("[]<>a", "G F a"),
    ],
)
def test_printing(text, printed):
    assert str(parse(text)) == printed


def test_a_node_is_printed_once_however_often_it_is_shared(monkeypatch):
    """Sorting a tableau's branches prints their formulas again and again (``Tableau.expand``), and
    ``nnf`` shares sub-formulas: each node keeps its string, so a formula is printed once."""
    import d2spo.ltl.formula as formula

    calls = []
    to_string = formula._to_string
    monkeypatch.setattr(formula, "_to_string", lambda f: calls.append(f) or to_string(f))
    p, q, r, s = (Prop(name) for name in "pqrs")  # new nodes, printed by no other test
    shared = Until(p, Or(q, r))
    f = And(Release(shared, s), Not(shared))
    assert str(f) == "((p U (q | r)) R s) & !(p U (q | r))"
    assert len(calls) == 9  # And, Release, Not, s, and the 5 nodes of shared once
    assert str(f) == str(And(f.left, f.right)) and len(calls) == 10  # the new And alone


@pytest.mark.timeout(60)
def test_a_shared_sub_formula_is_hashed_once():
    """A node keeps its hash; the dataclass's own hash recursed through every child on every call,
    2**64 nodes here (the NNF of ``a <-> b <-> ...`` doubles likewise with each <->)."""
    f = a
    for _ in range(64):
        f = And(f, f)
    assert hash(And(f.left, f.right)) == hash(f) and f in {f} and And(f.left, f.left) == f


@pytest.mark.parametrize("names, labels, apart", [
    (["Fb", "GFa", "XA1", "FFb", "G_2"], None, {"Fb": "F b", "GFa": "G F a", "XA1": "X A1", "FFb": "F F b"}),
    (["A1", "F1", "Xtrue", "XU", "Fx1"], None, {"Fx1": "F x1"}),  # no name after the F, a keyword after the X
    # words are not operators run into a name: a lab's rooms (`Goal`, `Fridge`, `Xray`) stay quiet
    (["Goal", "Fridge", "Xray", "Garage"], None, {}),
    # with a layout's labels: operators run into a label, whatever its length, unless itself a label
    (["GFdock", "Fridge", "Fb", "Goal", "Xa"], ["dock", "ridge", "Fb", "b"],
     {"GFdock": "G F dock", "Fridge": "F ridge", "Xa": "X a"}),
])
def test_run_together_lists_names_that_read_as_operators_and_a_name(names, labels, apart):
    assert run_together(names, labels) == apart


# Random syntax trees, printed and parsed back.
_leaves = st.sampled_from([a, b, Prop("A1"), Prop("goal_2"), TRUE, FALSE])
_trees = st.recursive(
    _leaves,
    lambda sub: st.one_of(
        st.builds(Not, sub),
        st.builds(Next, sub),
        st.builds(Eventually, sub),
        st.builds(Always, sub),
        *(st.builds(op, sub, sub) for op in (And, Or, Implies, Iff, Until, Release, WeakUntil)),
    ),
    max_leaves=12,
)


@settings(max_examples=300, deadline=None)
@given(_trees)
def test_round_trip(tree):
    text = str(tree)
    assert parse(text) == tree
    assert str(parse(text)) == text


@pytest.mark.parametrize(
    "text, column, expected",
    [
        ("A1 & & A2", 6, "a formula"),
        ("F (A1", 6, "')'"),
        ("A1 $ A2", 4, "unknown character '$'"),
        ("", 1, "a formula"),
        ("   ", 4, "a formula"),
        ("A1 A2", 4, "a binary operator or end of formula"),
        ("()", 2, "a formula"),
        ("a U", 4, "a formula"),
        ("a)", 2, "a binary operator or end of formula"),
        ("[ a", 1, "unknown character '['"),
        ("a <- b", 3, "unknown character '<'"),
        ("A1 & Ä", 6, "unknown character 'Ä'"),
        ("□ ∧ A1", 3, "a formula"),  # a Unicode operator's column is its character's
        ("A1 ≠ A2", 4, "unknown character '≠'"),
        ("F A₁", 4, "unknown character '₁' (write the digit 1: names are of letters, digits and _)"),
        ("a ⊃ b", 3, "unknown character '⊃' (write ->)"),
        ("F dock-west", 7, "'dock-west' is no proposition name: a formula names an area by its label"),
        ("(a & (b | c)", 13, "')' to close the '(' at column 1"),
    ],
)
def test_syntax_errors(text, column, expected):
    with pytest.raises(LTLSyntaxError) as info:
        parse(text)
    err = info.value
    assert isinstance(err, UserError)
    assert err.column == column
    assert expected in err.expected
    assert err.formula == text
    caret_line = err.pretty().splitlines()[-1]
    assert caret_line == "  " + " " * (column - 1) + "^"


def test_error_pretty_shows_the_formula_and_a_caret_under_the_token():
    with pytest.raises(LTLSyntaxError) as info:
        parse("A1 & & A2")
    assert info.value.pretty().splitlines() == [
        "LTL syntax error at column 6: expected a formula (a proposition, true, false, '(' or one of "
        "! X F G), found '&'",
        "  A1 & & A2",
        "       ^",
    ]


def test_parse_rejects_non_strings():
    with pytest.raises(TypeError):
        parse(None)  # type: ignore[arg-type]

