"""Checks of config fields: the one helper every config dataclass's ``__post_init__`` calls.

Each field is validated where it is defined (``TD3Config``, ``CBFConfig``, ``RewardConfig``,
``EnvConfig``, ``TrainConfig``, ...), by kind, so a bad value from a flag or from a config.json
ends in the same one-line ``ConfigError`` naming the field (``td3.gamma: must be in (0, 1], got
-1.0``), before anything is built or written.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
from typing import Any

from d2spo.errors import ConfigError, is_finite_number

MAX_LR = 1.0
"""Largest learning rate accepted. Every optimiser here is Adam (steps of about lr per update,
whatever the gradient) or the multiplier's SGD; a rate above 1 moves a weight of a tanh network by
more than its whole useful range in one step, so it is a typo rather than a setting (a CBF lr of
1e6 trained to 34 % safety with exit 0 before this bound)."""
MAX_SEED = 2**31 - 1
"""Largest seed. JAX keys take 32 bits (2**32 is the key of seed 0), and the final evaluation uses
seed + 10000, so seeds stay in the non-negative int32 range."""


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


KINDS: dict[str, tuple[Any, str]] = {
    "count": (lambda v: _is_int(v) and v >= 1, "a positive integer"),
    "natural": (lambda v: _is_int(v) and v >= 0, "an integer >= 0"),
    "seed": (lambda v: _is_int(v) and 0 <= v <= MAX_SEED, f"an integer in [0, {MAX_SEED}]"),
    "finite": (is_finite_number, "a finite number"),
    "positive": (lambda v: is_finite_number(v) and v > 0, "a finite number > 0"),
    "non_negative": (lambda v: is_finite_number(v) and v >= 0, "a finite number >= 0"),
    "at_least_one": (lambda v: is_finite_number(v) and v >= 1, "a finite number >= 1"),
    "discount": (lambda v: is_finite_number(v) and 0 < v <= 1, "in (0, 1]"),
    "rate": (lambda v: is_finite_number(v) and 0 < v <= 1, "in (0, 1]"),
    "fraction": (lambda v: is_finite_number(v) and 0 <= v <= 1, "in [0, 1]"),
    "lr": (lambda v: is_finite_number(v) and 0 < v <= MAX_LR, f"a learning rate in (0, {MAX_LR:g}]"),
    "widths": (lambda v: isinstance(v, tuple) and len(v) >= 1 and all(_is_int(w) and w >= 1 for w in v),
               "a non-empty list of positive layer widths"),
    "counts": (lambda v: isinstance(v, tuple) and all(_is_int(w) and w >= 1 for w in v),
               "a list of positive integers"),
    "flag": (lambda v: isinstance(v, bool), "true or false"),
}
"""Kind -> (predicate, what the value must be). ``discount`` (a gamma), ``rate`` (tau, a fraction
of a run) and ``fraction`` (GAE lambda) differ only in whether 0 is allowed."""
SEQUENCES = ("widths", "counts")
"""The kinds held as tuples; ``check_fields`` takes a list for one (``TrainConfig(snapshots=[50])``)."""


def check_fields(obj: Any, section: str = "", nullable: tuple[str, ...] = (), **kinds: tuple[str, ...]) -> None:
    """ConfigError on the first field of ``obj`` that is not of its kind.

    ``kinds`` maps a kind of ``KINDS`` to the field names of that kind; ``nullable`` names the
    fields that may also be None; ``section`` prefixes the field in the message (``td3.gamma``).
    """
    for kind, names in kinds.items():
        ok, what = KINDS[kind]
        for name in names:
            value = getattr(obj, name)
            if value is None and name in nullable:
                continue
            if kind in SEQUENCES and isinstance(value, list):  # from Python, as config.json and the flags give
                value = tuple(value)
                object.__setattr__(obj, name, value)  # the configs are frozen dataclasses
            if not ok(value):
                raise ConfigError(f"{section}.{name}" if section else name, f"must be {what}, got {value!r}")


def check_choice(obj: Any, name: str, choices, section: str = "") -> None:
    """ConfigError unless ``obj.<name>`` is one of ``choices``."""
    value = getattr(obj, name)
    if value not in tuple(choices):
        raise ConfigError(f"{section}.{name}" if section else name,
                          f"must be one of {list(choices)}, got {value!r}")


def field_docstring(cls: type, name: str) -> str:
    """The docstring under the field ``name`` of the dataclass ``cls`` in its source, as tyro reads
    it for --help (for a class that reuses another's fields, e.g. ``evaluate.DynamicsOverrides``)."""
    if name not in {f.name for f in dataclasses.fields(cls)}:
        raise KeyError(f"{cls.__name__} has no field {name!r}")
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    for node, after in zip(body, body[1:]):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.target.id == name
                and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)):
            return inspect.cleandoc(after.value.value)
    return ""
