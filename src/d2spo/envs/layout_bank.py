"""A bank of layouts of any world, each paired with a task, with one distance field per automaton
state of that task: the generalist's subgoal features (``nearest``).

An automaton state names target areas and forbidden ones (``envs.state_fields``: every area of a
label whose entry makes progress, every area of a label whose entry rejects). A policy that serves
every formula and layout reads, instead of the state's index, the distance and direction to the
nearest target along a path that goes round obstacles and round the forbidden areas. A slot of the
bank holds one layout (a rectangular arena, up to ``M_MAX`` boxes and ``D_MAX`` disks, up to
``N_AREAS`` areas, several of them may share a label), the task it is paired with and, per state
of that task, the state's target and forbidden areas and its field. The fields are computed when a
bank is made (``with_fields``): only the states of the slot's own task, never an enumeration of
area subsets, so the cost grows with the number of states, not with 2^areas.

Field s of a slot at a grid node is the length of the shortest 8-neighbour grid path from the node
to the nearest target area's disk (the last step is the straight distance to the disk), where

* a step costs its length times the mean of its two nodes' multipliers: 1 in the open,
  ``CLEARANCE_COST`` (2) where the node is closer than ``clearance`` (0.3 m, the reward's
  shaping clearance) to an obstacle or wall, and ``COLLIDE_COST`` (100) where it is closer than
  the robot's radius (0.15 m) or outside the arena. The clearance tier is 2 (nav's too since
  2026-11-25; it was 10): a 0.6-0.8 m opening lies wholly in it, and at 10x the path length jumped by metres for a step
  sideways across the opening's mouth (6 m for 0.2 m on ``random:2``); the first generalist
  trained with 10x stopped in front of such openings. The third tier is not in ``envs.geodesic``:
  without it a thin wall costs the same as the opening beside it, and the field would cross a
  corridor's wall rather than take a long detour to an opening;
* entering the disk of a forbidden area costs ``BLOCKED_COST`` arena diagonals (finite, as in
  ``envs.state_fields``: a target walled off by forbidden areas still has a field), leaving it
  nothing; coming closer than ``clearance`` to such a disk costs ``BLOCKED_COST`` times the approach.

The grid has ``G`` x ``G`` nodes over the square of the arena's longer side (spacing side / (G - 1):
0.07 m at 6.6 m, 0.21 m at 20 m); nodes beyond the shorter side lie outside the arena. ``G`` = 96
resolves the narrowest gap the generators draw (0.6 m) up to ``MAX_SIDE`` (20 m): the node
nearest the gap's centre line is at most half a spacing (0.105 m) off it, so the opening holds a line
of nodes with clearance > 0.19 m > the robot radius (cost 2x), while the wall makes a band of
>= 0.4 m of 100x nodes that no step (0.3 m diagonally) jumps (docs/layouts.md, "Field bank").

The step costs and the two solvers that give the same fields live in ``envs.bank_fields``
(``fields_numpy``: scipy's Dijkstra; ``fields_jax``: pure JAX sweeps), with the grid and cost
constants named above (``G``, ``CLEARANCE``, ``CLEARANCE_COST``, ``COLLIDE_COST``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.envs.bank_fields import G, fields_batch, fields_numpy
from d2spo.envs.workspace import Layout, validate
from d2spo.errors import ConfigError

N_AREAS = 16
"""Area slots per layout (unused slots are masked): the most areas a generalist reads."""
M_MAX = 24
"""Box obstacle slots per layout (unused slots are masked)."""
D_MAX = 12
"""Disk obstacle slots per layout (unused slots are masked)."""
MAX_SIDE = 20.0
"""Longest arena side (m) a bank holds: ``G`` resolves a 0.6 m gap up to it (module docstring)."""
TOL_SIDE = 1e-6
"""Slack (m) when comparing an arena's side with ``MAX_SIDE``."""


