"""An exported policy on a robot: ``Policy.load(DIR)`` reads what ``d2spo export`` wrote and maps
the robot's lidar ranges, pose and automaton state to an action, with numpy alone.

The observation is built as ``envs.nav.Env.observe`` builds it (the manifest's ``observation``
lists its parts); D²SPO's executed action is π_Ω(x, π_rl(obs)) with x = b(z, O_s) read off the
observation (``sensors.cbf_input_from_obs``), then, with the filter on, the runtime filter's
(``deploy.filter``). docs/deploy.md describes the artefact and the calls.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from d2spo.deploy.dual import F32
from d2spo.deploy.filter import Filter
from d2spo.deploy.geometry import Map
from d2spo.deploy.manifest import (
    CHECKSUMMED_SINCE,
    CONTENT_KEY,
    FORMAT,
    FORMAT_VERSIONS,
    MANIFEST,
    WEIGHTS,
    check_content,
    content_sha256,
    file_sha256,
)
from d2spo.deploy.nets import Layer, Mlp, SafetyPolicy
from d2spo.deploy.task import Automaton, TaskTracker
from d2spo.errors import ArtefactError

POSE_SLACK = 0.5
"""How far (m) outside the arena a pose may lie before it is refused: a localisation estimate at a
wall may stray a little; a pose in another frame (an origin at the arena's centre, millimetres)
strays far."""


def numbers(value, name: str, size: int | None, what: str) -> np.ndarray:
    """``value`` as float32 [size] (any size when None), or one ValueError that names the argument:
    a nested or ragged sequence, a string, a count other than ``size``, or a NaN or infinity (except
    where the caller allows +inf) is refused. ``what`` says what the argument holds."""
    try:
        a = np.asarray(value)
    except ValueError:  # ragged
        a = None
    if a is None or a.ndim > 1 or not np.issubdtype(a.dtype, np.number):
        raise ValueError(f"{name} must be {what}; got {value!r:.80}")
    a = a.astype(F32).reshape(-1)
    if size is not None and a.shape[0] != size:
        raise ValueError(f"{name} must be {what}; got {a.shape[0]} value{'s' if a.shape[0] != 1 else ''}")
    return a


def finite(a: np.ndarray, name: str, what: str) -> np.ndarray:
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise ValueError(f"{name} must be {what}; entries {bad.tolist()[:8]} are not finite: {a[bad[:3]].tolist()}")
    return a


def _array(data, name: str, where: Path) -> np.ndarray:
    if name not in data:
        raise ArtefactError(f"{where}: {WEIGHTS} has no array {name!r}")
    return np.asarray(data[name])


class Policy:
    """An exported policy: its networks, the map and the task, ready to act."""

    def __init__(self, directory: Path, manifest: dict, arrays: dict, backend: str = "numpy"):
        self.directory = Path(directory)
        self.manifest = m = manifest
        layers = lambda specs: tuple(Layer(_array(arrays, s["kernel"], directory).astype(F32),  # noqa: E731
                                           _array(arrays, s["bias"], directory).astype(F32), s["activation"])
                                     for s in specs)
        sensor, lay = m["sensor"], m["layout"]
        self.n_rays = int(sensor["n_rays"])
        self.H = F32(sensor["sensing_radius"])
        pts = lambda key, k, n: np.array([o[k] for o in lay[key]], F32).reshape(-1, n)  # noqa: E731
        self.map = Map(np.array(lay["arena_lo"], F32), np.array(lay["arena_hi"], F32), pts("boxes", "lo", 2),
                       pts("boxes", "hi", 2), pts("disks", "center", 2), pts("disks", "radius", 1)[:, 0],
                       self.n_rays, self.H)
        self.automaton = Automaton.of_manifest(m)
        self.parts = {p["name"]: slice(p["start"], p["start"] + p["size"]) for p in m["observation"]["parts"]}
        self.observation_size = int(m["observation"]["size"])
        path = m.get("path_field")
        self.path_field = None if path is None else _array(arrays, path["array"], directory).astype(F32)
        nets = m["networks"]
        self.actor = Mlp(layers(nets["actor"]["layers"]))
        sp = nets.get("safety_policy")
        self.safety_policy = None if sp is None else SafetyPolicy(
            Mlp(layers(sp["hidden"])), *layers([sp["beta"], sp["a"]]), self.H)
        f = m.get("filter")
        self.runtime_filter = None if f is None else Filter(Mlp(layers(nets["cbf"]["layers"])),
                                                    Mlp(layers(nets["nominal"]["layers"])), self.map, float(f["dt"]),
                                                    f["alpha"], float(f["alpha_coef"]), int(f["iters"]),
                                                    int(f["n_bisect"]))
        """The runtime filter (``deploy.filter.Filter``; None for a policy without one: not D²SPO)."""
        self.filter_on = bool(f is not None and f["enabled"])
        """Whether ``act`` filters by default: as the run was trained, or as ``d2spo export`` set it."""
        act = m["action"]
        self.v_max, self.omega_max = float(act["v_max"]), float(act["omega_max"])
        self.v_mid = 0.5 * (self.v_max + float(act.get("v_min", -self.v_max)))  # no v_min: a robot that reverses
        self._session = None
        if backend == "onnxruntime":
            self._session = _onnx_session(self.directory, m)

    @classmethod
    def load(cls, directory, backend: str = "numpy") -> Policy:
        """The policy ``d2spo export`` wrote into ``directory``. ``backend``: 'numpy', or
        'onnxruntime' (the networks of π_rl and π_Ω run from policy.onnx; needs ``--onnx`` at export
        and onnxruntime). ArtefactError when the directory is not a readable export of this format."""
        if backend not in ("numpy", "onnxruntime"):
            raise ValueError(f"backend must be 'numpy' or 'onnxruntime', got {backend!r}")
        directory = Path(directory)
        path = directory / MANIFEST
        if not path.is_file():
            if not directory.exists():
                raise ArtefactError(f"{directory}: no such directory")
            if directory.is_file():
                raise ArtefactError(f"{directory}: is a file; give the directory `d2spo export` wrote"
                                    + (f" ({directory.parent})" if directory.name == MANIFEST else ""))
            if (directory / "config.json").is_file():
                raise ArtefactError(f"{directory}: is a run directory, not an export; `d2spo export {directory} "
                                    "--out DIR` writes one")
            raise ArtefactError(f"{directory}: no {MANIFEST}; is this a directory `d2spo export` wrote?")
        try:
            manifest = json.loads(path.read_bytes())
        except (ValueError, RecursionError) as e:
            raise ArtefactError(f"{path}: not valid JSON ({e})") from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            raise ArtefactError(f"{path}: not a {FORMAT} manifest")
        version = manifest.get("format_version")
        if isinstance(version, bool) or version not in FORMAT_VERSIONS:
            raise ArtefactError(f"{path}: format version {version!r}; this d2spo reads versions "
                                f"{' and '.join(map(str, FORMAT_VERSIONS))}")
        recorded = manifest.get(CONTENT_KEY)  # optional in version 1 only: its exports before 2026-12-02 have none
        if recorded is None and version >= CHECKSUMMED_SINCE:
            raise ArtefactError(f"{path}: damaged or edited since export (no {CONTENT_KEY}, which every manifest of "
                                f"format version {version} records); export the run again")
        if recorded is not None and recorded != content_sha256(manifest):
            raise ArtefactError(f"{path}: edited or damaged since export (its content's SHA-256 is not the one it "
                                "records); export the run again, with the flags that change what it should")
        try:
            weights = directory / manifest["weights"]["file"]
            if not weights.is_file():
                raise ArtefactError(f"{directory}: no {weights.name}")
            if file_sha256(weights) != manifest["weights"]["sha256"]:
                raise ArtefactError(f"{weights}: damaged (its SHA-256 is not the manifest's)")
            with np.load(weights, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
            check_content(manifest)
            policy = cls(directory, manifest, arrays, backend)
            policy._self_check()
            return policy
        except (KeyError, TypeError, IndexError, ValueError) as e:  # a manifest of a broken writer, or edited
            raise ArtefactError(f"{path}: damaged ({type(e).__name__}: {e})") from None

    def _self_check(self) -> None:
        """Act once at the layout's start pose in every automaton state (with and without the filter):
        arrays whose shapes do not chain, a path field short of a state, or an action or command that is
        not finite fail here, at load, rather than in the robot's control loop (ValueError)."""
        start = self.pose(self.manifest["layout"]["start"])
        ranges = self.scan(start)
        for q in range(self.automaton.n_states):
            for use_filter in (False, True) if self.runtime_filter is not None else (None,):
                u = self.act(ranges, start, q, filter=use_filter)
                if u.shape != (2,) or not np.isfinite(self.command(u)).all():
                    raise ValueError(f"acting at the layout's start in state {q} gives {u.tolist()}, command "
                                     f"{self.command(u)}")

    # ------------------------------------------------------------------------ the observation

    def observation(self, ranges, pose, q: int) -> np.ndarray:
        """float32 [observation_size]: the env's observation from the lidar ``ranges`` [K] (m, ray k at
        heading + 2πk/K counter-clockwise from the robot centre; above H or +inf read H), the pose
        (x, y, θ) in the layout's frame and the automaton state q (``TaskTracker.q``)."""
        ranges = self.ranges(ranges)
        q = self.state(q)
        pose = self.pose(pose)
        xy, c, s = pose[:2], np.cos(pose[2]), np.sin(pose[2])
        lo, hi = self.map.arena_lo, self.map.arena_hi
        extent = hi - lo
        rel = self.automaton.area_center - xy
        forward = (c * rel[:, 0] + s * rel[:, 1]) / np.max(extent)
        left = (c * rel[:, 1] - s * rel[:, 0]) / np.max(extent)
        values = {
            "lidar": np.clip(ranges, F32(0.0), self.H) / self.H,
            "pose": np.concatenate([F32(2.0) * (xy - lo) / extent - F32(1.0), np.array([c, s], F32)]),
            "areas": np.stack([forward, left], axis=-1).reshape(-1),
            "automaton": (np.arange(self.automaton.n_states) == int(q)).astype(F32),
        }
        if "path" in self.parts:
            d = self._descent(xy, int(q))
            values["path"] = np.array([c * d[0] + s * d[1], c * d[1] - s * d[0]], F32)
        obs = np.zeros(self.observation_size, F32)
        for name, part in self.parts.items():
            obs[part] = values[name]
        return obs

    def ranges(self, ranges) -> np.ndarray:
        """``ranges`` checked: float32 [K] lidar ranges (m), each >= 0 or +inf (no return). ValueError
        otherwise: a count other than K, a NaN, a negative range."""
        ranges = numbers(ranges, "ranges", self.n_rays, f"{self.n_rays} lidar ranges (m), one per ray")
        if np.isnan(ranges).any():  # a driver's "no return" is +inf (read as H), never NaN
            raise ValueError(f"lidar ranges {np.flatnonzero(np.isnan(ranges)).tolist()} are NaN; "
                             "give +inf for a ray with no return")
        if (ranges < 0).any():
            raise ValueError(f"lidar ranges {np.flatnonzero(ranges < 0).tolist()} are negative "
                             f"({ranges[ranges < 0][:3].tolist()}); a range is a distance >= 0 (m), +inf for no return")
        return ranges

    def pose(self, pose) -> np.ndarray:
        """``pose`` checked: float32 (x, y, θ), three finite numbers, (x, y) in metres in the layout's
        frame (within ``POSE_SLACK`` of the arena), θ in radians. ValueError otherwise."""
        what = "(x, y, theta): three finite numbers, metres in the layout's frame and radians"
        p = finite(numbers(pose, "pose", 3, what), "pose", what)
        lo, hi = self.map.arena_lo - F32(POSE_SLACK), self.map.arena_hi + F32(POSE_SLACK)
        if (p[:2] < lo).any() or (p[:2] > hi).any():
            raise ValueError(f"pose ({p[0]:g}, {p[1]:g}) lies outside the arena, x {self.map.arena_lo[0]:g}..."
                             f"{self.map.arena_hi[0]:g}, y {self.map.arena_lo[1]:g}...{self.map.arena_hi[1]:g} m; "
                             "is it in the layout's frame, in metres?")
        return p

    def state(self, q) -> int:
        """``q`` checked: an integer automaton state (``TaskTracker.q``). ValueError otherwise."""
        if isinstance(q, (bool, np.bool_)) or not isinstance(q, (int, np.integer)):
            raise ValueError(f"q must be an integer automaton state (TaskTracker.q); got {q!r:.40}")
        if not 0 <= int(q) < self.automaton.n_states:
            raise ValueError(f"automaton state {q} outside 0..{self.automaton.n_states - 1}")
        return int(q)

    def _descent(self, xy: np.ndarray, q: int) -> np.ndarray:
        """``envs.geodesic.descent`` of state q's field at xy."""
        spec = self.manifest["path_field"]
        eps = F32(spec["eps"])
        at = lambda d: _lookup(self.path_field[q], xy + d, F32(spec["spacing"]))  # noqa: E731
        grad = np.array([at(np.array([eps, 0], F32)) - at(np.array([-eps, 0], F32)),
                         at(np.array([0, eps], F32)) - at(np.array([0, -eps], F32))], F32)
        norm = np.sqrt(grad[0] * grad[0] + grad[1] * grad[1])
        return -grad / norm if norm > 0 else np.zeros(2, F32)

    def checked_observation(self, obs) -> np.ndarray:
        """``obs`` checked: float32 [observation_size], finite, each part within what
        ``observation`` can give (lidar in [0, 1], a pose in the arena with (cos θ, sin θ) a unit
        vector, a one-hot automaton state, a path direction of length at most 1). ValueError otherwise."""
        what = f"an observation of {self.observation_size} finite numbers (Policy.observation)"
        obs = finite(numbers(obs, "obs", self.observation_size, what), "obs", what)
        tol = F32(1e-3)

        def refuse(part: str, why: str):
            raise ValueError(f"obs: its {part} part (entries {self.parts[part].start}..{self.parts[part].stop - 1}) "
                             f"{why}; is it an observation of this policy's env (Policy.observation)?")

        lidar = obs[self.parts["lidar"]]
        if (lidar < -tol).any() or (lidar > 1 + tol).any():
            refuse("lidar", f"holds values outside [0, 1] ({lidar.min():g} .. {lidar.max():g})")
        p = obs[self.parts["pose"]].astype(np.float64)  # float64: a huge entry is refused, not overflowed
        if abs(float(p[2] * p[2] + p[3] * p[3]) - 1.0) > 1e-2:
            refuse("pose", f"has (cos θ, sin θ) = ({p[2]:g}, {p[3]:g}), not a unit vector")
        self.pose(self.pose_of_observation(obs))  # in the arena: the pose check's own error
        z = obs[self.parts["automaton"]]
        if not (np.isin(z, (0.0, 1.0)).all() and z.sum() == 1):
            refuse("automaton", "is not one-hot")
        if "path" in self.parts and float(np.linalg.norm(obs[self.parts["path"]].astype(np.float64))) > 1 + 1e-2:
            refuse("path", "is longer than a unit vector")
        return obs

    def x_of_observation(self, obs: np.ndarray) -> np.ndarray:
        """x = b(z, O_s) [K + 1] read off an observation: its lidar part times H and the distance from
        the position it reports to the nearest obstacle on the map (``sensors.cbf_input_from_obs``)."""
        obs = numbers(obs, "obs", self.observation_size, f"an observation of {self.observation_size} numbers")
        p = obs[self.parts["pose"]]
        lo, hi = self.map.arena_lo, self.map.arena_hi
        xy = (p[:2] + F32(1.0)) * F32(0.5) * (hi - lo) + lo
        return np.concatenate([obs[self.parts["lidar"]] * self.H, [self.map.nearest(xy)]]).astype(F32)

    def pose_of_observation(self, obs: np.ndarray) -> np.ndarray:
        """(x, y, θ) read back from an observation's pose part (for a simulator that gives no pose)."""
        obs = numbers(obs, "obs", self.observation_size, f"an observation of {self.observation_size} numbers")
        p = obs[self.parts["pose"]]
        lo, hi = self.map.arena_lo, self.map.arena_hi
        xy = (p[:2] + F32(1.0)) * F32(0.5) * (hi - lo) + lo
        return np.array([xy[0], xy[1], np.arctan2(p[3], p[2])], F32)

    # ------------------------------------------------------------------------------- acting

    def act(self, ranges, pose, q: int, filter: bool | None = None) -> np.ndarray:
        """The action [2] in [-1, 1] for lidar ``ranges`` [K], ``pose`` (x, y, θ) and automaton state q;
        ``filter``: the runtime filter on or off (None: ``filter_on``)."""
        return self.act_observation(self.observation(ranges, pose, q), pose, filter)

    def act_observation(self, obs, pose=None, filter: bool | None = None) -> np.ndarray:
        """The action [2] for an observation as the env gives it (``checked_observation``); the filter
        reads ``pose`` (default: the pose the observation reports)."""
        obs = self.checked_observation(obs)
        if filter is not None and not isinstance(filter, (bool, np.bool_)):
            raise ValueError(f"filter must be True, False or None; got {filter!r:.40}")
        use_filter = self.filter_on if filter is None else bool(filter)
        if use_filter and self.runtime_filter is None:
            raise ValueError("this policy has no runtime filter (only D²SPO's has one)")
        if self.safety_policy is None:
            u = self._run_onnx(obs) if self._session else self.actor(obs)
        else:
            x = self.x_of_observation(obs)
            u = self._run_onnx(obs, x) if self._session else self.safety_policy(x, self.actor(obs))
            if use_filter:
                pose = self.pose_of_observation(obs) if pose is None else self.pose(pose)
                u = self.runtime_filter(pose, u)[0]
        if not np.isfinite(u).all():  # never returned: a robot would drive on it
            raise ValueError(f"the policy's action for this observation is not finite ({np.asarray(u).tolist()})")
        return u

    def filter(self, pose, u0):
        """(action, whether c >= 0 holds, c): the runtime filter alone on the action ``u0`` [2] at
        ``pose``. ValueError for a policy without a filter (not D²SPO) or a malformed argument."""
        if self.runtime_filter is None:
            raise ValueError("this policy has no runtime filter (only D²SPO's has one)")
        what = "an action of two finite numbers (linear, angular) in [-1, 1]"
        u0 = finite(numbers(u0, "u0", 2, what), "u0", what)
        if (np.abs(u0) > 1 + 1e-6).any():
            raise ValueError(f"u0 must be {what}; got {u0.tolist()}")
        return self.runtime_filter(self.pose(pose), u0)

    def _run_onnx(self, obs: np.ndarray, x: np.ndarray | None = None) -> np.ndarray:
        feeds = {"obs": obs[None]} if x is None else {"obs": obs[None], "x": x[None]}
        return self._session.run(["action"], feeds)[0][0]

    def command(self, action) -> tuple[float, float]:
        """(v, ω) the robot is commanded: the action clipped to [-1, 1], a₀ mapped onto [v_min, v_max]
        (v = a₀ · v_max for a robot that reverses) and a₁ times ω_max."""
        what = "an action of two finite numbers (linear, angular) in [-1, 1]"
        a = np.clip(finite(numbers(action, "action", 2, what), "action", what), -1.0, 1.0)
        return float(a[0]) * (self.v_max - self.v_mid) + self.v_mid, float(a[1]) * self.omega_max

    def task_tracker(self) -> TaskTracker:
        """A fresh tracker of the automaton state (``TaskTracker.reset`` it at the start pose); it refuses
        a position more than ``POSE_SLACK`` outside the arena, as ``pose`` does."""
        slack = F32(POSE_SLACK)
        return TaskTracker(self.automaton, (self.map.arena_lo - slack, self.map.arena_hi + slack))

    def scan_error(self, ranges, pose) -> float:
        """The mean |ranges - scan(pose)| (m), both clipped to H, over the rays on which the map or the scan
        sees a surface within H (0 when neither sees one): how far the robot's scan is from what the map
        predicts at its pose. Near 0 on a good map and localisation; a large value means the pose is
        off, the map out of date (an obstacle not on it adds its rays' share) or the ranges in another
        unit (millimetres clip to H and read as free space), which ``act`` cannot tell by itself. Rays
        that both read as free say nothing of the pose and are left out: a median over every ray read
        0 for a pose 0.3 m off wherever half the rays saw nothing."""
        got, want = np.clip(self.ranges(ranges), 0.0, self.H), np.clip(self.scan(pose), 0.0, self.H)
        seen = (got < self.H) | (want < self.H)
        return float(np.mean(np.abs(got - want)[seen])) if seen.any() else 0.0

    def scan(self, pose) -> np.ndarray:
        """[K] the ranges the env's lidar reads at ``pose`` on the map (for a simulator, or to check a real scan)."""
        pose = self.pose(pose)
        return self.map.lidar(pose[:2], np.cos(pose[2]), np.sin(pose[2]))


def _lookup(field: np.ndarray, xy: np.ndarray, spacing: np.float32) -> np.float32:
    """Bilinear interpolation of one grid field at xy, clamped to the grid (``envs.geodesic.lookup``).
    xy / spacing is taken as xy times 1/spacing, as XLA compiles a division by a constant."""
    ny, nx = field.shape
    inv = F32(1.0) / spacing
    fx = np.clip(xy[0] * inv, F32(0.0), F32(nx - 1.0))
    fy = np.clip(xy[1] * inv, F32(0.0), F32(ny - 1.0))
    x0 = int(np.clip(np.floor(fx), 0, nx - 2))
    y0 = int(np.clip(np.floor(fy), 0, ny - 2))
    tx, ty = fx - F32(x0), fy - F32(y0)
    f00, f01, f10, f11 = field[y0, x0], field[y0, x0 + 1], field[y0 + 1, x0], field[y0 + 1, x0 + 1]
    one = F32(1.0)
    return (one - ty) * ((one - tx) * f00 + tx * f01) + ty * ((one - tx) * f10 + tx * f11)


def _onnx_session(directory: Path, manifest: dict):
    onnx = manifest.get("onnx")
    if not onnx:
        raise ArtefactError(f"{directory}: no ONNX networks (export with `d2spo export --onnx`)")
    try:
        import onnxruntime
    except ImportError:
        raise ArtefactError("the onnxruntime backend needs onnxruntime (pip install 'd2spo[onnx]')") from None
    path = directory / onnx["policy"]["file"]
    if not path.is_file() or file_sha256(path) != onnx["policy"]["sha256"]:
        raise ArtefactError(f"{path}: missing or damaged (its SHA-256 is not the manifest's)")
    return onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
