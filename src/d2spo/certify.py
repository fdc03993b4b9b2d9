"""`d2spo certify RUN`: Propositions 1 and 2 checked on a trained D²SPO run (docs/certify.md).

The maths is in `safety/certify.py` (per point) and `safety/bounds.py` (interval bounds). This
module loads a run, builds the nets, measures the nominal model's residual on held-out transitions,
classifies every point, runs the search for counterexamples (`certify_search.py`), and writes
RUN/certify.json and RUN/certify.png (drawn by `map_plots.certify_figure`). Nothing here prints; the CLI renders
the summary.

Nets: the run's X_L (Proposition 1) and P_exp (Proposition 2: D, the explored set, where T_e of
Eq. (9) acts), and a grid over the layout's poses (x, y, θ) mapped through the sensor: poses whose
nearest obstacle is within `unsafe_max` (the ring and contact) for Proposition 1; for Proposition
2 the grid's explored part (cells holding a P_exp row, with its automaton state) and, apart, every
free pose with every live automaton state (beyond D).
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from d2spo import certify_search as search
from d2spo.certify_load import CBFRun, Policy, load_cbf_run, policy_of
from d2spo.certify_search import cell_index, explored_cells, grid_axes, live_states, pose_grid, search_counterexamples
from d2spo.config import config_to_dict
from d2spo.envs import geometry
from d2spo.fields import check_fields
from d2spo.runio import atomic_write_json
from d2spo.safety import bounds
from d2spo.safety import certify as cert
from d2spo.safety.cbf import class_k, p_exp_threshold
from d2spo.safety.joint_policy import safe_action
from d2spo.safety.nominal import nominal_next


@dataclass(frozen=True)
class CertifyConfig:
    """What `d2spo certify` checks and how hard it searches."""

    eps_unsafe: float = 0.005
    """ε̄: radius (metres, ℓ∞ over the feature vector) of the balls around the points of ℒ (Prop. 1)."""
    eps_safe: float = 0.005
    """ε: radius (metres, ℓ∞ over the feature vector) of the balls around the points of D (Prop. 2)."""
    grid_step: float = 0.05
    """Spacing (metres) of the pose grid over the layout."""
    headings: int = 8
    """Headings θ per grid position."""
    residual_episodes: int = 32
    """Held-out episodes of the final policy (with TD3's exploration noise) on which the nominal
    model's error in h, ρ_h = |h(b(s')) − h(b(s_n(s, u)))|, is measured."""
    residual_quantile: float = 1.0
    """Quantile of the held-out residuals used as ρ_h (1.0: the largest one seen)."""
    search_starts: int = 128
    """Starting poses of each gradient search for counterexamples (the worst grid points)."""
    search_steps: int = 40
    """Gradient steps of each search."""
    seed: int = 0
    """Seed of the held-out episodes."""
    free_grid: bool = True
    """Also check Proposition 2 on every free grid pose with every live automaton state (beyond D:
    poses and states the policy may never visit; reported apart, not part of the targets)."""

    def __post_init__(self):
        check_fields(self, positive=("eps_unsafe", "eps_safe", "grid_step"), count=("headings", "residual_episodes",
                     "search_starts", "search_steps"), rate=("residual_quantile",), seed=("seed",),
                     flag=("free_grid",))


def _chunked(fn, *arrays, size: int = 8192):
    """fn over the leading axis of `arrays` (pytrees) in fixed-size padded chunks (one compilation)."""
    n = jax.tree_util.tree_leaves(arrays)[0].shape[0]
    if n == 0:
        return None
    out = []
    for i in range(0, n, size):
        part = jax.tree_util.tree_map(lambda a: a[i:i + size], arrays)
        m = jax.tree_util.tree_leaves(part)[0].shape[0]
        part = jax.tree_util.tree_map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], size - m, 0)]), part)
        out.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:m], fn(*part)))
    return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *out)


_COMPILED: dict[tuple, Any] = {}


def _compiled(run: CBFRun, ccfg: CertifyConfig) -> dict[str, Any]:
    """The jitted pieces of a check, compiled once per (learner, config): the parameters are
    arguments, so certifying another state of the same run (repair rounds, tests) reuses them."""
    key = (json.dumps(config_to_dict(run.cfg), sort_keys=True), ccfg)  # the same config builds the same learner
    if key in _COMPILED:
        return _COMPILED[key]
    lrn, env, params, cbf_cfg = run.learner, run.env, run.params, run.cfg.cbf
    H, dt, noise = lrn.H, lrn.dt, run.cfg.td3.exploration_noise
    template = jax.device_get(jax.jit(env.reset)(jax.random.PRNGKey(0), params)[0])
    alpha = class_k(cbf_cfg.alpha, cbf_cfg.alpha_coef)

    def context(pose):
        return lrn.sensed(jax.vmap(lambda p: geometry.sensed_mask(p[:2], params.geom, params.sensing_radius))(pose))

    def observe(pose, q):
        return jax.vmap(lambda p, qq: env.observe(template.replace(pose=p, q=qq), params))(
            pose, jnp.broadcast_to(jnp.asarray(q, jnp.int32), pose.shape[:1]))

    def next_features(pol: Policy, pose, ctx, obs):
        x = jax.vmap(lrn.features)(pose, ctx)
        u = safe_action(lrn.safety_nets, pol.safety, x, lrn.nets.actor.apply(pol.actor, obs))
        s_n = nominal_next(lrn.safety_nets.nominal, pol.safety.nominal, pose, u, dt)
        return x, jax.vmap(lrn.features)(s_n, ctx), u

    def p1(cbf, x):
        return cert.prop1(bounds.dense_layers(cbf), x, ccfg.eps_unsafe, H)

    def p2(cbf, x, xn, rho_h):
        return cert.prop2(bounds.dense_layers(cbf), x, xn, 0.0, ccfg.eps_safe, H, dt, cbf_cfg.alpha,
                          cbf_cfg.alpha_coef, rho_h)

    def residual(pol: Policy, key):
        k0, k1 = jax.random.split(key)
        state, obs = env.reset_batch(k0, params, ccfg.residual_episodes)

        def body(c, k):
            state, obs = c
            ka, ks = jax.random.split(k)
            u_rl = lrn.nets.actor.apply(pol.actor, obs)
            u_rl = jnp.clip(u_rl + noise * jax.random.normal(ka, u_rl.shape), lrn.nets.actor.action_low(), 1.0)
            u = lrn.execute(pol.safety, obs, u_rl, state.pose)
            state2, obs2, _, _, _, info = env.step_batch(ks, state, u, params)
            ctx = lrn.sensed(info["sensed"])
            x_true = jax.vmap(lrn.features)(info["next_pose"], ctx)
            s_n = nominal_next(lrn.safety_nets.nominal, pol.safety.nominal, info["pose"], u, dt)
            x_nom = jax.vmap(lrn.features)(s_n, ctx)
            h = lrn.safety_nets.cbf.apply(pol.safety.cbf, jnp.stack([x_true, x_nom]))
            return (state2, obs2), (jnp.max(jnp.abs(x_true - x_nom), axis=-1), jnp.abs(h[0] - h[1]))

        _, res = jax.lax.scan(body, (state, obs), jax.random.split(k1, int(params.max_steps)))
        return res[0].reshape(-1), res[1].reshape(-1)

    def h_values(cbf, pose):
        """h and the nearest-obstacle distance at poses [N, 3]."""
        x = jax.vmap(lrn.features)(pose, context(pose))
        return lrn.safety_nets.cbf.apply(cbf, x), jnp.min(x, -1)

    def e_values(pol: Policy, pose, q):
        """e through the nominal model, and the nearest-obstacle distance, at poses [N, 3] in states q."""
        x, xn, _ = next_features(pol, pose, context(pose), observe(pose, q))
        h = lrn.safety_nets.cbf.apply(pol.safety.cbf, x)
        hn = lrn.safety_nets.cbf.apply(pol.safety.cbf, xn)
        return (hn - h) / dt + alpha(h), jnp.min(x, -1)

    lo, hi = params.geom.arena_lo, params.geom.arena_hi

    def climb(values, feasible, p0, extra):
        return search.climb(values, feasible, p0, extra, lo, hi, ccfg.search_steps)

    thr = p_exp_threshold(cbf_cfg)

    def search_l(pol, p0):
        return climb(lambda p, _: h_values(pol.safety.cbf, p), lambda m, p, _: m <= cbf_cfg.unsafe_max, p0,
                     jnp.zeros(p0.shape[:1], jnp.int32))

    def search_d(pol, p0, q, explored):
        def neg_e(p, qq):
            v, m = e_values(pol, p, qq)
            return -v, m

        def inside(m, p, qq):  # in D: beyond the P_exp threshold, in an explored cell with this state
            return (m >= thr) & explored[cell_index(p, lo, ccfg, explored.shape, jnp) + (qq,)]

        bp, bv = climb(neg_e, inside, p0, q)
        return bp, -bv

    fns = {
        "residual": jax.jit(residual),
        "p1": jax.jit(p1),
        "p2_rows": jax.jit(lambda pol, pose, ctx, obs, rho_h: p2(pol.safety.cbf, *next_features(pol, pose, ctx, obs)[:2], rho_h)),
        "nearest": jax.jit(lambda pose: jnp.min(jax.vmap(lrn.features)(pose, context(pose)), -1)),
        "grid_p1": jax.jit(lambda cbf, pose: p1(cbf, jax.vmap(lrn.features)(pose, context(pose)))),
        "grid_p2": jax.jit(lambda pol, pose, q, rho_h: p2(pol.safety.cbf, *next_features(
            pol, pose, context(pose), observe(pose, q))[:2], rho_h)),
        "search_l": jax.jit(search_l),
        "search_d": jax.jit(search_d),
        "context": jax.jit(context),
        "observe": jax.jit(observe),
        "next_features": jax.jit(next_features),
    }
    _COMPILED[key] = fns
    return fns


def model_residual(run: CBFRun, ccfg: CertifyConfig, pol: Policy | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The nominal model's error on held-out transitions, in features, ‖b(s', O_s) − b(s_n(s, u), O_s)‖∞,
    and in h, |h(b(s', O_s)) − h(b(s_n(s, u), O_s))|: `residual_episodes` fresh episodes of the
    final policy with TD3's exploration noise on u_rl (the nominal model never saw them)."""
    fx, fh = _compiled(run, ccfg)["residual"](pol or policy_of(run), jax.random.PRNGKey(ccfg.seed + 20_000))
    return np.asarray(fx), np.asarray(fh)


