"""The layouts of a zero-shot evaluation of a generalist (``d2spo eval RUN --task FORMULA --layout L``).

A generalist (``d2spo train --generalist``) reads the subgoal in its own frame, never the layout's
coordinates or the automaton's state index (``envs.generalist``), so its policy can run on any task
over the areas A1..A4 and on any layout the field bank can hold: a square arena of at most
``MAX_SIDE`` m, the four areas A1..A4 (not overlapping), at most ``layout_bank.M_MAX`` box
obstacles. For every layout of an evaluation:

1. the layout and the task are checked as for training a specialist there (``nav.make_env``): the
   robot fits and reaches every area, the propositions name areas, the task can be done with the
   letters the layout can produce, and the forbidden areas do not cut every route to a target.
   Each failure is one ``ConfigError`` line (exit 2), never a silent 0%;
2. its 32 distance fields are computed (``layout_bank.bank_of``, about 0.07 s);
3. the policy runs ``episodes`` deterministic episodes on a one-layout bank. Every layout of an
   evaluation has the same array shapes and the same episode limit (the longest any of them needs,
   and at least the training limit), so one compilation serves them all.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.algos.generalist import build_generalist
from d2spo.config import TrainConfig
from d2spo.envs import layout_bank
from d2spo.envs.compiled_task import compile_task
from d2spo.envs.generalist import GENERALIST_MAX_STEPS, view
from d2spo.envs.nav import make_env
from d2spo.envs.preflight import preflight
from d2spo.envs.workspace import Layout
from d2spo.errors import ConfigError
from d2spo.ltl.automaton import Automaton
from d2spo.ltl.reward import PER_STATE
from d2spo.ltl.tasks import TASKS
from d2spo.rollout import make_rollout, rates, visit_optimum

MAX_SIDE = 10.0
"""Largest arena side (m) a generalist is evaluated on: the training distribution's largest
(``envs.generator.SIDE``); the bank's 64-node grid resolves a 0.6 m gap up to it."""
TOL = 1e-6
"""Slack (m) when comparing an arena's side with ``MAX_SIDE``."""


def generalist_layout(env_cfg, name: str, task: str, margin: float = 0.0) -> tuple[Layout, int]:
    """The layout ``name`` checked for a generalist and for ``task`` (module docstring, step 1),
    its areas in the order A1..A4, and the episode limit a specialist would get there. ``margin``:
    the generalist's barrier margin d: a warning when no route keeps it (``preflight.check_margin``;
    0: not checked)."""
    cfg = dataclasses.replace(env_cfg, layout=name, max_steps=None,
                              reward=dataclasses.replace(env_cfg.reward, shaping_metric=PER_STATE))
    env, params = make_env(cfg, task)  # the layout's and the task's checks; the specialist's episode limit
    preflight(env, params, repr(task), margin=margin, episode_time=False)
    lay = env.layout
    where = f"layout {lay.name!r}"
    w, h = lay.arena
    if abs(w - h) > TOL:
        raise ConfigError("layout", f"{where}: a generalist runs on square arenas (its field bank), got {w:g} x {h:g} m")
    if w > MAX_SIDE + TOL:
        raise ConfigError("layout", f"{where}: arena side {w:g} m is larger than the generalist's {MAX_SIDE:g} m")
    names = sorted(a.name for a in lay.areas)
    wanted = [f"A{i + 1}" for i in range(layout_bank.N_AREAS)]
    if names != wanted:
        raise ConfigError("layout", f"{where}: a generalist reads the areas {', '.join(wanted)}; "
                          f"this layout has {', '.join(names) or 'none'}")
    if relabelled := [a.name for a in lay.areas if a.label != a.name]:
        raise ConfigError("layout", f"{where}: a generalist reads each area as the proposition of its name; "
                          f"areas {', '.join(relabelled)} carry other labels")
    if lay.disks:
        raise ConfigError("layout", f"{where}: a generalist senses box obstacles only; this layout has "
                          f"{len(lay.disks)} disk obstacles")
    areas = tuple(sorted(lay.areas, key=lambda a: a.name))
    for i, a in enumerate(areas):
        for b in areas[i + 1:]:
            if math.dist(a.center, b.center) < a.radius + b.radius:
                raise ConfigError("layout", f"{where}: areas {a.name} and {b.name} overlap; a generalist "
                                  "plans one area at a time")
    if len(lay.obstacles) > layout_bank.M_MAX:
        raise ConfigError("layout", f"{where}: {len(lay.obstacles)} obstacles, more than the generalist's "
                          f"{layout_bank.M_MAX}")
    return dataclasses.replace(lay, areas=areas), int(params.max_steps)


def task_tag(task: str) -> str:
    """A file-name-safe name of a task: its name, or ``f-`` and a hash of the formula."""
    if task in TASKS:
        return task
    return "f-" + hashlib.sha256(task.encode()).hexdigest()[:10]


def generalist_on(cfg: TrainConfig, env_cfg, task: str, checked: list[tuple[Layout, int]]):
    """(env, params, learner, episode limit) of the generalist trained with ``cfg``, built once for
    ``task`` alone under the dynamics of ``env_cfg``, on the first of the ``checked`` layouts; the
    limit is the longest any of them needs (``generalist_layout``), and at least the training one."""
    limit = max([cfg.env.max_steps or GENERALIST_MAX_STEPS] + [n for _, n in checked])
    cfg = dataclasses.replace(cfg, env=env_cfg, task=task, generalist_tasks=0)
    env, params, learner = build_generalist(cfg, layout_bank.bank_of([checked[0][0]]), limit)
    return env, params, learner, limit


def rollouts(env, params, learner, policy, checked: list[tuple[Layout, int]], episodes: int, seed: int, limit: int,
             keep_paths: int = 0) -> list[dict]:
    """Rates per layout of the generalist ``policy`` on the ``checked`` layouts: one compiled
    rollout; each layout swaps its one-layout bank into ``params``. With ``keep_paths`` each layout's
    rates also hold ``"paths"``: (Layout, poses [k, T + 1, 3], collided [k], completed [k]) of its
    first ``keep_paths`` episodes."""
    run = make_rollout(learner, env, episodes, limit)
    results = []
    for k, (lay, _) in enumerate(checked):
        if k > 0:
            params = view(params.replace(bank=layout_bank.bank_of([lay])), jnp.zeros((), jnp.int32))
        res = run(params, policy, jax.random.PRNGKey(seed))
        results.append(rates(*res))
        if params.aut.visit is not None and isinstance(env.automaton, Automaton):  # a Büchi task's visits
            # against what a perfect robot would make on this layout in ``limit`` steps
            task = compile_task(env.automaton, lay, env.config.label_mode, env.config.robot_radius)
            results[-1].update(visit_optimum(task, limit, env.config, results[-1]["accepting_visits_per_episode"]))
        if keep_paths:
            poses, collided, completed = (np.asarray(a[:keep_paths]) for a in (res[4], res[0], res[1]))
            results[-1]["paths"] = (lay, poses, collided, completed)
    return results
