"""Ctrl-C in the `d2spo` command: the SIGINT handler and ``sys.unraisablehook`` that ``cli.main``
installs (``install``), so that an interrupt ends the command with one line and exit 130 even when
Python cannot raise it where it lands (an XLA garbage-collection callback, on a loaded machine).
SIGTERM (`timeout`, a batch scheduler's stop, `docker stop`) ends it the same way, with the line
"terminated" and exit 143 (128 + 15, what the signal's default action gives), instead of silently.
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


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised as an interrupt is, so that the command closes what it holds the same way;
    ``cli.main`` says "terminated" and exits ``TERMINATED``."""


INTERRUPTED, TERMINATED = 130, 143
"""Exit statuses: 128 + the signal's number, as a shell reports a process the signal ended."""


def ending(exc: KeyboardInterrupt) -> tuple[str, int]:
    """The line and exit status of an interrupt (``Terminated`` or Ctrl-C's KeyboardInterrupt)."""
    return ("terminated", TERMINATED) if isinstance(exc, Terminated) else ("interrupted", INTERRUPTED)


def _leave(line: str, status: int) -> None:
    error(line)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def _raise(exc: KeyboardInterrupt) -> None:
    """Raise ``exc``, with a watchdog that exits with its line and status after ``GRACE`` seconds.
    The exception can land in a garbage-collection callback (XLA's), where Python prints it as
    "Exception ignored" and carries on compiling: seen on a loaded 2-core machine, where the
    command then ran on."""
    line, status = ending(exc)

    def leave() -> None:  # pragma: no cover - only when the exception was swallowed
        time.sleep(GRACE)
        _leave(line, status)

    threading.Thread(target=leave, name="d2spo-interrupt-watchdog", daemon=True).start()
    raise exc


def interrupted(signum, frame) -> None:
    """The `d2spo` command's SIGINT handler: KeyboardInterrupt as usual, and a watchdog (``_raise``)."""
    _raise(KeyboardInterrupt())


def terminated(signum, frame) -> None:
    """The `d2spo` command's SIGTERM handler: ``Terminated``, and a watchdog (``_raise``)."""
    _raise(Terminated())


def leave_if_swallowed(unraisable) -> None:
    """``sys.unraisablehook`` of the `d2spo` command: an interrupt that Python could not raise (it
    landed in a callback, XLA's garbage-collection one say, and would be printed as "Exception
    ignored") ends the command at once with its usual line and status, instead of after the
    watchdog's ``GRACE`` seconds; anything else goes to Python's own hook."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        _leave(*ending(unraisable.exc_value))
    sys.__unraisablehook__(unraisable)


def finished(status: int) -> None:
    """The command's work is done (its files written, its summary printed), and ``status`` is its
    exit status: from here on SIGINT and SIGTERM end the process at once with that status and no
    line, instead of raising an interrupt in interpreter teardown, which Python reports by dying of
    the signal (exit -2, silently: seen when a Ctrl-C landed just after a short training ended)."""

    def leave(signum, frame) -> None:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)

    signal.signal(signal.SIGINT, leave)
    signal.signal(signal.SIGTERM, leave)


def install() -> None:
    """Make ``interrupted`` the SIGINT handler, ``terminated`` the SIGTERM one and
    ``leave_if_swallowed`` the unraisable hook (the `d2spo` command, from its main thread; a caller
    of ``cli.main(args)`` keeps its own)."""
    signal.signal(signal.SIGINT, interrupted)
    signal.signal(signal.SIGTERM, terminated)
    sys.unraisablehook = leave_if_swallowed
