"""`d2spo certify RUN --repair`: counterexample-guided training of h and π_Ω (docs/certify.md).

Each round: certify the current state; add the points that are not certified or violated, and
the gradient search's counterexamples, to the run's datasets (features to X_L; poses to P_exp as
rows whose next pose is the nominal model's, so T_e sees them through s_n exactly as the runtime
filter does); then run UPDATE(Ω, Θ) of Algorithm 1 (`safety.joint_policy.update`, the nominal
model is refitted on T as in training). Repair stops when the certified fraction (the smaller of
ℒ's and D's) stops rising, and keeps the best round. The result is written as an ordinary run
directory: the original's files, with the repaired state in its checkpoint (the same format,
`runio.save_checkpoint`), so `d2spo eval` and `d2spo train --resume` work on it.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.algos.common import replay
from d2spo.certify import CBFRun, CertifyConfig, _compiled, certify_run, load_cbf_run, policy_of, write_outputs
from d2spo.errors import RunDirError
from d2spo.safety import certify as cert
from d2spo.safety import datasets as sd
from d2spo.safety.joint_policy import update
from d2spo.safety.nominal import nominal_next


def _score(summary: dict) -> float:
    return min(summary["certified_L"], summary["certified_D"])


def _new_rows(run: CBFRun, nets: dict, found: dict) -> tuple[np.ndarray, list[tuple[np.ndarray, int]]]:
    """Features for X_L and (poses, automaton state) groups for P_exp: every grid point that is
    not certified, and the search's counterexamples."""
    feats = []
    g1 = nets["grid_L"]
    if g1["p"] is not None:
        feats.append(g1["pose"][np.asarray(g1["p"].status) != cert.CERTIFIED])
    if found["L"]:
        feats.append(np.array([c["pose"] for c in found["L"] if c["counterexample"]], np.float32).reshape(-1, 3))
    poses_l = np.concatenate(feats) if feats else np.zeros((0, 3), np.float32)
    groups = []
    g2 = nets["grid_D"]
    if g2["p"] is not None:
        bad = np.asarray(g2["p"].status) != cert.CERTIFIED
        for q in np.unique(g2["q"][bad]):
            groups.append((g2["pose"][bad & (g2["q"] == q)], int(q)))
    for c in found["D"]:
        if c["counterexample"]:
            groups.append((np.array([c["pose"]], np.float32), int(c["q"])))
    return poses_l, groups


def add_counterexamples(run: CBFRun, ccfg: CertifyConfig, carry, poses_l: np.ndarray, groups, copies: int):
    """The datasets with `copies` copies of each new row (so they weigh in the next minibatches)."""
    lrn, fn, pol = run.learner, _compiled(run, ccfg), policy_of(run._replace(carry=carry))
    data = carry.data
    if len(poses_l):
        p = jnp.asarray(np.repeat(poses_l, copies, 0))
        x = jax.vmap(lrn.features)(p, fn["context"](p))
        data = data.replace(unsafe=replay.add_batch(data.unsafe, x))
    for poses, q in groups:
        p = jnp.asarray(np.repeat(poses, copies, 0))
        ctx = fn["context"](p)
        obs = fn["observe"](p, jnp.int32(q))
        _, _, u = fn["next_features"](pol, p, ctx, obs)
        u_rl = lrn.nets.actor.apply(carry.agent.actor, obs)
        nxt = nominal_next(lrn.safety_nets.nominal, carry.safety.nominal, p, u, lrn.dt)
        tr = sd.Transition(pose=p, next_pose=nxt, context=ctx, obs=obs, action=u, u_rl=u_rl)
        data = data.replace(p_exp=replay.add_batch(data.p_exp, tr))
    return carry.replace(data=data)


_TRAIN: dict = {}


def train_safety(run: CBFRun, carry, key: jax.Array, calls: int):
    """`calls` times UPDATE(Ω, Θ) of Algorithm 1 on the run's datasets (the actor is not trained)."""
    lrn = run.learner
    if (id(lrn), calls) not in _TRAIN:
        def many(actor, safety, data, key):
            def body(s, k):
                s, m = update(k, s, data, nets=lrn.safety_nets, cfg=lrn.cbf_cfg, features_fn=lrn.features,
                              dt=lrn.dt, u_rl_fn=lambda o: lrn.nets.actor.apply(actor, o))
                return s, m["safety/total"]

            return jax.lax.scan(body, safety, jax.random.split(key, calls))

        _TRAIN[(id(lrn), calls)] = jax.jit(many)
    safety, losses = _TRAIN[(id(lrn), calls)](carry.agent.actor, carry.safety, carry.data, key)
    return carry.replace(safety=safety), float(losses[-1])


def repair_run(run_dir: Path, out: Path, ccfg: CertifyConfig | None = None, rounds: int = 6, calls: int = 100,
               copies: int = 4, progress: Callable[[dict], None] | None = None) -> dict[str, Any]:
    """Repair a run into `out` (a new run directory). Returns {"rounds": [...], "before", "after"}."""
    from d2spo.checkpoint import Checkpoints, run_fingerprint
    from d2spo.runio import atomic_write_json, read_json

    ccfg = (ccfg or CertifyConfig()).check()
    run_dir, out = Path(run_dir), Path(out)
    if out.resolve() == run_dir.resolve():
        raise RunDirError(f"{out}: --repair writes a new run directory; choose another --out")
    if out.exists():
        raise RunDirError(f"{out}: already exists; choose another --out")
    run = load_cbf_run(run_dir)
    key = jax.random.PRNGKey(ccfg.seed + 30_000)
    carry = run.carry
    summary, nets = certify_run(run_dir, ccfg, run=run)
    before = summary
    best = (_score(summary), carry, summary, nets)
    history = [{"round": 0, "certified_L": summary["certified_L"], "certified_D": summary["certified_D"],
                "grid_L_violated": summary["grid_L_violated"], "grid_D_violated": summary["grid_D_violated"]}]
    if progress:
        progress(history[-1])
    for r in range(1, rounds + 1):
        poses_l, groups = _new_rows(run, nets, summary["counterexamples"])
        carry = add_counterexamples(run, ccfg, carry, poses_l, groups, copies)
        key, k = jax.random.split(key)
        carry, loss = train_safety(run, carry, k, calls)
        run = run._replace(carry=carry)
        summary, nets = certify_run(out, ccfg, run=run)
        history.append({"round": r, "certified_L": summary["certified_L"], "certified_D": summary["certified_D"],
                        "grid_L_violated": summary["grid_L_violated"],
                        "grid_D_violated": summary["grid_D_violated"], "added_L": int(len(poses_l)),
                        "added_D": int(sum(len(p) for p, _ in groups)), "loss": loss})
        if progress:
            progress(history[-1])
        if _score(summary) > best[0] + 1e-4:
            best = (_score(summary), carry, summary, nets)
        else:
            break  # the certified fraction stopped rising
    _, carry, summary, nets = best
    shutil.copytree(run_dir, out, ignore=shutil.ignore_patterns("checkpoint*", "certify.*", "eval-*.json", ".*"))
    Checkpoints(out, run_fingerprint(out)).save(carry, run.meta)
    if (out / "summary.json").is_file():  # training figures stay true; the final evaluation does not
        s = read_json(out / "summary.json", "summary")
        s.pop("eval", None)
        atomic_write_json(out / "summary.json", dict(s, repaired_from=str(run_dir)))
    summary = dict(summary, run=str(out), repaired_from=str(run_dir), repair_rounds=history)
    write_outputs(out, run._replace(carry=carry), ccfg, summary, nets)
    return {"rounds": history, "before": before, "after": summary}
