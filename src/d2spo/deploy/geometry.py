"""The sensor model x = b(z, O_s) over the exported map, in numpy: ``envs.sensors`` without JAX.

The runtime filter reads h at the pose the nominal model predicts, so it casts the lidar on the
map itself (``Map.lidar``), and π_Ω's input ends with the distance to the nearest obstacle or wall
(``Map.nearest``), which no ray measures. Each function mirrors its JAX twin operation for
operation (``envs.sensors.lidar_cs``, ``_box_range``, ``_disk_range``, ``nearest_obstacle``;
``envs.geometry``'s signed distances) and takes plain arrays or ``dual.Dual`` values, so the
filter gets ∇_u through the ray casts (``deploy.dual``). float32 throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from d2spo.deploy import dual as ad
from d2spo.deploy.dual import F32

_EPS = F32(1e-9)
"""Ray direction components smaller than this are taken as ±_EPS (``envs.sensors._EPS``)."""


def ray_offsets(n_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin [K] of the ray angles relative to the heading: ray k at 2πk/K, counter-clockwise."""
    phi = 2.0 * math.pi * np.arange(n_rays) / n_rays
    return np.cos(phi).astype(F32), np.sin(phi).astype(F32)


@dataclass(frozen=True)
class Map:
    """The layout's obstacles as float32 arrays (the manifest's ``layout``)."""

    arena_lo: np.ndarray
    """[2]: lower-left corner of the arena (the origin)."""
    arena_hi: np.ndarray
    """[2]: upper-right corner."""
    box_lo: np.ndarray
    """[M, 2]: lower corners of the boxes."""
    box_hi: np.ndarray
    """[M, 2]: upper corners."""
    disk_center: np.ndarray
    """[D, 2]: centres of the disks."""
    disk_radius: np.ndarray
    """[D]: their radii."""
    n_rays: int
    """K."""
    H: np.float32
    """Sensing radius (m): ranges are clipped to [0, H]."""

    def lidar(self, xy, c, s):
        """[K] ranges (m) from xy with heading cosine c and sine s, every obstacle visible."""
        cos_phi, sin_phi = ray_offsets(self.n_rays)
        H = self.H
        dx = c * cos_phi - s * sin_phi
        dy = s * cos_phi + c * sin_phi
        inv_x, inv_y = _safe_inverse(dx), _safe_inverse(dy)
        alo = self.arena_lo - xy
        ahi = self.arena_hi - xy
        t_wall = ad.minimum(ad.maximum(alo[0] * inv_x, ahi[0] * inv_x), ad.maximum(alo[1] * inv_y, ahi[1] * inv_y))
        rows = [ad.minimum(t_wall, H)[None]]  # [1, K], then [M, K] boxes and [D, K] disks
        if self.box_lo.shape[0]:
            lo, hi = self.box_lo - xy, self.box_hi - xy  # [M, 2]
            rows.append(_box_range(lo[:, 0][:, None], lo[:, 1][:, None], hi[:, 0][:, None], hi[:, 1][:, None],
                                   inv_x, inv_y, H))
        if self.disk_center.shape[0]:
            rel = self.disk_center - xy
            rows.append(_disk_range(rel[:, 0][:, None], rel[:, 1][:, None], self.disk_radius[:, None], dx, dy, H))
        t = ad.min_first(ad.concat(rows, axis=0)) if len(rows) > 1 else rows[0][0]
        return ad.clip(t, F32(0.0), H)

    def nearest(self, xy):
        """Distance from xy to the nearest obstacle or wall, clipped to [0, H] (``nearest_obstacle``)."""
        parts = []
        if self.box_lo.shape[0]:
            parts.append(_box_signed_distance(xy, self.box_lo, self.box_hi))
        if self.disk_center.shape[0]:
            parts.append(_disk_signed_distance(xy, self.disk_center, self.disk_radius))
        lo = xy - self.arena_lo
        hi = self.arena_hi - xy
        walls = ad.minimum(ad.minimum(lo[0], lo[1]), ad.minimum(hi[0], hi[1]))
        return ad.clip(ad.min_last(ad.concat(parts + [ad.stack([walls])])), F32(0.0), self.H)

    def features(self, pose):
        """x = b(z, O_s) [K + 1] at ``pose`` (x, y, θ) with every obstacle sensed (``sensors.cbf_input``)."""
        xy = pose[0:2] if isinstance(pose, ad.Dual) else np.asarray(pose[:2], F32)
        th = pose[2]
        return ad.concat([self.lidar(xy, ad.cos(th), ad.sin(th)), ad.stack([self.nearest(xy)])])


def _safe_inverse(d):
    small = np.abs(ad.value(d)) < _EPS
    guard = np.where(ad.value(d) < 0.0, -_EPS, _EPS)
    return F32(1.0) / ad.where(small, guard, d)


def _box_range(lo_x, lo_y, hi_x, hi_y, inv_x, inv_y, H):
    """[M, K] ranges to each box along each ray (or H when missed); corners [M, 1] relative to the robot."""
    tx1, tx2 = lo_x * inv_x, hi_x * inv_x
    ty1, ty2 = lo_y * inv_y, hi_y * inv_y
    t_near = ad.maximum(ad.minimum(tx1, tx2), ad.minimum(ty1, ty2))
    t_far = ad.minimum(ad.maximum(tx1, tx2), ad.maximum(ty1, ty2))
    t_enter = ad.maximum(t_near, F32(0.0))
    return ad.where(ad.value(t_far) >= ad.value(t_enter), t_enter, H)


def _disk_range(cx, cy, radius, dx, dy, H):
    """[D, K] ranges to each disk (or H when missed, 0 from inside); centres [D, 1] relative to the robot."""
    b = cx * dx + cy * dy
    c = cx * cx + cy * cy - radius * radius
    disc = b * b - c
    real = ad.value(disc) > 0.0
    t = b - ad.where(real, ad.sqrt(ad.where(real, disc, F32(1.0))), F32(0.0))
    cv, bv = ad.value(c), ad.value(b)
    return ad.where(cv <= 0.0, F32(0.0), ad.where(real & (bv >= 0.0), t, H))


def _box_signed_distance(xy, box_lo, box_hi):
    centre = F32(0.5) * (box_lo + box_hi)
    half = F32(0.5) * (box_hi - box_lo)
    dx = ad.abs(xy[0] - centre[:, 0]) - half[:, 0]
    dy = ad.abs(xy[1] - centre[:, 1]) - half[:, 1]
    ox, oy = ad.maximum(dx, F32(0.0)), ad.maximum(dy, F32(0.0))
    sq = ox * ox + oy * oy
    positive = ad.value(sq) > 0.0
    outside = ad.where(positive, ad.sqrt(ad.where(positive, sq, F32(1.0))), F32(0.0))
    inside = ad.minimum(ad.maximum(dx, dy), F32(0.0))
    return outside + inside


def _disk_signed_distance(xy, center, radius):
    dx = xy[0] - center[:, 0]
    dy = xy[1] - center[:, 1]
    sq = dx * dx + dy * dy
    positive = ad.value(sq) > 0.0
    return ad.where(positive, ad.sqrt(ad.where(positive, sq, F32(1.0))), F32(0.0)) - radius
