"""Count the lasso words on which ``to_dba``'s automata disagree with an independent evaluator of LTL.

    python bench/buchi_exactness.py [--formulas 60] [--words 200] [--seed 0]

The evaluator is the tests' (``tests/_ltl_reference.py``: ``holds``, the fixpoints of LTL on a
lasso u·v^ω, written without any automaton). Checked: every hand-written formula of those tests,
the Büchi suite (``ltl.tasks.BUCHI_SUITE``) and ``--formulas`` random formulas of depth <= 3 over
p, q, r (a formula without a DBA must be refused with a witness the evaluator confirms), each on
``--words`` random lassos (|u| <= 3, 1 <= |v| <= 4). Prints the counts; exit 1 on any mismatch.
"""

from __future__ import annotations

import argparse
import random
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from _ltl_reference import BINARY, UNARY, encode, holds, refutes_dba  # noqa: E402
from test_ltl_buchi import NAMED, STATES  # noqa: E402

from d2spo.ltl import NoDeterministicBuchi, to_dba  # noqa: E402
from d2spo.ltl.formula import FALSE, TRUE, Formula, Prop  # noqa: E402
from d2spo.ltl.parser import parse  # noqa: E402
from d2spo.ltl.tasks import BUCHI_SUITE, TASKS  # noqa: E402

APS = ("p", "q", "r")


def random_formula(rng: random.Random, depth: int) -> Formula:
    if depth == 0 or rng.random() < 0.25:
        return rng.choice([Prop(a) for a in APS] * 2 + [TRUE, FALSE])
    if rng.random() < 0.4:
        return rng.choice(UNARY)(random_formula(rng, depth - 1))
    return rng.choice(BINARY)(random_formula(rng, depth - 1), random_formula(rng, depth - 1))


def check(f: Formula, aps: tuple[str, ...], words: int, rng: random.Random) -> tuple[int, int, bool]:
    """(words checked, mismatches, refused) of ``f`` over ``aps``."""
    try:
        dba = to_dba(f)
    except NoDeterministicBuchi as refusal:
        return 0, int(not refutes_dba(f, refusal.witness)), True
    n, bad = 0, 0
    for _ in range(words):
        u = [rng.randrange(1 << len(aps)) for _ in range(rng.randint(0, 3))]
        v = [rng.randrange(1 << len(aps)) for _ in range(rng.randint(1, 4))]
        read = [encode(a, aps, dba.aps) for a in u], [encode(a, aps, dba.aps) for a in v]
        n += 1
        bad += dba.accepts_lasso(*read) != holds(f, aps, u, v)
    return n, bad, False


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--formulas", type=int, default=60)
    ap.add_argument("--words", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    named = sorted(set(STATES) | set(NAMED) | {TASKS[t] for t in BUCHI_SUITE})
    totals = {"named": [0, 0, 0, 0], "random": [0, 0, 0, 0]}  # formulas, words, mismatches, refused
    for kind, fs in (("named", [parse(t) for t in named]),
                     ("random", [random_formula(rng, 3) for _ in range(args.formulas)])):
        for f in fs:
            aps = tuple(sorted(f.aps())) if kind == "named" else APS
            n, bad, refused = check(f, aps, args.words, rng)
            t = totals[kind]
            t[0] += 1
            t[1] += n
            t[2] += bad
            t[3] += refused
    for kind, (nf, nw, bad, refused) in totals.items():
        print(f"{kind}: {nf} formulas ({refused} refused, each with a confirmed witness), {nw} lasso words, "
              f"{bad} mismatches")
    sys.exit(1 if totals["named"][2] or totals["random"][2] else 0)


if __name__ == "__main__":
    main()
