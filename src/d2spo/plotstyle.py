"""The look every d2spo figure shares, and the one way each is written to a file.

* colours: the Okabe–Ito palette (Okabe & Ito 2008, "Color Universal Design"), whose eight
  colours stay distinct under the common colour-vision deficiencies; no figure pairs red with green;
* fields: one perceptually uniform colour map (``FIELD_CMAP``) for a non-negative quantity, one
  diverging map (``SIGNED_CMAP``) for a signed one, and one colour scale per figure;
* files: ``save_figure`` writes PNG at ``DPI`` (300) or PDF/SVG (vector) by the path's suffix,
  with a tight bounding box so that no title or legend is cut. ``check_picture_path`` refuses any
  other suffix, and a missing folder, as a one-line ``ConfigError`` before the work that draws.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from d2spo.errors import ConfigError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

BLACK = "#000000"
ORANGE = "#E69F00"
SKY_BLUE = "#56B4E9"
BLUISH_GREEN = "#009E73"
YELLOW = "#F0E442"
BLUE = "#0072B2"
VERMILLION = "#D55E00"
REDDISH_PURPLE = "#CC79A7"
GREY = "#999999"
PALETTE = (SKY_BLUE, ORANGE, BLUISH_GREEN, REDDISH_PURPLE, BLUE, VERMILLION, YELLOW, BLACK)
"""The Okabe–Ito colours in the order categorical marks (lines, labels) take them."""

FIELD_CMAP = "viridis"
"""Colour map of a non-negative field (a distance, a cost): perceptually uniform, readable in grey."""
SIGNED_CMAP = "PuOr"
"""Colour map of a signed field (the CBF h), centred on 0: orange below, purple above; colour-blind safe."""

DPI = 300
"""Resolution of every PNG (PDF and SVG are vector)."""
FORMATS = ("png", "pdf", "svg")
"""Picture formats, by the file name's suffix."""


def check_picture_path(path: Path, field: str) -> None:
    """ConfigError naming ``field`` unless ``path`` ends in a ``FORMATS`` suffix and its folder
    exists. Checked before the work that draws it."""
    path = Path(path)
    if path.suffix[1:].lower() not in FORMATS:
        raise ConfigError(field, f"{path}: not a picture format; end the name in one of "
                          f"{', '.join('.' + f for f in FORMATS)}")
    if not path.parent.is_dir():
        raise ConfigError(field, f"{path}: the folder {path.parent} does not exist")


def save_figure(fig: Figure, path: str | Path, field: str = "path") -> Path:
    """Write ``fig`` to ``path`` in the format its suffix names (``check_picture_path``), PNG at
    ``DPI``, cropped to what is drawn (``bbox_inches="tight"``); returns the path."""
    path = Path(path)
    check_picture_path(path, field)
    fig.savefig(str(path), format=path.suffix[1:].lower(), dpi=DPI, bbox_inches="tight", pad_inches=0.05)
    return path
