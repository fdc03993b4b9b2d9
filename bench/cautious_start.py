"""Safety of pure exploration before any env step: uniform random proposals, raw vs through π_Ω.

    .venv/bin/python bench/cautious_start.py [--episodes 256] [--seeds 0 1 2]

For each layout, the D²SPO learner is initialised (cautious start: h, π_Ω and f_n pre-trained on
synthetic sensed data only) and ``--episodes`` episodes of uniform random proposals are run with
and without π_Ω. Last line: one JSON object {layout: {"raw": ..., "shielded": ...}} (means over seeds).
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.rollout import random_proposal_safety
from d2spo.run import build

CASES = {"paper": "phi1", "relaxed": "relaxed", "physical-4": "F A3", "random:7": "F A4"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=256)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args()
    out = {}
    for layout, task in CASES.items():
        raw, shielded = [], []
        for seed in args.seeds:
            cfg = TrainConfig(algo="d2spo", task=task, seed=seed, env=EnvConfig(layout=layout)).check()
            env, params, learner = build(cfg)
            carry = jax.jit(learner.init)(jax.random.PRNGKey(seed))
            raw.append(random_proposal_safety(learner, carry, env, params, False, args.episodes, seed + 100))
            shielded.append(random_proposal_safety(learner, carry, env, params, True, args.episodes, seed + 100))
        out[layout] = {"raw": round(float(np.mean(raw)), 4), "shielded": round(float(np.mean(shielded)), 4)}
        print(f"{layout:12s} random proposals safe in {100 * out[layout]['raw']:.1f}% of episodes; "
              f"through pi_Omega: {100 * out[layout]['shielded']:.1f}%  (seeds {args.seeds})", flush=True)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
