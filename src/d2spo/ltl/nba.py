"""LTL formula -> nondeterministic Büchi automaton (NBA), the first step of ``buchi.to_dba``.

A tableau in the style of ``tableau.py``, but one that keeps the letter of each branch, so its
nodes and branches form a generalised Büchi automaton (GBA): a node is a set of NNF formulas that
must hold now; expanding it by the one-step laws gives branches (literals the letter must satisfy,
the node of the next position, the eventualities ``U``/``F`` the branch postpones). A word is
accepted from a node iff it satisfies the node's conjunction and some run postpones no eventuality
forever (one acceptance set per eventuality: the branches that do not postpone it).

Three reductions keep the automaton small and often deterministic. Per letter, a branch is dropped
when another one for that letter has a subset of its next node and a subset of its postponed
eventualities (the run that follows the truth values of the word's sub-formulas can always switch
to the smaller branch and still postpones an eventuality only while it is not yet fulfilled).
A node leaves out the formulas that its other formulas make every branch process anyway
(``normalise``). Nodes from which no fair cycle is reachable are dropped. The GBA is then degeneralised into an NBA
with transition-based acceptance by a counter over the eventualities.
"""

from __future__ import annotations

from dataclasses import dataclass

from d2spo.ltl.automaton import AutomatonTooLarge
from d2spo.ltl.formula import Always, And, Const, Eventually, Formula, Next, Not, Or, Prop, Release, Until, WeakUntil

Branch = tuple[int, int, frozenset, frozenset]
"""(letter bits that must be set, letter bits that must be clear, next node, postponed eventualities)."""


@dataclass(frozen=True)
class Nba:
    """A nondeterministic Büchi automaton with transition-based acceptance."""

    n_states: int
    initial: int
    succ: tuple[tuple[tuple[tuple[int, bool], ...], ...], ...]
    """succ[q][letter]: the (target, accepting) pairs of the transitions of q on the letter."""


def branches(node: frozenset, bit: dict[str, int], budget: list[int] | None = None) -> list[Branch]:
    """The branches of a tableau node (a set of NNF formulas), duplicates removed. ``budget``:
    [work left, work allowed], counted as ``tableau.Tableau.expand`` counts it and decremented
    here; ``AutomatonTooLarge`` when it runs out (a node can have exponentially many branches:
    ``G F G F … a``)."""
    found: set[Branch] = set()
    # A partial branch: formulas still to process, bits set, bits clear, next node, postponed, processed.
    work = [(list(node), 0, 0, frozenset(), frozenset(), frozenset())]
    while work:
        todo, pos, neg, nxt, post, done = work.pop()
        alive = True
        while todo and alive:
            if budget is not None:
                budget[0] -= 1 + len(done)  # each step copies the branch's set of processed formulas
                if budget[0] < 0:
                    raise AutomatonTooLarge(f"the Büchi automaton needs more than MAX_NBA_STEPS={budget[1]} "
                                            "tableau steps; simplify the formula")
            f = todo.pop()
            if f in done:
                continue
            done = done | {f}
            if isinstance(f, Const):
                alive = f.value
            elif isinstance(f, Prop):
                pos |= bit[f.name]
                alive = not pos & neg
            elif isinstance(f, Not):
                neg |= bit[f.arg.name]  # type: ignore[attr-defined]
                alive = not pos & neg
            elif isinstance(f, And):
                todo += [f.left, f.right]
            elif isinstance(f, Next):
                nxt = nxt | {f.arg}
            elif isinstance(f, Always):
                todo.append(f.arg)
                nxt = nxt | {f}
            else:  # a choice: the first option goes on here, the second is queued
                if isinstance(f, Or):
                    now, later, later_next, later_post = [f.left], [f.right], nxt, post
                elif isinstance(f, Eventually):
                    now, later, later_next, later_post = [f.arg], [], nxt | {f}, post | {f}
                elif isinstance(f, Until):
                    now, later, later_next, later_post = [f.right], [f.left], nxt | {f}, post | {f}
                elif isinstance(f, WeakUntil):
                    now, later, later_next, later_post = [f.right], [f.left], nxt | {f}, post
                elif isinstance(f, Release):
                    now, later, later_next, later_post = [f.left, f.right], [f.right], nxt | {f}, post
                else:
                    raise TypeError(f"not an NNF formula node: {f!r}")
                work.append((todo + later, pos, neg, later_next, later_post, done))
                todo = todo + now
        if alive:
            found.add((pos, neg, frozenset(nxt), frozenset(post)))
    return sorted(found, key=lambda b: (b[0], b[1], len(b[2]), sorted(map(str, b[2])), sorted(map(str, b[3]))))


def normalise(node: frozenset) -> frozenset:
    """The node without the formulas that its other formulas make every branch process anyway
    (both sides of ``&``, the argument of ``G``, the right side of ``R``, recursively): such a
    formula changes none of the node's branches, so ``{G F a, F a}`` is the node ``{G F a}``."""
    implied: set[Formula] = set()
    stack = list(node)
    while stack:
        f = stack.pop()
        parts = (f.left, f.right) if isinstance(f, And) else (f.arg,) if isinstance(f, Always) else \
            (f.right,) if isinstance(f, Release) else ()
        for g in parts:
            if g not in implied:
                implied.add(g)
                stack.append(g)
    return node - implied


