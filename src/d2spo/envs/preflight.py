"""The checks before a run, on a compiled task (``envs.compiled_task``): can the robot complete the
task on the layout (``check_feasible``, an error), within an episode (``check_time``, a warning),
and while keeping a learned barrier's margin (``check_margin``, a warning)? ``preflight`` runs them
on an env; training and evaluation call it. ``default_max_steps`` is the step limit that follows
the task's shortest route.
"""

from __future__ import annotations

import difflib
import math
import re
import warnings

import numpy as np

from d2spo.envs import routes
from d2spo.envs.compiled_task import CompiledTask
from d2spo.envs.layouts import letters_at
from d2spo.envs.state_fields import FORBIDDEN, TARGET, named_areas
from d2spo.errors import ConfigError, TaskWarning
from d2spo.ltl.automaton import UNREACHABLE
from d2spo.ltl.buchi_task import endless_branch
from d2spo.ltl.formula import Always, And, Eventually, Implies, Not, Or, Prop
from d2spo.ltl.parser import parse, run_together
from d2spo.ltl.tasks import close_task_names

TIGHT_FRACTION = 0.6
"""``check_time`` warns when the shortest route needs more than this fraction of the episode's steps
at full speed. A trained policy drives more than the shortest route: on `paper` D²SPO's phi1
episodes take a median of 123 steps for a 10.1 m route (1.22x)."""
ROOM = 2.0
"""``default_max_steps`` gives a longer task this many times its shortest route at full speed."""
RECURRENCE_VISITS = 3
"""``default_max_steps`` gives a recurrence room for this many accepting visits: the first and two
laps of its cycle (so that its visits per episode measure the patrol, not only the way to it)."""

NOTHING_TO_REACH = ("asks for nothing to reach: its automaton accepts before the robot moves (a formula already "
                    "true, or a 'never' part alone)")
"""What ``check_letters`` refuses (and ``d2spo ltl`` notes) in a task whose initial state accepts."""


def goal_hint(formula: str, goal: str) -> str:
    """The goal ``check_letters`` and ``d2spo ltl`` suggest for a task with nothing to reach: ``F goal``,
    and with the formula's own never parts kept where it is only those (``G !haz`` -> ``G !haz & F
    dock``; a user trial read the former ``G !x & F dock`` as a made-up x)."""
    if re.fullmatch(r"[\sG!&()\w-]+", formula) and re.search(r"G\s*\(?\s*!", formula):
        return f"'{formula} & F {goal}'"
    return f"'F {goal}' (with a never part: 'G !x & F {goal}')"


def check_letters(task: CompiledTask, what: str) -> None:
    """ConfigError unless a sequence of the letters the layout can produce completes the task, and
    unless the task needs one (``true``, ``A1 | !A1``: done before the first step); ``what`` names the
    task in the message. What ``make_env`` checks for every task."""
    arrays = task.arrays
    if bool(arrays.accepting[int(arrays.initial)]):
        others = [label for label in task.layout.labels if label not in task.automaton.aps]
        goal = (others or list(task.layout.labels) or ["A1"])[0]  # an area the formula does not name, if any
        missing = missing_labels(task.automaton.aps, task.layout)  # `G !a4`: meant to name an area, names none
        hint = f" (layout {task.layout.name!r}: {missing})" if missing else ""
        text = what[1:-1] if len(what) > 1 and what[0] == what[-1] == "'" else what  # the formula, repr() or not
        raise ConfigError("task", f"{what} {NOTHING_TO_REACH}, so there is nothing to learn; add a goal, e.g. "
                          f"{goal_hint(text, goal)}{hint}")
    if int(arrays.distance[int(arrays.initial)]) >= UNREACHABLE:
        aut = task.automaton
        if aut.initial in getattr(aut, "rejecting", ()):  # no layout is to blame: no run satisfies it
            raise ConfigError("task", f"{what} is unsatisfiable: no run satisfies it, on any layout (its automaton "
                              "starts in its rejecting state; `d2spo ltl` shows it)")
        layout = task.layout
        missing = sorted(set(task.automaton.aps) - set(layout.labels))
        hint = ""
        if missing:
            hint = f" ({missing_labels(task.automaton.aps, layout)})"
        done = "make one accepting visit" if task.recurrence else "be completed"  # a patrol never completes
        close = close_task_names(what)  # `--task patrol22`: a misspelt name, read as a proposition
        if close:  # the likelier mistake first
            raise ConfigError("task", f"{what} is not a task name (did you mean {', '.join(close)}?); read as a "
                              f"formula, the proposition {what}, it cannot {done} in layout {layout.name!r}{hint}")
        raise ConfigError("task", f"{what} cannot {done} in layout {layout.name!r}{hint}: no sequence of the "
                          "letters it can produce (areas entered alone, or together where they overlap) does it")


