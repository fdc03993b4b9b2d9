"""Ctrl-C in the `d2spo` command: the SIGINT handler and ``sys.unraisablehook`` that ``cli.main``
installs (``install``), so that an interrupt ends the command with one line and exit 130 even when
Python cannot raise it where it lands (an XLA garbage-collection callback, on a loaded machine).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

from d2spo.console import error

GRACE = 10.0
"""Seconds the `d2spo` command waits, after Ctrl-C, for its KeyboardInterrupt to end it (closing
what it holds, a Ray cluster say) before it leaves anyway (``interrupted``)."""


def interrupted(signum, frame) -> None:
    """The `d2spo` command's SIGINT handler: KeyboardInterrupt as usual, and a watchdog that exits
    130 with one line after ``GRACE`` seconds. The exception can land in a
    garbage-collection callback (XLA's), where Python prints it as "Exception ignored" and carries
    on compiling: seen on a loaded 2-core machine, where the command then ran on."""

    def leave() -> None:  # pragma: no cover - only when the KeyboardInterrupt was swallowed
        time.sleep(GRACE)
        error("interrupted")
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)

    threading.Thread(target=leave, name="d2spo-interrupt-watchdog", daemon=True).start()
    raise KeyboardInterrupt


def leave_if_swallowed(unraisable) -> None:
    """``sys.unraisablehook`` of the `d2spo` command: a KeyboardInterrupt that Python could not
    raise (it landed in a callback, XLA's garbage-collection one say, and would be printed as
    "Exception ignored") ends the command at once with the usual line and 130, instead of after
    the watchdog's ``GRACE`` seconds; anything else goes to Python's own hook."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        error("interrupted")
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    sys.__unraisablehook__(unraisable)


def install() -> None:
    """Make ``interrupted`` the SIGINT handler and ``leave_if_swallowed`` the unraisable hook (the
    `d2spo` command, from its main thread; a caller of ``cli.main(args)`` keeps its own)."""
    signal.signal(signal.SIGINT, interrupted)
    sys.unraisablehook = leave_if_swallowed
