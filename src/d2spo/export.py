"""``d2spo export RUN --out DIR``: the policy a robot runs, as a small self-contained directory.

DIR holds ``weights.npz`` (float32 arrays: the networks, and the per-state path field where the
observation reads one), ``manifest.json`` (what every array is, the observation's layout, the
action's scaling, the map, the task's automaton, the runtime filter's settings, the run's config;
docs/deploy.md gives the schema) and, with ``onnx=True``, the networks as ONNX graphs
(``export_onnx``). ``d2spo.deploy.Policy`` reads it with numpy alone. The manifest is written
last: a directory with a manifest is a complete export.

Exported learners: D²SPO and SL (π_rl, π_Ω, and h with the nominal model f_n for the filter), and
the learners whose evaluation action is a tanh-squashed MLP of the observation (td3, tlgrl,
td3-lag; sac-lag, rcrl: tanh of the Gaussian's mean). Not PPO-Lag or CPO (their running
observation normalisation is not exported yet), nor a generalist (its observation reads a field
bank). Nothing here prints: the CLI reports.
"""

from __future__ import annotations

import dataclasses
import io
import json
from dataclasses import dataclass
from pathlib import Path

import flax.linen as nn
import jax
import numpy as np

from d2spo.algos import has_runtime_filter
from d2spo.algos.common.networks import DeterministicActor, GaussianActor
from d2spo.checkpoint import has_checkpoint, run_fingerprint
from d2spo.config import config_to_dict
from d2spo.console import version
from d2spo.deploy.manifest import CONTENT_KEY, FORMAT, FORMAT_VERSION, MANIFEST, WEIGHTS, content_sha256, file_sha256
from d2spo.envs import geodesic
from d2spo.errors import ConfigError, NaNError, RunDirError
from d2spo.fields import check_choice, check_fields
from d2spo.run import POLICY_CHOICES, build, check_layout_unchanged, load_policy, load_run_config
from d2spo.runio import atomic_write_bytes, atomic_write_json, make_run_dir, temporary_of

ACTIVATION_NAMES = {nn.relu: "relu", nn.tanh: "tanh"}
"""The hidden activations an exported network may use, by name (``deploy.nets.ACTIVATIONS``)."""
N_BISECT = 50
"""Bisection steps of the filter's projection (``safety.filter.project_halfspace_box``'s default)."""


@dataclass(frozen=True)
class ExportConfig:
    """What `d2spo export` writes: which policy, the filter's settings, ONNX or not."""

    policy: str = "best"
    """best: the validated policy where there is one (a generalist's, a patrol's on one layout), else the
    last; last: the newest checkpoint's."""
    runtime_filter: bool | None = None
    """D²SPO only: whether deploy filters by default; default: on, since a robot's dynamics are not the
    simulator's (`d2spo eval` turns the filter on under other dynamics); False: π_Ω alone, as a run trains
    (Policy.act(..., filter=) overrides either)."""
    filter_iters: int | None = None
    """D²SPO only: linearise-and-project iterations of the runtime filter; default: as trained."""
    filter_alpha: float | None = None
    """D²SPO only: coefficient of α in the runtime filter's condition; default: as trained."""
    onnx: bool = False
    """Also write the networks as ONNX graphs (needs the extra: pip install 'd2spo[onnx]')."""

    def __post_init__(self):
        check_fields(self, nullable=("filter_iters", "filter_alpha"), count=("filter_iters",),
                     positive=("filter_alpha",), flag=("onnx",))
        check_choice(self, "policy", POLICY_CHOICES)


