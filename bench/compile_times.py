"""How long a learner's programs take to lower and compile, without the compilation cache.

    python bench/compile_times.py [--task phi1] [--layout paper] [--algo d2spo] [--fast] [--no-pretrain]

Builds the learner of the config (``d2spo.run.build``) and lowers then compiles ``init`` and
``chunk`` as ``d2spo.train`` does (``learner_program``), one after the other, printing the seconds of
each phase. Run it with ``D2SPO_COMPILE_CACHE=off`` or a fresh cache directory: a cache hit is not a
compilation. Figures in bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax

from d2spo.algos.d2spo import D2SPOConfig
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.run import build
from d2spo.train import learner_program


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--algo", default="d2spo")
    ap.add_argument("--task", default="phi1")
    ap.add_argument("--layout", default="paper")
    ap.add_argument("--fast", action="store_true")
    ap.add_argument("--no-pretrain", action="store_true")
    args = ap.parse_args()
    jax.config.update("jax_enable_compilation_cache", False)
    cfg = TrainConfig(algo=args.algo, task=args.task, env=EnvConfig(layout=args.layout), episodes=32, fast=args.fast)
    if args.no_pretrain:
        cfg = dataclasses.replace(cfg, d2spo=D2SPOConfig(pretrain=False))
    _, _, learner = build(cfg.check())
    key = jax.random.PRNGKey(0)
    for name, arg in (("init", key), ("chunk", jax.eval_shape(learner.init, key))):
        t0 = time.perf_counter()
        lowered = learner_program(learner, name, donate=name == "chunk").lower(arg)
        t1 = time.perf_counter()
        lowered.compile()
        t2 = time.perf_counter()
        print(f"{name}: lower {t1 - t0:.1f} s, compile {t2 - t1:.1f} s", flush=True)


if __name__ == "__main__":
    main()
