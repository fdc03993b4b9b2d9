"""The zones layout family, ``zones:SEED``: ZoneEnv's conventions (the benchmark of LTL2Action,
GCRL-LTL, DeepLTL and GenZ-LTL, built on Safety Gym) on d2spo's robot and arena.

A 6.6 m square arena whose walls end an episode as a collision (as every d2spo wall does); no
obstacles; 8 disk zones of radius 0.4 m, two each labelled ``green``, ``yellow``, ``blue`` and
``magenta`` (areas ``green-1``, ``green-2``, ...: docs/layouts.md, "Labels"), their centres drawn
uniformly in the central 5 m x 5 m; a start pose drawn uniformly there too, any heading. Keep-outs
follow Safety Gym's placement rule (two objects' centres at least the sum of their keep-out radii
apart): 0.55 m per zone, so zone centres 1.1 m apart, and 0.4 m for the robot, so the start 0.95 m
from every zone centre. A deterministic function of SEED.
"""

from __future__ import annotations

import math

import numpy as np

from d2spo.envs.workspace import Area, Layout, validate

COLOURS = ("green", "yellow", "blue", "magenta")
"""The zones' labels, two zones each."""
ARENA = 6.6
"""Side of the square arena (m)."""
CENTRAL = 5.0
"""Side of the central square the zones and the start are drawn in (m)."""
ZONE_RADIUS = 0.4
"""Radius of a zone (m)."""
ZONE_KEEPOUT = 0.55
"""Keep-out radius of a zone (m): zone centres are at least twice this apart."""
ROBOT_KEEPOUT = 0.4
"""Keep-out radius of the robot at the start (m): the start is ZONE_KEEPOUT + this from every zone centre."""


def zones_layout(seed: int) -> Layout:
    """The layout ``zones:SEED``: zones placed one after another by rejection sampling, then the start."""
    rng = np.random.default_rng(seed)
    lo, hi = (ARENA - CENTRAL) / 2, (ARENA + CENTRAL) / 2
    for _ in range(1000):
        centres: list[np.ndarray] = []
        for _ in range(2000):
            c = np.round(rng.uniform(lo, hi, 2), 3)
            if all(np.linalg.norm(c - d) >= 2 * ZONE_KEEPOUT for d in centres):
                centres.append(c)
                if len(centres) == 2 * len(COLOURS):
                    break
        if len(centres) < 2 * len(COLOURS):
            continue
        for _ in range(2000):
            xy = np.round(rng.uniform(lo, hi, 2), 3)
            if all(np.linalg.norm(xy - c) >= ZONE_KEEPOUT + ROBOT_KEEPOUT for c in centres):
                break
        else:
            continue
        theta = round(float(rng.uniform(-math.pi, math.pi)), 3)
        areas = tuple(Area(f"{colour}-{k + 1}", (float(c[0]), float(c[1])), ZONE_RADIUS, colour)
                      for i, c in enumerate(centres) for colour, k in [(COLOURS[i // 2], i % 2)])
        layout = Layout(f"zones:{seed}", (ARENA, ARENA), (float(xy[0]), float(xy[1]), theta), (), areas)
        validate(layout)
        return layout
    raise RuntimeError(f"zones:{seed}: no placement found")  # pragma: no cover (the draws leave ample room)
