"""NBA -> deterministic parity automaton (Safra's trees, Piterman's naming) -> Büchi acceptance.

Steps 2 and 3 of ``buchi.to_dba`` (docs/ltl.md, "Büchi automata"):

* ``determinise``: Safra's construction for an NBA with transition-based acceptance. A state is an
  ordered tree of nodes, each labelled by a set of NBA states (children: disjoint subsets of their
  parent, older children first). Reading a letter moves every label to its successors and gives
  each node a new youngest child holding the targets of accepting transitions; a state stays only
  in the oldest node that holds it among siblings; empty nodes go; a node whose children cover its
  label drops them and *flashes*. Nodes are named 1..n by age (new nodes get the next names and
  survivors are renumbered in order), so a node keeps its name until it or an older node goes.
  The transition's priority is ``2f`` when the oldest flashing node f is older than every node
  that went (the oldest of which is e), else ``2e - 1``; neutral (large, odd) when nothing
  happened. A run is accepting iff its least priority seen infinitely often is even: then node f
  eventually lives forever and flashes infinitely often, which is Safra's acceptance.
* ``buchi_marks``: whether that parity automaton is Büchi-type and, if so, its accepting
  transitions. In each strongly connected component (SCC) with least priority m: if m is even its
  m-transitions are marked accepting; the m-transitions are then removed and the remaining SCCs
  are treated the same way. Every accepting cycle contains a mark by construction. The language
  has a deterministic Büchi automaton iff no rejecting cycle contains a mark (Landweber: no
  accepting cycle lies inside a rejecting one, in any deterministic automaton of the language);
  a rejecting cycle with least (odd) priority k through a mark exists iff, in the graph of the
  transitions of priority >= k, an SCC holds both a k-transition and a mark. Such a cycle and an
  accepting one through the same mark give the words of the refusal's witness.
"""

from __future__ import annotations

from d2spo.ltl.automaton import AutomatonTooLarge
from d2spo.ltl.nba import Nba, sccs

Tree = tuple
"""(name, frozenset of NBA states, tuple of child trees); ``()`` is the empty tree (no run left)."""


class Parity:
    """A complete deterministic parity automaton (min-even acceptance) over letter classes."""

    def __init__(self, trees: list[Tree], delta: list[list[int]], priority: list[list[int]], letter_class: list[int]):
        self.trees = trees
        """Per state, its Safra tree."""
        self.delta = delta
        """delta[q][c]: the successor of q on the letters of class c."""
        self.priority = priority
        """priority[q][c]: the priority of that transition."""
        self.letter_class = letter_class
        """Per letter, its class (letters that every NBA state reads alike share one)."""


def _names(tree: Tree) -> list[int]:
    out, stack = [], [tree]
    while stack:
        name, _, children = stack.pop()
        if name is not None:
            out.append(name)
        stack.extend(children)
    return out


def _step(tree: Tree, letter: int, nba: Nba, neutral: int) -> tuple[Tree, int]:
    """Safra's step on one letter: the next tree and the transition's priority."""
    if not tree:
        return (), neutral
    removed: list[int] = []
    green: list[int] = []

    def advance(node: Tree) -> list:
        name, label, children = node
        moved: set[int] = set()
        fresh: set[int] = set()
        for q in label:
            for t, accepting in nba.succ[q][letter]:
                moved.add(t)
                if accepting:
                    fresh.add(t)
        kids = [advance(c) for c in children]
        if fresh:
            kids.append([None, fresh, []])
        return [name, moved, kids]

    def prune(node: list, allowed: set[int]) -> bool:
        """Horizontal merge: keep each state in the oldest node that holds it; drop empty nodes."""
        node[1] &= allowed
        if not node[1]:
            removed.extend(_names(_freeze(node)))
            return False
        taken: set[int] = set()
        kept = []
        for child in node[2]:
            if prune(child, node[1] - taken):
                taken |= child[1]
                kept.append(child)
        node[2] = kept
        return True

    def flash(node: list) -> None:
        """Vertical merge: a node whose children cover its label flashes and loses them."""
        if node[2] and set().union(*(c[1] for c in node[2])) == node[1]:
            green.append(node[0])
            for child in node[2]:
                removed.extend(_names(_freeze(child)))
            node[2] = []
        else:
            for child in node[2]:
                flash(child)

    root = advance(tree)
    if not prune(root, set(root[1])):
        return (), 1  # the root went: name 1, priority 2 * 1 - 1
    flash(root)
    # Renumber: surviving nodes in the order of their old names, then the new ones.
    order: list[list] = []
    stack = [root]
    while stack:
        node = stack.pop()
        order.append(node)
        stack.extend(reversed(node[2]))
    old = sorted((n for n in order if n[0] is not None), key=lambda n: n[0])
    new = [n for n in order if n[0] is None]
    rename = {id(n): i + 1 for i, n in enumerate(old + new)}
    e = min(removed, default=None)
    f = min((g for g in green if g is not None), default=None)
    if f is not None and (e is None or f < e):
        priority = 2 * f
    elif e is not None:
        priority = 2 * e - 1
    else:
        priority = neutral

    def freeze(node: list) -> Tree:
        return (rename[id(node)], frozenset(node[1]), tuple(freeze(c) for c in node[2]))

    return freeze(root), priority


