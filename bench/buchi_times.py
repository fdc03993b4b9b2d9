"""How long ``d2spo.ltl.to_dba`` takes on the tasks issue #34 names, and the states it builds.

    python bench/buchi_times.py

Best of 3 per formula (bench/RESULTS.md).
"""

from __future__ import annotations

import time

from d2spo.ltl import to_dba

FORMULAS = ["G !A4 & F A1", "GF A1 & GF A3 & G !A4", "G (A1 -> F A2)",
            "G !purple & F (red & F (green & F yellow))", "GF blue & GF green & GF yellow & G !magenta"]


def main() -> None:
    for text in FORMULAS:
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            dba = to_dba(text)
            best = min(best, time.perf_counter() - t)
        print(f"{best * 1e3:8.2f} ms  {dba.n_states:3d} states  {text}")


if __name__ == "__main__":
    main()
