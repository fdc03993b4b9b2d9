"""Named LTL tasks: the paper's (Sec. V) and a suite of examples. docs/ltl.md explains each."""

from __future__ import annotations

import difflib
import re

import numpy as np

from d2spo.ltl.parser import parse

TASKS: dict[str, str] = {
    # Visit A1, then A2, then A3, and enter no area early. The paper's text says so, but its printed
    # formula (below) lacks the conjunct "F A3"; this is the intended task.
    "phi1": "(!A3 U A2) & (!A2 U A1) & F A1 & F A3",
    # phi1 exactly as printed in the paper: done as soon as A2 is reached after A1 (A3 never needed).
    "phi1-printed": "(!A3 U A2) & (!A2 U A1) & F A1",
    # A1 and A3 in either order, one right after the other; then, later, A4; then, later still, A2.
    "phi2": "((A1 & X A3) | (A3 & X A1)) & X (F (A4 & X (F A2)))",
    # The relaxed task of Sec. V-B: visit A1, then A2 (two areas).
    "relaxed": "(!A2 U A1) & F A2",
    # --- the example suite (SUITE below) ---
    # A1, then A2, then A3; other visits in between are allowed.
    "tour3": "F (A1 & F (A2 & F A3))",
    # A1, A2, A3, A4 in this order; other visits in between are allowed.
    "tour4": "F (A1 & F (A2 & F (A3 & F A4)))",
    # A1, A2, A3, A4 in this order, and no area before its turn.
    "strict4": "(!A2 & !A3 & !A4) U (A1 & ((!A3 & !A4) U (A2 & (!A4 U (A3 & F A4)))))",
    # A1, A2 and A3, in any order.
    "any-order3": "F A1 & F A2 & F A3",
    # Avoid A4 until A2 is reached, then A3 (A4 lies on the straight route from the start to A2).
    "avoid-until": "!A4 U (A2 & F A3)",
    # A1, then A3, never entering A4 (A4 lies on the straight route from A1 to A3). "G !A4 & F ..."
    # has no good prefix (it can always still fail), so "never" is "not before the task is done".
    "never-a4": "!A4 U (A1 & (!A4 U A3))",
    # A1 or A3 (either), then A2.
    "either-then": "F ((A1 | A3) & F A2)",
    # A3 at some time, and A1 with A2 as the very next task area entered (so no A3 in between).
    "next-pair": "F (A1 & X A2) & F A3",
    # A3, next A4, next A1: three areas entered back to back.
    "next-chain": "F (A3 & X (A4 & X A1))",
    # A1, then A4, then back to A1 (the robot must leave A1 and enter it again).
    "return": "F (A1 & F (A4 & F A1))",
    # A1 and A2 at the same time: impossible where the two areas do not overlap (rejected before training).
    "a1-and-a2": "F (A1 & A2)",
    # --- tasks no finite run completes (BUCHI_SUITE below; docs/ltl.md, "Tasks no finite run completes") ---
    # A3, never entering A4: done when A3 is reached with A4 never entered (the episode ends there).
    "reach-never": "G !A4 & F A3",
    # A1 and A3 again and again, never A4: scored by its accepting visits, one per A1 -> A3 round.
    "patrol2": "G F A1 & G F A3 & G !A4",
    # A1, A2 and A3 again and again, never A4.
    "patrol3": "G F A1 & G F A2 & G F A3 & G !A4",
    # every A1 answered by a later A2, and A1 again and again.
    "respond": "G (A1 -> F A2) & G F A1",
    # A2 from some time on, for good: no deterministic Büchi automaton (refused in one line).
    "persist": "F G A2",
}
"""Task name -> formula in the syntax of ``d2spo.ltl.parse``."""

SUITE: tuple[str, ...] = ("tour3", "tour4", "strict4", "any-order3", "avoid-until", "never-a4", "either-then",
                          "next-pair", "next-chain", "return", "a1-and-a2")
"""The example tasks (bench/task_suite.py trains each on ``paper``); ``a1-and-a2`` cannot be done there."""
BUCHI_SUITE: tuple[str, ...] = ("reach-never", "patrol2", "patrol3", "respond", "persist")
"""Tasks no finite run completes (``bench/task_suite.py --suite buchi`` trains each on ``paper``); ``persist`` has no
deterministic Büchi automaton and is refused."""


def task_formula(name_or_formula: str) -> str:
    """The formula of a named task, or the argument itself when it is not a task name."""
    return TASKS.get(name_or_formula, name_or_formula)


