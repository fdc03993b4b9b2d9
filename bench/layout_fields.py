"""Time the world generator and the two solvers of ``envs.layout_bank`` (one field per task state).

    PYTHONPATH=src python bench/layout_fields.py --layouts 16 --bank 256

Per slot: ``world.generate``; ``fields_numpy`` (scipy Dijkstra, one slot at a time); ``fields_jax``
jitted and vmapped, one slot per call and ``--chunk`` per call (after a compile that is timed
apart), for the generalist's default task mixture (ϕ1 and 16 reach-avoid sequences: S states per
slot). Both solvers are checked to agree. Then the time to build a bank of ``--bank`` slots
(generator + roles + fields, ``GeneralistEnv.bank``'s "auto" choice); ``--bank 0`` skips it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import numpy as np

from d2spo.config import GENERALIST_TASKS
from d2spo.envs import bank_fields as bf
from d2spo.envs import layout_bank as lb
from d2spo.envs import world
from d2spo.envs.task_plan import task_plan
from d2spo.ltl.tasks import reach_avoid_tasks


def _timed(fn, *args, **kw):
    t = time.perf_counter()
    out = fn(*args, **kw)
    jax.block_until_ready(out)
    return out, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layouts", type=int, default=16, help="slots timed per solver (world:0..N-1)")
    ap.add_argument("--chunk", type=int, default=16, help="slots per vmapped JAX call")
    ap.add_argument("--grid", type=int, default=bf.G)
    ap.add_argument("--bank", type=int, default=256, help="slots in the bank timed at the end (0: none)")
    args = ap.parse_args()
    n, g = args.layouts, args.grid
    plan = task_plan(["phi1", *reach_avoid_tasks(GENERALIST_TASKS)], "event")

    gen = [_timed(world.generate, s) for s in range(n)]
    layouts = [lay for lay, _ in gen]
    roles = [plan.slot_roles(lay, k % len(plan.names)) for k, lay in enumerate(layouts)]
    bank = lb.pair(lb.pack(layouts), *(np.stack(x) for x in zip(*roles)))
    arrays = lb._slot_args(bank)
    one = lambda k: [a[k] for a in arrays]  # noqa: E731

    bf.fields_numpy(*one(0), grid=g)  # compiles the step costs (shared by both solvers)
    ref, t_np = zip(*(_timed(bf.fields_numpy, *one(k), grid=g) for k in range(n)), strict=True)

    single = lambda k: bf.fields_batch(*[a[k:k + 1] for a in arrays], g)  # noqa: E731
    _, compile_one = _timed(single, 0)
    out1, t_one = zip(*(_timed(single, k) for k in range(n)), strict=True)
    c = min(args.chunk, n)
    batch = lambda s: bf.fields_batch(*[a[s:s + c] for a in arrays], g)  # noqa: E731
    _, compile_chunk = _timed(batch, 0)
    t_chunk = [_timed(batch, s)[1] / c for s in range(0, n - c + 1, c)]
    got = np.concatenate([np.asarray(o) for o in out1])
    want = np.stack(ref)
    finite = np.isfinite(want)
    err = float(np.max(np.abs(got[finite] - want[finite]) / np.maximum(want[finite], 1.0)))

    res = {
        "grid": g, "slots": n, "states_per_slot": plan.states, "generate_s": statistics.median(t for _, t in gen),
        "numpy_s_per_slot": statistics.median(t_np), "jax_one_s": statistics.median(t_one), "jax_chunk": c,
        "jax_chunk_s_per_slot": statistics.median(t_chunk), "jax_compile_one_s": compile_one,
        "jax_compile_chunk_s": compile_chunk, "max_rel_diff": err,
    }
    print(json.dumps(res, indent=1))
    if args.bank:
        t = time.perf_counter()
        drawn = [world.generate(s) for s in range(args.bank)]
        t_gen = time.perf_counter() - t
        built, t_fields = _timed(plan.bank, drawn)
        print(json.dumps({"bank": args.bank, "generate_s": t_gen, "roles_and_fields_s": t_fields,
                          "total_s": t_gen + t_fields, "fields_mb": built.fields.nbytes / 2**20}, indent=1))


if __name__ == "__main__":
    main()
