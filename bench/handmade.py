"""A generalist on the hand-made layouts (tests/data/layouts/handmade), zero-shot: layouts no generator drew.

    python bench/handmade.py --run RUN [--episodes 100] [--policy best|last] [--cases N] [--out runs/handmade]

Each layout with areas A1..A4 is evaluated on three tasks: ϕ1 (``phi1``), the reverse tour
``F (A3 & F (A2 & F A1))`` and the avoid-until ``!A4 U (A2 & F A3)``; ``lab-12x6`` on
``F (desk & F kitchen)`` and ``F (door & F desk)``; ``warehouse-16`` on ``F (dock & F A1)`` and
``F (A2 & F dock)``. Every (layout, task) pair is checked as for training (``zero_shot.generalist_layout``:
one line and no figure when it cannot be done) and runs ``--episodes`` deterministic episodes with
π_Ω alone and with the runtime filter. Prints a markdown table and the targets' figures (mean
completion with the filter, the worst cell, π_Ω's and the filter's safety); writes OUT/handmade.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent.parent / "tests" / "data" / "layouts" / "handmade"
A_TASKS = ("phi1", "F (A3 & F (A2 & F A1))", "!A4 U (A2 & F A3)")
OWN_TASKS = {"lab-12x6": ("F (desk & F kitchen)", "F (door & F desk)"),
             "warehouse-16": ("F (dock & F A1)", "F (A2 & F dock)")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="a generalist run directory")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--out", type=Path, default=Path("runs/handmade"))
    ap.add_argument("--policy", choices=("best", "last"), default="best",
                    help="the run's validated policy (best) or its newest checkpoint's (last)")
    ap.add_argument("--cases", type=int, default=None, help="the first N cases only (a check of the script)")
    args = ap.parse_args()
    from d2spo import compile_cache

    compile_cache.enable()  # the commands' cache: a second seed or mode of the same program compiles nothing

    from d2spo.errors import UserError
    from d2spo.evaluate import eval_env_config
    from d2spo.run import load_policy
    from d2spo.zero_shot import generalist_layout, generalist_on, rollouts, seen_forbidden_range

    cfg, _, policy, meta = load_policy(args.run, args.policy)
    env_cfg = seen_forbidden_range(eval_env_config(cfg, None))  # as d2spo eval sees it
    print(f"{args.run}: its {meta['policy']} policy", flush=True)
    rows = []
    cases = [(path, task) for path in sorted(HERE.glob("*.json")) for task in OWN_TASKS.get(path.stem, A_TASKS)]
    if args.cases is not None and args.cases < len(cases):
        print(f"--cases {args.cases}: the first {args.cases} of the {len(cases)} hand-made cases only; "
              "these figures are not the table's", flush=True)
    for path, task in cases[:args.cases]:
        row = {"layout": path.stem, "task": task}
        try:
            checked = [generalist_layout(env_cfg, str(path), task, cfg.cbf.d)]
        except UserError as e:
            row["refused"] = str(e)
            rows.append(row)
            print(json.dumps(row), flush=True)
            continue
        for mode, on in (("alone", False), ("filter", True)):
            c = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, runtime_filter=on))
            env, params, learner, limit = generalist_on(c, env_cfg, task, checked)
            (res,) = rollouts(env, params, learner, policy, checked, args.episodes, 0, limit)
            row[mode] = {k: res[k] for k in ("completion_rate", "safety_rate", "mean_length")}
            row["max_steps"] = limit
        rows.append(row)
        print(json.dumps(row), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "handmade.json").write_text(json.dumps({"run": str(args.run), "policy": meta["policy"],
                                                        "episodes": args.episodes, "cases_of": len(cases), "rows": rows}, indent=1))
    done = [r for r in rows if "filter" in r]
    print("\n| layout | task | complete (π_Ω) | safe (π_Ω) | complete (filter) | safe (filter) |")
    print("|---|---|---:|---:|---:|---:|")
    for r in rows:
        if "refused" in r:
            print(f"| {r['layout']} | `{r['task']}` | refused: {r['refused']} | | | |")
            continue
        a, f = r["alone"], r["filter"]
        print(f"| {r['layout']} | `{r['task']}` | {a['completion_rate']:.0%} | {a['safety_rate']:.1%} | "
              f"{f['completion_rate']:.0%} | {f['safety_rate']:.1%} |")
    if done:
        comp = [r["filter"]["completion_rate"] for r in done]
        worst = min(done, key=lambda r: r["filter"]["completion_rate"])
        print(f"\n{len(done)} cases of {len(cases)} ({len(rows) - len(done)} refused): mean completion with the filter "
              f"{np.mean(comp):.1%} (π_Ω alone {np.mean([r['alone']['completion_rate'] for r in done]):.1%}); "
              f"worst {worst['filter']['completion_rate']:.0%} ({worst['layout']}, {worst['task']}); safety π_Ω "
              f"{np.mean([r['alone']['safety_rate'] for r in done]):.2%} (worst "
              f"{min(r['alone']['safety_rate'] for r in done):.0%}), with the filter "
              f"{np.mean([r['filter']['safety_rate'] for r in done]):.2%} (worst "
              f"{min(r['filter']['safety_rate'] for r in done):.0%})")


if __name__ == "__main__":
    main()
