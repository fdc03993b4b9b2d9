"""Run directories: config.json, episodes.csv, the lock, atomic writes, summary.json.

Layout of a run directory (docs/runs.md)::

    DIR/config.json        the one resolved config of the run
    DIR/episodes.csv       one row per finished training episode
    DIR/checkpoint*.json   checkpoint manifests, DIR/checkpoint-G.msgpack their state (d2spo.checkpoint)
    DIR/summary.json       written when the run ends
    DIR/tb/                TensorBoard scalars
    DIR/.lock              held (flock) by the training that writes DIR

Every file is replaced atomically (a temporary ``.NAME.*.tmp`` beside it, fsync, rename), created
with the permissions the umask allows; temporary files a kill left behind are removed when a
training next takes the directory.
"""

from __future__ import annotations

import csv
import errno
import io
import json
import os
import re
import secrets
import socket
import stat
import time
from collections.abc import Iterable
from contextlib import suppress
from pathlib import Path
from typing import Any

import numpy as np

from d2spo.errors import RunDirError, RunInUseError, json_trouble
from d2spo.inputs import read_regular

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Windows
    fcntl = None

EPISODE_FIELDS = ("episode", "return", "cost", "collided", "completed", "completed_relaxed", "length", "end_x", "end_y")
VISITS_FIELD = "accepting_visits"
"""The column after ``EPISODE_FIELDS`` in a Büchi task's episodes.csv (one with accepting visits, a
patrol): the episode's accepting visits. A task without them (every co-safe task) has no such column."""
_INT_COLUMNS = (0, 3, 4, 5, 6, 9)


def _named(e: OSError, path: Path) -> OSError:
    """``e`` with the file it concerns, for a one-line report (write() and fsync() name none)."""
    if e.filename is None and e.errno is not None:
        return type(e)(e.errno, e.strerror, str(path))
    return e


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a reader sees the old file or the new one, never half."""
    atomic_write_parts(path, (data,))


def atomic_write_parts(path: Path, parts: Iterable[bytes | memoryview]) -> None:
    """``atomic_write_bytes`` of the concatenation of ``parts``, written as they come (a checkpoint's
    arrays are written from their own memory, never joined into one copy)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")  # as temporary_of reads it
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies
        with os.fdopen(fd, "wb") as f:
            for part in parts:
                f.write(part)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        with suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise _named(e, path) from None
        raise
    _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
    """Make a rename in ``path`` durable (best effort: some file systems refuse it)."""
    with suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True) + "\n").encode())


def temporary_of(name: str) -> str | None:
    """The file name a temporary of ``atomic_write_bytes`` (``.NAME.PID-HEX.tmp``) stands for; None
    for any other name."""
    m = re.fullmatch(r"\.(.+)\.\d+-[0-9a-f]{8}\.tmp", name)
    return m.group(1) if m else None


def remove_file(path: Path) -> None:
    with suppress(FileNotFoundError):
        os.unlink(path)


def remove_tmp_files(directory: Path) -> None:
    """Temporary files of writes a kill interrupted (this and earlier versions' names)."""
    for p in Path(directory).iterdir():
        if (p.name.startswith(".") and p.name.endswith(".tmp")) or p.name == "episodes.csv.tmp":
            remove_file(p)


def read_json(path: Path, what: str) -> dict:
    path = Path(path)
    if not path.exists():
        if (path.parent / "manifest.json").is_file():  # what `d2spo export` writes (d2spo.deploy.manifest.MANIFEST)
            raise RunDirError(f"{path.parent}: is an exported policy (`d2spo export`), not a run directory; give "
                              "the run it was exported from, or load it with d2spo.deploy.Policy.load")
        raise RunDirError(f"{path.parent}: no {path.name} ({what}); is this a d2spo run directory?"
                          + _runs_hint(path.parent, path.name))
    data = read_regular(path, RunDirError)  # not /dev/zero, a FIFO or a directory in its place
    try:
        value = json.loads(data)
    except json.JSONDecodeError as e:
        raise RunDirError(f"{path}: not valid JSON ({e.msg}: line {e.lineno}, column {e.colno})") from None
    except (RecursionError, ValueError) as e:  # nested too deeply, not UTF-8, a number too long to read
        raise RunDirError(f"{path}: not valid JSON ({json_trouble(e)})") from None
    if not isinstance(value, dict):  # every file of a run holds one object
        kind = {list: "array", str: "string", bool: "boolean", type(None): "null"}.get(type(value), "number")
        raise RunDirError(f"{path}: holds a JSON {kind} where {what} is an object")
    return value


