"""`d2spo certify RUN`: Propositions 1 and 2 checked on a trained D²SPO run (docs/certify.md).

The maths is in `safety/certify.py` (per point) and `safety/bounds.py` (interval bounds). This
module loads a run, builds the nets, measures the nominal model's residual on held-out transitions,
classifies every point, searches for counterexamples by gradient steps on the pose, and writes
RUN/certify.json and RUN/certify.png. Nothing here prints; the CLI renders the summary.

Nets: the run's X_L (Proposition 1) and P_exp (Proposition 2: where T_e of Eq. (9) acts), and a
grid over the layout's poses (x, y, θ) mapped through the sensor: poses whose nearest obstacle is
within `unsafe_max` (the ring and contact) are checked for Proposition 1, poses at or beyond the
P_exp threshold for Proposition 2 (with the RL proposal of every non-absorbing automaton state).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.errors import ConfigError, RunDirError
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
    search_starts: int = 64
    """Starting poses of each gradient search for counterexamples (the worst grid points)."""
    search_steps: int = 40
    """Gradient steps of each search."""
    seed: int = 0
    """Seed of the held-out episodes."""

    def check(self) -> CertifyConfig:
        for name in ("eps_unsafe", "eps_safe", "grid_step"):
            if not getattr(self, name) > 0:
                raise ConfigError(name, f"must be > 0, got {getattr(self, name)}")
        for name in ("headings", "residual_episodes"):
            if getattr(self, name) < 1:
                raise ConfigError(name, f"must be ≥ 1, got {getattr(self, name)}")
        if not 0.0 < self.residual_quantile <= 1.0:
            raise ConfigError("residual_quantile", f"must lie in (0, 1], got {self.residual_quantile}")
        return self


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
    from d2spo.algos import config_sections
    from d2spo.checkpoint import has_checkpoint, load_checkpoint, run_fingerprint
    from d2spo.train import build, load_run_config

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunDirError(f"{run_dir}: no such run directory")
    cfg = load_run_config(run_dir)
    if "cbf" not in config_sections(cfg.algo):
        raise RunDirError(f"{run_dir}: a {cfg.algo!r} run has no learned CBF to certify (use a d2spo or sl run)")
    if not has_checkpoint(run_dir):
        raise RunDirError(f"{run_dir}: no checkpoint (checkpoint.json) to certify")
    env, params, learner = build(cfg)
    template = jax.eval_shape(learner.init, jax.random.PRNGKey(0))
    carry, meta = load_checkpoint(run_dir, template, run_fingerprint(run_dir))
    got = jax.tree_util.tree_leaves(carry)
    want = jax.tree_util.tree_leaves(template)
    if len(got) != len(want) or any(np.shape(a) != b.shape for a, b in zip(got, want)):
        raise RunDirError(f"{run_dir}: checkpoint.msgpack does not match this run's config (a foreign checkpoint?)")
    return CBFRun(cfg, env, params, learner, jax.tree_util.tree_map(jnp.asarray, carry), meta)


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


class Policy(NamedTuple):
    """The parameters certification reads: the RL actor π_rl and the safety state (h, π_Ω, f_n)."""

    actor: Any
    safety: Any


def policy_of(run: CBFRun) -> Policy:
    return Policy(run.carry.agent.actor, run.carry.safety)


_COMPILED: dict[tuple, Any] = {}


def _compiled(run: CBFRun, ccfg: CertifyConfig) -> dict[str, Any]:
    """The jitted pieces of a check, compiled once per (learner, config): the parameters are
    arguments, so certifying another state of the same run (repair rounds, tests) reuses them."""
    key = (id(run.learner), ccfg)
    if key in _COMPILED:
        return _COMPILED[key]
    lrn, env, params, cbf_cfg = run.learner, run.env, run.params, run.cfg.cbf
    H, dt, noise = lrn.H, lrn.dt, run.cfg.td3.exploration_noise
    template = jax.device_get(jax.jit(env.reset)(jax.random.PRNGKey(0), params)[0])
    alpha = class_k(cbf_cfg.alpha, cbf_cfg.alpha_coef)

    def context(pose):
        from d2spo.envs import geometry

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
            u_rl = jnp.clip(u_rl + noise * jax.random.normal(ka, u_rl.shape), -1.0, 1.0)
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

    def h_at(pol: Policy, p):
        x = lrn.features(p, jax.tree_util.tree_map(lambda c: c[0], context(p[None])))
        return lrn.safety_nets.cbf.apply(pol.safety.cbf, x), jnp.min(x)

    def e_at(pol: Policy, p, q):
        x, xn, _ = next_features(pol, p[None], context(p[None]), observe(p[None], q))
        h = lrn.safety_nets.cbf.apply(pol.safety.cbf, x[0])
        hn = lrn.safety_nets.cbf.apply(pol.safety.cbf, xn[0])
        return (hn - h) / dt + alpha(h), jnp.min(x[0])

    lo, hi = params.geom.arena_lo, params.geom.arena_hi
    step = jnp.array([0.01, 0.01, 0.05])

    def climb(objective, feasible, p0):
        """Signed-gradient ascent on the pose; a step that leaves the set is undone; the best kept."""
        def body(c, i):
            p, best_p, best_v = c
            (_, _), g = jax.value_and_grad(objective, has_aux=True)(p)
            cand = p + step * (1.0 - i / ccfg.search_steps) * jnp.sign(g)
            cand = cand.at[:2].set(jnp.clip(cand[:2], lo, hi))
            vc, mc = objective(cand)
            ok = feasible(mc)
            better = ok & (vc > best_v)
            return (jnp.where(ok, cand, p), jnp.where(better, cand, best_p), jnp.where(better, vc, best_v)), None

        v0, _ = objective(p0)
        (_, bp, bv), _ = jax.lax.scan(body, (p0, p0, v0), jnp.arange(ccfg.search_steps, dtype=jnp.float32))
        return bp, bv

    thr = p_exp_threshold(cbf_cfg)

    def search_l(pol, p0):
        return jax.vmap(lambda p: climb(lambda z: h_at(pol, z), lambda m: m <= cbf_cfg.unsafe_max, p))(p0)

    def search_d(pol, p0, q):
        def neg_e(z, qq):
            v, m = e_at(pol, z, qq)
            return -v, m

        bp, bv = jax.vmap(lambda p, qq: climb(lambda z: neg_e(z, qq), lambda m: m >= thr, p))(p0, q)
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


def pose_grid(run: CBFRun, ccfg: CertifyConfig) -> np.ndarray:
    """[G, 3] poses: positions every `grid_step` metres over the arena (cell centres), `headings` each."""
    lo, hi = np.asarray(run.params.geom.arena_lo), np.asarray(run.params.geom.arena_hi)
    xs = np.arange(lo[0] + ccfg.grid_step / 2, hi[0], ccfg.grid_step)
    ys = np.arange(lo[1] + ccfg.grid_step / 2, hi[1], ccfg.grid_step)
    th = np.linspace(-np.pi, np.pi, ccfg.headings, endpoint=False)
    gx, gy, gt = np.meshgrid(xs, ys, th, indexing="ij")
    return np.stack([gx.ravel(), gy.ravel(), gt.ravel()], -1).astype(np.float32)


def live_states(run: CBFRun) -> list[int]:
    """Automaton states that are neither accepting nor rejecting (the robot still moves there)."""
    aut = run.params.aut
    return [q for q in range(int(aut.accepting.shape[0])) if not (bool(aut.accepting[q]) or bool(aut.rejecting[q]))]


def check_nets(run: CBFRun, ccfg: CertifyConfig, rho_h: float) -> dict[str, Any]:
    """Propositions 1-2 on every net. Returns per-net arrays (status, margins, values, poses)."""
    fn, pol, cbf_cfg = _compiled(run, ccfg), policy_of(run), run.cfg.cbf
    rho_h = jnp.float32(rho_h)
    out: dict[str, Any] = {}
    unsafe = run.carry.data.unsafe
    out["X_L"] = {"p": _chunked(lambda x: fn["p1"](pol.safety.cbf, x), unsafe.data[: int(unsafe.size)])}
    pe = run.carry.data.p_exp
    rows = jax.tree_util.tree_map(lambda a: a[: int(pe.size)], pe.data)
    out["P_exp"] = {"p": _chunked(lambda *a: fn["p2_rows"](pol, *a, rho_h), rows.pose, rows.context, rows.obs)}
    grid = pose_grid(run, ccfg)
    nearest = _chunked(fn["nearest"], jnp.asarray(grid))
    ring = nearest <= cbf_cfg.unsafe_max
    safe = nearest >= p_exp_threshold(cbf_cfg)
    out["grid_L"] = {"p": _chunked(lambda p: fn["grid_p1"](pol.safety.cbf, p), jnp.asarray(grid[ring])),
                     "pose": grid[ring]}
    worst, worst_q = None, None
    for q in live_states(run):
        r = _chunked(lambda p, q=q: fn["grid_p2"](pol, p, jnp.int32(q), rho_h), jnp.asarray(grid[safe]))
        if r is None:
            break
        qs = np.full(r.status.shape, q)
        if worst is None:
            worst, worst_q = r, qs
        else:
            pick = r.margin < worst.margin
            worst = jax.tree_util.tree_map(lambda a, b: np.where(pick, a, b), r, worst)
            worst_q = np.where(pick, qs, worst_q)
    out["grid_D"] = {"p": worst, "pose": grid[safe], "q": worst_q}
    return out


def search_counterexamples(run: CBFRun, ccfg: CertifyConfig, nets: dict) -> dict[str, list[dict]]:
    """Gradient steps on the pose from the worst grid points: maximise h where the nearest obstacle
    is within unsafe_max (ℒ and contact), minimise e (through the nominal model) where it is at least
    the P_exp threshold (D). Steps that leave the set are undone. Returns the 10 worst found, each
    with its pose and value; `counterexample` is true where the condition fails (h ≥ 0, e < 0)."""
    fn, pol, n = _compiled(run, ccfg), policy_of(run), ccfg.search_starts
    found: dict[str, list[dict]] = {"L": [], "D": []}

    def starts(values, poses, extra=None):
        idx = np.argsort(values)[:n]
        idx = np.concatenate([idx, np.repeat(idx[-1:], n - len(idx))])  # a fixed shape: one compilation
        return jnp.asarray(poses[idx]), (None if extra is None else jnp.asarray(extra[idx], jnp.int32))

    g1 = nets["grid_L"]
    if g1["p"] is not None:
        poses, vals = fn["search_l"](pol, starts(-np.asarray(g1["p"].h), g1["pose"])[0])
        for p, v in sorted(zip(np.asarray(poses), np.asarray(vals)), key=lambda t: -t[1])[:10]:
            found["L"].append({"pose": [round(float(a), 4) for a in p], "h": float(v), "counterexample": bool(v >= 0)})
    g2 = nets["grid_D"]
    if g2["p"] is not None:
        p0, q0 = starts(np.asarray(g2["p"].e), g2["pose"], g2["q"])
        poses, vals = fn["search_d"](pol, p0, q0)
        for p, v, q in sorted(zip(np.asarray(poses), np.asarray(vals), np.asarray(q0)), key=lambda t: t[1])[:10]:
            found["D"].append({"pose": [round(float(a), 4) for a in p], "q": int(q), "e": float(v),
                               "counterexample": bool(v < 0)})
    return found


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


def certify_run(run_dir: Path, ccfg: CertifyConfig | None = None, run: CBFRun | None = None,
                search: bool = True) -> tuple[dict, dict]:
    """Check Propositions 1-2 on a run. Returns (summary, nets); `write_outputs` saves them."""
    ccfg = (ccfg or CertifyConfig()).check()
    t0 = time.perf_counter()
    run = run or load_cbf_run(run_dir)
    times = {}
    res, res_h = model_residual(run, ccfg)
    rho_h = float(np.quantile(res_h, ccfg.residual_quantile))
    times["residual"] = time.perf_counter() - t0
    nets = check_nets(run, ccfg, rho_h)
    times["nets"] = time.perf_counter() - t0 - sum(times.values())
    found = search_counterexamples(run, ccfg, nets) if search else {"L": [], "D": []}
    times["search"] = time.perf_counter() - t0 - sum(times.values())
    glob = {k: v / run.learner.H for k, v in bounds.global_lipschitz(bounds.dense_layers(run.carry.safety.cbf)).items()}
    summary = {
        "run": str(run_dir), "algo": run.cfg.algo, "task": run.cfg.task, "layout": run.cfg.layout,
        "episodes_trained": run.meta.get("episodes"), "config": dataclasses.asdict(ccfg),
        "feature_space": "l_inf balls over b(z, O_s) (metres)",
        "residual": {"rho_h": rho_h, "quantile": ccfg.residual_quantile, "transitions": int(res.size),
                     "h": {"p50": float(np.quantile(res_h, 0.5)), "p99": float(np.quantile(res_h, 0.99)),
                           "max": float(res_h.max())},
                     "features_m": {"p50": float(np.quantile(res, 0.5)), "p99": float(np.quantile(res, 0.99)),
                                    "max": float(res.max())}},
        "lipschitz_h_global": glob,
        "nets": {"X_L": _net_summary(nets["X_L"]["p"], "L"), "grid_L": _net_summary(nets["grid_L"]["p"], "L"),
                 "P_exp": _net_summary(nets["P_exp"]["p"], "D"), "grid_D": _net_summary(nets["grid_D"]["p"], "D")},
        "counterexamples": found,
    }
    summary["certified_L"] = summary["nets"]["X_L"].get("certified", float("nan"))
    summary["certified_D"] = summary["nets"]["P_exp"].get("certified", float("nan"))
    for k in ("grid_L", "grid_D"):
        viol = 0 if nets[k]["p"] is None else int(np.sum(np.asarray(nets[k]["p"].status) == cert.VIOLATED))
        summary[f"{k}_violated"] = viol
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    summary["seconds_by_stage"] = {k: round(v, 1) for k, v in times.items()}
    return summary, nets


def status_maps(run: CBFRun, ccfg: CertifyConfig, nets: dict) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Worst status over θ (and automaton states) per grid cell, for Prop. 1 and Prop. 2: arrays
    [ny, nx] of -1 (not in that set), 0 certified, 1 not certified, 2 violated; and the extent."""
    lo, hi = np.asarray(run.params.geom.arena_lo), np.asarray(run.params.geom.arena_hi)
    nx = len(np.arange(lo[0] + ccfg.grid_step / 2, hi[0], ccfg.grid_step))
    ny = len(np.arange(lo[1] + ccfg.grid_step / 2, hi[1], ccfg.grid_step))
    maps = []
    for key in ("grid_L", "grid_D"):
        m = np.full((ny, nx), -1, np.int32)
        net = nets[key]
        if net["p"] is not None:
            ix = np.clip(((net["pose"][:, 0] - lo[0]) / ccfg.grid_step).astype(int), 0, nx - 1)
            iy = np.clip(((net["pose"][:, 1] - lo[1]) / ccfg.grid_step).astype(int), 0, ny - 1)
            np.maximum.at(m, (iy, ix), np.asarray(net["p"].status, np.int32))
        maps.append(m)
    return maps[0], maps[1], (lo[0], hi[0], lo[1], hi[1])


