"""The annealed subtask radius of Sec. IV-C (TLGRL).

During training an area counts as reached when k1 d_s e^(k2 I_ep) <= d_bar (d_s: distance to the
area's centre, I_ep: episode index). Early in training this is a wide disk; it shrinks until it is
the area itself. It only changes the labelling that drives the reward and the episode's end;
every reported completion rate uses the true labelling (robot inside the area).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from d2spo.fields import check_choice, check_fields

RELAX_MODES = ("all", "targets")
"""Which areas the annealed radius relaxes: every area, or in each automaton state only the areas
whose entry makes progress (``AnnealConfig.relax``)."""


@dataclass(frozen=True)
class AnnealConfig:
    """Annealed subtask radius of Sec. IV-C: an area counts as reached when k1 d_s e^(k2 I_ep) <= d_bar."""

    enabled: bool = True
    """Relax the labelling early in training."""
    k1: float = 0.1
    """k1 of the paper: the initial radius is d_bar / k1."""
    k2: float | None = None
    """k2 of the paper (per episode); None: set by until."""
    until: float = 0.5
    """With k2 None: fraction of the run that is relaxed."""
    d_bar: float | None = None
    """Threshold d_bar (m); None = each area's own radius."""
    separate: bool = True
    """Cap relaxed disks so none overlap (not in the paper)."""

    relax: str = "targets"
    """Areas relaxed: "targets" (those whose entry makes progress) or "all" (the paper's)."""

    def __post_init__(self) -> None:
        check_fields(self, "anneal", nullable=("k2", "d_bar"), positive=("k1", "d_bar"), non_negative=("k2",),
                     rate=("until",), flag=("enabled", "separate"))
        check_choice(self, "relax", RELAX_MODES, "anneal")

    def rate(self, total_episodes: int) -> float:
        """k2: explicit, or ln(1/k1) / (until * episodes) so that k1 e^(k2 I) reaches 1 at I = until * episodes."""
        if self.k2 is not None:
            return self.k2
        return math.log(1.0 / self.k1) / max(1.0, self.until * total_episodes) if self.k1 < 1 else 0.0


def separation_cap(area_center: jax.Array, area_radius: jax.Array) -> jax.Array:
    """Per area: half the distance to the nearest other area's centre, at least its true radius (inf if alone)."""
    rel = area_center[:, None, :] - area_center[None, :, :]
    dist = jnp.sqrt(jnp.sum(rel * rel, axis=-1))
    n = area_center.shape[0]
    dist = jnp.where(jnp.eye(n, dtype=bool), jnp.inf, dist)
    return jnp.maximum(area_radius, 0.5 * jnp.min(dist, axis=-1, initial=jnp.inf))


def label_radius(area_radius: jax.Array, episodes: jax.Array, cfg: AnnealConfig, k2: float,
                 cap: jax.Array | None = None) -> jax.Array:
    """Radius within which an area counts as reached after ``episodes`` episodes (never below the true one).

    Sec. IV-C: reached when k1 d_s e^(k2 I_ep) <= d_bar, i.e. d_s <= d_bar / (k1 e^(k2 I_ep)).
    ``cap`` (per area) bounds the relaxed radius from above (see ``AnnealConfig.separate``).
    """
    if not cfg.enabled:
        return area_radius
    d_bar = area_radius if cfg.d_bar is None else jnp.full_like(area_radius, cfg.d_bar)
    relaxed = d_bar / (cfg.k1 * jnp.exp(k2 * episodes.astype(jnp.float32)))
    if cap is not None:
        relaxed = jnp.minimum(relaxed, cap)
    return jnp.maximum(area_radius, relaxed)


def annealed_params(params, episodes: jax.Array, cfg: AnnealConfig, k2: float):
    """Env params whose labelling radius is the annealed one after ``episodes`` finished episodes;
    ``params`` as they are when annealing is off (their ``label_radius``: the areas' true radii, or
    ``--label-radius``'s fixed relaxed radius)."""
    if not cfg.enabled:
        return params
    cap = separation_cap(params.area_center, params.area_radius) if cfg.separate else None
    radius = label_radius(params.area_radius, episodes, cfg, k2, cap)
    if cfg.relax == "targets":
        return params.replace(label_radius=radius, relax_mask=params.advance)
    return params.replace(label_radius=radius)
