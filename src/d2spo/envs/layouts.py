"""Layouts by name: a built-in name, ``random:SEED``, ``random5:SEED`` or a JSON file; and the letters a layout can produce.

``load(name_or_path)`` returns a validated ``workspace.Layout``: a built-in name (``paper``,
``relaxed``, ``open``, ``physical-1`` .. ``physical-4``), ``random`` / ``random:SEED`` for a
procedural layout (``envs.generator.generate``; ``random5:SEED`` for the 5 m one,
``generator.random_layout``), or the path of a JSON file (schema in docs/layouts.md, read by
``from_json``). Every mistake raises ``ConfigError`` naming the offending field (``layout``,
``layout.areas[2].radius``, ...). ``feasible_letters`` lists the letters labelling can produce
on a layout, ``letters_at`` the letter at given points.
"""

from __future__ import annotations

import difflib
import functools
import itertools
import json
import math
import operator
import os
import warnings
from importlib import resources
from pathlib import Path

import numpy as np

from d2spo.envs import generator
from d2spo.envs.workspace import PROPOSITION_RULE, Area, DiskObstacle, Layout, Obstacle, is_proposition, validate
from d2spo.envs.zones import zones_layout
from d2spo.errors import ConfigError, D2SPOWarning, in_file, is_finite_number, json_trouble
from d2spo.inputs import read_regular

BUILTIN = ("paper", "relaxed", "open", "physical-1", "physical-2", "physical-3", "physical-4")
"""Names of the layouts shipped as JSON files in ``d2spo/envs/layouts/``."""

RANDOM_KINDS = ("random", "random5", "zones", "world")
"""Procedural layouts by seed: ``random:SEED`` (``generator.generate``: 5-10 m arenas of three
styles), ``random5:SEED`` (``generator.random_layout``: 5 m arenas), ``zones:SEED``
(``zones.zones_layout``: ZoneEnv's eight coloured zones) and ``world:SEED`` (``world.generate``:
the generalist's training world, rectangular arenas of 5-20 m, boxes and pillars, 4-12 areas)."""


# ----------------------------------------------------------------------------------- JSON parsing


