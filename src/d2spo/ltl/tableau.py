"""Satisfiability of LTL formulas over infinite words, by tableau (step 3 of ``translate``).

``translate`` asks it whether a progressed state can still be satisfied (else the state is the
rejecting ``false``) and whether its negation can (else it is the accepting ``true``); docs/ltl.md
has the argument for exactness.
"""

from __future__ import annotations

from d2spo.ltl.automaton import AutomatonTooLarge
from d2spo.ltl.formula import Always, And, Const, Eventually, Next, Not, Or, Prop, Release, Until, WeakUntil


class Tableau:
    """Satisfiability of sets of NNF formulas over infinite words.

    A node is a set of formulas that must hold now. Expanding a node by the one-step laws gives
    its branches: each branch is a consistent set of literals (the letter constraint, always
    realisable when consistent), the set of formulas that must hold at the next position (the
    successor node), and the eventualities (``U``/``F`` formulas) the branch postpones. An infinite
    path is a model iff no eventuality is postponed forever, so a node is satisfiable iff it can
    reach a strongly connected set of nodes whose internal edges, together, leave no eventuality
    postponed on all of them (a generalised Büchi emptiness check).
    """

    def __init__(self, max_nodes: int, max_steps: int):
        self.max_nodes = max_nodes
        """Most nodes it may build (``translate.MAX_TABLEAU_NODES``)."""
        self.max_steps = max_steps
        """Most work it may do (``translate.MAX_TABLEAU_STEPS``; see ``expand``)."""
        self.steps_left = max_steps
        self.edges: dict[frozenset, list[tuple[frozenset, frozenset]]] = {}
        self.good: dict[frozenset, bool] = {}

    def expand(self, node: frozenset) -> list[tuple[frozenset, frozenset]]:
        """Branches of a node as (successor node, postponed eventualities)."""
        found: set[tuple[frozenset, frozenset]] = set()
        # A branch: (formulas to process, literals, next-step obligations, postponed, processed).
        work = [(list(node), frozenset(), frozenset(), frozenset(), frozenset())]
        while work:
            todo, lits, nxt, post, done = work.pop()
            alive = True
            while todo and alive:
                self.steps_left -= 1 + len(done)  # each step copies the branch's set of processed formulas
                if self.steps_left < 0:
                    raise AutomatonTooLarge(
                        f"the satisfiability check needs more than MAX_TABLEAU_STEPS={self.max_steps} tableau "
                        "steps; simplify the formula (e.g. split a long ordered visit into shorter tasks)"
                    )
                f = todo.pop()
                if f in done:
                    continue
                done = done | {f}
                if isinstance(f, Const):
                    alive = f.value
                elif isinstance(f, Prop):
                    alive = Not(f) not in lits
                    lits = lits | {f}
                elif isinstance(f, Not):
                    alive = f.arg not in lits
                    lits = lits | {f}
                elif isinstance(f, And):
                    todo += [f.left, f.right]
                elif isinstance(f, Next):
                    nxt = nxt | {f.arg}
                elif isinstance(f, Always):
                    todo.append(f.arg)
                    nxt = nxt | {f}
                else:  # a choice: work on the first option, queue the second
                    if isinstance(f, Or):
                        first, second = [f.left], [f.right]
                        later = (nxt, post)
                    elif isinstance(f, Eventually):
                        first, second = [f.arg], []
                        later = (nxt | {f}, post | {f})
                    elif isinstance(f, Until):
                        first, second = [f.right], [f.left]
                        later = (nxt | {f}, post | {f})
                    elif isinstance(f, WeakUntil):
                        first, second = [f.right], [f.left]
                        later = (nxt | {f}, post)
                    elif isinstance(f, Release):
                        first, second = [f.left, f.right], [f.right]
                        later = (nxt | {f}, post)
                    else:
                        raise TypeError(f"not an NNF formula node: {f!r}")
                    work.append((todo + second, lits, later[0], later[1], done))
                    todo = todo + first
            if alive:
                found.add((frozenset(nxt), frozenset(post)))
        return sorted(found, key=lambda e: (len(e[0]), len(e[1]), sorted(map(str, e[0]))))

    def _successors(self, node: frozenset) -> list[tuple[frozenset, frozenset]]:
        if node not in self.edges:
            if len(self.edges) >= self.max_nodes:
                raise AutomatonTooLarge(
                    f"the satisfiability check needs more than {self.max_nodes} tableau nodes; "
                    "simplify the formula"
                )
            self.edges[node] = self.expand(node)
        return self.edges[node]

    def satisfiable(self, node: frozenset) -> bool:
        if node not in self.good:
            self._solve(node)
        return self.good[node]

    def _solve(self, root: frozenset) -> None:
        """Tarjan's SCC algorithm (iterative) from ``root``; fills ``self.good``."""
        index: dict[frozenset, int] = {}
        low: dict[frozenset, int] = {}
        on_stack: set[frozenset] = set()
        stack: list[frozenset] = []
        calls = [(root, 0)]
        while calls:
            v, i = calls.pop()
            if i == 0:
                index[v] = low[v] = len(index)
                stack.append(v)
                on_stack.add(v)
            succ = self._successors(v)
            if i > 0:  # returned from succ[i - 1]
                low[v] = min(low[v], low[succ[i - 1][0]])
            while i < len(succ):
                w = succ[i][0]
                if w not in self.good and w not in index:
                    calls.append((v, i + 1))
                    calls.append((w, 0))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
                i += 1
            else:
                if low[v] == index[v]:
                    component = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        component.append(w)
                        if w == v:
                            break
                    self._mark(set(component))

    def _mark(self, component: set[frozenset]) -> None:
        pending = None  # eventualities postponed on every internal edge so far
        reaches_good = False
        for v in component:
            for w, post in self.edges[v]:
                if w in component:
                    pending = post if pending is None else pending & post
                else:
                    reaches_good = reaches_good or self.good[w]
        fair_cycle = pending is not None and not pending
        for v in component:
            self.good[v] = reaches_good or fair_cycle