def _freeze(node: list) -> Tree:
    return (node[0], frozenset(node[1]), tuple(_freeze(c) for c in node[2]))


def determinise(nba: Nba, n_letters: int, max_states: int, what: str) -> Parity:
    """Safra-Piterman determinisation, states numbered breadth-first from the initial tree 0.
    ``AutomatonTooLarge`` (naming ``what``) beyond ``max_states`` states."""
    signatures: dict[tuple, int] = {}
    letter_class = [signatures.setdefault(tuple(row[a] for row in nba.succ), len(signatures))
                    for a in range(n_letters)]
    representative = [letter_class.index(c) for c in range(len(signatures))]
    neutral = 2 * nba.n_states + 3
    trees: list[Tree] = [(1, frozenset({nba.initial}), ())]
    number = {trees[0]: 0}
    delta, priority = [], []
    for tree in trees:  # grows while we iterate
        row, prow = [], []
        for letter in representative:
            target, p = _step(tree, letter, nba, neutral)
            if target not in number:
                if len(trees) >= max_states:
                    raise AutomatonTooLarge(f"the deterministic automaton of {what} has more than "
                                            f"max_states={max_states} states")
                number[target] = len(trees)
                trees.append(target)
            row.append(number[target])
            prow.append(p)
        delta.append(row)
        priority.append(prow)
    return Parity(trees, delta, priority, letter_class)


def _internal_groups(n: int, edges: list[tuple[int, int]], subset: list[int]) -> list[list[int]]:
    """The edges of ``subset`` inside each SCC of the graph they form (SCCs with no such edge
    omitted)."""
    succ: list[list[int]] = [[] for _ in range(n)]
    for e in subset:
        succ[edges[e][0]].append(edges[e][1])
    comp = sccs(n, succ)
    groups: dict[int, list[int]] = {}
    for e in subset:
        src, dst = edges[e]
        if comp[src] == comp[dst]:
            groups.setdefault(comp[src], []).append(e)
    return list(groups.values())


Witness = tuple[list[int], list[int], list[int]]
"""Letter classes (u, x, y): u·x^ω is accepted, and so is u·z·x^ω for every word z over {x, y},
but no u·x^k1·y·x^k2·y··· is; so no deterministic Büchi automaton accepts the language."""


def _path(edges: list[tuple[int, int]], allowed: list[int], start: int, goal: int) -> list[int]:
    """The edges of a shortest path from ``start`` to ``goal`` over the ``allowed`` edges."""
    parent: dict[int, int | None] = {start: None}
    frontier = [start]
    for v in frontier:  # grows while we iterate: breadth-first
        if v == goal:
            break
        for e in allowed:
            if edges[e][0] == v and edges[e][1] not in parent:
                parent[edges[e][1]] = e
                frontier.append(edges[e][1])
    out: list[int] = []
    while goal != start:
        e = parent[goal]
        assert e is not None
        out.append(e)
        goal = edges[e][0]
    return out[::-1]


def buchi_marks(dpa: Parity) -> tuple[list[list[bool]] | None, Witness | None]:
    """Accepting transitions of a Büchi condition equivalent to the parity condition on the same
    graph (marks[q][c]), or, when no such condition exists, a ``Witness`` that no deterministic
    Büchi automaton recognises the language: a rejecting cycle through a mark, joined to an
    accepting cycle through that mark (the union of the two loops is rejecting, so Landweber's
    condition fails)."""
    n, width = len(dpa.delta), len(dpa.delta[0])
    edges = [(q, dpa.delta[q][c]) for q in range(n) for c in range(width)]
    prio = [dpa.priority[q][c] for q in range(n) for c in range(width)]
    marked: dict[int, list[int]] = {}  # a marked edge -> the edges of the SCC it was marked in
    work = [list(range(len(edges)))]
    while work:
        for inside in _internal_groups(n, edges, work.pop()):
            least = min(prio[e] for e in inside)
            if least % 2 == 0:
                marked.update((e, inside) for e in inside if prio[e] == least)
            rest = [e for e in inside if prio[e] != least]
            if rest:
                work.append(rest)
    for k in sorted({p for p in prio if p % 2}):
        for inside in _internal_groups(n, edges, [e for e in range(len(edges)) if prio[e] >= k]):
            odd = [e for e in inside if prio[e] == k]
            bad = [e for e in inside if e in marked]
            if odd and bad:
                t, r = bad[0], odd[0]
                s = edges[t][0]
                x = [t] + _path(edges, marked[t], edges[t][1], s)
                y = [t] + _path(edges, inside, edges[t][1], edges[r][0]) + [r] + _path(edges, inside, edges[r][1], s)
                u = _path(edges, list(range(len(edges))), 0, s)
                return None, ([e % width for e in u], [e % width for e in x], [e % width for e in y])
    return [[q * width + c in marked for c in range(width)] for q in range(n)], None
