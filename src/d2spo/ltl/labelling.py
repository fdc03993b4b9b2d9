"""Labelling of a trajectory: which letters the automaton reads (pure JAX).

Two modes:

* ``step``: the automaton reads one letter per time step, the set of areas the robot is in.
* ``event`` (default): the automaton reads a letter only when the set of areas changes and the new
  set is non-empty. Time spent inside one area, or travelling between areas, is not a sequence of
  letters. This is what makes "A1 and next A3" (the paper's phi2) mean "the area visited right
  after A1 is A3"; under ``step`` labelling the robot would have to jump from A1 to A3 in one
  time step.
"""

from __future__ import annotations

import jax.numpy as jnp

from d2spo.ltl.automaton import AutomatonArrays

LABEL_MODES = ("event", "step")


def next_state(
    aut: AutomatonArrays, q: jnp.ndarray, letter: jnp.ndarray, prev_letter: jnp.ndarray, event: bool
) -> jnp.ndarray:
    """Automaton state after observing ``letter`` (the previous step's letter is ``prev_letter``)."""
    moved = aut.delta[q, letter]
    if not event:
        return moved
    emitted = (letter != prev_letter) & (letter != 0)
    return jnp.where(emitted, moved, q)


def accepting_visit(
    aut: AutomatonArrays, q: jnp.ndarray, letter: jnp.ndarray, prev_letter: jnp.ndarray, event: bool
) -> jnp.ndarray | None:
    """Whether the step that ``next_state`` takes reads an accepting transition of a Büchi task
    (``AutomatonArrays.visit``); None for a monitor, which has none."""
    if aut.visit is None:
        return None
    visit = aut.visit[q, letter]
    if not event:
        return visit
    return visit & (letter != prev_letter) & (letter != 0)
