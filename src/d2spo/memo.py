"""In-process reuse of what a config builds and what JAX compiles for it.

JAX reuses a traced and compiled program only for the same Python function object: a learner built
again, or the same learner wrapped in a new ``jax.jit``, is traced, lowered and compiled again (the
persistent compile cache, ``d2spo.compile_cache``, only skips XLA's part). Tracing D²SPO's chunk
takes seconds. So, within one process:

- ``built(key, make)``: ``run.build``'s (env, params, learner) per config (its seed aside: no
  learner reads it) and layout file content, the ``MAX_BUILDS`` most recent;
- ``per_object(owner, key, make)``: a value made once per live object and key, such as a learner's
  jitted ``chunk`` (``train.learner_program``) or an evaluation rollout (``rollout.make_rollout``).

A second training of a config in one process (``d2spo reproduce``'s seeds run one after another,
``d2spo eval`` after ``train`` in a notebook, the tests) then starts running at once. The objects
cached are stateless (a learner's methods are pure functions of their arguments), so a reused one
computes what a fresh one would. ``clear()`` forgets everything: a test that replaces a function a
build calls (``tests/_counting.py``) clears first, so it sees the build it asks for.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, Hashable
from typing import Any

MAX_BUILDS = 8
"""Builds kept (least recently used dropped first): a generalist's holds its field bank."""

_builds: collections.OrderedDict[Hashable, Any] = collections.OrderedDict()
_ATTR = "_d2spo_memo"
_generation = [0]  # clear() moves it on: tables of an older generation are stale
_lock = threading.RLock()


def built(key: Hashable, make: Callable[[], Any]) -> Any:
    """``make()``'s value the first time ``key`` is asked for; the same object after that."""
    with _lock:
        if key in _builds:
            _builds.move_to_end(key)
            return _builds[key]
    value = make()  # a ConfigError here is raised to the caller and nothing is kept
    with _lock:
        _builds[key] = value
        while len(_builds) > MAX_BUILDS:
            _builds.popitem(last=False)
    return value


def per_object(owner: object, key: Hashable, make: Callable[[], Any]) -> Any:
    """``make()``'s value, made once per (``owner``, ``key``) and kept in an attribute of ``owner``:
    it goes with ``owner`` (a jitted method refers back to its owner, a cycle the garbage collector
    frees; a weak-keyed table would keep such owners for ever). A shallow copy of ``owner``
    (``rollout.acting_on``) gets its own table, not the original's. An owner without a ``__dict__``
    gets a fresh value every time."""
    with _lock:
        table = getattr(owner, "__dict__", {}).get(_ATTR)
        if table is None or table[0] != (id(owner), _generation[0]):
            table = ((id(owner), _generation[0]), {})
            try:
                object.__setattr__(owner, _ATTR, table)
            except (AttributeError, TypeError):
                return make()
        values = table[1]
        if key not in values:
            values[key] = make()
        return values[key]


def clear() -> None:
    """Forget every build and per-object value (``jax.clear_caches`` forgets JAX's own)."""
    with _lock:
        _builds.clear()
        _generation[0] += 1
