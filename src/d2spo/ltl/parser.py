"""Parser for LTL formulas (paper Sec. II-B), by recursive descent.

Grammar, loosest binding first (see docs/ltl.md)::

    iff     := implies ('<->' implies)*            left-associative
    implies := or ('->' implies)?                  right-associative
    or      := and ('|' and)*
    and     := binary ('&' binary)*
    binary  := unary (('U' | 'R' | 'W') binary)?   right-associative
    unary   := ('!' | 'X' | 'F' | 'G') unary | atom
    atom    := 'true' | 'false' | NAME | '(' iff ')'

Accepted alternates: ``~`` for ``!``, ``&&`` for ``&``, ``||`` for ``|``, ``=>`` for ``->``,
``<=>`` for ``<->``, ``[]`` for ``G``, ``<>`` for ``F``, and the textbook's symbols: ``□ ◻`` for
``G``, ``◇ ◊ ⋄`` for ``F``, ``○ ◯`` for ``X``, ``¬ ∧ ∨`` for ``! & |``, ``→ ⇒ ⟶ ⟹`` for ``->``,
``↔ ⇔ ⟷ ⟺`` for ``<->``, ``⊤ ⊥`` for ``true false``. A NAME is ``[A-Za-z_][A-Za-z0-9_]*``
other than the keywords ``true false X F G U R W`` and the words made of the letters X, F and G only,
which are chains of those operators (``GF a`` is ``G F a``, ``FG a`` is ``F G a``); names are read
greedily, so ``XA1`` is the proposition ``XA1`` while ``X A1`` and ``X(A1)`` are "next A1".
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import NamedTuple

from d2spo.errors import LTLSyntaxError
from d2spo.ltl.formula import (
    FALSE,
    MAX_DEPTH,
    MAX_SIZE,
    TRUE,
    Always,
    And,
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
)

_OPERAND = "a formula (a proposition, true, false, '(' or one of ! X F G)"
_UNARY_LETTERS = {"X", "F", "G"}
"""A word of these letters only (``GF``, ``FG``, ``XX``) is that chain of unary operators."""
_KEYWORDS = {"true": "true", "false": "false", "X": "X", "F": "F", "G": "G", "U": "U", "R": "R", "W": "W"}
# Longest symbols first, so that "&&" is not read as "&" "&" and "<->" not as "<" "->".
_SYMBOLS = [
    ("<->", "<->"), ("<=>", "<->"), ("->", "->"), ("=>", "->"), ("&&", "&"), ("||", "|"),
    ("[]", "G"), ("<>", "F"), ("!", "!"), ("~", "!"), ("&", "&"), ("|", "|"), ("(", "("), (")", ")"),
    ("\u25a1", "G"), ("\u25fb", "G"), ("\u25c7", "F"), ("\u25ca", "F"), ("\u25cb", "X"), ("\u25ef", "X"),
    ("\u00ac", "!"), ("\u2227", "&"), ("\u2228", "|"),
    ("\u2192", "->"), ("\u21d2", "->"), ("\u2194", "<->"), ("\u21d4", "<->"), ("\u22a4", "true"), ("\u22a5", "false"),
    ("\u22c4", "F"), ("\u27f6", "->"), ("\u27f9", "->"), ("\u27f7", "<->"), ("\u27fa", "<->"),
]  # fmt: skip
"""The Unicode ones: □ ◻ ◇ ◊ ⋄ ○ ◯ ¬ ∧ ∨ → ⇒ ⟶ ⟹ ↔ ⇔ ⟷ ⟺ ⊤ ⊥ (written as escapes so that no editor
mistakes them)."""
_HINTS = {"\u2283": "->", "\U0001d4b0": "U", "\U0001d4b2": "W", "\U0001d445": "R", "\u223c": "!"}
"""Symbols some papers use, not accepted (⊃ is also "superset"; the script letters are many): the
ASCII to write instead, named in the error."""
_SUBSCRIPTS = str.maketrans("\u2080\u2081\u2082\u2083\u2084\u2085\u2086\u2087\u2088\u2089", "0123456789")
_UNARY = {"!": Not, "X": Next, "F": Eventually, "G": Always}
_TEMPORAL = {"U": Until, "R": Release, "W": WeakUntil}


class _Token(NamedTuple):
    kind: str  # an operator symbol, "(", ")", "true", "false", "name" or "end"
    text: str
    column: int  # 1-based


def _tokenize(text: str) -> list[_Token]:
    tokens = []
    i = 0
    while i < len(text):
        c = text[i]
        if c.isspace():
            i += 1
            continue
        if c.isascii() and (c.isalpha() or c == "_"):
            j = i + 1
            while j < len(text) and text[j].isascii() and (text[j].isalnum() or text[j] == "_"):
                j += 1
            word = text[i:j]
            if len(word) > 1 and set(word) <= _UNARY_LETTERS:  # "GF a", "FG a", "XX a": one operator per letter
                tokens.extend(_Token(op, op, i + 1 + k) for k, op in enumerate(word))
            else:
                tokens.append(_Token(_KEYWORDS.get(word, "name"), word, i + 1))
            i = j
            continue
        for symbol, kind in _SYMBOLS:
            if text.startswith(symbol, i):
                tokens.append(_Token(kind, symbol, i + 1))
                i += len(symbol)
                break
        else:
            expected = f"a proposition, constant, operator or parenthesis, found unknown character {c!r}"
            if c in _HINTS:
                expected += f" (write {_HINTS[c]})"
            elif c.translate(_SUBSCRIPTS) != c:  # A₁: a name is of ASCII letters, digits and _
                expected += f" (write the digit {c.translate(_SUBSCRIPTS)}: names are of letters, digits and _)"
            if c in "-." and tokens and tokens[-1].kind == "name" and tokens[-1].column + len(tokens[-1].text) == i + 1:
                # `F dock-west`: an area's name, which a formula names by its label (docs/layouts.md)
                word = re.match(r"[\w.-]+", text[tokens[-1].column - 1:]).group()
                expected += (f" ({word!r} is no proposition name: a formula names an area by its label, of "
                             "letters, digits and _)")
            raise LTLSyntaxError(text, i + 1, expected)
    tokens.append(_Token("end", "", len(text) + 1))
    return tokens


class _Parser:
    def __init__(self, text: str):
        self.text = text
        self.tokens = _tokenize(text)
        if len(self.tokens) > MAX_SIZE + 1:  # a token makes at most one node, but for parentheses
            raise FormulaTooLarge(f"the formula has {len(self.tokens) - 1} symbols (names, operators "
                                  f"and parentheses); at most MAX_SIZE={MAX_SIZE} are supported")
        self.pos = 0
        self.depth = 0

    def nest(self, step: int) -> None:
        """Enter (+1) or leave (-1) a nested construct; refuse nesting deeper than ``MAX_DEPTH``."""
        self.depth += step
        if self.depth > MAX_DEPTH:
            raise FormulaTooLarge(f"the formula is nested more than MAX_DEPTH={MAX_DEPTH} levels deep (each "
                                  "operator and each pair of parentheses is a level); simplify it")

    def peek(self) -> _Token:
        return self.tokens[self.pos]

    def take(self) -> _Token:
        token = self.tokens[self.pos]
        self.pos += 1
        return token

    def fail(self, expected: str) -> LTLSyntaxError:
        token = self.peek()
        found = "end of formula" if token.kind == "end" else repr(token.text)
        return LTLSyntaxError(self.text, token.column, f"{expected}, found {found}")

    def formula(self) -> Formula:
        f = self.iff()
        if self.peek().kind != "end":
            raise self.fail("a binary operator or end of formula")
        return f

    def iff(self) -> Formula:
        f = self.implies()
        while self.peek().kind == "<->":
            self.take()
            f = Iff(f, self.implies())
        return f

    def implies(self) -> Formula:
        f = self.disjunction()
        if self.peek().kind == "->":
            self.take()
            self.nest(1)
            right = self.implies()
            self.nest(-1)
            return Implies(f, right)
        return f

    def disjunction(self) -> Formula:
        f = self.conjunction()
        while self.peek().kind == "|":
            self.take()
            f = Or(f, self.conjunction())
        return f

    def conjunction(self) -> Formula:
        f = self.binary()
        while self.peek().kind == "&":
            self.take()
            f = And(f, self.binary())
        return f

    def binary(self) -> Formula:
        f = self.unary()
        kind = self.peek().kind
        if kind in _TEMPORAL:
            self.take()
            self.nest(1)
            right = self.binary()
            self.nest(-1)
            return _TEMPORAL[kind](f, right)
        return f

    def unary(self) -> Formula:
        kind = self.peek().kind
        if kind in _UNARY:
            self.take()
            self.nest(1)
            arg = self.unary()
            self.nest(-1)
            return _UNARY[kind](arg)
        return self.atom()

    def atom(self) -> Formula:
        token = self.peek()
        if token.kind == "true":
            self.take()
            return TRUE
        if token.kind == "false":
            self.take()
            return FALSE
        if token.kind == "name":
            self.take()
            return Prop(token.text)
        if token.kind == "(":
            self.take()
            self.nest(1)
            f = self.iff()
            self.nest(-1)
            if self.peek().kind != ")":
                raise self.fail(f"')' to close the '(' at column {token.column}")
            self.take()
            return f
        raise self.fail(_OPERAND)


def run_together(names: Iterable[str], labels: Iterable[str] | None = None) -> dict[str, str]:
    """The names among ``names`` that read as unary operators run into a name, each with how it reads
    with the operators apart: ``Fb`` -> ``F b``, ``GFa`` -> ``G F a``, ``XA1`` -> ``X A1``. The parser
    reads names greedily, so each is one proposition. A name is listed when what follows its
    operator letters is a letter and digits only (``Fb``, ``XA1``, ``Fx1``: ``Goal``, ``Fridge`` or
    ``Xray`` are words, not ``G oal``) or, given ``labels`` (a layout's), one of them (``GFdock``);
    never when it is itself one of ``labels`` (an area may be labelled ``Fb``). ``F1`` (no name after
    the F) is never listed."""
    labels = set(labels or ())
    out = {}
    for name in names:
        rest = name.lstrip("".join(_UNARY_LETTERS))
        meant = rest in labels or re.fullmatch(r"[A-Za-z][0-9]*", rest)
        if rest != name and meant and rest not in _KEYWORDS and name not in labels:
            out[name] = " ".join([*name[:len(name) - len(rest)], rest])
    return out


def parse(text: str) -> Formula:
    """Parse an LTL formula; raises ``LTLSyntaxError`` (1-based column, what was expected)."""
    if not isinstance(text, str):
        raise TypeError(f"parse expects a str, got {type(text).__name__}")
    f = _Parser(text).formula()
    check_size(f)  # chains of & | <-> nest without recursing in the parser
    return f