def check_nets(run: CBFRun, ccfg: CertifyConfig, rho_h: float, data=None) -> dict[str, Any]:
    """Propositions 1-2 on every net, with the parameters of `run` and the datasets `data` (default: the
    run's own). Returns per-net arrays (status, margins, values, poses) and the explored-cell table."""
    fn, pol, cbf_cfg = _compiled(run, ccfg), policy_of(run), run.cfg.cbf
    data = run.carry.data if data is None else data
    rho_h = jnp.float32(rho_h)
    out: dict[str, Any] = {}
    unsafe = data.unsafe
    out["X_L"] = {"p": _chunked(lambda x: fn["p1"](pol.safety.cbf, x), unsafe.data[: int(unsafe.size)])}
    pe = data.p_exp
    rows = jax.tree_util.tree_map(lambda a: a[: int(pe.size)], pe.data)
    out["P_exp"] = {"p": _chunked(lambda *a: fn["p2_rows"](pol, *a, rho_h), rows.pose, rows.context, rows.obs)}
    grid = pose_grid(run, ccfg)
    nearest = _chunked(fn["nearest"], jnp.asarray(grid))
    ring = nearest <= cbf_cfg.unsafe_max
    free = nearest >= p_exp_threshold(cbf_cfg)
    out["grid_L"] = {"p": _chunked(lambda p: fn["grid_p1"](pol.safety.cbf, p), jnp.asarray(grid[ring])),
                     "pose": grid[ring]}
    # the grid's explored part: every (cell, state) of D whose cell centre is beyond the threshold
    explored = explored_cells(run, ccfg, data)
    xs, ys, th = grid_axes(run, ccfg)
    ix, iy, it, iq = np.nonzero(explored & free.reshape(explored.shape[:3])[..., None])
    pose_d, q_d = np.stack([xs[ix], ys[iy], th[it]], -1).astype(np.float32), iq.astype(np.int32)
    out["grid_D"] = {"p": _chunked(lambda p, q: fn["grid_p2"](pol, p, q, rho_h), jnp.asarray(pose_d), jnp.asarray(q_d)),
                     "pose": pose_d, "q": q_d}
    out["explored"] = explored
    if not ccfg.free_grid:
        return out
    worst, worst_q = None, None  # beyond D: every free pose, every live state, the worst state kept
    for q in live_states(run):
        p = jnp.asarray(grid[free])
        r = _chunked(lambda a, b: fn["grid_p2"](pol, a, b, rho_h), p, jnp.full(p.shape[:1], q, jnp.int32))
        if r is None:
            break
        if worst is None:
            worst, worst_q = r, np.full(r.status.shape, q)
        else:
            pick = r.margin < worst.margin
            worst = jax.tree_util.tree_map(lambda a, b: np.where(pick, a, b), r, worst)
            worst_q = np.where(pick, q, worst_q)
    out["grid_free"] = {"p": worst, "pose": grid[free], "q": worst_q}
    return out