def save_picture(run: CBFRun, ccfg: CertifyConfig, nets: dict, summary: dict, path: Path) -> None:
    """Two panels over the layout: where Proposition 1 (ℒ and contact) and Proposition 2 (D) are
    certified (green), not certified (orange) or violated (red), worst over θ; counterexamples as x."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure

    from d2spo.envs.render import draw_layout

    m1, m2, extent = status_maps(run, ccfg, nets)
    cmap = ListedColormap(["white", "tab:green", "orange", "tab:red"])
    fig = Figure(figsize=(11, 5.2))
    titles = (f"Prop. 1: h < 0 near obstacles (ε̄ = {ccfg.eps_unsafe:g} m)",
              f"Prop. 2: e ≥ 0 in D (ε = {ccfg.eps_safe:g} m, ρ_h = {summary['residual']['rho_h']:.3g})")
    for i, (m, title, key, val) in enumerate(((m1, titles[0], "L", "h"), (m2, titles[1], "D", "e"))):
        ax = fig.add_subplot(1, 2, i + 1)
        ax.imshow(m + 1, origin="lower", extent=extent, cmap=cmap, vmin=0, vmax=3, interpolation="nearest")
        draw_layout(run.env.layout, ax, show_sensing=False)
        for c in summary["counterexamples"][key]:
            ax.plot(c["pose"][0], c["pose"][1], "x", color="black" if c["counterexample"] else "grey", markersize=7)
        ax.set_title(title, fontsize=9)
    fig.suptitle(f"{summary['run']}: green certified, orange not certified, red violated (worst over θ); "
                 "x = worst found by gradient search (black: a counterexample)", fontsize=8)
    FigureCanvasAgg(fig).print_png(str(path))


def write_outputs(run_dir: Path, run: CBFRun, ccfg: CertifyConfig, summary: dict, nets: dict) -> tuple[Path, Path]:
    """RUN/certify.json and RUN/certify.png."""
    from d2spo.runio import atomic_write_json

    run_dir = Path(run_dir)
    j, p = run_dir / "certify.json", run_dir / "certify.png"
    atomic_write_json(j, summary)
    save_picture(run, ccfg, nets, summary, p)
    return j, p
