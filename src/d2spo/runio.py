"""Run directories: config.json, episodes.csv, checkpoints (atomic), summary.json.

Layout of a run directory::

    DIR/config.json        the one resolved config of the run
    DIR/episodes.csv       one row per finished training episode
    DIR/checkpoint.msgpack training state (flax msgpack), replaced atomically
    DIR/checkpoint.json    host-side counters that go with it
    DIR/summary.json       written when the run ends
    DIR/tb/                TensorBoard scalars
"""

from __future__ import annotations

import csv
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from flax import serialization

from d2spo.errors import RunDirError

EPISODE_FIELDS = ("episode", "return", "cost", "collided", "completed", "completed_relaxed", "length", "end_x", "end_y")


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a reader sees the old file or the new one, never half."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True) + "\n").encode())


def read_json(path: Path, what: str) -> dict:
    path = Path(path)
    if not path.is_file():
        raise RunDirError(f"{path.parent}: no {path.name} ({what}); is this a d2spo run directory?")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise RunDirError(f"{path}: not valid JSON ({e.msg} at line {e.lineno})") from None


class EpisodeWriter:
    """Appends finished episodes to episodes.csv and keeps them in memory for the summary."""

    def __init__(self, path: Path, keep_rows: int = 0):
        self.path = Path(path)
        self.rows: list[tuple] = read_episodes(self.path)[:keep_rows] if keep_rows > 0 else []
        self._rewrite()

    def _rewrite(self) -> None:
        tmp = self.path.with_suffix(".csv.tmp")
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(EPISODE_FIELDS)
            w.writerows(self.rows)
        os.replace(tmp, self.path)

    def append(self, rows: list[tuple]) -> None:
        if not rows:
            return
        self.rows.extend(rows)
        with open(self.path, "a", newline="") as f:
            csv.writer(f).writerows(rows)

    def __len__(self) -> int:
        return len(self.rows)


def read_episodes(path: Path) -> list[tuple]:
    path = Path(path)
    if not path.is_file():
        raise RunDirError(f"{path.parent}: no episodes.csv")
    out = []
    with open(path, newline="") as f:
        r = csv.reader(f)
        header = next(r, None)
        if header is None or tuple(header) != EPISODE_FIELDS:
            raise RunDirError(f"{path}: unexpected header {header}")
        for row in r:
            out.append(
                (int(row[0]), float(row[1]), float(row[2]), int(row[3]), int(row[4]), int(row[5]), int(row[6]),
                 float(row[7]), float(row[8]))
            )
    return out


def window_rates(rows: list[tuple], window: int) -> dict[str, float]:
    """Safety and completion rates over the last ``window`` episodes (the paper's metric)."""
    if not rows:
        nan = float("nan")
        return {"safety_rate": nan, "completion_rate": nan, "completion_rate_relaxed": nan, "mean_return": nan,
                "window_episodes": 0}
    a = np.asarray(rows[-window:], dtype=np.float64)
    return {
        "safety_rate": float(1.0 - a[:, 3].mean()),
        "completion_rate": float(a[:, 4].mean()),
        "completion_rate_relaxed": float(a[:, 5].mean()),
        "mean_return": float(a[:, 1].mean()),
        "window_episodes": len(a),
    }


def save_checkpoint(run_dir: Path, carry: Any, meta: dict) -> None:
    """State first, then the counters that refer to it: a crash between the two is detected."""
    run_dir = Path(run_dir)
    atomic_write_bytes(run_dir / "checkpoint.msgpack", serialization.to_bytes(carry))
    atomic_write_json(run_dir / "checkpoint.json", meta)


def load_checkpoint(run_dir: Path, template: Any) -> tuple[Any, dict]:
    run_dir = Path(run_dir)
    meta = read_json(run_dir / "checkpoint.json", "checkpoint counters")
    blob = run_dir / "checkpoint.msgpack"
    if not blob.is_file():
        raise RunDirError(f"{run_dir}: checkpoint.json without checkpoint.msgpack")
    try:
        carry = serialization.from_bytes(template, blob.read_bytes())
    except Exception as e:  # a corrupt or foreign file
        raise RunDirError(f"{blob}: cannot restore training state ({type(e).__name__})") from None
    return carry, meta