def _net_summary(p, kind: str) -> dict[str, Any]:
    if p is None:
        return {"points": 0}
    s = cert.fractions(p.status)
    s["worst_margin"] = float(np.min(p.margin))
    s["median_lipschitz"] = float(np.median(p.lip))
    if kind == "L":
        s["max_h"] = float(np.max(p.h))
        s["certified_by_interval_bound"] = float(np.mean(np.asarray(p.h_upper) < 0))
    else:
        s["min_e"] = float(np.min(p.e))
        s["median_residual_term"] = float(np.median(p.residual_term))
    return s


DEFINITIONS = {
    "L": "X_L: the run's buffer of feature vectors sampled in the unsafe ring (Proposition 1's net)",
    "D": "P_exp: the explored set, the run's buffer of visited transitions beyond the P_exp threshold "
         "(where T_e of Eq. (9) acts; Proposition 2's net), each with pi_rl's current proposal",
    "grid_L": "every grid pose (x, y, theta) whose nearest obstacle is within unsafe_max: the ring and contact",
    "grid_D": "the grid's explored part: the centre of every grid cell (5 cm x 5 cm x one heading sector) "
              "that holds a row of P_exp, with that row's automaton state, if the centre is beyond the threshold",
    "grid_free": "beyond D: every grid pose beyond the threshold with every live automaton state, the worst "
                 "kept (poses and states the policy may never visit; a stress test, not claimed by the paper)",
    "proven": "from the weights by interval arithmetic: h < 0 on each certified ball of L; on each certified "
              "ball of D, e >= 0 for the nominal model's next state, given |h(true next) - h(nominal next)| <= rho_h",
    "measured": "rho_h: the nominal model's largest error in h on held-out transitions (not a proof)",
    "balls": "l_inf balls in the sensor-feature space b(z, O_s) (metres); nothing is proven between grid poses",
}