def _runs_hint(directory: Path, name: str) -> str:
    """For a folder that holds runs rather than being one (`make demo`'s demo_out, `d2spo reproduce`'s
    OUT): the runs to give instead, as a clause to end the error with; '' when it holds none."""
    try:
        found = sorted(d for base in (directory, directory / "runs") if base.is_dir()
                       for d in base.iterdir() if d.is_dir() and (d / name).is_file())
    except OSError:
        return ""
    if not found:
        return ""
    shown = ", ".join(str(d) for d in found[:3]) + (f" and {len(found) - 3} more" if len(found) > 3 else "")
    return f" It holds {'a run' if len(found) == 1 else 'runs'}: give {'it' if len(found) == 1 else 'one'} instead ({shown})"


def make_run_dir(path: Path) -> None:
    """Create a run directory (and its parents); a file in the way is a RunDirError."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise RunDirError(f"{path}: exists and is not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise RunDirError(f"{path}: cannot be created, a file is in the way") from None


class RunLock:
    """Exclusive use of a run directory by one training: ``DIR/.lock``, held with ``flock`` (the
    kernel drops it when its process dies, so a lock left by a killed training is taken over)
    and naming its holder. Creates the directory."""

    def __init__(self, run_dir: Path):
        self.dir = Path(run_dir)
        self.path = self.dir / ".lock"
        self._fd: int | None = None

    def __enter__(self) -> RunLock:
        make_run_dir(self.dir)
        if fcntl is None:  # pragma: no cover
            return self
        for _ in range(5):
            fd = _open_lock(self.path, os.O_RDWR | os.O_CREAT)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _holder_line(fd)
                os.close(fd)
                raise RunInUseError(f"{self.dir}: in use by another training ({holder}); wait for it to end or "
                                    "stop it, or use another directory") from None
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:  # not a file its last holder unlinked while we waited
                os.ftruncate(fd, 0)
                os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}, since "
                             f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode())
                self._fd = fd
                return self
            os.close(fd)
        raise RunDirError(f"{self.dir}: cannot take its lock {self.path}")

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            remove_file(self.path)
            os.close(self._fd)
            self._fd = None


_NO_FOLLOW = getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)


def _open_lock(path: Path, flags: int) -> int:
    """A descriptor of the lock file ``path``, which must be a plain file: a symbolic link planted
    there is not followed (its target, perhaps outside the directory, would be truncated and
    written), nor is a FIFO, device or directory opened as one (RunDirError)."""
    try:
        fd = os.open(path, flags | _NO_FOLLOW, 0o666)
    except OSError as e:
        if e.errno not in (errno.ELOOP, errno.EISDIR, errno.ENXIO, errno.EWOULDBLOCK):
            raise _named(e, path) from None
        fd = None
    if fd is None or not stat.S_ISREG(os.fstat(fd).st_mode):
        if fd is not None:
            os.close(fd)
        what = "a symbolic link" if path.is_symlink() else "not a plain file"
        raise RunDirError(f"{path}: {what}; a run's lock is a plain file d2spo creates: remove it, or use another "
                          "directory")
    return fd


def _holder_line(fd: int) -> str:
    """The line a ``RunLock`` holder wrote into its lock file."""
    return os.read(fd, 200).decode(errors="replace").strip() or "unknown holder"


def run_holder(run_dir: Path) -> str | None:
    """Who holds ``RunLock(run_dir)`` now (its line, e.g. ``pid 12 on host, since …``), or None when
    no training holds it. Probes without creating anything, for callers that are about to change
    the directory and must not pull it from under a live training."""
    path = Path(run_dir) / ".lock"
    if fcntl is None:  # pragma: no cover (no flock)
        return None
    try:
        fd = _open_lock(path, os.O_RDONLY)
    except FileNotFoundError:  # never locked, or removed by its holder as it finished
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _holder_line(fd)
    finally:
        os.close(fd)
    return None


class EpisodeWriter:
    """Appends finished episodes to episodes.csv and keeps them in memory for the summary.

    ``keep_rows`` > 0 resumes: the file must hold at least that many valid rows (the episodes
    before the checkpoint); they are kept byte for byte and whatever follows them is dropped.
    ``visits``: the rows end with the episode's accepting visits (``VISITS_FIELD``; a patrol); a
    resumed file keeps the columns it has."""

    def __init__(self, path: Path, keep_rows: int = 0, visits: bool = False):
        self.path, self.visits = Path(path), visits
        fields = EPISODE_FIELDS + ((VISITS_FIELD,) if visits else ())
        if keep_rows > 0:
            header, lines, self.rows = _read_rows(self.path, keep_rows)
            # the file's columns go on: a patrol trained before the column existed resumes without it
            self.visits = header.rstrip(b"\r\n").endswith(b"," + VISITS_FIELD.encode())
            if len(self.rows) < keep_rows:
                raise RunDirError(f"{self.path}: holds {len(self.rows)} episodes but the checkpoint was taken "
                                  f"after {keep_rows}; it was truncated or edited, so the run cannot resume")
            data = header + b"".join(lines)
        else:
            self.rows = []
            data = _csv_bytes([fields])
        atomic_write_bytes(self.path, data)

    def append(self, rows: list[tuple]) -> None:
        if not rows:
            return
        data = _csv_bytes(rows)
        with open(self.path, "ab") as f:
            start = f.tell()
            try:
                f.write(data)
                f.flush()
            except OSError as e:  # e.g. a full disk: leave no half row behind
                with suppress(OSError):
                    f.truncate(start)
                raise _named(e, self.path) from None
        self.rows.extend(rows)

    def sync(self) -> None:
        """Make the rows written so far durable (before a checkpoint that counts them)."""
        fd = os.open(self.path, os.O_RDONLY)
        try:
            os.fsync(fd)
        except OSError as e:
            raise _named(e, self.path) from None
        finally:
            os.close(fd)

    def __len__(self) -> int:
        return len(self.rows)


def _csv_bytes(rows) -> bytes:
    buf = io.StringIO()
    csv.writer(buf).writerows(rows)
    return buf.getvalue().encode()


def read_episodes(path: Path) -> list[tuple]:
    """Every row of an episodes.csv; a damaged row is a RunDirError naming its line."""
    return _read_rows(Path(path), None)[2]


def _read_rows(path: Path, limit: int | None) -> tuple[bytes, list[bytes], list[tuple]]:
    """(header line, the first ``limit`` row lines, their parsed rows); lines after them are not read.
    The header is ``EPISODE_FIELDS``, or those and ``VISITS_FIELD`` (a patrol's file)."""
    if not path.is_file():
        raise RunDirError(f"{path.parent}: no episodes.csv")
    lines = path.read_bytes().splitlines(keepends=True)
    headers = {",".join(EPISODE_FIELDS + extra).encode(): len(EPISODE_FIELDS + extra) for extra in ((), (VISITS_FIELD,))}
    width = headers.get(lines[0].rstrip(b"\r\n")) if lines else None
    if width is None:
        head = lines[0][:80].decode(errors="replace").strip() if lines else ""
        raise RunDirError(f"{path}: not an episodes.csv (header {head!r})")
    body = lines[1:] if limit is None else lines[1:1 + limit]
    rows = [_parse_row(path, i, line, width) for i, line in enumerate(body)]
    return lines[0], body, rows


def _parse_row(path: Path, i: int, line: bytes, width: int) -> tuple:
    where = f"{path}, line {i + 2}"
    if not line.endswith(b"\n"):
        raise RunDirError(f"{where}: the row is cut short (the file is damaged)")
    try:
        fields = line.decode("ascii").rstrip("\r\n").split(",")
        if len(fields) != width:
            raise ValueError
        row = tuple(int(v) if j in _INT_COLUMNS else float(v) for j, v in enumerate(fields))
    except ValueError:
        raise RunDirError(f"{where}: not a valid row (the file is damaged)") from None
    if row[0] != i:
        raise RunDirError(f"{where}: episode {row[0]} where {i} was expected (the file is damaged)")
    return row


def rejected(collided, completed, length, max_steps: int) -> np.ndarray:
    """bool [E]: the episodes the task rejected (a 'never' part broken, an area entered out of
    order): ended before ``max_steps``, neither collided nor completed. One rejected at the very
    last step is taken for out of time."""
    return (np.asarray(length) < max_steps) & ~np.asarray(collided, bool) & ~np.asarray(completed, bool)


def window_rates(rows: list[tuple], window: int, max_steps: int | None = None) -> dict[str, float]:
    """Safety and completion rates over the last ``window`` episodes (the paper's metric); with
    ``max_steps``, the share the task rejected too (``rejection_rate``: ended before the limit,
    neither collided nor completed under the labelling that ended it, the relaxed one in training;
    ``rejected`` with that column)."""
    if not rows:
        nan = float("nan")
        return {"safety_rate": nan, "completion_rate": nan, "completion_rate_relaxed": nan, "mean_return": nan,
                "window_episodes": 0, **({"rejection_rate": nan} if max_steps is not None else {})}
    a = np.asarray(rows[-window:], dtype=np.float64)
    out = {
        "safety_rate": float(1.0 - a[:, 3].mean()),
        "completion_rate": float(a[:, 4].mean()),
        "completion_rate_relaxed": float(a[:, 5].mean()),
        "mean_return": float(a[:, 1].mean()),
        "window_episodes": len(a),
    }
    if max_steps is not None:
        out["rejection_rate"] = float(rejected(a[:, 3] > 0, a[:, 5] > 0, a[:, 6], max_steps).mean())
    return out
