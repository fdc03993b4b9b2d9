"""The layouts of a zero-shot evaluation of a generalist (``d2spo eval RUN --task FORMULA --layout L``).

A generalist (``d2spo train --generalist``) reads the subgoal in its own frame, never the layout's
coordinates, its label names or the automaton's state index (``envs.generalist``), so its policy
can run on any task and on any layout a bank slot can hold (``layout_bank.check_fits``): a
rectangular arena of at most ``layout_bank.MAX_SIDE`` m a side, at most ``layout_bank.N_AREAS``
areas that do not overlap (any labels, shared or not), ``layout_bank.M_MAX`` boxes and
``layout_bank.D_MAX`` disks. For every layout of an evaluation:

1. the layout and the task are checked as for training a specialist there (``nav.make_env``): the
   robot fits and reaches every area, the propositions are labels of areas, the task can be done
   with the letters the layout can produce, and the forbidden areas do not cut every route to a
   target. Each failure is one ``ConfigError`` line (exit 2), never a silent 0%;
2. the distance fields of the task's states are computed on it (``GeneralistEnv.bank``);
3. the policy runs ``episodes`` deterministic episodes on a one-layout bank. Every layout of an
   evaluation has the same array shapes and the same episode limit (the longest any of them needs,
   and at least the training limit), so one compilation serves them all.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.algos.generalist import build_generalist
from d2spo.config import TrainConfig
from d2spo.envs import layout_bank
from d2spo.envs.compiled_task import compile_task
from d2spo.envs.generalist import view
from d2spo.envs.nav import make_env
from d2spo.envs.preflight import preflight
from d2spo.envs.task_plan import slot_max_steps
from d2spo.envs.workspace import Layout
from d2spo.ltl.automaton import Automaton
from d2spo.ltl.reward import PER_STATE
from d2spo.rollout import make_rollout, rates, visit_optimum


def seen_forbidden_range(env_cfg, given: float | None = None):
    """``env_cfg`` with the forbidden range of a zero-shot evaluation (``EnvConfig.forbidden_range``):
    ``given`` when asked for (``d2spo eval --forbidden-range``; inf: a forbidden area seen at any
    distance); else the run's own, when it was trained with one; else the robot's lidar range
    (``sensing_radius``, 1.2 m for the default robot): a generalist trained seeing every forbidden
    area at any distance is evaluated seeing one only as far as the robot senses (README,
    "Departures from the paper"; bench/RESULTS.md, "2026-12-03, night")."""
    if given is not None:
        far = None if np.isinf(given) else float(given)
    elif env_cfg.forbidden_range is not None:
        return env_cfg
    else:
        far = float(env_cfg.resolved().sensing_radius)
    return dataclasses.replace(env_cfg, forbidden_range=far)


def generalist_layout(env_cfg, name: str, task: str, margin: float = 0.0,
                      max_steps: int | None = None) -> tuple[Layout, int]:
    """The layout ``name`` checked for a generalist and for ``task`` (module docstring, step 1) and
    the episode limit a specialist would get there. ``margin``: the generalist's barrier margin d:
    a warning when no route keeps it (``preflight.check_margin``; 0: not checked). ``max_steps``: an
    episode limit asked for instead (``d2spo eval --max-steps``), checked to fit the task there."""
    cfg = dataclasses.replace(env_cfg, layout=name, max_steps=max_steps,
                              reward=dataclasses.replace(env_cfg.reward, shaping_metric=PER_STATE))
    env, params = make_env(cfg, task)  # the layout's and the task's checks; the specialist's episode limit
    preflight(env, params, repr(task), margin=margin, episode_time=max_steps is not None)
    layout_bank.check_fits(env.layout)
    return env.layout, int(params.max_steps)


def generalist_on(cfg: TrainConfig, env_cfg, task: str, checked: list[tuple[Layout, int]], limit: int | None = None):
    """(env, params, learner, episode limit) of the generalist trained with ``cfg``, built once for
    ``task`` alone under the dynamics of ``env_cfg``, on the first of the ``checked`` layouts; the
    limit is ``limit`` when given, else the longest any of them needs (``generalist_layout``), and at
    least what training gives each (its ``max_steps``, else ``envs.task_plan.slot_max_steps``)."""
    if limit is None:
        limit = max(max(cfg.env.max_steps or slot_max_steps(lay), n) for lay, n in checked)
    cfg = dataclasses.replace(cfg, env=env_cfg, task=task, generalist_tasks=0, generalist_patrols=0,
                              generalist_pairings=1)
    env, params, learner = build_generalist(cfg, [checked[0][0]], limit)
    return env, params, learner, limit


def rollouts(env, params, learner, policy, checked: list[tuple[Layout, int]], episodes: int, seed: int, limit: int,
             keep_paths: int = 0, margin: float | None = None, on_layout=None) -> list[dict]:
    """Rates per layout of the generalist ``policy`` on the ``checked`` layouts: one compiled
    rollout; each layout swaps its one-layout bank into ``params``. With ``keep_paths`` each layout's
    rates also hold ``"paths"``: (Layout, poses [k, T + 1, 3], collided [k], completed [k]) of its
    first ``keep_paths`` episodes. ``margin``: the barrier's margin d, for a patrol's
    ``route_optimal_visits_margin`` (``rollout.visit_optimum``). ``on_layout(k, n, name)`` is called before the k-th layout's rollouts (``evaluate.evaluate_run``)."""
    run = make_rollout(learner, env, episodes, limit)
    results = []
    for k, (lay, _) in enumerate(checked):
        if on_layout is not None:
            on_layout(k, len(checked), lay.name)
        if k > 0:
            params = view(params.replace(bank=env.bank([lay], max_steps=limit)), jnp.zeros((), jnp.int32))
        res = run(params, policy, jax.random.PRNGKey(seed))
        results.append(rates(*res, max_steps=limit))
        if params.aut.visit is not None and isinstance(env.automaton, Automaton):  # a Büchi task's visits
            # against what a perfect robot would make on this layout in ``limit`` steps
            task = compile_task(env.automaton, lay, env.config.label_mode, env.config.robot_radius)
            results[-1].update(visit_optimum(task, limit, env.config, results[-1]["accepting_visits_per_episode"],
                                             margin))
        if keep_paths:
            poses, collided, completed = (np.asarray(a[:keep_paths]) for a in (res[4], res[0], res[1]))
            results[-1]["paths"] = (lay, poses, collided, completed)
    return results