def check_out(out: Path) -> None:
    """RunDirError unless ``out`` can take an export: absent, empty, an earlier export (replaced), or
    what an export stopped before its manifest left (its own files only: the manifest comes last)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RunDirError(f"{out}: exists and is not a directory")
    if out.is_dir() and not (out / MANIFEST).is_file() and not all(map(_an_exports_file, out.iterdir())):
        raise RunDirError(f"{out}: not empty and holds no exported policy ({MANIFEST}); choose another --out")


def _an_exports_file(path: Path) -> bool:
    """Whether ``path`` is a file an export writes before its manifest (or one's temporary file)."""
    name = temporary_of(path.name) or path.name
    return path.is_file() and (name == WEIGHTS or name.endswith(".onnx"))  # export_onnx's graphs: policy, cbf, nominal


def export_run(run_dir: Path, out: Path, ecfg: ExportConfig = ExportConfig()) -> dict:
    """Write the export of the run ``run_dir`` into ``out``; returns its manifest (with the files' sizes
    in ``sizes``). RunDirError/ConfigError for a run that cannot be exported, or an ``out`` in the way."""
    run_dir, out = Path(run_dir), Path(out)
    cfg = load_run_config(run_dir)
    if cfg.generalist:
        raise RunDirError(f"{run_dir}: a generalist reads a field bank of layouts; export takes a run on one layout")
    if cfg.algo in ("ppo-lag", "cpo"):
        raise RunDirError(f"{run_dir}: {cfg.algo} is not exported (its running observation normalisation is not "
                          "in the format yet); export takes d2spo, sl, td3, tlgrl, td3-lag, sac-lag and rcrl runs")
    filtered = has_runtime_filter(cfg.algo)
    for name in ("runtime_filter", "filter_iters", "filter_alpha"):
        if getattr(ecfg, name) is not None and not filtered:
            raise ConfigError(name, f"only D²SPO has a runtime filter; this run is {cfg.algo!r}")
    if not has_checkpoint(run_dir):
        raise RunDirError(f"{run_dir}: no checkpoint to export; has the run written one yet?")
    check_layout_unchanged(run_dir, cfg, "the export's map would not be the one the policy and its barrier learnt: "
                           "restore the file, or train a new run on it")
    check_out(out)
    env, params, learner = build(cfg)
    _, _, policy, meta = load_policy(run_dir, ecfg.policy, learner)
    policy = jax.device_get(policy)
    if not all(np.isfinite(np.asarray(leaf)).all() for leaf in jax.tree_util.tree_leaves(policy)
               if np.issubdtype(np.asarray(leaf).dtype, np.floating)):  # a robot must never get NaN weights
        raise NaNError(f"{run_dir}: the {meta['policy']} policy has non-finite weights; nothing exported")
    source = {"run": str(run_dir.resolve()), "algo": cfg.algo, "task": cfg.task, "layout": cfg.layout,
              "policy": meta["policy"], "episodes": meta.get("episodes"), "config_sha256": run_fingerprint(run_dir)}
    return write_export(out, cfg, (env, params, learner), policy, source, ecfg)


def write_export(out: Path, cfg, built, policy, source: dict, ecfg: ExportConfig = ExportConfig()) -> dict:
    """Write the export of ``policy`` (``learner.policy``'s value, as numpy arrays) into ``out``;
    ``built`` is ``run.build(cfg)``'s (env, env params, learner), ``source`` says where the policy came
    from. Returns the manifest, with the files' sizes in ``sizes``."""
    env, params, learner = built
    out = Path(out)
    check_out(out)
    filtered = has_runtime_filter(cfg.algo)
    arrays: dict[str, np.ndarray] = {}
    actor_params = policy[0] if filtered else policy
    networks = {"actor": {"input": "the observation [D]", "output": "u_rl [2]: the RL policy's action",
                          "layers": _actor_layers(learner.nets.actor, actor_params, arrays)}}
    if filtered:
        networks.update(_safety_networks(learner, policy[1], arrays))
    m = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "d2spo_version": version(), "source": source,
        "networks": networks,
        "observation": {"size": env.observation_size, "parts": [
            {"name": name, "start": s.start, "size": s.stop - s.start, "what": PART_DOCS[name]}
            for name, s in env.observation_slices.items()]},
        "sensor": {"n_rays": env.n_rays, "sensing_radius": _f(params.sensing_radius),
                   "rays": "ray k points at heading + 2*pi*k/K (counter-clockwise, ray 0 straight ahead) from the "
                           "robot centre; a range is the distance (m) to the first surface hit, clipped to [0, H]"},
        "action": {"size": env.action_size, "low": -1.0, "high": 1.0, "v_max": float(env.config.v_max),
                   "v_min": -float(env.config.v_max) if env.config.reverse else 0.0,
                   "omega_max": float(env.config.omega_max), "dt": float(env.config.dt),
                   "command": "v = v_min + (a[0] + 1) / 2 * (v_max - v_min), omega = a[1] * omega_max, "
                              "a clipped to [-1, 1]"},
        "robot": {"radius": float(env.config.robot_radius)},
        "layout": _layout(env, params),
        "automaton": _automaton(env, params),
        "path_field": _path_field(env, params, arrays),
        "filter": _filter(cfg, ecfg, float(env.config.dt)) if filtered else None,
        "config": config_to_dict(cfg),
    }
    earlier = _listed_files(out)  # an earlier export's files, replaced below
    make_run_dir(out)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(out / WEIGHTS, buf.getvalue())
    m["weights"] = {"file": WEIGHTS, "sha256": file_sha256(out / WEIGHTS)}
    m["onnx"] = None
    if ecfg.onnx:
        from d2spo.export_onnx import write_onnx

        m["onnx"] = write_onnx(out, m, arrays)
    m[CONTENT_KEY] = content_sha256(m)  # written last: Policy.load refuses a manifest edited since
    atomic_write_json(out / MANIFEST, m)
    files = [WEIGHTS, MANIFEST] + ([v["file"] for v in m["onnx"].values()] if m["onnx"] else [])
    for name in earlier - set(files):  # e.g. the ONNX graphs of an earlier export with --onnx
        (out / name).unlink(missing_ok=True)
    return {**m, "sizes": {f: (out / f).stat().st_size for f in files}}


