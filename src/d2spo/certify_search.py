"""The pose grid of `d2spo certify` and its search for counterexamples (docs/certify.md, "Counterexamples").

The grid: cells of `grid_step` metres over the arena, `headings` headings each; the cells of the
explored set D are those that hold a row of P_exp.

The search: signed steps along a central-difference gradient of h (to maximise, in ℒ and contact) or of −e
(in D's explored part) over the pose, from the worst grid points, all starts and probes in one
batch. A heuristic: it enters no certificate; a point is a counterexample because h ≥ 0 or e < 0
was evaluated there. The jitted searches themselves are built in `certify._compiled`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

STEP = (0.01, 0.01, 0.05)
"""Probe offsets and largest step in x, y (metres) and θ (radians)."""


def climb(values, feasible, p0, extra, lo, hi, steps: int):
    """Signed steps along a central-difference gradient of values(pose, extra)[0] over the pose,
    from every start p0 [N, 3] at once. Each step evaluates the candidate and its 6 probes in one
    batch (one compiled copy of the forward pass; differentiating through the lidar and the
    automaton instead cost ~100 s of compilation). A candidate outside the set is not taken; the
    best feasible point evaluated (candidates and probes) is kept."""
    step = jnp.array(STEP)
    probes = jnp.concatenate([jnp.zeros((1, 3)), jnp.diag(step), -jnp.diag(step)])  # [7, 3]
    n = p0.shape[0]
    extra7 = jnp.repeat(extra, 7, 0)

    def body(c, i):
        p, g, best_p, best_v = c
        cand = p + step * (1.0 - i / steps) * jnp.sign(g)
        cand = cand.at[:, :2].set(jnp.clip(cand[:, :2], lo, hi))
        pts = (cand[:, None, :] + probes).reshape(-1, 3)
        v, m = values(pts, extra7)
        ok = feasible(m, pts, extra7).reshape(n, 7)
        v, pts = v.reshape(n, 7), pts.reshape(n, 7, 3)
        vm = jnp.where(ok, v, -jnp.inf)
        k = jnp.argmax(vm, 1)
        vk = jnp.max(vm, 1)
        better = vk > best_v
        best_p = jnp.where(better[:, None], pts[jnp.arange(n), k], best_p)
        best_v = jnp.where(better, vk, best_v)
        p = jnp.where(ok[:, :1], cand, p)
        return (p, v[:, 1:4] - v[:, 4:7], best_p, best_v), None

    init = (p0, jnp.zeros_like(p0), p0, jnp.full((n,), -jnp.inf))
    (_, _, bp, bv), _ = jax.lax.scan(body, init, jnp.arange(steps, dtype=jnp.float32))
    return bp, bv


def _distinct(rows: list, n: int = 10, tol: float = 0.01) -> list:
    """The first n rows whose poses (row[0]) differ from every earlier kept one by more than `tol`."""
    kept: list = []
    for r in rows:
        if all(np.max(np.abs(r[0] - k[0])) > tol for k in kept):
            kept.append(r)
        if len(kept) == n:
            break
    return kept


def search_counterexamples(run, ccfg, nets: dict, fn: dict, pol) -> dict[str, list[dict]]:
    """Signed steps along a finite-difference gradient of the pose, from the worst grid points:
    maximise h where the nearest obstacle is within unsafe_max (ℒ and contact), minimise e (through
    the nominal model) in D (beyond the P_exp threshold, in an explored cell with the start's
    automaton state). Returns the 10 worst found, each with its pose and value; `counterexample` is
    true where the condition fails (h ≥ 0, e < 0)."""
    n = ccfg.search_starts
    found: dict[str, list[dict]] = {"L": [], "D": []}

    def starts(values, poses, extra=None):
        idx = np.argsort(values)[:n]
        idx = np.concatenate([idx, np.repeat(idx[-1:], n - len(idx))])  # a fixed shape: one compilation
        return jnp.asarray(poses[idx]), (None if extra is None else jnp.asarray(extra[idx], jnp.int32))

    g1 = nets["grid_L"]
    if g1["p"] is not None:
        poses, vals = fn["search_l"](pol, starts(-np.asarray(g1["p"].h), g1["pose"])[0])
        nets["search_L"] = {"pose": np.asarray(poses), "h": np.asarray(vals)}
        for p, v in _distinct(sorted(zip(np.asarray(poses), np.asarray(vals)), key=lambda t: -t[1])):
            found["L"].append({"pose": [round(float(a), 4) for a in p], "h": float(v), "counterexample": bool(v >= 0)})
    g2 = nets["grid_D"]
    if g2["p"] is not None:
        p0, q0 = starts(np.asarray(g2["p"].e), g2["pose"], g2["q"])
        poses, vals = fn["search_d"](pol, p0, q0, jnp.asarray(nets["explored"]))
        nets["search_D"] = {"pose": np.asarray(poses), "e": np.asarray(vals), "q": np.asarray(q0)}
        for p, v, q in _distinct(sorted(zip(np.asarray(poses), np.asarray(vals), np.asarray(q0)), key=lambda t: t[1])):
            found["D"].append({"pose": [round(float(a), 4) for a in p], "q": int(q), "e": float(v),
                               "counterexample": bool(v < 0)})
    return found


def grid_axes(run, ccfg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The grid's cell centres in x and y (every `grid_step` metres over the arena) and its headings."""
    lo, hi = np.asarray(run.params.geom.arena_lo), np.asarray(run.params.geom.arena_hi)
    xs = np.arange(lo[0] + ccfg.grid_step / 2, hi[0], ccfg.grid_step)
    ys = np.arange(lo[1] + ccfg.grid_step / 2, hi[1], ccfg.grid_step)
    return xs, ys, np.linspace(-np.pi, np.pi, ccfg.headings, endpoint=False)


