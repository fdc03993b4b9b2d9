"""JSON files a user names or a run directory holds (a layout, a dynamics file, config.json,
reproduce.json): read only when they are regular files of sane size, so that ``/dev/zero``, a FIFO
or a directory given as one is one line, not a hang or a memory blow-up; and their SHA-256, which a
run records to notice a layout file edited under it (``d2spo.run``)."""

from __future__ import annotations

import hashlib
import os
import stat
from collections.abc import Callable
from pathlib import Path

MAX_JSON_BYTES = 16 * 2**20
"""Largest JSON input read. Layouts, dynamics files and run files are a few kB."""

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _kind(mode: int) -> str:
    return next((what for test, what in _KINDS if test(mode)), "not a plain file")


def read_regular(path: str | Path, fail: Callable[[str], Exception], limit: int = MAX_JSON_BYTES) -> bytes:
    """The bytes of the regular file ``path``; anything else raises ``fail(message)``, a one-line
    message naming the file: missing or unreadable, not a regular file (checked before it is opened
    for reading, which blocks on a FIFO), or larger than ``limit`` bytes."""
    path = Path(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise fail(f"{path}: not a regular file ({_kind(st.st_mode)})")
        if st.st_size > limit:
            raise fail(f"{path}: {st.st_size} bytes, more than the {limit // 2**20} MiB a JSON input may hold")
        # O_NONBLOCK: should a FIFO have taken its place since, opening it does not wait for a writer
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise fail(f"{path}: not a regular file ({_kind(os.fstat(fd).st_mode)})")
            data = f.read(limit + 1)
    except OSError as e:
        raise fail(f"cannot read {path}: {e.strerror or e}") from None
    if len(data) > limit:
        raise fail(f"{path}: more than the {limit // 2**20} MiB a JSON input may hold")
    return data


def sha256_of(path: str | Path, fail: Callable[[str], Exception]) -> str:
    """SHA-256 (hex) of the regular file ``path`` (``read_regular``)."""
    return hashlib.sha256(read_regular(path, fail)).hexdigest()