def certify_run(run_dir: Path, ccfg: CertifyConfig | None = None, run: CBFRun | None = None,
                search: bool = True, data=None, on_stage=None) -> tuple[dict, dict]:
    """Check Propositions 1-2 on a run (on the datasets `data`, default the run's own). Returns
    (summary, nets); `write_outputs` saves them. ``on_stage(text)``, if given, hears each stage begin."""
    ccfg = ccfg or CertifyConfig()
    stage = on_stage or (lambda text: None)
    t0, c0 = time.perf_counter(), time.process_time()
    run = run or load_cbf_run(run_dir)
    times = {}
    stage("the nominal model's residual on the data (compiling first)")
    res, res_h = model_residual(run, ccfg)
    rho_h = float(np.quantile(res_h, ccfg.residual_quantile))
    times["residual"] = time.perf_counter() - t0
    stage("Propositions 1-2 on the datasets and the grids")
    nets = check_nets(run, ccfg, rho_h, data)
    times["nets"] = time.perf_counter() - t0 - sum(times.values())
    if search:
        stage("searching for counterexamples")
    found = search_counterexamples(run, ccfg, nets, _compiled(run, ccfg), policy_of(run)) if search else {"L": [], "D": []}
    times["search"] = time.perf_counter() - t0 - sum(times.values())
    glob = {k: v / run.learner.H for k, v in bounds.global_lipschitz(bounds.dense_layers(run.carry.safety.cbf)).items()}
    keys = [k for k in ("X_L", "grid_L", "P_exp", "grid_D", "grid_free") if k in nets]
    summary = {
        "run": str(run_dir), "algo": run.cfg.algo, "task": run.cfg.task, "layout": run.cfg.layout,
        "episodes_trained": run.meta.get("episodes"), "policy": run.meta.get("policy"), "config": dataclasses.asdict(ccfg),
        "definitions": DEFINITIONS,
        "residual": {"rho_h": rho_h, "quantile": ccfg.residual_quantile, "transitions": int(res.size),
                     "h": {"p50": float(np.quantile(res_h, 0.5)), "p99": float(np.quantile(res_h, 0.99)),
                           "max": float(res_h.max())},
                     "features_m": {"p50": float(np.quantile(res, 0.5)), "p99": float(np.quantile(res, 0.99)),
                                    "max": float(res.max())}},
        "lipschitz_h_global": glob,
        "nets": {k: _net_summary(nets[k]["p"], "L" if k in ("X_L", "grid_L") else "D") for k in keys},
        "explored_cells": int(nets["explored"].any(-1).sum()),
        "counterexamples": found,
    }
    summary["certified_L"] = summary["nets"]["X_L"].get("certified", float("nan"))
    summary["certified_D"] = summary["nets"]["P_exp"].get("certified", float("nan"))
    for k in keys[1:]:
        if k != "P_exp":
            viol = 0 if nets[k]["p"] is None else int(np.sum(np.asarray(nets[k]["p"].status) == cert.VIOLATED))
            summary[f"{k}_violated"] = viol
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    summary["cpu_seconds"] = round(time.process_time() - c0, 1)
    summary["seconds_by_stage"] = {k: round(v, 1) for k, v in times.items()}
    return summary, nets