def same_task(a: str, b: str) -> bool:
    """Whether two task names or formulas say the same formula, however spelt (``patrol2``,
    ``GF A1 & GF A3 & G !A4``, ``□◇A1 ∧ □◇A3 ∧ □¬A4``): equal parse trees. A formula that does not
    parse raises its LTLSyntaxError."""
    return a == b or parse(task_formula(a)) == parse(task_formula(b))


def reach_avoid_tasks(n: int, seed: int = 0, areas: int = 4, longest: int = 4) -> list[str]:
    """``n`` distinct random reach-avoid sequences over A1 .. A{areas}, a deterministic function of
    ``seed``: visit t1, then t2, ... (1 to ``longest`` targets, each other than the one before),
    and on the way to each, keep out of a random subset of the other areas (each with probability
    1/3; never the leg's target or the area the robot has just reached). Written with U and F, e.g.
    ``((!A3) U (A1 & F A2))``. The generalist trains on such a mixture (``--generalist-tasks``), so
    that the named tasks above are formulas it never saw."""
    rng = np.random.default_rng(seed)
    out: list[str] = []
    for _ in range(100 * n):
        if len(out) == n:
            break
        legs, prev = [], None
        for _ in range(int(rng.integers(1, longest + 1))):
            t = int(rng.choice([a for a in range(1, areas + 1) if a != prev]))
            avoid = [a for a in range(1, areas + 1) if a not in (t, prev) and rng.random() < 1 / 3]
            legs.append((t, avoid))
            prev = t
        f = None
        for t, avoid in reversed(legs):
            goal = f"A{t}" if f is None else f"(A{t} & {f})"
            f = f"F {goal}" if not avoid else f"(({' & '.join(f'!A{a}' for a in avoid)}) U {goal})"
        if f not in out:
            out.append(f)
    return out


HELD_OUT_RECURRENCES: frozenset = frozenset({
    (frozenset({1, 3}), frozenset({4})),  # patrol2
    (frozenset({1, 2, 3}), frozenset({4})),  # patrol3
    (frozenset({1, 2}), frozenset()),  # respond: G (A1 -> F A2) & G F A1 holds where G F A1 & G F A2 does
})
"""The suite's recurrences as (areas visited again and again, areas never entered), which
``patrol_tasks`` never draws in any wording: a generalist meets them zero-shot."""


MAX_PATROLS = 23
"""Distinct recurrences ``patrol_tasks`` can draw over A1..A4: 18 patrols of two areas, 8 of three
(each without or with one "never" area), less the suite's three (a response's runs are a patrol's)."""


def patrol_tasks(n: int, seed: int = 0, areas: int = 4) -> list[str]:
    """``n`` distinct random recurrences over A1 .. A{areas} (fewer when fewer exist: ``MAX_PATROLS``
    over four), a deterministic function of ``seed``,
    none of them one of the suite's in any wording (``HELD_OUT_RECURRENCES``): patrols of two or three areas
    (``G F A1 & G F A2``), half of them with one other area never entered (``& G !A4``), and
    responses (``G (A1 -> F A2) & G F A1``). Each has a deterministic Büchi automaton and no
    completed state: it runs to the episode limit and is scored by its accepting visits. The
    generalist trains on them beside the reach-avoid sequences (``--generalist-patrols``)."""
    rng = np.random.default_rng(seed)
    out: list[str] = []
    seen: set = set()
    for _ in range(100 * n):
        if len(out) == n:
            break
        kind = rng.choice(["patrol", "patrol", "respond"])
        if kind == "respond":
            a, b = (int(x) for x in rng.choice(np.arange(1, areas + 1), size=2, replace=False))
            key = (frozenset({a, b}), frozenset())  # the same runs as G F Aa & G F Ab
            f = f"G (A{a} -> F A{b}) & G F A{a}"
        else:
            k = int(rng.integers(2, 4)) if areas > 2 else 2
            visit = sorted(int(x) for x in rng.choice(np.arange(1, areas + 1), size=k, replace=False))
            rest = [a for a in range(1, areas + 1) if a not in visit]
            never = [int(rng.choice(rest))] if rest and rng.random() < 0.5 else []
            key = (frozenset(visit), frozenset(never))
            f = " & ".join([f"G F A{a}" for a in visit] + [f"G !A{a}" for a in never])
        if key in HELD_OUT_RECURRENCES or key in seen:
            continue
        seen.add(key)
        out.append(f)
    return out


def close_task_names(word: str) -> list[str]:
    """The task names ``word`` may be a misspelling of (``patrol22``: patrol2, patrol3), when it is
    a single word and no task name itself: read as a formula, it is one proposition of that name,
    which is rarely meant. Empty otherwise."""
    if word in TASKS or not re.fullmatch(r"[A-Za-z_][\w-]*", word):
        return []
    return difflib.get_close_matches(word, TASKS, n=3, cutoff=0.6)
