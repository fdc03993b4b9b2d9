"""A trained run as `d2spo certify` reads it (``d2spo.certify``, ``d2spo.repair``): its config, env,
learner and newest checkpoint (``load_cbf_run``), the policy whose barrier is checked (``with_policy``:
the validated one by default, as `d2spo eval` and `d2spo export` take it) and the parameters the
checks read (``policy_of``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.algos import config_sections
from d2spo.checkpoint import has_checkpoint, load_checkpoint, run_fingerprint
from d2spo.errors import RunDirError
from d2spo.run import build, carry_template, check_layout_unchanged, checkpoint_policy, load_run_config


class CBFRun(NamedTuple):
    """A loaded run: its config, env, learner, training state (carry) and checkpoint counters."""

    cfg: Any
    env: Any
    params: Any
    learner: Any
    carry: Any
    meta: dict


def load_cbf_run(run_dir: Path) -> CBFRun:
    """Load a run of a learner with a learned CBF (d2spo, sl). RunDirError/ConfigError on bad input."""
    run_dir = Path(run_dir)
    cfg = load_run_config(run_dir)  # a missing run directory, or a file given as one, is one line there
    if "cbf" not in config_sections(cfg.algo):
        raise RunDirError(f"{run_dir}: a {cfg.algo!r} run has no learned CBF to certify (use a d2spo or sl run)")
    if cfg.generalist:  # its barrier is checked per layout of a bank: the grid and search here take one layout
        raise RunDirError(f"{run_dir}: a generalist reads a field bank of layouts; certify takes a run trained on one "
                          "layout (d2spo train --algo d2spo --layout L, without --generalist)")
    if not has_checkpoint(run_dir):
        raise RunDirError(f"{run_dir}: no checkpoint (checkpoint.json) to certify")
    check_layout_unchanged(run_dir, cfg, "the barrier would be checked against another map than the one it "
                           "learnt: restore the file, or train a new run on it")
    env, params, learner = build(cfg)
    template = carry_template(learner)
    carry, meta = load_checkpoint(run_dir, template, run_fingerprint(run_dir))
    got = jax.tree_util.tree_leaves(carry)
    want = jax.tree_util.tree_leaves(template)
    if len(got) != len(want) or any(np.shape(a) != b.shape for a, b in zip(got, want)):
        raise RunDirError(f"{run_dir}: checkpoint.msgpack does not match this run's config (a foreign checkpoint?)")
    carry = jax.tree_util.tree_map(jnp.asarray, carry)
    return CBFRun(cfg, env, params, learner, carry, checkpoint_policy(run_dir, "last", learner, carry, meta)[1])


def with_policy(run: CBFRun, run_dir: Path, which: str) -> CBFRun:
    """``run`` with the actor and the safety networks (h, π_Ω, f_n) of the policy ``which`` (as
    ``d2spo eval`` and ``d2spo export`` take it: "best" is a validated run's kept policy where there is
    one, else the newest checkpoint's; "last" the newest checkpoint's); the datasets stay the
    checkpoint's. ``meta["policy"]`` says which was taken."""
    (actor, safety), meta = checkpoint_policy(run_dir, which, run.learner, run.carry, run.meta)
    c = run.carry
    carry = c.replace(td3=c.td3.replace(agent=c.agent.replace(actor=actor)), safety=safety)
    return run._replace(carry=jax.tree_util.tree_map(jnp.asarray, carry), meta=meta)


class Policy(NamedTuple):
    """The parameters certification reads: the RL actor π_rl and the safety state (h, π_Ω, f_n)."""

    actor: Any
    safety: Any


def policy_of(run: CBFRun) -> Policy:
    return Policy(run.carry.agent.actor, run.carry.safety)
