"""How the figures draw an episode's path and name its outcome (``d2spo.plots`` uses these in
every trajectory figure): completed, collided, out of time, or rejected by the task."""

from __future__ import annotations

import numpy as np
from matplotlib.lines import Line2D

from d2spo.envs.render import draw_trajectory
from d2spo.plotstyle import BLUISH_GREEN, ORANGE, REDDISH_PURPLE, VERMILLION
from d2spo.runio import rejected

OUTCOME_COLORS = {"completed": BLUISH_GREEN, "collided": VERMILLION, "neither": REDDISH_PURPLE, "rejected": ORANGE}
"""Trajectory colours: the task completed (true labelling), a collision, the episode ran out, or it
ended before its step limit with none of these (the task rejected it: a 'never' part broken, an
area entered out of order)."""
OUTCOME_NAMES = {"completed": "task completed", "collided": "collision", "neither": "out of time",
                 "rejected": "the task rejected it (what it forbids entered)"}
"""How the legends name each outcome of ``OUTCOME_COLORS``."""


def outcomes(poses, collided, completed) -> list[str]:
    """Each episode's outcome (a key of ``OUTCOME_COLORS``) from its poses [E, T+1, 3] (NaN after its
    end): an episode that ended before the last step, neither collided nor completed, was rejected."""
    poses = np.asarray(poses)
    length = np.isfinite(poses[:, :, 0]).sum(axis=1) - 1  # the start pose, then one per step taken
    refused = rejected(collided, completed, length, poses.shape[1] - 1)
    return ["collided" if c else "completed" if d else "rejected" if e else "neither"
            for c, d, e in zip(collided, completed, refused)]


def draw_trajectories(ax, poses, collided, completed) -> set[str]:
    """Each episode's path (poses [E, T+1, 3], NaN after its end) coloured by its outcome; returns the
    outcomes drawn."""
    drawn = outcomes(poses, collided, completed)
    for i, outcome in enumerate(drawn):
        xy = poses[i, :, :2]
        xy = xy[np.all(np.isfinite(xy), axis=-1)]
        draw_trajectory(ax, xy, color=OUTCOME_COLORS[outcome])
    return set(drawn)


RECURRENCE_OUTCOME_NAMES = {**OUTCOME_NAMES, "neither": "ran to the step limit, as a patrol does"}
"""``OUTCOME_NAMES`` for a recurrence (a patrol), which no episode completes: its safe episodes end
at the step limit, and its score is the accepting visits of the panel titles."""


def outcome_handles(recurrence: bool = False, drawn: set[str] = frozenset()) -> list[Line2D]:
    """Legend entries of ``draw_trajectories``' colours (``recurrence``: a patrol's names); a rejected
    trajectory's only where one is ``drawn``."""
    names = RECURRENCE_OUTCOME_NAMES if recurrence else OUTCOME_NAMES
    return [Line2D([], [], color=c, marker="x", markevery=[1], label=f"trajectory: {names[k]} (x: end)")
            for k, c in OUTCOME_COLORS.items()
            if not (recurrence and k == "completed") and (k != "rejected" or k in drawn)]
