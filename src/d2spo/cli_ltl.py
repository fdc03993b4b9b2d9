"""``d2spo ltl FORMULA``: a formula or a named task translated to its automaton, printed as a table,
JSON or Graphviz dot, with its shaping distances over the letters a layout (or one area at a time)
can produce, and with ``--plot`` each automaton state's distance field drawn on a layout."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import tyro

from d2spo.envs import EnvConfig, layouts
from d2spo.envs.compiled_task import default_task
from d2spo.envs.preflight import (
    NOTHING_TO_REACH,
    check_feasible,
    check_lap,
    goal_hint,
    missing_labels,
    warn_if_endless_branch,
    warn_if_run_together,
)
from d2spo.errors import TaskWarning, UserError
from d2spo.fields import check_choice
from d2spo.ltl import task_automaton, task_formula
from d2spo.ltl.buchi_task import is_recurrence
from d2spo.ltl.labelling import LABEL_MODES
from d2spo.ltl.tasks import close_task_names
from d2spo.plotstyle import check_picture_path


def warn_if_task_name_typo(formula: str) -> None:
    """One warning line when ``formula`` is a single word that is no task name but close to one
    (``phi3``): it is read as a formula over one proposition of that name, which is rarely meant."""
    close = close_task_names(formula)
    if close:
        warnings.warn(f"{formula!r} is not a task name (did you mean {', '.join(close)}?); read as a formula: "
                      f"the proposition {formula}", TaskWarning, stacklevel=2)


@dataclasses.dataclass
class LtlCmd:
    """Translate an LTL formula, or a named task (the paper's phi1, phi1-printed, phi2, relaxed; the
    suite's tour3, patrol2, respond, ...: docs/ltl.md lists them all), to an automaton."""

    formula: tyro.conf.Positional[str]
    """The formula, e.g. '(!A2 U A1) & F A2', or a named task."""
    json: bool = False
    """Print exactly one JSON object (aps, initial, accepting, rejecting, delta, distance; a Büchi task
    also visits, per state the letters that are accepting visits, and recurrence)."""
    dot: bool = False
    """Print the automaton in Graphviz dot format."""
    layout: str | None = None
    """Distances over the letters this layout can produce (name or JSON file); default: one area at a time."""
    all_letters: bool = False
    """Distances over every letter, as if all areas could hold at once (e.g. {A1, A2, A3} in one step)."""
    label_mode: str = "event"
    """Labelling the distances assume: 'event' (no empty letter) or 'step'."""
    plot: Path | None = None
    """With --layout: draw per automaton state its shaping distance field (--shaping-metric
    geodesic-per-state) with its target and forbidden areas into this picture (.png at 300 dpi, .pdf or .svg),
    then check the task can be done (a recurrence: that its laps are more than a step out of an area and
    back), as train and env check do."""

    def run(self) -> int:
        if self.json and self.dot:
            raise UserError("--json and --dot are exclusive; choose one")
        if self.layout is not None and self.all_letters:
            raise UserError("--layout and --all-letters are exclusive; choose one")
        if self.plot is not None and self.layout is None:
            raise UserError("--plot needs --layout")
        check_choice(self, "label_mode", LABEL_MODES)  # before anything is printed
        if self.plot is not None:
            check_picture_path(self.plot, "plot")
        warn_if_task_name_typo(self.formula)
        aut = task_automaton(task_formula(self.formula))  # a Büchi task where no finite run completes it
        if aut.initial in aut.rejecting:  # the empty prefix is already bad: unsatisfiable
            warnings.warn(f"{self.formula!r} is unsatisfiable: no run satisfies it (its automaton starts in "
                          "its rejecting state), so no policy can be trained on it", TaskWarning, stacklevel=2)
        elif aut.initial in aut.accepting:  # `true`, `G !a`: done before the robot moves
            warnings.warn(f"{self.formula!r} {NOTHING_TO_REACH}: no run has anything to do, and `d2spo train` refuses "
                          f"it; add a goal, e.g. {goal_hint(self.formula, 'A1')}", TaskWarning, stacklevel=2)
        warn_if_endless_branch(aut, repr(self.formula))
        lay = None
        if self.all_letters:
            feasible, letters = None, "every letter (all areas may hold at once)"
        elif self.layout is not None:
            lay = layouts.load(self.layout)
            feasible = layouts.feasible_letters(lay, aut.aps, self.label_mode)
            letters = f"the letters layout {lay.name!r} can produce"
            if missing := missing_labels(aut.aps, lay):
                warnings.warn(f"layout {lay.name!r}: {missing}", TaskWarning, stacklevel=2)
        else:  # disjoint areas, as on every built-in layout: the robot is in at most one area
            feasible = [1 << i for i in range(len(aut.aps))] + ([0] if self.label_mode == "step" else [])
            letters = ("one area at a time (disjoint areas; --layout NAME for a layout's, "
                       "--all-letters for every letter)")
        warn_if_run_together(aut.aps, None if lay is None else lay.labels)  # `Fb`: no warning where an area is so labelled
        if self.json:
            print(json.dumps(aut.to_json(feasible)))
        elif self.dot:
            print(aut.to_dot())
        else:
            print(aut.pretty(feasible))
            goal = "the next accepting visit" if is_recurrence(aut) else "accept"
            print(f"distance: area visits (letters) still needed to {goal}, over {letters}")
        if self.plot is not None:
            from d2spo.map_plots import state_fields_figure  # matplotlib: imported only to draw

            task = default_task(aut, self.layout, self.label_mode)
            state_fields_figure(task, self.plot)
            print(f"wrote {self.plot}")
            check_feasible(task, repr(self.formula))  # after the picture, which shows why
            if task.recurrence:  # as training checks it: laps, not jitter at an area's edge
                check_lap(task, EnvConfig(layout=self.layout).resolved().robot_radius, repr(self.formula))
        return 0