def _minimal(options: list[tuple[frozenset, frozenset]]) -> list[tuple[frozenset, frozenset]]:
    """The options (next node, postponed) not dominated by another (subset in both)."""
    options = sorted(set(options), key=lambda o: (len(o[0]), len(o[1]), sorted(map(str, o[0])), sorted(map(str, o[1]))))
    kept: list[tuple[frozenset, frozenset]] = []
    for nxt, post in options:
        if not any(k[0] <= nxt and k[1] <= post for k in kept):
            kept.append((nxt, post))
    return kept


def sccs(n: int, succ: list[list[int]]) -> list[int]:
    """Strongly connected components (iterative Tarjan): the component number of each vertex.
    Components are numbered in reverse topological order (a component's successors come first)."""
    index = [-1] * n
    low = [0] * n
    comp = [-1] * n
    on_stack = [False] * n
    stack: list[int] = []
    counter = n_comp = 0
    for root in range(n):
        if index[root] >= 0:
            continue
        calls = [(root, 0)]
        while calls:
            v, i = calls.pop()
            if i == 0:
                index[v] = low[v] = counter
                counter += 1
                stack.append(v)
                on_stack[v] = True
            else:
                low[v] = min(low[v], low[succ[v][i - 1]])
            while i < len(succ[v]):
                w = succ[v][i]
                if index[w] < 0:
                    calls.append((v, i + 1))
                    calls.append((w, 0))
                    break
                if on_stack[w]:
                    low[v] = min(low[v], index[w])
                i += 1
            else:
                if low[v] == index[v]:
                    while True:
                        w = stack.pop()
                        on_stack[w] = False
                        comp[w] = n_comp
                        if w == v:
                            break
                    n_comp += 1
    return comp


def to_nba(f: Formula, aps: tuple[str, ...], max_nodes: int, budget: list[int] | None = None) -> Nba:
    """NBA of the NNF formula ``f`` over the letters of ``aps`` (``AutomatonTooLarge`` beyond
    ``max_nodes`` tableau nodes, or when the work of expanding them exhausts ``budget``, a list
    [steps left, steps allowed] that several calls may share)."""
    bit = {name: 1 << i for i, name in enumerate(aps)}
    n_letters = 1 << len(aps)
    nodes = [normalise(frozenset({f}))]
    number = {nodes[0]: 0}
    # gba[v][letter]: list of (target node number, postponed eventualities)
    gba: list[list[list[tuple[int, frozenset]]]] = []
    for node in nodes:  # grows while we iterate
        options = branches(node, bit, budget)
        row = []
        memo: dict[tuple, list[tuple[int, frozenset]]] = {}
        for letter in range(n_letters):
            fits = tuple(i for i, (pos, neg, _, _) in enumerate(options) if letter & pos == pos and not letter & neg)
            if fits not in memo:
                kept = []
                for nxt, post in _minimal([(normalise(options[i][2]), options[i][3]) for i in fits]):
                    if nxt not in number:
                        if len(nodes) >= max_nodes:
                            raise AutomatonTooLarge(f"the Büchi automaton of {f} needs more than {max_nodes} tableau "
                                                    "nodes; simplify the formula")
                        number[nxt] = len(nodes)
                        nodes.append(nxt)
                    kept.append((number[nxt], post))
                memo[fits] = kept
            row.append(memo[fits])
        gba.append(row)
    eventualities = sorted({e for row in gba for edges in row for _, post in edges for e in post}, key=str)
    alive = _alive(gba, eventualities)
    return _degeneralise(gba, eventualities, alive)


def _alive(gba: list[list[list[tuple[int, frozenset]]]], eventualities: list) -> list[bool]:
    """Per node: some fair cycle (one that fulfils every eventuality) is reachable."""
    n = len(gba)
    succ = [sorted({t for edges in row for t, _ in edges}) for row in gba]
    comp = sccs(n, succ)
    fulfilled: dict[int, set] = {}
    for v, row in enumerate(gba):
        for edges in row:
            for t, post in edges:
                if comp[t] == comp[v]:
                    fulfilled.setdefault(comp[v], set()).update(e for e in eventualities if e not in post)
    good = {c for c, done in fulfilled.items() if len(done) == len(eventualities)}
    members: list[list[int]] = [[] for _ in range(max(comp, default=-1) + 1)]
    for v in range(n):
        members[comp[v]].append(v)
    alive = [comp[v] in good for v in range(n)]
    for group in members:  # reverse topological order: successors first
        if any(alive[t] for v in group for t in succ[v]):
            for v in group:
                alive[v] = True
    return alive


def _degeneralise(gba: list[list[list[tuple[int, frozenset]]]], eventualities: list, alive: list[bool]) -> Nba:
    """NBA states (node, level): at level i the run waits for the i-th eventuality to be fulfilled;
    a transition that fulfils the last one it waits for is accepting and goes back to level 0."""
    k = len(eventualities)
    states = [(0, 0)]
    number = {states[0]: 0}
    succ = []
    for v, level in states:  # grows while we iterate
        row = []
        for edges in gba[v]:
            out = []
            for t, post in edges:
                if not alive[t]:
                    continue
                j = level
                while j < k and eventualities[j] not in post:
                    j += 1
                accepting = j == k
                target = (t, 0 if accepting else j)
                if target not in number:
                    number[target] = len(states)
                    states.append(target)
                out.append((number[target], accepting))
            row.append(tuple(sorted(set(out))))
        succ.append(tuple(row))
    return Nba(n_states=len(states), initial=0, succ=tuple(succ))