class LayoutBank(NamedTuple):
    """B slots as fixed-shape arrays (a pytree): a layout, its task, and per state of the task the
    target and forbidden areas and the field. S is the most states of a task of the bank's mixture."""

    arena: jax.Array
    """float32 [B, 2]: (width, height) in metres."""
    box_lo: jax.Array
    """float32 [B, M_MAX, 2]: lower-left corners of the boxes (unused slots: 0)."""
    box_hi: jax.Array
    """float32 [B, M_MAX, 2]: upper-right corners of the boxes (unused slots: 0)."""
    box_mask: jax.Array
    """bool [B, M_MAX]: which box slots hold a box."""
    disk_center: jax.Array
    """float32 [B, D_MAX, 2]: centres of the disk obstacles (unused slots: 0)."""
    disk_radius: jax.Array
    """float32 [B, D_MAX]: radii of the disk obstacles (unused slots: 0)."""
    disk_mask: jax.Array
    """bool [B, D_MAX]: which disk slots hold a disk."""
    area_center: jax.Array
    """float32 [B, N_AREAS, 2]: centres of the areas, in the layout's order (unused slots: 0)."""
    area_radius: jax.Array
    """float32 [B, N_AREAS]: radii of the areas (unused slots: 0)."""
    area_mask: jax.Array
    """bool [B, N_AREAS]: which area slots hold an area."""
    start: jax.Array
    """float32 [B, 3]: start pose (x, y, theta)."""
    max_steps: jax.Array
    """int32 [B]: the episode limit of the slot (``pair``; 0 before)."""
    task: jax.Array
    """int32 [B]: the task of the mixture the slot is paired with (``pair``; 0 before)."""
    area_bits: jax.Array
    """int32 [B, N_AREAS]: the letter bit of each area's label in the automaton (0: a label no task
    names, or an unused slot)."""
    target: jax.Array
    """bool [B, S, N_AREAS]: in state s of the slot's task, entering the area (alone) makes progress."""
    forbidden: jax.Array
    """bool [B, S, N_AREAS]: in state s of the slot's task, entering the area (alone) rejects the task
    or moves away from acceptance."""
    fields: jax.Array
    """float32 [B, S, G, G]: field s, row y, column x (module docstring); [B, 0] before ``with_fields``.
    float32, not float16: the direction is a difference of neighbouring values 0.07-0.21 m apart,
    and float16 resolves 0.03 m between 32 and 64 m (a route in a 10 m arena), a 20-40% error."""

    @property
    def size(self) -> int:
        return int(self.arena.shape[0])

    @property
    def grid(self) -> int:
        return int(self.fields.shape[-1]) if self.fields.ndim == 4 else 0


# ------------------------------------------------------------------------------------ packing


def check_fits(lay: Layout) -> None:
    """ConfigError (one line) when ``lay`` is no valid layout (``workspace.validate``: a ``Layout``
    built in Python reaches the generalist without a file's checks) or exceeds what a bank slot
    holds."""
    where = f"layout {lay.name!r}"
    w, h = lay.arena
    if max(w, h) > MAX_SIDE + TOL_SIDE:
        raise ConfigError("layout.arena", f"{where}: arena {w:g} x {h:g} m; a generalist reads arenas of at most "
                          f"{MAX_SIDE:g} m a side")
    for what, n, most in (("areas", len(lay.areas), N_AREAS), ("box obstacles", len(lay.boxes), M_MAX),
                          ("disk obstacles", len(lay.disks), D_MAX)):
        if n > most:
            raise ConfigError("layout", f"{where}: {n} {what}, more than the {most} a generalist reads")
    areas = lay.areas
    for i, a in enumerate(areas):
        for b in areas[i + 1:]:
            if math.dist(a.center, b.center) < a.radius + b.radius:
                raise ConfigError("layout.areas", f"{where}: areas {a.name} and {b.name} overlap; a generalist "
                                  "plans one area at a time")
    try:
        validate(lay)
    except ConfigError as e:
        raise ConfigError(e.field, f"{where}: {str(e).removeprefix(f'{e.field}: ')}") from None