def missing_labels(aps, layout) -> str:
    """Words on the propositions of ``aps`` that label no area of ``layout`` (empty when none): with the
    labels there are, and the one each was likely meant to be (`Dock`: dock)."""
    missing = sorted(set(aps) - set(layout.labels))
    if not missing:
        return ""
    meant = [f"{label} for {p}" for p in missing if (label := _label_meant(p, layout))]
    guess = f"; did you mean {', '.join(meant)}?" if meant else ""
    return f"propositions with no area, always false: {missing}; its labels: {', '.join(layout.labels) or 'none'}{guess}"


def warn_if_run_together(aps, labels=None) -> None:
    """A TaskWarning per proposition of ``aps`` that reads as operators run into a name (``Fb``: one
    proposition to the parser, rarely meant for ``F b``; ``parser.run_together``): with ``labels``
    (a layout's), operators run into one of them and not itself a label (an area may be labelled
    ``Fb``); without, operators run into a letter and digits."""
    for name, apart in run_together(sorted(set(aps)), labels).items():
        warnings.warn(TaskWarning(f"proposition {name!r} looks like {apart!r}; write operators apart from names "
                                  f"(the parser reads {name!r} as one proposition)"), stacklevel=2)


def _label_meant(prop: str, layout) -> str | None:
    """The label ``prop`` was likely meant to be: the one it equals but for case; an area's name
    written as a proposition (``lab_bench`` for the area ``lab-bench``, whose label is ``lab``: a
    formula names areas by label); operators run into a label (``GFdock``: ``G F dock``, one
    proposition to the parser); else the closest."""
    labels = layout.labels
    same = [lab for lab in labels if lab.lower() == prop.lower()]
    named = [a for a in layout.areas if re.sub(r"[^0-9a-z]", "_", a.name.lower()) == prop.lower()]
    if not same and named:
        return f"{named[0].label} (area {named[0].name}'s label)"
    if not same:
        ops = len(prop) - len(prop.lstrip("GFX"))
        if 0 < ops < len(prop) and prop[ops:] in labels:
            return " ".join(prop[:ops]) + " " + prop[ops:]
    return (same or difflib.get_close_matches(prop, labels, n=1, cutoff=0.6) or [None])[0]


def check_feasible(task: CompiledTask, name: str, radius: float | None = None, robot: str | None = None) -> None:
    """ConfigError unless a robot of ``radius`` (default: the task's robot) can drive from the start
    to an accepting state. ``robot`` names that robot in the error (default: "a robot of radius R m").

    Propositions must be labels of the layout's areas, the letters the layout can produce must complete
    the task, and a search over (automaton state, grid cell) (``routes.reachable_states``) must
    reach acceptance. The error names the farthest state reached and its target and forbidden areas.
    """
    aut, layout = task.automaton, task.layout
    missing = [p for p in aut.aps if p not in layout.labels]
    if missing:
        meant = _label_meant(missing[0], layout)
        hint = f"; did you mean {meant} for {missing[0]}?" if meant else ""
        raise ConfigError("task", f"{name}: proposition {missing[0]!r} names no area of layout {layout.name!r} "
                          f"(no area has that label; its labels: {', '.join(layout.labels) or 'none'}{hint})")
    distance = task.distance
    if distance[aut.initial] is None:
        raise ConfigError("task", f"{name} cannot be completed on layout {layout.name!r}: no sequence of the "
                          "letters it can produce (areas entered alone, or together where they overlap) does it")
    if radius is None:
        radius, reached = task.robot_radius, task.reached
    else:
        reached = routes.reachable_states(aut, layout, task.label_mode, radius)
    if task.recurrence:  # no accepting state: a route must make an accepting visit
        if radius == task.robot_radius:
            visits = [task.route_length] if math.isfinite(task.route_length) else []
        else:
            visits = routes.visit_lengths(aut, layout, task.label_mode, radius, math.inf, 1)
        if visits:
            return
    elif any(reached[q] for q in aut.accepting):
        return
    done = "make one accepting visit" if task.recurrence else "be completed"  # a patrol never completes
    ends = aut.accepting | aut.rejecting
    live = [q for q in range(aut.n_states) if reached[q] and q not in ends and distance[q] is not None]
    if not live:
        sx, sy = layout.start[:2]
        inside = [a.name for a in layout.areas if (a.center[0] - sx) ** 2 + (a.center[1] - sy) ** 2 <= a.radius ** 2]
        if inside:
            where = (f": the start ({sx:g}, {sy:g}) lies inside {', '.join(inside)}, and the automaton reads that area "
                     "at once, which fails the task before the robot moves; move the start out of it")
        elif task.label_mode == "step" and aut.delta[aut.initial][0] in aut.rejecting:
            where = (": step labelling reads the empty letter (no area) at the start, which fails the task before "
                     "the robot moves" + (" ('event' labelling, --label-mode event, reads no empty letter)"
                                          if robot is None else ""))
        else:
            where = ": the first area the robot can enter from the start rejects it"
        raise ConfigError("task", f"{name} cannot {done} on layout {layout.name!r}{where}")
    q = min(live, key=lambda s: (distance[s], s))
    targets, forbidden = (named_areas(aut, layout, task.roles, role)[q] for role in (TARGET, FORBIDDEN))
    goal = " or ".join(targets) or "an area that makes progress"
    why = f" without entering {', '.join(forbidden)} (forbidden there)" if forbidden else ""
    if (task.label_mode == "step" and robot is None  # the letters fail it, not the geometry: event labelling would not
            and any(routes.reachable_states(aut, layout, "event", radius)[s] for s in aut.accepting)):
        why += (" (--label-mode step: every step is a letter, the empty one between areas too, and X and U "
                "read them step by step; 'event' reads one on entering areas)")
    raise ConfigError("task", f"{name} cannot {done} on layout {layout.name!r}: in automaton state {q} "
                      f"({aut.state_formulas[q]}) {robot or f'a robot of radius {radius:g} m'} cannot "
                      f"reach {goal}{why}")


