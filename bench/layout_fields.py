"""Time the layout generator and the two solvers of ``envs.layout_bank`` (32 fields per layout).

    PYTHONPATH=src python bench/layout_fields.py --layouts 16 --bank 1024

Per layout: ``generator.generate``; ``fields_numpy`` (scipy Dijkstra, one layout at a time);
``fields_jax`` jitted and vmapped, one layout per call and ``--chunk`` per call (after a compile
that is timed apart). Both solvers are checked to agree. Then the time to build a bank of
``--bank`` layouts (generator + fields) with the faster solver; ``--bank 0`` skips it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import numpy as np

from d2spo.envs import generator
from d2spo.envs import layout_bank as lb


def _timed(fn, *args):
    t = time.perf_counter()
    out = fn(*args)
    jax.block_until_ready(out)
    return out, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layouts", type=int, default=16, help="layouts timed per solver (seeds 0..N-1)")
    ap.add_argument("--chunk", type=int, default=16, help="layouts per vmapped JAX call")
    ap.add_argument("--grid", type=int, default=lb.G)
    ap.add_argument("--bank", type=int, default=1024, help="layouts in the bank timed at the end (0: none)")
    args = ap.parse_args()
    n, g = args.layouts, args.grid

    gen = [_timed(generator.generate, s) for s in range(n)]
    layouts = [lay for lay, _ in gen]
    bank = lb.pack(layouts)
    arrays = (bank.arena, bank.box_lo, bank.box_hi, bank.box_mask, bank.area_center, bank.area_radius)
    one = lambda k: [a[k] for a in arrays]  # noqa: E731

    lb.fields_numpy(*one(0), grid=g)  # compiles the step costs (shared by both solvers)
    ref, t_np = zip(*(_timed(lb.fields_numpy, *one(k), g) for k in range(n)), strict=True)

    single = lambda k: lb._fields_batch(*[a[k:k + 1] for a in arrays], g)  # noqa: E731
    _, compile_one = _timed(single, 0)
    out1, t_one = zip(*(_timed(single, k) for k in range(n)), strict=True)
    c = min(args.chunk, n)
    batch = lambda s: lb._fields_batch(*[a[s:s + c] for a in arrays], g)  # noqa: E731
    _, compile_chunk = _timed(batch, 0)
    t_chunk = [_timed(batch, s)[1] / c for s in range(0, n - c + 1, c)]
    got = np.concatenate([np.asarray(o) for o in out1])
    err = float(np.max(np.abs(got - np.stack(ref)) / np.maximum(np.stack(ref), 1.0)))

    res = {
        "grid": g, "layouts": n, "generate_s": statistics.median(t for _, t in gen),
        "numpy_s": statistics.median(t_np), "jax_one_s": statistics.median(t_one), "jax_chunk": c,
        "jax_chunk_s_per_layout": statistics.median(t_chunk), "jax_compile_one_s": compile_one,
        "jax_compile_chunk_s": compile_chunk, "max_rel_diff": err,
    }
    print(json.dumps(res, indent=1))
    if args.bank:
        fastest = min(("numpy", res["numpy_s"]), ("jax", min(res["jax_one_s"], res["jax_chunk_s_per_layout"])),
                      key=lambda m: m[1])[0]
        t = time.perf_counter()
        drawn = [generator.generate(s) for s in range(args.bank)]
        t_gen = time.perf_counter() - t
        built, t_fields = _timed(lb.bank_of, drawn, fastest, c, g)
        print(json.dumps({"bank": args.bank, "method": fastest, "generate_s": t_gen, "fields_s": t_fields,
                          "total_s": t_gen + t_fields, "fields_mb": built.fields.nbytes / 2**20}, indent=1))


if __name__ == "__main__":
    main()