def pack(layouts: Sequence[Layout], tasks: Sequence[int] | None = None) -> LayoutBank:
    """The layouts as arrays (slot k holds layouts[k], paired with task tasks[k], default 0); labels,
    roles and fields not set yet (``pair``, ``with_fields``). Raises ConfigError (``check_fits``)."""
    b = len(layouts)
    if b == 0:
        raise ConfigError("layouts", "a bank needs at least one layout")
    for lay in layouts:
        check_fits(lay)
    lo, hi, bmask = np.zeros((b, M_MAX, 2)), np.zeros((b, M_MAX, 2)), np.zeros((b, M_MAX), bool)
    dc, dr, dmask = np.zeros((b, D_MAX, 2)), np.zeros((b, D_MAX)), np.zeros((b, D_MAX), bool)
    ac, ar, amask = np.zeros((b, N_AREAS, 2)), np.zeros((b, N_AREAS)), np.zeros((b, N_AREAS), bool)
    for k, lay in enumerate(layouts):
        for m, o in enumerate(lay.boxes):
            lo[k, m], hi[k, m], bmask[k, m] = o.lo, o.hi, True
        for m, o in enumerate(lay.disks):
            dc[k, m], dr[k, m], dmask[k, m] = o.center, o.radius, True
        for m, a in enumerate(lay.areas):
            ac[k, m], ar[k, m], amask[k, m] = a.center, a.radius, True
    f32 = lambda x: jnp.asarray(np.asarray(x, np.float64), jnp.float32)  # noqa: E731
    return LayoutBank(
        arena=f32([lay.arena for lay in layouts]), box_lo=f32(lo), box_hi=f32(hi), box_mask=jnp.asarray(bmask),
        disk_center=f32(dc), disk_radius=f32(dr), disk_mask=jnp.asarray(dmask),
        area_center=f32(ac), area_radius=f32(ar), area_mask=jnp.asarray(amask),
        start=f32([lay.start for lay in layouts]), max_steps=jnp.zeros(b, jnp.int32),
        task=jnp.asarray(np.zeros(b, np.int32) if tasks is None else np.asarray(tasks, np.int32)),
        area_bits=jnp.zeros((b, N_AREAS), jnp.int32), target=jnp.zeros((b, 0, N_AREAS), bool),
        forbidden=jnp.zeros((b, 0, N_AREAS), bool), fields=jnp.zeros((b, 0), jnp.float32))


def pair(bank: LayoutBank, area_bits: np.ndarray, target: np.ndarray, forbidden: np.ndarray,
         max_steps: np.ndarray | None = None) -> LayoutBank:
    """``bank`` with its slots' letter bits [B, N_AREAS], roles [B, S, N_AREAS] (``envs.generalist``
    derives them from the slots' labels and tasks) and episode limits [B] (None: unchanged); the
    fields still to compute."""
    if max_steps is not None:
        bank = bank._replace(max_steps=jnp.asarray(max_steps, jnp.int32))
    return bank._replace(area_bits=jnp.asarray(area_bits, jnp.int32), target=jnp.asarray(target, bool),
                         forbidden=jnp.asarray(forbidden, bool), fields=jnp.zeros((bank.size, 0), jnp.float32))


def _slot_args(bank: LayoutBank) -> tuple:
    return (bank.arena, bank.box_lo, bank.box_hi, bank.box_mask, bank.disk_center, bank.disk_radius, bank.disk_mask,
            bank.area_center, bank.area_radius, bank.area_mask, bank.target, bank.forbidden)


