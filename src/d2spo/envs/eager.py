"""Environment methods that, called on concrete arrays, run as one compiled program
(``compiled_when_eager``): the env's ``reset``/``step`` family (``envs/nav.py``) and the generalist's
(``envs/generalist.py``)."""

from __future__ import annotations

import functools

import jax


def compiled_when_eager(static_argnums: tuple[int, ...] = ()):
    """A method of an environment that, called on concrete arrays (outside ``jax.jit``, ``vmap`` or
    ``scan``), runs as one compiled program, kept with the environment for its next calls, rather
    than operation by operation: a Python loop over ``env.step`` compiles once instead of once per
    operation and shape (tests/test_env_nav.py and friends: about twice as fast to their first
    result). Traced calls, as in training, run the method itself, so the programs training compiles
    are unchanged. ``static_argnums`` counts the arguments after ``self`` (``reset_batch``'s ``n``)."""

    def wrap(method):
        @functools.wraps(method)
        def call(self, *args, **kwargs):
            if kwargs or not _concrete(args, static_argnums):
                return method(self, *args, **kwargs)
            programs = self.__dict__.setdefault("_eager_programs", {})
            program = programs.get(method)
            if program is None:
                program = programs[method] = jax.jit(functools.partial(method, self), static_argnums=static_argnums)
            return program(*args)

        return call

    return wrap


def _concrete(args: tuple, static_argnums: tuple[int, ...]) -> bool:
    """Whether a call's arguments are all concrete: no tracer among them, and no list or tuple where
    an array goes (an action given as a list: the method itself refuses it, with its own error)."""
    for i, a in enumerate(args):
        if i in static_argnums:
            continue
        if isinstance(a, (list, tuple)) or any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(a)):
            return False
    return True