def check_margin(task: CompiledTask, margin: float, name: str) -> None:
    """A ``TaskWarning`` when every route that completes the task passes closer than ``margin`` (a
    learned barrier's d: D²SPO's barrier keeps the robot's centre about d from every sensed obstacle
    and wall) to an obstacle or wall, although the robot gets through: e.g. a gap of 0.35 m between
    an obstacle and an area the task forbids. A warning, not an error: the learned h lets the robot
    a little closer than d (a generalist completes routes that need 0.29 m), and routes that need
    0.27 m were not learnt (bench/barrier_margin.py, bench/RESULTS.md)."""
    try:
        check_feasible(task, name, radius=margin, robot="the robot")
    except ConfigError as e:
        why = str(e).removeprefix("task: ").replace(" cannot be completed on ", " on ", 1)
        warnings.warn(f"{why} while keeping {margin:g} m from every obstacle and wall (the barrier's margin d, "
                      "--cbf.d): every route passes closer, where the barrier may hold the robot back", TaskWarning,
                      stacklevel=3)


MAX_DERIVED_STEPS = 100_000
"""The longest episode limit ``default_max_steps`` may give: a longer one comes from a time step or
speed too small for the layout (``--dt 1e-6``), and ``make_env`` refuses it."""


def default_max_steps(task: CompiledTask, dt: float, v_max: float, base: int, recurrence_floor: int = 0) -> int:
    """The step limit of ``EnvConfig.max_steps=None``: ``base`` (``EnvConfig.base_max_steps``), or,
    when the task's shortest route at ``v_max`` needs more than ``TIGHT_FRACTION`` of those steps,
    ``ROOM`` times the route's steps rounded up to a multiple of 50 (then over ``base``). ``base``
    too when no route exists (``check_time`` then says so). A recurrence's route is the shortest
    that makes ``RECURRENCE_VISITS`` accepting visits, and its limit is at least
    ``recurrence_floor`` (``EnvConfig.recurrence_max_steps``): it never completes, so the limit is
    the window its visits are counted over."""
    length = task.visits_length(RECURRENCE_VISITS) if task.recurrence else task.route_length
    need = length / (v_max * dt)
    if not math.isfinite(need) or need <= TIGHT_FRACTION * base:
        steps = int(base)
    else:
        steps = int(50 * math.ceil(min(ROOM * need, 2.0 ** 40) / 50))  # bounded: a 1e-300 s step overflowed int
    return max(steps, int(recurrence_floor)) if task.recurrence else steps