def with_fields(bank: LayoutBank, method: str = "jax", chunk: int = 16, grid: int = G) -> LayoutBank:
    """``bank`` with the fields of every slot on ``grid`` x ``grid`` nodes, by ``fields_jax`` (``chunk``
    slots a call, the last call padded: one compiled program, and a slot's field the same bit for bit
    whichever slots share its call; the faster for many slots, after its compilation) or
    ``fields_numpy`` (one at a time). A bank of fewer than ``chunk`` slots is one call of the next
    power of two slots: a zero-shot evaluation's single layout or a redraw's few solve 1, 2 or 4
    fields, not 16 (at XLA's level 0, the tests', one slot took 0.2 s against 3.1 s for a padded
    call of 16; at the default level 0.05 s against 0.45 s; 2026-11-29, slow Intel)."""
    if bank.target.shape[1] == 0:
        raise ConfigError("bank", "the bank's slots have no task states yet (layout_bank.pair)")
    # on the host: slicing and padding device arrays eagerly compiles a program per shape (seconds
    # of a 2-core machine's time per bank), and copies are exact
    args = [np.asarray(a) for a in _slot_args(bank)]
    n = bank.size
    if method == "jax":
        out = []
        chunk = min(chunk, 1 << max(n - 1, 0).bit_length())  # n <= chunk: the power of two >= n
        for s in range(0, n, chunk):
            part = [a[s:s + chunk] for a in args]
            short = chunk - part[0].shape[0]
            if short:  # one compiled shape: pad the last call with copies of its first slot
                part = [np.concatenate([a, np.repeat(a[:1], short, axis=0)]) for a in part]
            out.append(fields_batch(*part, grid)[:chunk - short])
    elif method == "numpy":
        out = [fields_numpy(*(a[k] for a in args), grid=grid)[None] for k in range(n)]
    else:
        raise ConfigError("method", f"expected 'jax' or 'numpy', got {method!r}")
    fields = jnp.concatenate([jnp.asarray(o) for o in out])
    return bank._replace(fields=jnp.where(jnp.isfinite(fields), fields, 0.0))  # a state with no target: 0


# ------------------------------------------------------------------------------------ lookup


def field_at(bank: LayoutBank, b, s, xy: jax.Array) -> jax.Array:
    """Field s of slot b, bilinear at xy [2] (clamped to the grid), as ``geodesic.lookup``; it
    gathers the four nodes from the whole bank, so no slice of a field is copied when b and s are
    traced (inside the training step)."""
    g = bank.fields.shape[-1]
    spacing = jnp.maximum(bank.arena[b, 0], bank.arena[b, 1]) / (g - 1)
    fx = jnp.clip(xy[0] / spacing, 0.0, g - 1.0)
    fy = jnp.clip(xy[1] / spacing, 0.0, g - 1.0)
    x0 = jnp.clip(jnp.floor(fx).astype(jnp.int32), 0, g - 2)
    y0 = jnp.clip(jnp.floor(fy).astype(jnp.int32), 0, g - 2)
    tx, ty = fx - x0, fy - y0
    f00, f01 = bank.fields[b, s, y0, x0], bank.fields[b, s, y0, x0 + 1]
    f10, f11 = bank.fields[b, s, y0 + 1, x0], bank.fields[b, s, y0 + 1, x0 + 1]
    return (1 - ty) * ((1 - tx) * f00 + tx * f01) + ty * ((1 - tx) * f10 + tx * f11)


def nearest(bank: LayoutBank, b, s, xy: jax.Array):
    """(distance [], direction [2], any []) at xy to the nearest target area of state s of slot b,
    along a path avoiding the state's forbidden areas; ``any``: the state has a target.

    The direction is the unit vector of steepest descent of the bilinear field, by central
    differences half a grid spacing either side; with no target (or a flat field) both are 0.
    """
    any_target = jnp.any(bank.target[b, s] & bank.area_mask[b])
    eps = 0.5 * jnp.maximum(bank.arena[b, 0], bank.arena[b, 1]) / (bank.fields.shape[-1] - 1)
    probe = lambda dxy: field_at(bank, b, s, xy + dxy)  # noqa: E731
    grad = jnp.stack([probe(jnp.array([eps, 0.0])) - probe(jnp.array([-eps, 0.0])),
                      probe(jnp.array([0.0, eps])) - probe(jnp.array([0.0, -eps]))]) / (2 * eps)
    grad = jnp.where(jnp.isfinite(grad), grad, 0.0)
    norm = jnp.linalg.norm(grad)
    direction = jnp.where(any_target & (norm > 0), -grad / jnp.where(norm > 0, norm, 1.0), 0.0)
    return jnp.where(any_target, field_at(bank, b, s, xy), 0.0), direction, any_target
