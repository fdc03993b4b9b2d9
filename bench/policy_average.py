"""Do averaged policies hold up better than single snapshots? A generalist's validation on its snapshots.

    .venv/bin/python bench/policy_average.py --run RUN [--windows 500 1000] [--out FILE]

RUN is a ``d2spo train --generalist`` directory trained with ``--snapshots`` (policy-N.msgpack after
N episodes). Every snapshot is scored by the run's own validation (``validation.Validation``: the same
held-out layouts, tasks and episodes as in training), and so is the mean of the snapshots of the
last W episodes, for each W of ``--windows`` (every floating-point parameter averaged: the TD3
actor, π_Ω, the barrier and the nominal model alike; integer leaves from the newest snapshot).
A question for issue 33 ("training improves what it keeps"): whether weight averaging over the
late snapshots scores as well as the best single one. Prints one JSON line per policy; ``--out``
writes them all as one JSON file. ``--keep-as DIR`` writes the first window's mean as a shareable
run (DIR: config.json, summary.json, policy-best.msgpack, as docs/env.md describes) that
``d2spo eval`` and ``bench/handmade.py`` run.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp


def snapshots(run: Path) -> list[int]:
    found = [int(m.group(1)) for p in run.glob("policy-*.msgpack") if (m := re.fullmatch(r"policy-(\d+)\.msgpack", p.name))]
    return sorted(found)


def average(policies: list):
    """The leaf-wise mean of floating-point leaves; other leaves from the last policy."""
    def mean(*leaves):
        last = leaves[-1]
        if jnp.issubdtype(jnp.asarray(last).dtype, jnp.floating):
            return jnp.mean(jnp.stack([jnp.asarray(x) for x in leaves]), axis=0).astype(jnp.asarray(last).dtype)
        return last
    return jax.tree_util.tree_map(mean, *policies)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True)
    ap.add_argument("--windows", type=int, nargs="+", default=[500, 1000])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--keep-as", type=Path, default=None)
    args = ap.parse_args(argv)

    from flax import serialization

    from d2spo.run import best_policy_path, build, load_run_config, load_snapshot
    from d2spo.validation import Validation

    cfg = load_run_config(args.run)
    found = snapshots(args.run)
    if not found:
        raise SystemExit(f"{args.run}: no policy-N.msgpack snapshots (train with --snapshots)")
    env, params, learner = build(cfg)
    validation = Validation(cfg, env, params, learner)
    rows = []
    loaded = {n: load_snapshot(args.run, n, learner) for n in found}
    for n in found:
        rows.append({"policy": f"snapshot {n}", **validation(loaded[n])})
        print(json.dumps(rows[-1]), flush=True)
    last = found[-1]
    for i, w in enumerate(args.windows):
        members = [n for n in found if n > last - w]
        mean = average([loaded[n] for n in members])
        rows.append({"policy": f"mean of {len(members)} snapshots {members[0]}..{members[-1]}", **validation(mean)})
        print(json.dumps(rows[-1]), flush=True)
        if i == 0 and args.keep_as is not None:
            args.keep_as.mkdir(parents=True, exist_ok=True)
            shutil.copy(args.run / "config.json", args.keep_as / "config.json")
            summary = json.loads((args.run / "summary.json").read_text())
            summary["validation"]["best"] = {**rows[-1], "episodes": last}
            (args.keep_as / "summary.json").write_text(json.dumps(summary, indent=1))
            best_policy_path(args.keep_as).write_bytes(serialization.to_bytes(jax.device_get(mean)))
    if args.out is not None:
        args.out.write_text(json.dumps({"run": str(args.run), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
