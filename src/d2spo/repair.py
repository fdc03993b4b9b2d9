"""`d2spo certify RUN --repair`: counterexample-guided training of h and π_Ω (docs/certify.md).

Each round adds the *counterexamples* of the current state to the run's datasets (nothing that is
merely not certified): the grid poses where a proposition fails at the point itself (h ≥ 0 in the
ring or in contact, e < 0 on an explored cell) and every point the gradient search found with
h ≥ 0 or e < 0. Features go to X_L; poses to P_exp as rows whose next pose is the nominal model's,
so T_e sees them through s_n exactly as the runtime filter does. Then UPDATE(Ω, Θ) of Algorithm 1
runs `calls` times (`safety.joint_policy.update`, the nominal model refitted on T as in training;
π_rl is not trained), and the state is certified again.

Every round is certified on the run's **original** datasets (X_L and P_exp as training left them),
so rounds are compared on the same points and the added rows do not count themselves. A round is
better when it is worse in nothing (neither certified fraction, of ℒ or of D, falls; no more grid
points of ℒ or of D's explored part are violated) and better in something; repair stops at the
first round that is not better and keeps the best. With `eval_episodes > 0` the kept state is then evaluated (`d2spo
eval`'s rollout, the same episodes before and after); if its safety or completion rate is lower
than the original's, the original state is kept instead and the report says so. The result is an
ordinary run directory: the original's files and checkpoint with the kept h, π_Ω and f_n (and their
optimiser states) in place of the original ones; the datasets are the original's (the added
counterexamples were a means of training), so `d2spo certify OUT` checks the same points and
reproduces the kept round's figures. `d2spo eval` and `d2spo train --resume` work on it.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from d2spo import replay
from d2spo.certify import CertifyConfig, _compiled, certify_run, write_outputs
from d2spo.certify_load import CBFRun, load_cbf_run, policy_of
from d2spo.checkpoint import Checkpoints, run_fingerprint
from d2spo.errors import RunDirError
from d2spo.evaluate import EvalConfig, evaluate_run
from d2spo.fields import check_fields
from d2spo.run import best_policy_path
from d2spo.runio import atomic_write_json, read_json
from d2spo.safety import certify as cert
from d2spo.safety import datasets as sd
from d2spo.safety.joint_policy import update
from d2spo.safety.nominal import nominal_next
from d2spo.wandb_log import RUN_ID


def _figures(s: dict) -> tuple[float, float, int, int]:
    """(certified fraction of ℒ, of D, violated grid points of ℒ, of D's explored part); nan → 0."""
    return (float(np.nan_to_num(s["certified_L"])), float(np.nan_to_num(s["certified_D"])),
            int(s["grid_L_violated"]), int(s.get("grid_D_violated", 0)))


def better(s: dict, than: dict) -> bool:
    """True when `s` is better than `than` and worse in nothing: neither certified fraction falls, no
    more grid points of ℒ are violated and no more of D's (each count on its own: fewer violations in
    D do not buy new ones in the ring, Proposition 1's), and one of the four improves."""
    now, was = _figures(s), _figures(than)
    certified_ok = now[0] >= was[0] and now[1] >= was[1]
    violated_ok = now[2] <= was[2] and now[3] <= was[3]
    return certified_ok and violated_ok and (now[0] > was[0] or now[1] > was[1] or now[2] < was[2] or now[3] < was[3])


def counterexamples(nets: dict) -> tuple[np.ndarray, list[tuple[np.ndarray, int]]]:
    """Poses for X_L, and (poses, automaton state) groups for P_exp: the violated grid points of ℒ and
    of D's explored part, and every point of the searches where h ≥ 0 or e < 0."""
    poses_l = [np.zeros((0, 3), np.float32)]
    g1 = nets["grid_L"]
    if g1["p"] is not None:
        poses_l.append(g1["pose"][np.asarray(g1["p"].status) == cert.VIOLATED])
    if "search_L" in nets:
        poses_l.append(nets["search_L"]["pose"][nets["search_L"]["h"] >= 0])
    pose_d, q_d = [np.zeros((0, 3), np.float32)], [np.zeros((0,), np.int32)]
    g2 = nets["grid_D"]
    if g2["p"] is not None:
        bad = np.asarray(g2["p"].status) == cert.VIOLATED
        pose_d.append(g2["pose"][bad])
        q_d.append(g2["q"][bad])
    if "search_D" in nets:
        bad = nets["search_D"]["e"] < 0
        pose_d.append(nets["search_D"]["pose"][bad])
        q_d.append(nets["search_D"]["q"][bad])
    pose_d, q_d = np.concatenate(pose_d), np.concatenate(q_d)
    groups = [(pose_d[q_d == q], int(q)) for q in np.unique(q_d)]
    return np.unique(np.concatenate(poses_l), axis=0), groups


def add_counterexamples(run: CBFRun, ccfg: CertifyConfig, carry, poses_l: np.ndarray, groups, copies: int):
    """The datasets with `copies` copies of each new row (the oldest rows make room)."""
    fn, pol = _compiled(run, ccfg), policy_of(run._replace(carry=carry))
    add_unsafe, add_explored = _adders(run.learner, fn)
    data = carry.data
    if len(poses_l):
        data = add_unsafe(data, jnp.asarray(np.repeat(poses_l, copies, 0)))
    for poses, q in groups:
        data = add_explored(data, pol, carry.agent.actor, carry.safety.nominal,
                            jnp.asarray(np.repeat(poses, copies, 0)), jnp.int32(q))
    return carry.replace(data=data)


_ADD: dict = {}


def _adders(lrn, fn: dict):
    """``add_counterexamples``'s two steps, jitted once per learner and certify functions (each
    compiles once per number of rows): X_L's new rows, and P_exp's rows for one automaton state."""
    if (id(lrn), id(fn)) not in _ADD:
        def unsafe(data, p):
            x = jax.vmap(lrn.features)(p, fn["context"](p))
            return data.replace(unsafe=replay.add_batch(data.unsafe, x))

        def explored(data, pol, actor, nominal, p, q):
            ctx = fn["context"](p)
            obs = fn["observe"](p, q)
            _, _, u = fn["next_features"](pol, p, ctx, obs)
            u_rl = lrn.nets.actor.apply(actor, obs)
            nxt = nominal_next(lrn.safety_nets.nominal, nominal, p, u, lrn.dt)
            tr = sd.Transition(pose=p, next_pose=nxt, context=ctx, obs=obs, action=u, u_rl=u_rl)
            return data.replace(p_exp=replay.add_batch(data.p_exp, tr))

        _ADD[(id(lrn), id(fn))] = jax.jit(unsafe), jax.jit(explored)
    return _ADD[(id(lrn), id(fn))]


_TRAIN: dict = {}


def train_safety(run: CBFRun, carry, key: jax.Array, calls: int, gamma_exp: float | None = None):
    """`calls` times UPDATE(Ω, Θ) of Algorithm 1 on the run's datasets (the actor is not trained),
    with T_e's margin γ_exp replaced by `gamma_exp` if given."""
    lrn = run.learner
    cbf_cfg = lrn.cbf_cfg if gamma_exp is None else dataclasses.replace(lrn.cbf_cfg, gamma_exp=float(gamma_exp))
    if (id(lrn), calls, cbf_cfg) not in _TRAIN:
        def many(actor, safety, data, key):
            def body(s, k):
                s, m = update(k, s, data, nets=lrn.safety_nets, cfg=cbf_cfg, features_fn=lrn.features_for_grad,
                              dt=lrn.dt, u_rl_fn=lambda o: lrn.nets.actor.apply(actor, o))
                return s, m["safety/total"]

            return jax.lax.scan(body, safety, jax.random.split(key, calls))

        _TRAIN[(id(lrn), calls, cbf_cfg)] = jax.jit(many)
    safety, losses = _TRAIN[(id(lrn), calls, cbf_cfg)](carry.agent.actor, carry.safety, carry.data, key)
    return carry.replace(safety=safety), float(losses[-1])


def _row(r: int, s: dict, **extra) -> dict:
    return {"round": r, "certified_L": s["certified_L"], "certified_D": s["certified_D"],
            "grid_L_violated": s["grid_L_violated"], "grid_D_violated": s.get("grid_D_violated", 0),
            "certified_grid_D": s["nets"]["grid_D"].get("certified", float("nan")),
            "worst_margin_D": s["nets"]["P_exp"].get("worst_margin", float("nan")),
            "rho_h": s["residual"]["rho_h"], **extra}


def _save(run_dir: Path, out: Path, carry, meta: dict, note: dict) -> None:
    if out.exists():
        shutil.rmtree(out)
    # not the W&B run's id (wandb_log.RUN_ID): the repaired run is not the W&B run of the one it repairs
    # nor the validated policy (best_policy_path) and its entry: the repaired h and π_Ω are the
    # checkpoint's, and `d2spo eval`, `export` and `certify` take a kept policy before it
    shutil.copytree(run_dir, out, ignore=shutil.ignore_patterns("checkpoint*", "certify.*", "eval-*.json", ".*",
                                                                RUN_ID, best_policy_path(out).name))
    Checkpoints(out, run_fingerprint(out)).save(carry, {k: v for k, v in meta.items() if k != "best"})
    if (out / "summary.json").is_file():  # training figures stay true; the final evaluations do not
        s = read_json(out / "summary.json", "summary")
        s.pop("eval", None)
        s.pop("eval_best", None)
        atomic_write_json(out / "summary.json", dict(s, **note))


def _evaluate(path: Path, episodes: int) -> dict:
    r = evaluate_run(path, EvalConfig(episodes=episodes, policy="last"))  # the checkpoint's: what repair trains
    return {k: r[k] for k in ("safety_rate", "completion_rate", "mean_return", "mean_distance")}


@dataclasses.dataclass(frozen=True)
class RepairConfig:
    """How `d2spo certify --repair` repairs a run."""

    rounds: int = 6
    """With --repair: at most this many rounds of (certify, add counterexamples, train)."""
    calls: int = 50
    """With --repair: UPDATE(Ω, Θ) calls of Algorithm 1 per round (each `cbf.updates_per_iter` steps)."""
    copies: int = 4
    """With --repair: copies of each counterexample added to the datasets."""
    gamma_exp: float | None = None
    """With --repair: T_e's margin γ_exp while repairing (default: the margin certification asks of the
    median point of D, ρ_h/Δt + L_e ε; 0: the run's own)."""
    eval_episodes: int = 100
    """With --repair: evaluate the original and the repaired policy on these episodes (as `d2spo eval`)
    and keep the original state if the repaired one is less safe or completes less (0: skip)."""

    def __post_init__(self):
        check_fields(self, nullable=("gamma_exp",), count=("rounds", "calls", "copies"), natural=("eval_episodes",),
                     non_negative=("gamma_exp",))


def repair_run(run_dir: Path, out: Path, ccfg: CertifyConfig | None = None, rcfg: RepairConfig = RepairConfig(),
               progress: Callable[[dict], None] | None = None) -> dict[str, Any]:
    """Repair a run into `out` (a new run directory) as ``rcfg`` says. Returns {"rounds", "before",
    "after", "kept", "eval_before", "eval_after", "gamma_exp"}; `kept` is the round whose state `out`
    holds (0: the original). T_e's margin while repairing, `rcfg.gamma_exp`: None: the margin
    certification asks of the median point of D, ρ_h/Δt + L_e ε (the run's own γ_exp is usually far
    below it); 0: the run's own."""
    ccfg = ccfg or CertifyConfig()
    rounds, calls, copies, eval_episodes, gamma_exp = rcfg.rounds, rcfg.calls, rcfg.copies, rcfg.eval_episodes, rcfg.gamma_exp
    run_dir, out = Path(run_dir), Path(out)
    if out.resolve() == run_dir.resolve():
        raise RunDirError(f"{out}: --repair writes a new run directory; choose another --out")
    if out.exists():
        raise RunDirError(f"{out}: already exists; choose another --out")
    run = load_cbf_run(run_dir)
    data0 = run.carry.data  # every round is certified on the original datasets
    key = jax.random.PRNGKey(ccfg.seed + 30_000)
    carry = run.carry
    summary, nets = certify_run(run_dir, ccfg, run=run, data=data0)
    before, nets0 = summary, nets
    if gamma_exp is None:
        gamma_exp = summary["residual"]["rho_h"] / run.learner.dt + summary["nets"]["P_exp"].get(
            "median_lipschitz", 0.0) * ccfg.eps_safe
    gamma_exp = float(gamma_exp) if gamma_exp and gamma_exp > 0 else None
    history = [_row(0, summary)]
    best = {"round": 0, "carry": carry, "summary": summary, "nets": nets}
    if progress:
        progress(history[-1])
    for r in range(1, rounds + 1):
        poses_l, groups = counterexamples(nets)
        n_d = int(sum(len(p) for p, _ in groups))
        if not len(poses_l) and not n_d:
            break  # nothing left to learn from
        carry = add_counterexamples(run, ccfg, carry, poses_l, groups, copies)
        key, k = jax.random.split(key)
        carry, loss = train_safety(run, carry, k, calls, gamma_exp)
        summary, nets = certify_run(out, ccfg, run=run._replace(carry=carry), data=data0)
        ok = better(summary, best["summary"])
        history.append(_row(r, summary, added_L=int(len(poses_l)), added_D=n_d, loss=loss, better=ok))
        if progress:
            progress(history[-1])
        if not ok:
            break  # the certified fraction stopped rising
        best = {"round": r, "carry": carry, "summary": summary, "nets": nets}
    note = {"repaired_from": str(run_dir), "repair_round": best["round"]}
    _save(run_dir, out, best["carry"].replace(data=data0), run.meta, note)
    res = {"rounds": history, "before": before, "kept": best["round"], "eval_before": None, "eval_after": None,
           "gamma_exp": gamma_exp if gamma_exp is not None else run.cfg.cbf.gamma_exp}
    if eval_episodes and best["round"] > 0:
        res["eval_before"] = _evaluate(run_dir, eval_episodes)
        res["eval_after"] = _evaluate(out, eval_episodes)
        worse = any(res["eval_after"][k] < res["eval_before"][k] for k in ("safety_rate", "completion_rate"))
        if progress:
            progress({"eval_before": res["eval_before"], "eval_after": res["eval_after"], "reverted": worse})
        if worse:  # never leave the run worse than it was: keep the original state
            res["reverted_from_round"] = best["round"]
            best = {"round": 0, "carry": run.carry, "summary": before, "nets": nets0}
            note["repair_round"] = 0
            _save(run_dir, out, run.carry, run.meta, dict(note, reverted="the repaired policy evaluated worse"))
            res["kept"] = 0
    summary = dict(best["summary"], run=str(out), repaired_from=str(run_dir), repair_rounds=history,
                   repair_kept_round=res["kept"], repair_gamma_exp=res["gamma_exp"], eval_before=res["eval_before"], eval_after=res["eval_after"])
    if "reverted_from_round" in res:
        summary["repair_reverted_from_round"] = res["reverted_from_round"]
    write_outputs(out, run._replace(carry=best["carry"]), ccfg, summary, best["nets"])
    res["after"] = summary
    return res
