"""Products and reduction of deterministic Büchi automata with accepting transitions (``buchi.to_dba``).

``product`` gives the automaton of the union or the intersection of two languages. ``reduce``
shrinks an automaton (step 4 of ``to_dba``).

Every step keeps the language of every remaining state:

1. the states with no accepting continuation (``dead_states``) become one rejecting sink, those with
   every continuation accepted (``universal_states``) one accepting sink with an accepting
   ``true`` self-loop;
2. partition refinement: states that agree, for every letter, on the successor's block and on
   whether the transition is accepting are merged;
3. merging of language-equivalent states: q is dropped and its incoming transitions are sent to p
   when L(p) = L(q) and either no predecessor of q can be reached from p afterwards (so a run takes
   a redirected transition at most once, and from then on reads the rest of the word from p,
   which accepts what q would have accepted) or a product check shows that the automaton accepts
   the same words after the merge; then refinement again.

States are finally renumbered breadth-first from the initial state 0.
"""

from __future__ import annotations

from collections.abc import Sequence

from d2spo.ltl.automaton import AutomatonTooLarge
from d2spo.ltl.nba import sccs

MAX_PRODUCT_EDGES = 2_000_000
"""Step 3 starts with the product of the automaton with itself; it is skipped when that product
would have more edges than this."""
MAX_CHECK_EDGES = 250_000
"""Step 3 stops checking merges by products once its checks together have built this many product
edges (about a second; the automaton is then larger, not wrong)."""


def co_reach(delta: Sequence[Sequence[int]], targets: set[int]) -> set[int]:
    """The states that reach none of ``targets``."""
    n = len(delta)
    pred: list[set[int]] = [set() for _ in range(n)]
    for q, row in enumerate(delta):
        for t in row:
            pred[t].add(q)
    seen = set(targets)
    frontier = list(targets)
    while frontier:
        for p in pred[frontier.pop()]:
            if p not in seen:
                seen.add(p)
                frontier.append(p)
    return set(range(n)) - seen


def dead_states(delta: Sequence[Sequence[int]], accepting: Sequence[Sequence[bool]]) -> set[int]:
    """States from which no accepting cycle is reachable: none reaches an accepting transition
    inside a strongly connected component (one outside any can be taken once at most)."""
    n = len(delta)
    comp = sccs(n, [sorted(set(row)) for row in delta])
    live = {q for q in range(n) for a, t in enumerate(delta[q]) if accepting[q][a] and comp[t] == comp[q]}
    return co_reach(delta, live)


def universal_states(delta: Sequence[Sequence[int]], accepting: Sequence[Sequence[bool]]) -> set[int]:
    """States from which every infinite run is accepting: no cycle of non-accepting transitions
    is reachable."""
    n = len(delta)
    plain = [sorted({t for a, t in enumerate(row) if not accepting[q][a]}) for q, row in enumerate(delta)]
    comp = sccs(n, plain)
    return co_reach(delta, {q for q in range(n) for t in plain[q] if comp[t] == comp[q]})


def _refine(delta: list[list[int]], accepting: list[list[bool]], kind: list[str]) -> list[int]:
    """Coarsest partition (block per state) compatible with ``kind`` and with (successor's block,
    accepting) per letter; the sinks' transitions are ignored (they become self-loops)."""
    block = [{"dead": 0, "done": 1, "live": 2}[k] for k in kind]
    n_blocks = len(set(block))
    while True:
        signatures = [(block[q],) if kind[q] != "live" else
                      (block[q], tuple((block[t], accepting[q][a]) for a, t in enumerate(delta[q])))
                      for q in range(len(delta))]
        ids: dict[tuple, int] = {}
        block = [ids.setdefault(s, len(ids)) for s in signatures]
        if len(ids) == n_blocks:
            return block
        n_blocks = len(ids)


def _quotient(delta, accepting, kind, block, initial):
    """The automaton of the blocks, renumbered breadth-first from the initial state's block."""
    width = len(delta[0])
    order, rep = {block[initial]: 0}, [initial]
    for q in rep:  # grows while we iterate: breadth-first
        for t in delta[q]:
            if block[t] not in order:
                order[block[t]] = len(rep)
                rep.append(t)
    new_delta, new_accepting = [], []
    for i, q in enumerate(rep):
        if kind[q] == "live":
            new_delta.append([order[block[t]] for t in delta[q]])
            new_accepting.append(list(accepting[q]))
        else:
            new_delta.append([i] * width)
            new_accepting.append([kind[q] == "done"] * width)
    return new_delta, new_accepting, [kind[q] for q in rep]