def check_time(task: CompiledTask, max_steps: int, dt: float, v_max: float, name: str) -> None:
    """A ``TaskWarning`` when no route completes the task within ``max_steps`` steps at ``v_max``
    (every episode will time out), or when the shortest route needs more than ``TIGHT_FRACTION`` of
    them. A warning, not an error: short episodes are how smoke runs and tests exercise the machinery."""
    length = task.route_length
    need = length / (v_max * dt)
    budget = f"{max_steps} steps of {dt:g} s at {v_max:g} m/s"
    layout = task.layout
    if need / routes.OCTILE_EXCESS > max_steps:  # only what no continuous route could do
        warnings.warn(TaskWarning(
            f"{name} cannot be completed on layout {layout.name!r} within {budget}: its shortest route is "
            f"{length:.1f} m ({math.ceil(need)} steps at full speed), so every episode will time out "
            "(--max-steps raises the limit; unset, it follows the task)"), stacklevel=3)
    elif need > TIGHT_FRACTION * max_steps:
        warnings.warn(TaskWarning(
            f"{name}: the shortest route on layout {layout.name!r} is {length:.1f} m, {math.ceil(need)} of the "
            f"{max_steps} steps at full speed ({need / max_steps:.0%}); a policy that drives about 1.2x the shortest "
            "route may run out of time (--max-steps raises the limit; unset, it follows the task)"), stacklevel=3)


def preflight(env, params, name: str, margin: float = 0.0, episode_time: bool = True) -> None:
    """The checks of a run before it starts, on ``env.task`` (``name`` names the task in messages):
    with per-state shaping fields, the robot can complete the task (``check_feasible``; ``make_env``
    has checked it, so this reads its result); with ``margin`` over the robot's radius, a route keeps
    it (``check_margin``: D²SPO's and SL's barrier d); with ``episode_time``, the task fits in
    ``params.max_steps`` (``check_time``; evaluating a trained run skips it: nothing can be done about
    its episodes then). Nothing to check without one task on one layout (the generalist's bank),
    with an automaton given by its arrays only, or for a recurrence task (no state completes it: it
    runs to the step limit, scored by its accepting visits; ``ltl.buchi_task``)."""
    task = env.task
    if task is None or task.distance is None or not (task.automaton.accepting or task.recurrence):
        return
    warn_if_endless_branch(task.automaton, name)
    check_start(task, name)
    cfg = env.config
    if task.fields is not None:
        check_feasible(task, name)
    if margin > cfg.robot_radius:
        check_margin(task, margin, name)
    if task.recurrence:
        check_lap(task, cfg.robot_radius, name)
    if episode_time and task.recurrence:
        check_cycle(task, int(params.max_steps), cfg.dt, cfg.v_max * cfg.v_gain, name)
    elif episode_time:
        check_time(task, int(params.max_steps), cfg.dt, cfg.v_max * cfg.v_gain, name)


def start_state(task: CompiledTask) -> int:
    """The automaton state an episode starts in: the initial state after reading the letter of the
    start pose (the env's reset reads it: with event labelling only a non-empty letter)."""
    aut, layout = task.automaton, task.layout
    letter = int(letters_at(np.asarray(layout.start[:2], float), layout, aut.aps))
    if letter == 0 and task.label_mode == "event":
        return aut.initial
    return aut.delta[aut.initial][letter]


def check_start(task: CompiledTask, name: str) -> None:
    """A ``TaskWarning`` when the start pose lies inside an area whose reading completes the task:
    every episode then completes on its first step, and nothing is learnt (``env check`` once said
    such a task "needs 1 area visit")."""
    aut, layout = task.automaton, task.layout
    if task.recurrence or start_state(task) not in aut.accepting:  # a patrol never completes
        return
    sx, sy = layout.start[:2]
    inside = [a.name for a in layout.areas
              if a.label in aut.aps and (a.center[0] - sx) ** 2 + (a.center[1] - sy) ** 2 <= a.radius ** 2]
    warnings.warn(TaskWarning(
        f"{name} on layout {layout.name!r}: the start ({sx:g}, {sy:g}) lies inside {', '.join(inside)}, and the "
        "automaton reads that area at once and accepts: every episode completes on its first step, with nothing "
        "to learn; move the start out of it"))


def warn_if_endless_branch(aut, name: str) -> None:
    """A TaskWarning when a task that completes can also be satisfied forever without completing
    (``ltl.buchi_task.endless_branch``: ``GF A1 & GF A3 | F A2``'s patrol, ``F A1 | G !A2``'s
    avoidance): it trains as a task that completes, and a run on that branch scores nothing."""
    formulas = getattr(aut, "state_formulas", ())
    if aut.accepting and not getattr(aut, "visits", None) and formulas and endless_branch(formulas[aut.initial]):
        warnings.warn(TaskWarning(
            f"{name} can also be satisfied forever without ever completing it (a branch with no finite end, "
            "such as a patrol or a 'never' in a disjunction); it trains as a task that completes, so a robot on "
            "that branch scores nothing and is not rewarded for it: to train that branch, give it alone"))