def pose_grid(run, ccfg) -> np.ndarray:
    """[G, 3] poses: the cell centres, `headings` each."""
    gx, gy, gt = np.meshgrid(*grid_axes(run, ccfg), indexing="ij")
    return np.stack([gx.ravel(), gy.ravel(), gt.ravel()], -1).astype(np.float32)


def cell_index(pose, lo, ccfg, shape, xp=np) -> tuple:
    """(ix, iy, iθ) of the grid cell holding each pose: 5 cm squares and heading sectors centred on
    the grid's headings. Works in numpy and (xp=jnp) inside jit."""
    ix = xp.clip(xp.floor((pose[..., 0] - lo[0]) / ccfg.grid_step), 0, shape[0] - 1).astype(xp.int32)
    iy = xp.clip(xp.floor((pose[..., 1] - lo[1]) / ccfg.grid_step), 0, shape[1] - 1).astype(xp.int32)
    it = xp.mod(xp.round((pose[..., 2] + np.pi) * ccfg.headings / (2 * np.pi)), ccfg.headings).astype(xp.int32)
    return ix, iy, it


def live_states(run) -> list[int]:
    """Automaton states that are neither accepting nor rejecting (the robot still moves there)."""
    aut = run.params.aut
    return [q for q in range(int(aut.accepting.shape[0])) if not (bool(aut.accepting[q]) or bool(aut.rejecting[q]))]


def explored_cells(run, ccfg, data) -> np.ndarray:
    """bool [nx, ny, headings, n_states]: the grid cells (with the automaton state) that hold at least
    one row of P_exp, the explored set D. The state of a row is read from its stored observation."""
    xs, ys, _ = grid_axes(run, ccfg)
    n_states = int(run.params.aut.accepting.shape[0])
    pe = data.p_exp
    n = int(pe.size)
    table = np.zeros((len(xs), len(ys), ccfg.headings, n_states), bool)
    if n:
        pose = np.asarray(pe.data.pose[:n])
        q = np.argmax(np.asarray(pe.data.obs[:n, run.env.observation_slices["automaton"]]), -1)
        table[cell_index(pose, np.asarray(run.params.geom.arena_lo), ccfg, table.shape) + (q,)] = True
    return table