def _not_included(d1: list[list[int]], a1: list[list[bool]], d2: list[list[int]], a2: list[list[bool]]
                  ) -> set[tuple[int, int]]:
    """The pairs (p, q) with a word accepted from state p of the first automaton and not from state
    q of the second: in their product, the pairs that reach a cycle on which the second never
    accepts and the first does."""
    n1, n2 = len(d1), len(d2)
    succ_all: list[set[int]] = [set() for _ in range(n1 * n2)]
    succ_plain: list[list[tuple[int, bool]]] = [[] for _ in range(n1 * n2)]
    for p in range(n1):
        for q in range(n2):
            v = p * n2 + q
            for a in range(len(d1[p])):
                w = d1[p][a] * n2 + d2[q][a]
                succ_all[v].add(w)
                if not a2[q][a]:
                    succ_plain[v].append((w, a1[p][a]))
    comp = sccs(n1 * n2, [sorted({w for w, _ in edges}) for edges in succ_plain])
    bad = {v for v in range(n1 * n2) for w, acc in succ_plain[v] if acc and comp[w] == comp[v]}
    reach_bad = set(range(n1 * n2)) - co_reach(succ_all, bad)
    return {(v // n2, v % n2) for v in reach_bad}


def _same_language_after_merge(delta: list[list[int]], accepting: list[list[bool]], start: int, q: int, p: int
                               ) -> tuple[bool, int]:
    """Whether the automaton accepts the same words from ``start`` once the transitions into q go
    to p instead, and the number of product edges that took: no cycle reachable in the product
    of the two accepts on one side and never on the other."""
    index = {(start, p if start == q else start): 0}
    pairs = list(index)
    edges: list[list[tuple[int, bool, bool]]] = []
    for s1, s2 in pairs:  # grows while we iterate
        out = set()
        for a, (t1, t2) in enumerate(zip(delta[s1], delta[s2], strict=True)):
            w = (t1, p if t2 == q else t2)
            if w not in index:
                index[w] = len(pairs)
                pairs.append(w)
            out.add((index[w], accepting[s1][a], accepting[s2][a]))
        edges.append(sorted(out))
    for side in (1, 2):  # side 1: a cycle accepted before the merge and not after it
        keep = [[(w, x1 if side == 1 else x2) for w, x1, x2 in out if not (x2 if side == 1 else x1)] for out in edges]
        comp = sccs(len(pairs), [sorted({w for w, _ in out}) for out in keep])
        if any(acc and comp[w] == comp[v] for v, out in enumerate(keep) for w, acc in out):
            return False, len(pairs) * len(delta[0])
    return True, len(pairs) * len(delta[0])


def _merge_equivalent(delta: list[list[int]], accepting: list[list[bool]], kind: list[str]) -> list[int]:
    """Step 3: per state, the state it was merged into (itself if kept). A merge is taken when the
    cheap condition holds, else when the automaton after it accepts the same words (a product
    check, tried once per pair, while ``MAX_CHECK_EDGES`` are left)."""
    n, width = len(delta), len(delta[0])
    differ = _not_included(delta, accepting, delta, accepting)
    same = {q: [p for p in range(n) if p != q and kind[p] == "live" and (p, q) not in differ and (q, p) not in differ]
            for q in range(n) if kind[q] == "live"}
    budget = MAX_CHECK_EDGES
    target = list(range(n))  # target[q] = q, or the state q was merged into
    present = set(range(n))
    refused: set[tuple[int, int]] = set()
    merged = True
    while merged:  # passes until one merges nothing
        merged = False
        for q in sorted(same, reverse=True):
            if q not in present:
                continue
            preds = {s for s in present if s != q and q in delta[s]}
            for p in same[q]:
                if p not in present or (p, q) in refused:
                    continue
                reach, frontier = {p}, [p]
                while frontier:
                    for t in delta[frontier.pop()]:
                        t = p if t == q else t
                        if t not in reach:
                            reach.add(t)
                            frontier.append(t)
                if reach & preds:
                    if budget <= 0:
                        continue
                    ok, cost = _same_language_after_merge(delta, accepting, target[0], q, p)
                    budget -= cost + n * width
                    if not ok:
                        refused.add((p, q))
                        continue
                for s in present:
                    if q in delta[s]:
                        delta[s] = [p if t == q else t for t in delta[s]]
                present.discard(q)
                target = [p if t == q else t for t in target]
                merged = True
                break
    return target


def product(parts: list[tuple[list[list[int]], list[list[bool]]]], both: bool, max_states: int, what: str
            ) -> tuple[list[list[int]], list[list[bool]]]:
    """The automaton of the words accepted by all the automata ``parts`` (``both``) or by one of
    them, initial states 0, reachable states only. One of them: a transition is accepting when one
    of theirs is. All: a level says whose accepting transition is awaited; each of theirs moves it
    on to the next automaton (several at once when several accept together), and the transition
    that moves it past the last one is accepting and sets it back to the first.
    ``AutomatonTooLarge`` (naming ``what``) beyond ``max_states`` states."""
    k = len(parts)
    states = [((0,) * k, 0)]
    index = {states[0]: 0}
    delta, accepting = [], []
    for qs, level in states:  # grows while we iterate
        row, marks = [], []
        for a in range(len(parts[0][0][0])):
            targets = tuple(d[q][a] for (d, _), q in zip(parts, qs, strict=True))
            hits = [acc[q][a] for (_, acc), q in zip(parts, qs, strict=True)]
            if both:
                j = level
                while j < k and hits[j]:
                    j += 1
                hit, nxt = j == k, (targets, 0 if j == k else j)
            else:
                hit, nxt = any(hits), (targets, 0)
            if nxt not in index:
                if len(states) >= max_states:
                    raise AutomatonTooLarge(f"the deterministic automaton of {what} has more than "
                                            f"max_states={max_states} states")
                index[nxt] = len(states)
                states.append(nxt)
            row.append(index[nxt])
            marks.append(hit)
        delta.append(row)
        accepting.append(marks)
    return delta, accepting


def saturate(delta: list[list[int]], accepting: list[list[bool]]) -> list[list[bool]]:
    """The same language with as many accepting transitions as possible inside the strongly
    connected components: a transition may be made accepting iff no cycle through it is free of
    accepting transitions, i.e. its ends lie in different components of the graph of the
    non-accepting transitions (marking such transitions leaves those components as they are)."""
    n = len(delta)
    comp = sccs(n, [sorted(set(row)) for row in delta])
    plain = sccs(n, [sorted({t for a, t in enumerate(row) if not accepting[q][a]}) for q, row in enumerate(delta)])
    return [[accepting[q][a] or (comp[t] == comp[q] and plain[t] != plain[q]) for a, t in enumerate(row)]
            for q, row in enumerate(delta)]


def reduce(delta: list[list[int]], accepting: list[list[bool]]) -> tuple[list, list, set[int], set[int]]:
    """Steps 1-3 on the automaton as given and on its ``saturate``d form; the smaller result wins
    (the one as given on a tie: fewer accepting transitions). Returns delta, accepting, the
    rejecting sinks and the accepting sinks (at most one of each), the initial state being 0."""
    plain = _reduce(delta, accepting)
    rich = _reduce(delta, saturate(delta, accepting))
    return rich if len(rich[0]) < len(plain[0]) else plain


def _reduce(delta: list[list[int]], accepting: list[list[bool]]) -> tuple[list, list, set[int], set[int]]:
    dead, done = dead_states(delta, accepting), universal_states(delta, accepting)
    kind = ["dead" if q in dead else "done" if q in done else "live" for q in range(len(delta))]
    delta, accepting, kind = _quotient(delta, accepting, kind, _refine(delta, accepting, kind), 0)
    if len(delta) ** 2 * len(delta[0]) <= MAX_PRODUCT_EDGES:
        target = _merge_equivalent([list(row) for row in delta], accepting, kind)
        merged = [[target[t] for t in row] for row in delta]
        block = _refine(merged, accepting, kind)
        block = [block[target[q]] for q in range(len(delta))]
        delta, accepting, kind = _quotient(merged, accepting, kind, block, target[0])
    return (delta, accepting, {q for q, k in enumerate(kind) if k == "dead"},
            {q for q, k in enumerate(kind) if k == "done"})
