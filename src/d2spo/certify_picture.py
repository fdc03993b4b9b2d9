"""The picture of `d2spo certify` (RUN/certify.png): where each proposition is certified, not
certified or violated over the layout (docs/certify.md, "The picture")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from d2spo.certify import CBFRun, CertifyConfig, cell_index, grid_axes


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


def save_picture(run: CBFRun, ccfg: CertifyConfig, nets: dict, summary: dict, path: Path) -> None:
    """Panels over the layout: where Proposition 1 (ℒ and contact) and Proposition 2 (the grid's
    explored part; then the whole free space, if checked) are certified (green), not certified
    (orange) or violated (red), worst over θ and states; the search's worst points as x."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure

    from d2spo.envs.render import draw_layout

    maps, extent = status_maps(run, ccfg, nets)
    cmap = ListedColormap(["white", "tab:green", "orange", "tab:red"])
    rho = summary["residual"]["rho_h"]
    titles = (f"Prop. 1: h < 0 in the ring and contact (ε̄ = {ccfg.eps_unsafe:g} m)",
              f"Prop. 2: e ≥ 0 on explored cells (D; ε = {ccfg.eps_safe:g} m, ρ_h = {rho:.3g})",
              "Prop. 2 beyond D: every free pose, every live state")
    fig = Figure(figsize=(5.5 * len(maps), 5.2))
    for i, m in enumerate(maps):
        ax = fig.add_subplot(1, len(maps), i + 1)
        ax.imshow(m + 1, origin="lower", extent=extent, cmap=cmap, vmin=0, vmax=3, interpolation="nearest")
        draw_layout(run.env.layout, ax, show_sensing=False)
        key, val = ("L", "h") if i == 0 else ("D", "e")
        if i < 2:
            for c in summary["counterexamples"][key]:
                ax.plot(c["pose"][0], c["pose"][1], "x", color="black" if c["counterexample"] else "grey", markersize=7)
        ax.set_title(titles[i], fontsize=9)
    fig.suptitle(f"{summary['run']}: green certified, orange not certified, red violated (worst over θ and "
                 "automaton state), white outside the set; x = worst found by the search (black: a counterexample)",
                 fontsize=8)
    FigureCanvasAgg(fig).print_png(str(path))