def _listed_files(out: Path) -> set[str]:
    """The files an earlier export in ``out`` lists in its manifest (plain names only), or none."""
    try:
        m = json.loads((out / MANIFEST).read_text())
        names = {m["weights"]["file"]} | {v["file"] for v in (m.get("onnx") or {}).values()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return set()
    return {n for n in names if isinstance(n, str) and n == Path(n).name and n not in ("", ".", "..")}


PART_DOCS = {
    "lidar": "the K ranges divided by H (1: nothing within H)",
    "pose": "x, y scaled to [-1, 1] over the arena (2 (p - arena_lo) / (arena_hi - arena_lo) - 1), cos(theta), sin(theta)",
    "areas": "per area, its centre in the robot frame (forward, left) divided by the arena's longer side",
    "automaton": "one-hot of the automaton state q (read with the areas' label radii)",
    "path": "the direction of steepest descent of state q's path field at the robot (path_field), in the robot "
            "frame (forward, left); 0 where the field is flat",
}
"""What each part of the observation holds (``envs.nav.Env``'s docstring)."""


def _f(a) -> float:
    return float(np.float32(a))


def _fl(a) -> list:
    return np.asarray(a, np.float32).tolist()


def _dense(params: dict, name: str, key: str, activation: str, arrays: dict) -> dict:
    for part in ("kernel", "bias"):
        arrays[f"{key}.{part}"] = np.asarray(params[name][part], np.float32)
    return {"kernel": f"{key}.kernel", "bias": f"{key}.bias", "activation": activation}


def _activation(module) -> str:
    name = ACTIVATION_NAMES.get(module.activation)
    if name is None:
        raise ConfigError("activation", f"{module.activation!r} is not an activation the export format has")
    return name


def _actor_layers(module, params, arrays: dict) -> list[dict]:
    """The actor as dense layers: the MLP's hidden layers, then the output squashed by tanh (TD3's
    action; SAC's evaluation action tanh(mean)); an actor with a smaller box (``--td3.forward-only``:
    a = c0 + c1 tanh(·)) ends with that map as a diagonal linear layer."""
    p = params["params"]
    hidden = len(module.hidden)
    act = _activation(module)
    layers = [_dense(p["MLP_0"], f"Dense_{i}", f"actor.{i}", act, arrays) for i in range(hidden)]
    if isinstance(module, DeterministicActor):
        layers.append(_dense(p["MLP_0"], f"Dense_{hidden}", f"actor.{hidden}", "tanh", arrays))
        if module.low is not None:
            c0, c1 = (np.asarray(c, np.float32) for c in module.affine())
            box = {f"Dense_{hidden + 1}": {"kernel": np.diag(c1), "bias": c0}}
            layers.append(_dense(box, f"Dense_{hidden + 1}", f"actor.{hidden + 1}", "linear", arrays))
    elif isinstance(module, GaussianActor):
        layers.append(_dense(p, "Dense_0", f"actor.{hidden}", "tanh", arrays))  # the mean's head
    else:
        raise ConfigError("algo", f"the actor {type(module).__name__} is not one the export format has")
    return layers


def _mlp(params, n_hidden: int, key: str, arrays: dict, last: str = "linear") -> list[dict]:
    p = params["params"]
    return [_dense(p, f"Dense_{i}", f"{key}.{i}", "tanh" if i < n_hidden else last, arrays) for i in range(n_hidden + 1)]


def _safety_networks(learner, safety, arrays: dict) -> dict:
    nets = learner.safety_nets
    if nets.nominal.use_position:
        raise ConfigError("cbf", "a nominal model that reads the position is not one the export format has")
    n = len(nets.policy.hidden)
    p = safety.policy["params"]
    return {
        "safety_policy": {
            "input": "concat(x / H, min(x) / H, u_rl), x = b(z, O_s) [K + 1]: the lidar ranges (m) and the "
                     "distance to the nearest obstacle or wall on the map",
            "output": "u = u_rl + beta * (a - u_rl)",
            "hidden": [_dense(p, f"Dense_{i}", f"safety_policy.{i}", "tanh", arrays) for i in range(n)],
            "beta": _dense(p, f"Dense_{n}", "safety_policy.beta", "sigmoid", arrays),
            "a": _dense(p, f"Dense_{n + 1}", "safety_policy.a", "tanh", arrays)},
        "cbf": {"input": "concat(x / H, min(x) / H)", "output": "h(x) = the last layer's only output",
                "layers": _mlp(safety.cbf, len(nets.cbf.hidden), "cbf", arrays)},
        "nominal": {"input": "concat(cos(theta), sin(theta), u)",
                    "output": "the pose's rate (dx/dt, dy/dt, dtheta/dt); s_n = s + rate * dt (Eq. (5))",
                    "layers": _mlp(safety.nominal, len(nets.nominal.hidden), "nominal", arrays)},
    }


def _path_field(env, params, arrays: dict) -> dict | None:
    if "path" not in env.observation_slices:
        return None
    arrays["path_field"] = np.asarray(params.state_field, np.float32)
    return {"array": "path_field", "shape": list(arrays["path_field"].shape), "spacing": geodesic.SPACING,
            "eps": 2 * geodesic.SPACING, "origin": [0.0, 0.0],
            "what": "per automaton state, the path length (m) from each grid node (row y, column x, every spacing "
                    "m from the origin) to what makes progress; read bilinearly, clamped to the grid; the "
                    "observation's path is minus its gradient by central differences eps either side, normalised"}


def _layout(env, params) -> dict:
    geom = params.geom
    disks = [] if geom.disk_center is None else [{"center": _fl(c), "radius": _f(r)}
                                                  for c, r in zip(geom.disk_center, geom.disk_radius)]
    areas = [{"name": a.name, "label": a.label, "center": _fl(c), "radius": _f(r), "label_radius": _f(lr),
              "bit": int(b)}
             for a, c, r, lr, b in zip(env.layout.areas, params.area_center, params.area_radius, params.label_radius,
                                       params.area_bits)]
    return {"name": env.layout.name, "arena_lo": _fl(geom.arena_lo), "arena_hi": _fl(geom.arena_hi),
            "boxes": [{"lo": _fl(lo), "hi": _fl(hi)} for lo, hi in zip(geom.box_lo, geom.box_hi)],
            "disks": disks, "areas": areas, "start": _fl(params.start)}


def _automaton(env, params) -> dict:
    aut = params.aut
    return {"aps": list(env.aps), "initial": int(aut.initial), "accepting": np.asarray(aut.accepting).tolist(),
            "rejecting": np.asarray(aut.rejecting).tolist(), "delta": np.asarray(aut.delta).tolist(),
            "distance": np.asarray(aut.distance).tolist(), "label_mode": env.config.label_mode,
            # a Büchi task's accepting transitions (``ltl.labelling.accepting_visit``): a patrol's laps
            "visit": None if aut.visit is None else np.asarray(aut.visit).tolist(),
            "letters": "bit i of a letter holds while the robot centre is within label_radius of an area whose "
                       "bit is 1 << i (aps[i]); event labelling reads a letter only when it differs from the last "
                       "one and is not empty"}


def _filter(cfg, ecfg: ExportConfig, dt: float) -> dict:
    """The filter's settings: the run's, with those ``ecfg`` gives instead (as ``d2spo eval`` takes them)."""
    changes = {k: v for k, v in (("filter_iters", ecfg.filter_iters), ("filter_alpha_coef", ecfg.filter_alpha))
               if v is not None}
    cbf = dataclasses.replace(cfg.cbf, **changes)
    on = True if ecfg.runtime_filter is None else ecfg.runtime_filter  # a robot: other dynamics (docs/deploy.md)
    return {"enabled": bool(on), "alpha": cbf.alpha, "alpha_coef": float(cbf.filter_alpha),
            "iters": int(cbf.filter_iters), "n_bisect": N_BISECT, "dt": dt,
            "condition": "c(u) = (h(b(s_n(s, u))) - h(b(s))) / dt + alpha(h(b(s))) >= 0, b on the map with every "
                         "obstacle sensed; the action closest to u0 meeting it, by iters rounds of linearising c "
                         "and projecting onto the half-space within [-1, 1]^2"}