def _number(value, field: str, positive: bool = False) -> float:
    if not is_finite_number(value):
        raise ConfigError(field, f"expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise ConfigError(field, f"must be positive, got {value!r}")
    return float(value)


def _vector(value, n: int, field: str, positive: bool = False) -> tuple[float, ...]:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigError(field, f"expected a list of {n} numbers, got {value!r}")
    return tuple(_number(v, f"{field}[{i}]", positive) for i, v in enumerate(value))


def _get(obj: dict, key: str, field: str):
    if not isinstance(obj, dict):
        raise ConfigError(field, f"expected an object, got {obj!r}")
    if key not in obj:
        raise ConfigError(f"{field}.{key}", "missing")
    return obj[key]


LAYOUT_KEYS = ("name", "description", "arena", "start", "obstacles", "areas")
AREA_KEYS = ("name", "label", "center", "radius")
OBSTACLE_KEYS = ("center", "half_extents", "radius")


def _no_unknown_keys(obj, known: tuple[str, ...], field: str, what: str) -> None:
    """ConfigError naming a key of ``obj`` (an object) that is not one of ``known``, with the known
    key it is closest to: a misspelt ``label`` would otherwise be dropped without a word, and the
    area's label with it."""
    if not isinstance(obj, dict):
        raise ConfigError(field, f"expected an object, got {obj!r}")
    for key in obj:
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(f"{field}.{key}", f"unknown key{hint}; {what} has {', '.join(known)}")


def from_json(data: dict, default_name: str = "custom") -> Layout:
    """A validated layout from a dict with keys arena, start, obstacles, areas (and optional name)."""
    f = "layout"
    if not isinstance(data, dict):
        raise ConfigError(f, f"expected a JSON object, got {type(data).__name__}")
    _no_unknown_keys(data, LAYOUT_KEYS, f, "a layout")
    name = data.get("name", default_name)
    if not isinstance(name, str):
        raise ConfigError(f"{f}.name", f"expected a string, got {name!r}")
    if not isinstance(data.get("description", ""), str):
        raise ConfigError(f"{f}.description", f"expected a string, got {data['description']!r}")
    arena = _vector(_get(data, "arena", f), 2, f"{f}.arena", positive=True)
    start = _vector(_get(data, "start", f), 3, f"{f}.start")
    if abs(start[2]) > 2 * math.pi:  # accepted (any angle is a heading), but 90 is rarely meant in radians
        warnings.warn(D2SPOWarning(f"{f}.start: the heading {start[2]:g} is larger than 2π; it is read in "
                                   f"radians (90° is {math.pi / 2:.4f}), as {start[2] % (2 * math.pi):.4f} rad"),
                      stacklevel=2)
    obstacles_raw = _get(data, "obstacles", f)
    if not isinstance(obstacles_raw, list):
        raise ConfigError(f"{f}.obstacles", "expected a list")
    obstacles = tuple(_obstacle(o, f"{f}.obstacles[{i}]") for i, o in enumerate(obstacles_raw))
    areas_raw = _get(data, "areas", f)
    if not isinstance(areas_raw, list):
        raise ConfigError(f"{f}.areas", "expected a list")
    areas = []
    for i, a in enumerate(areas_raw):
        g = f"{f}.areas[{i}]"
        _no_unknown_keys(a, AREA_KEYS, g, "an area")
        area_name = _get(a, "name", g)
        if not isinstance(area_name, str) or not area_name.strip():
            raise ConfigError(f"{g}.name", f"expected a non-empty string, got {area_name!r}")
        label = a.get("label")
        if "label" in a and not is_proposition(label):  # given, even as the name: it must be a proposition
            raise ConfigError(f"{g}.label", f"{label!r} is not a proposition name ({PROPOSITION_RULE})")
        if "label" not in a and not is_proposition(area_name):  # else no formula could name the area
            raise ConfigError(g, f"the name {area_name!r} is not a proposition name ({PROPOSITION_RULE}) and the area "
                              'has no "label": add one (e.g. "label": "dock") for formulas to name it by')
        areas.append(
            Area(area_name, _vector(_get(a, "center", g), 2, f"{g}.center"),
                 _number(_get(a, "radius", g), f"{g}.radius", positive=True), label)
        )
    layout = Layout(name, arena, start, obstacles, tuple(areas))
    validate(layout)
    return layout


def _obstacle(o, g: str) -> Obstacle | DiskObstacle:
    """One obstacle entry: a box (``half_extents``) or a disk (``radius``)."""
    _no_unknown_keys(o, OBSTACLE_KEYS, g, "an obstacle (a box or a disk)")
    center = _vector(_get(o, "center", g), 2, f"{g}.center")
    if "radius" in o and "half_extents" in o:
        raise ConfigError(g, "give half_extents (a box) or radius (a disk), not both")
    if "radius" in o:
        return DiskObstacle(center, _number(o["radius"], f"{g}.radius", positive=True))
    if "half_extents" not in o:
        raise ConfigError(f"{g}.half_extents", "missing (a box has half_extents, a disk radius)")
    return Obstacle(center, _vector(o["half_extents"], 2, f"{g}.half_extents", positive=True))


# ----------------------------------------------------------------------------------- letters


def feasible_letters(layout: Layout, aps: tuple[str, ...], label_mode: str) -> list[int]:
    """Letters (bitmasks over ``aps``) that labelling can actually produce in this layout.

    A letter is the set of propositions true at one position: the labels of the areas that contain
    the robot centre together. A set of areas can hold together iff their disks have a common point;
    for disks, the intersection (if non-empty) contains either one of the centres or an intersection
    point of two circles, so those candidate points are checked. Propositions that label no area are
    always false. The empty letter is included under ``step`` labelling only (``event`` labelling
    never reads it).
    """
    bit = {name: 1 << i for i, name in enumerate(aps)}
    centres = np.array([a.center for a in layout.areas], dtype=np.float64).reshape(-1, 2)
    radii = np.array([a.radius for a in layout.areas], dtype=np.float64)
    candidates = [c for c in centres]
    for i, j in itertools.combinations(range(len(radii)), 2):
        candidates.extend(_circle_intersections(centres[i], radii[i], centres[j], radii[j]))
    letters = {0}
    for p in candidates:
        inside = np.linalg.norm(centres - p, axis=-1) <= radii * (1 + 1e-9) + 1e-12
        letters.add(functools.reduce(operator.or_, (bit.get(a.label, 0) for a, ok in zip(layout.areas, inside) if ok), 0))
    if label_mode == "event":
        letters.discard(0)
    return sorted(letters)


def letters_at(points: np.ndarray, layout: Layout, aps: tuple[str, ...]) -> np.ndarray:
    """int [...]: the letter at each point [..., 2] (bit i <=> the robot centre is inside an area labelled aps[i])."""
    out = np.zeros(points.shape[:-1], np.int64)
    for a in layout.areas:
        if a.label in aps:
            inside = np.hypot(points[..., 0] - a.center[0], points[..., 1] - a.center[1]) <= a.radius
            out |= np.where(inside, 1 << aps.index(a.label), 0)
    return out


def _circle_intersections(c1, r1, c2, r2) -> list[np.ndarray]:
    d = float(np.linalg.norm(c2 - c1))
    if d == 0 or d > r1 + r2 or d < abs(r1 - r2):
        return []
    a = (r1 * r1 - r2 * r2 + d * d) / (2 * d)
    hh = math.sqrt(max(r1 * r1 - a * a, 0.0))
    u = (c2 - c1) / d
    mid = c1 + a * u
    perp = np.array([-u[1], u[0]])
    return [mid + hh * perp, mid - hh * perp]


# ----------------------------------------------------------------------------------- loading


def load(name_or_path: str | os.PathLike) -> Layout:
    """A validated layout by built-in name, ``random[:SEED]`` (``generator.generate``), ``random5[:SEED]``
    (``generator.random_layout``), or JSON file path (a string or a ``pathlib.Path``)."""
    if isinstance(name_or_path, os.PathLike):
        name_or_path = os.fspath(name_or_path)
    if not isinstance(name_or_path, str) or not name_or_path:
        raise ConfigError("layout", f"expected a layout name or a JSON path, got {name_or_path!r}")
    if name_or_path in BUILTIN:
        text = resources.files("d2spo.envs").joinpath("layouts", f"{name_or_path}.json").read_text()
        return from_json(json.loads(text), default_name=name_or_path)
    kind, _, seed_text = name_or_path.partition(":")
    if kind in RANDOM_KINDS and (seed_text or name_or_path == kind):
        seed_text = seed_text or "0"
        try:
            seed = int(seed_text)
        except ValueError:
            raise ConfigError("layout", f"a {kind}:SEED layout's seed must be a whole number >= 0, got {seed_text!r}") from None
        if seed < 0:
            raise ConfigError("layout", f"a {kind}:SEED layout's seed must be a whole number >= 0, got {seed}")
        if kind == "zones":
            return zones_layout(seed)
        if kind == "world":
            from d2spo.envs import world  # it reads the bank's limits (jax): only when asked for

            return world.generate(seed)
        return generator.random_layout(seed) if kind == "random5" else generator.generate(seed)
    path = Path(name_or_path)
    if path.suffix == ".json" or path.exists():
        try:
            text = read_regular(path, lambda message: ConfigError("layout", message)).decode("utf-8-sig")  # a BOM too
        except UnicodeDecodeError as e:
            raise ConfigError("layout", f"{path}: not UTF-8 text (byte {e.start})") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            where = f"line {e.lineno}, column {e.colno}"
            raise ConfigError("layout", f"{path}: malformed JSON: {e.msg} ({where})") from None
        except (RecursionError, ValueError) as e:  # nested too deeply; a number too long to read
            raise ConfigError("layout", f"{path}: unreadable JSON ({json_trouble(e)})") from None
        try:
            return from_json(data, default_name=path.stem)
        except ConfigError as e:  # which file, as the JSON errors above say
            raise in_file(e, path) from None
    raise ConfigError("layout", f"unknown layout {name_or_path!r}; use one of {list(BUILTIN)}, "
                      "'random[:SEED]', 'random5[:SEED]', 'zones[:SEED]', 'world[:SEED]' or a path to a .json file")


def random_seed(name_or_path: str) -> tuple[str, int] | None:
    """(kind, seed) of a drawn layout ``KIND[:SEED]`` (KIND in ``RANDOM_KINDS``) that ``load``
    accepts; None for any other name."""
    kind, _, seed_text = name_or_path.partition(":")
    if kind not in RANDOM_KINDS or not (seed_text or name_or_path == kind):
        return None
    try:
        seed = int(seed_text or "0")
    except ValueError:
        return None
    return (kind, seed) if seed >= 0 else None


def layout_file(name_or_path: str) -> Path | None:
    """The JSON file ``load(name_or_path)`` reads; None for a built-in or a procedural layout."""
    kind, _, seed_text = name_or_path.partition(":")
    if name_or_path in BUILTIN or (kind in RANDOM_KINDS and (seed_text or name_or_path == kind)):
        return None
    return Path(name_or_path)