def check_lap(task: CompiledTask, robot_radius: float, name: str) -> None:
    """ConfigError when a recurrence's accepting visit can follow the one before within the robot's
    diameter (``GF dock``: leave the dock and enter it again): its visits would count jitter at an
    area's edge, not laps, and its route-optimal count nearly one per step. Every lap of the first
    2 n + 2 visits is checked (n: the automaton's states), not only the first: on overlapping areas
    ``G (A1 -> F A2) & GF A1``'s first lap is 0.55 m and every later one 0.05 m (crossing from A1
    alone into A1 and A2)."""
    first = task.route_length
    if not math.isfinite(first):
        return
    lengths = routes.visit_lengths(task.automaton, task.layout, task.label_mode, task.robot_radius, math.inf,
                                   2 * task.automaton.n_states + 2)
    lap = min((b - a for a, b in zip(lengths, lengths[1:])), default=math.inf)
    if lap < 2 * robot_radius:
        triggers = untriggered_responses(getattr(task.automaton, "state_formulas", ()) and
                                         task.automaton.state_formulas[task.automaton.initial])
        hint = (f"; for a response, make its trigger recur: add '& G F {triggers[0]}' (the suite's respond: "
                "'G (A1 -> F A2) & G F A1')" if triggers else "")
        how = ("every step in an area reads its letter again, with --label-mode step" if task.label_mode == "step"
               else "leaving an area and entering it again")
        raise ConfigError("task", f"{name}: on layout {task.layout.name!r} an accepting visit can follow the "
                          f"last after {lap:.2f} m ({how}), so its visits would "
                          "count moves at an area's edge, not laps; give two areas to alternate between, e.g. "
                          f"'GF a & GF b', or a goal to reach once, 'F a'{hint}")


def untriggered_responses(formula: str) -> list[str]:
    """The triggers p of the response conjuncts ``G (p -> F q)`` of ``formula`` (an automaton state's
    residual, where it reads ``G (!p | F q)``) that no conjunct ``G F p`` makes recur: alone, such a
    response is met by never meeting p, and every step away from p is an accepting visit."""
    if not formula:
        return []
    conjuncts, todo = [], [parse(formula)]
    while todo:
        f = todo.pop()
        if isinstance(f, And):
            todo += [f.left, f.right]
        else:
            conjuncts.append(f)
    recurring = {c.arg.arg for c in conjuncts if isinstance(c, Always) and isinstance(c.arg, Eventually)}
    triggers = []
    for c in conjuncts:
        body = c.arg if isinstance(c, Always) else None
        if isinstance(body, Implies) and isinstance(body.right, Eventually):
            p = body.left
        elif isinstance(body, Or) and isinstance(body.left, Not) and isinstance(body.right, Eventually):
            p = body.left.arg
        else:
            continue
        text = str(p) if isinstance(p, Prop) else f"({p})"
        if p not in recurring and text not in triggers:
            triggers.append(text)
    return triggers


def check_cycle(task: CompiledTask, max_steps: int, dt: float, v_max: float, name: str) -> None:
    """ConfigError when a recurrence's first accepting visit (one lap of its cycle) cannot be made
    within ``max_steps`` steps at ``v_max`` by any route: every episode would score 0 visits."""
    length = task.route_length
    need = length / (v_max * dt)
    if need / routes.OCTILE_EXCESS > max_steps:
        raise ConfigError("env.max_steps", f"{name}: an episode of {max_steps} steps of {dt:g} s at {v_max:g} m/s is "
                          f"too short for one accepting visit on layout {task.layout.name!r}: the shortest route to "
                          f"the first is {length:.1f} m ({math.ceil(need)} steps at full speed); raise --max-steps "
                          "(unset, it follows the task)")
    second = task.visits_length(2)
    if math.isfinite(second) and second / (v_max * dt) / routes.OCTILE_EXCESS > max_steps:
        warnings.warn(TaskWarning(
            f"{name}: an episode of {max_steps} steps of {dt:g} s at {v_max:g} m/s holds only one accepting visit "
            f"on layout {task.layout.name!r} (route-optimal count 1): the second needs {second:.1f} m "
            f"({math.ceil(second / (v_max * dt))} steps at full speed), so no episode goes round again and the "
            "robot never learns the lap; raise --max-steps (unset, it follows the task)"), stacklevel=3)
