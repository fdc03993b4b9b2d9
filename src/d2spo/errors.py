"""Errors a user can cause. The CLI reports each as one line on stderr with exit status 2."""

from __future__ import annotations

import math


class UserError(Exception):
    """Base class for mistakes in user input: a formula, a layout, a flag, a run directory."""


class ConfigError(UserError, ValueError):
    """A configuration value is invalid. The message names the offending field."""

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(f"{field}: {message}")


def is_finite_number(value) -> bool:
    """Whether ``value`` is a JSON number (an int or a float, not a bool) that is finite as a float.
    An int beyond float's range (``1e400`` written as digits) is not: ``math.isfinite`` would raise
    OverflowError on it instead of answering."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def in_file(e: ConfigError, path) -> ConfigError:
    """``e`` with the file it is about named at its end, "(in PATH)" (a layout's, a dynamics file's)."""
    return ConfigError(e.field, f"{str(e).removeprefix(f'{e.field}: ')} (in {path})")


class LTLSyntaxError(UserError, ValueError):
    """A formula does not parse. `column` is 1-based; str() shows the formula with a caret."""

    def __init__(self, formula: str, column: int, expected: str):
        self.formula = formula
        self.column = column
        self.expected = expected
        super().__init__(f"LTL syntax error at column {column}: expected {expected}")

    def pretty(self) -> str:
        return f"{self}\n  {self.formula}\n  {' ' * (self.column - 1)}^"


class RunDirError(UserError):
    """A run directory is missing, incomplete or incompatible."""


class RunInUseError(RunDirError):
    """A run directory is locked by a training in another process (``runio.RunLock``)."""


class ArtefactError(UserError):
    """An exported policy directory (``d2spo export``) is missing, damaged or of another format."""


class NaNError(RuntimeError):
    """Training produced a non-finite value. Raised instead of training through it."""


class D2SPOWarning(UserWarning):
    """Something the user should know but that does not stop the command; the CLI shows each as one
    ``d2spo: warning:`` line on stderr."""


class TaskWarning(D2SPOWarning):
    """The task can be done on the layout, but its shortest route uses most of the episode's steps."""


class RunDirWarning(D2SPOWarning):
    """Something in a run directory was repaired or skipped (e.g. a damaged checkpoint replaced by
    the previous one). The CLI shows it as one line on stderr."""


def json_trouble(e: Exception) -> str:
    """Why ``json.loads`` gave up on a text, in a few words: nested too deeply (RecursionError), not
    UTF-8 text, or its own message (a number too long to read)."""
    if isinstance(e, RecursionError):
        return "nested too deeply"
    return "not UTF-8 text" if isinstance(e, UnicodeDecodeError) else str(e).split(";")[0]