def write_outputs(run_dir: Path, run: CBFRun, ccfg: CertifyConfig, summary: dict, nets: dict) -> tuple[Path, Path]:
    """RUN/certify.json and RUN/certify.png."""
    run_dir = Path(run_dir)
    j, p = run_dir / "certify.json", run_dir / "certify.png"
    atomic_write_json(j, summary)
    maps, extent = status_maps(run, ccfg, nets)
    from d2spo.map_plots import certify_figure  # matplotlib: imported only to draw

    certify_figure(run.env.layout, maps, extent, summary, ccfg.eps_unsafe, ccfg.eps_safe, p)
    return j, p


def status_maps(run: CBFRun, ccfg: CertifyConfig, nets: dict) -> tuple[list[np.ndarray], tuple]:
    """Worst status over θ (and automaton states) per grid cell, for grid_L, grid_D and grid_free (if
    checked): arrays [ny, nx] of -1 (not in that set), 0 certified, 1 not certified, 2 violated."""
    lo, hi = np.asarray(run.params.geom.arena_lo), np.asarray(run.params.geom.arena_hi)
    xs, ys, _ = grid_axes(run, ccfg)
    maps = []
    for key in ("grid_L", "grid_D", "grid_free"):
        if key not in nets:
            continue
        m = np.full((len(ys), len(xs)), -1, np.int32)
        net = nets[key]
        if net["p"] is not None:
            ix, iy, _ = cell_index(net["pose"], lo, ccfg, (len(xs), len(ys)))
            np.maximum.at(m, (iy, ix), np.asarray(net["p"].status, np.int32))
        maps.append(m)
    return maps, (lo[0], hi[0], lo[1], hi[1])
