"""LTL formula -> minimal deterministic automaton that tracks task progress (paper Sec. II-B).

The construction, in four steps (docs/ltl.md has the details and the argument for exactness):

1. Negation normal form (NNF): negations only on propositions; ``->``, ``<->`` expanded.
2. Formula progression. A state is a progressed formula kept in disjunctive normal form (DNF)
   over "atoms", the non-boolean sub-formulas of the NNF formula (literals, ``X``, ``U``, ``R``,
   ``W``, ``F``, ``G`` nodes). Reading a letter rewrites every atom by the one-step expansion laws
   (``a U b`` -> ``prog(b) | (prog(a) & a U b)``, ...). DNFs over a finite set of atoms, kept
   sorted, deduplicated and free of subsumed clauses, are finitely many, so progression stops.
3. Exact status. Each new state is checked with a tableau satisfiability test (``ltl/tableau.py``:
   an on-the-fly generalised Büchi automaton and an emptiness check): unsatisfiable clauses, and clauses that
   imply another clause, are dropped; if nothing is left the state is the rejecting state
   ``false``; if its negation is unsatisfiable it is the accepting state ``true``. This makes
   accepting/rejecting exact for every LTL formula, not only for the co-safe and safety fragments.
4. Minimisation of the resulting Moore machine (output = accepting / rejecting / undecided) by
   partition refinement, so the state count is the minimum for the status semantics.
"""

from __future__ import annotations

import warnings

from d2spo.ltl.automaton import Automaton, AutomatonTooLarge
from d2spo.ltl.formula import (
    Formula,
    check_size,
)
from d2spo.ltl.nnf import nnf
from d2spo.ltl.parser import parse
from d2spo.ltl.progression import (
    DNF_FALSE,
    DNF_TRUE,
    Dnf,
    Progression,
    clause_order,
    dnf_to_formula,
    negate_dnf,
    to_dnf,
)
from d2spo.ltl.tableau import Tableau

MAX_APS = 12
"""Most atomic propositions a formula may use (the transition table has 2**len(aps) columns)."""
MAX_TABLEAU_NODES = 200_000
"""Most tableau nodes the satisfiability checks of one translation may build."""
MAX_TABLEAU_STEPS = 10_000_000
"""Most work the tableau may do in one translation: each formula it expands counts one step plus
the formulas its branch has already processed (what that step copies). A bound on the time (1 to
4 s on a 2-core CPU, by the formula: 0.8 s for the ordered visit of 12 areas, 3.3 s for
``a W b W ... W h``), so a formula whose check grows exponentially is refused instead of running
for minutes: an ordered visit of 11 areas ``F(a & X F(b & X F(...))`` needs 8 million steps
(0.5 s), 12 areas are refused (15 took 184 s before this bound). The named tasks need at most
1100."""
class NeverCompletedWarning(UserWarning):
    """The formula has no good prefix: no finite run completes it (e.g. ``G F a``, ``G !obs``)."""


# --- 3. Exact status (tableau.Tableau); 4. determinisation by progression, then minimisation -----------


def translate(formula: Formula | str, max_states: int = 1000) -> Automaton:
    """Minimal deterministic automaton of ``formula`` whose accepting (rejecting) states are
    exactly the good (bad) prefixes. Raises ``LTLSyntaxError`` for an unparsable string and
    ``AutomatonTooLarge`` when a size limit is hit (``max_states`` before minimisation,
    ``MAX_APS``, ``MAX_TABLEAU_NODES``). Warns ``NeverCompletedWarning`` when no prefix is good."""
    f = formula if isinstance(formula, Formula) else parse(formula)  # parse: a TypeError for None, a number
    check_size(f)
    aps = tuple(sorted(f.aps()))
    if len(aps) > MAX_APS:
        raise AutomatonTooLarge(f"the formula uses {len(aps)} propositions; at most {MAX_APS} are supported")
    prog = Progression(aps)
    tableau = Tableau(MAX_TABLEAU_NODES, MAX_TABLEAU_STEPS)
    canonical: dict[Dnf, Dnf] = {}

    def decide(d: Dnf) -> Dnf:
        """DNF_FALSE / DNF_TRUE when ``d`` is unsatisfiable / valid; otherwise ``d`` without its
        unsatisfiable clauses and without each clause that implies another kept one."""
        if d not in canonical:
            clauses = [c for c in sorted(d, key=clause_order) if tableau.satisfiable(c)]
            for c in list(clauses):
                if any(c2 != c and not tableau.satisfiable(c | negate_dnf({c2})) for c2 in clauses):
                    clauses.remove(c)
            out = frozenset(clauses)
            if out and out != DNF_TRUE and not tableau.satisfiable(negate_dnf(out)):
                out = DNF_TRUE
            canonical[d] = out
        return canonical[d]

    states = [decide(to_dnf(nnf(f)))]
    number = {states[0]: 0}
    delta: list[list[int]] = []
    for d in states:  # grows while we iterate: breadth-first exploration
        # Only the propositions that occur in d matter; letters equal on them share a target.
        names = {name for clause in d for atom in clause for name in atom.aps()}
        relevant = sum(prog.bit[name] for name in names)
        row: list[int] = []
        by_relevant: dict[int, int] = {}
        for letter in range(1 << len(aps)):
            key = letter & relevant
            if key not in by_relevant:
                target = decide(prog.dnf(d, key))
                if target not in number:
                    if len(states) >= max_states:
                        raise AutomatonTooLarge(
                            f"the automaton of {f} has more than max_states={max_states} states"
                        )
                    number[target] = len(states)
                    states.append(target)
                by_relevant[key] = number[target]
            row.append(by_relevant[key])
        delta.append(row)
    status = [1 if d == DNF_TRUE else 2 if d == DNF_FALSE else 0 for d in states]
    if 1 not in status:
        warnings.warn(
            f"{f} has no good prefix: no finite run completes this task, so its automaton has no "
            "accepting state and no distance to acceptance (see docs/ltl.md, 'Which formulas')",
            NeverCompletedWarning,
            stacklevel=2,
        )
    return _minimise(aps, delta, status, [str(dnf_to_formula(d)) for d in states])


def _minimise(aps: tuple[str, ...], delta: list[list[int]], status: list[int], names: list[str]) -> Automaton:
    """Moore's partition refinement (output = status), states renumbered breadth-first from 0.

    State 0 is initial. The label of a merged state is that of its first-discovered member.
    """
    block = list(status)
    n_blocks = len(set(block))
    while True:
        signatures = [(block[q], tuple(block[t] for t in row)) for q, row in enumerate(delta)]
        ids: dict[tuple, int] = {}
        block = [ids.setdefault(s, len(ids)) for s in signatures]
        if len(ids) == n_blocks:
            break
        n_blocks = len(ids)
    order = {block[0]: 0}  # block -> new state number, breadth-first
    rep = [0]  # new state -> representative old state
    for q in rep:
        for t in delta[q]:
            if block[t] not in order:
                order[block[t]] = len(rep)
                rep.append(t)
    first = {}
    for q in range(len(delta)):
        first.setdefault(block[q], q)
    return Automaton(
        aps=aps,
        initial=0,
        accepting=frozenset(i for i, q in enumerate(rep) if status[q] == 1),
        rejecting=frozenset(i for i, q in enumerate(rep) if status[q] == 2),
        delta=tuple(tuple(order[block[t]] for t in delta[q]) for q in rep),
        state_formulas=tuple(names[first[block[q]]] for q in rep),
    )
