"""LTL formulas as an immutable syntax tree (paper Sec. II-B).

Every node is a frozen dataclass, so formulas are hashable, compare structurally and can be used as
dictionary keys. ``str(f)`` prints the formula in the syntax that ``d2spo.ltl.parse`` reads, with
parentheses where the precedences need them and, for readability, around every binary operand of
a different binary operator (``(a & b) | c``, ``(a U b) & c``), so ``parse(str(f)) == f``.

Precedence, tightest first: unary ``! X F G``; ``U R W`` (right-associative); ``&``; ``|``;
``->`` (right-associative); ``<->`` (left-associative).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from d2spo.errors import UserError

MAX_DEPTH = 100
"""Deepest syntax tree accepted (``X X X a`` has depth 4; a chain ``a | b | c`` of n operands
nests n - 1 binary nodes). Every pass over a formula (parsing, printing, hashing, translating)
recurses once per level, so this keeps them far from Python's recursion limit; the named tasks
have depth 8 at most."""
MAX_SIZE = 1000
"""Most nodes (operators, propositions, constants) in a formula."""


class FormulaTooLarge(UserError):
    """A formula is nested deeper than ``MAX_DEPTH`` or has more than ``MAX_SIZE`` nodes."""


def check_size(f: Formula) -> None:
    """FormulaTooLarge unless ``f`` is within ``MAX_DEPTH`` and ``MAX_SIZE`` (iterative: any input)."""
    size, stack = 0, [(f, 1)]
    while stack:
        node, depth = stack.pop()
        size += 1
        if depth > MAX_DEPTH:
            raise FormulaTooLarge(f"the formula is nested more than MAX_DEPTH={MAX_DEPTH} levels deep (a chain of "
                                  "n binary operators counts n levels); simplify it")
        if size > MAX_SIZE:
            raise FormulaTooLarge(f"the formula has more than MAX_SIZE={MAX_SIZE} operators and propositions; "
                                  "simplify it")
        stack.extend((c, depth + 1) for c in node.children())


class Formula:
    """Base class of all LTL syntax-tree nodes."""

    __slots__ = ("_hash", "_text")  # computed once per node (``_node``)

    def children(self) -> tuple[Formula, ...]:
        """Direct sub-formulas, left to right."""
        return ()

    def aps(self) -> frozenset[str]:
        """Names of the atomic propositions that occur in the formula."""
        found: set[str] = set()
        stack: list[Formula] = [self]
        while stack:
            node = stack.pop()
            if isinstance(node, Prop):
                found.add(node.name)
            stack.extend(node.children())
        return frozenset(found)

    def __str__(self) -> str:
        return _once(self, "_text", _to_string)


def _once(node: Formula, slot: str, compute) -> Any:
    """``compute(node)``, kept in the node's ``slot`` (``Formula.__slots__``) after the first call: a
    frozen node is never changed, so what is derived from it once holds for good."""
    try:
        return getattr(node, slot)
    except AttributeError:
        object.__setattr__(node, slot, compute(node))
        return getattr(node, slot)


def _node(cls: type) -> type:
    """``cls`` as a frozen dataclass with slots whose hash is computed once per node. Formulas
    share sub-formulas (``translate.nnf`` of ``a <-> b`` holds ``a`` twice), so a hash or a string
    that recursed through every child on every call would take time exponential in the depth of a
    chain ``a <-> b <-> c <-> ...``; cached, both take one pass over the distinct nodes."""
    cls = dataclass(frozen=True, slots=True)(cls)
    of_fields = cls.__hash__

    def __hash__(self) -> int:
        return _once(self, "_hash", of_fields)

    cls.__hash__ = __hash__
    return cls


@_node
class Const(Formula):
    """``true`` or ``false``."""

    value: bool


@_node
class Prop(Formula):
    """An atomic proposition, e.g. ``A1`` (the robot is in area A1)."""

    name: str


@_node
class Not(Formula):
    """``!arg``."""

    arg: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.arg,)


@_node
class Next(Formula):
    """``X arg``: arg holds at the next position."""

    arg: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.arg,)


@_node
class Eventually(Formula):
    """``F arg``: arg holds now or at some later position."""

    arg: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.arg,)


@_node
class Always(Formula):
    """``G arg``: arg holds now and at every later position."""

    arg: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.arg,)


@_node
class And(Formula):
    """``left & right``."""

    left: Formula
    right: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.left, self.right)


@_node
class Or(Formula):
    """``left | right``."""

    left: Formula
    right: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.left, self.right)


@_node
class Implies(Formula):
    """``left -> right``."""

    left: Formula
    right: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.left, self.right)


@_node
class Iff(Formula):
    """``left <-> right``."""

    left: Formula
    right: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.left, self.right)


@_node
class Until(Formula):
    """``left U right``: right eventually holds, and left holds at every position before."""

    left: Formula
    right: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.left, self.right)


@_node
class Release(Formula):
    """``left R right``: right holds up to and including the first position where left holds
    (forever if left never holds). Dual of until: ``!(a U b) == !a R !b``."""

    left: Formula
    right: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.left, self.right)


@_node
class WeakUntil(Formula):
    """``left W right``: ``left U right``, or left holds forever."""

    left: Formula
    right: Formula

    def children(self) -> tuple[Formula, ...]:
        return (self.left, self.right)


TRUE = Const(True)
FALSE = Const(False)

# Printing ------------------------------------------------------------------------------------

_IFF, _IMPLIES, _OR, _AND, _TEMPORAL, _UNARY, _ATOM = range(7)

_BINARY = {  # class -> (symbol, precedence, right-associative)
    Iff: ("<->", _IFF, False),
    Implies: ("->", _IMPLIES, True),
    Or: ("|", _OR, False),
    And: ("&", _AND, False),
    Until: ("U", _TEMPORAL, True),
    Release: ("R", _TEMPORAL, True),
    WeakUntil: ("W", _TEMPORAL, True),
}
_UNARY_SYMBOL = {Not: "!", Next: "X ", Eventually: "F ", Always: "G "}


def _precedence(f: Formula) -> int:
    if type(f) in _BINARY:
        return _BINARY[type(f)][1]
    if type(f) in _UNARY_SYMBOL:
        return _UNARY
    return _ATOM


def _to_string(f: Formula) -> str:
    if isinstance(f, Const):
        return "true" if f.value else "false"
    if isinstance(f, Prop):
        return f.name
    if type(f) in _UNARY_SYMBOL:
        inner = str(f.arg)  # type: ignore[attr-defined]
        if _precedence(f.arg) < _UNARY:  # type: ignore[attr-defined]
            inner = f"({inner})"
        return _UNARY_SYMBOL[type(f)] + inner
    symbol, prec, right_assoc = _BINARY[type(f)]
    left, right = f.children()
    # An operand at the same level needs parentheses on the side the operator does not associate.
    # For readability, a binary operand with another operator gets them too: "(a U b) & c".
    left_needs = _precedence(left) < prec or (_precedence(left) == prec and right_assoc)
    right_needs = _precedence(right) < prec or (_precedence(right) == prec and not right_assoc)
    left_needs = left_needs or (type(left) in _BINARY and type(left) is not type(f))
    right_needs = right_needs or (type(right) in _BINARY and type(right) is not type(f))
    left_s = f"({left})" if left_needs else str(left)
    right_s = f"({right})" if right_needs else str(right)
    return f"{left_s} {symbol} {right_s}"


def conjunction(parts: list[Formula]) -> Formula:
    """``parts[0] & parts[1] & ...`` (left-nested); ``true`` when empty."""
    if not parts:
        return TRUE
    out = parts[0]
    for p in parts[1:]:
        out = And(out, p)
    return out


def disjunction(parts: list[Formula]) -> Formula:
    """``parts[0] | parts[1] | ...`` (left-nested); ``false`` when empty."""
    if not parts:
        return FALSE
    out = parts[0]
    for p in parts[1:]:
        out = Or(out, p)
    return out
