"""Model selection while a run trains: the policy a run keeps as DIR/policy-best.msgpack.

``Validation`` scores a generalist on held-out layouts, ``PatrolValidation`` a recurrence (a patrol)
on its own layout; ``validation_for`` picks the one a config asks for, and ``better_validation``
decides whether a new score replaces the kept one. ``d2spo.record.RunRecord`` runs them between
chunks and writes the kept policy.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from d2spo.config import VALIDATION_SEED, TrainConfig
from d2spo.envs.compiled_task import compile_task
from d2spo.envs.generalist import view
from d2spo.envs.layouts import load as load_layout
from d2spo.rollout import make_rollout, rates, visit_optimum


def visit_scores(visits, optimum, collided) -> np.ndarray:
    """Each episode's accepting visits as a fraction of its route-optimal count (``optimum``, per
    episode or one for all), at most 1, and 0 for an episode with a collision: how both validations
    score a patrol."""
    frac = np.asarray(visits, float) / np.maximum(np.asarray(optimum, float), 1.0)
    return np.minimum(frac, 1.0) * ~np.asarray(collided)


def better_validation(entry: dict, best: dict) -> bool:
    """Whether a validation ``entry`` replaces the kept ``best``: more successful episodes; of equal
    success, fewer steps to success on average (the faster policy, as LTL benchmarks rank agents;
    validations before 2026-11-27 have no ``mean_steps_success`` and tie on it; None: no success); of
    equals in both, the later one, which has trained longer."""
    if entry["success_rate"] != best["success_rate"]:
        return entry["success_rate"] > best["success_rate"]

    def steps(e: dict) -> float:
        s = e.get("mean_steps_success")
        return math.inf if s is None else s

    return steps(entry) <= steps(best)


class Validation:
    """The generalist's model selection (``TrainConfig.validation_layouts``): ``policy -> rates`` of
    ``validation_episodes`` deterministic episodes on the held-out layouts WORLD:VALIDATION_SEED ..
    (WORLD: ``generalist_world``),
    the training task(s), the same episodes (key) every time. ``success_rate`` is the mean score of
    the episodes: 1 for one that completes its task without a collision, and for a patrol of the
    mixture (``--generalist-patrols``) its accepting visits as a fraction of its slot's
    route-optimal count (at most 1; 0 with a collision); ``mean_steps_success`` is the mean length
    of the successful episodes of tasks that complete: what the best policy is chosen by
    (``better_validation``)."""

    def __init__(self, cfg: TrainConfig, env, params, learner):
        n = cfg.validation_layouts
        self.layouts = f"{cfg.generalist_world}:{VALIDATION_SEED}..{VALIDATION_SEED + n - 1}"
        self.episodes = cfg.validation_episodes
        tasks = len(env.plan.names)  # every layout with every task of the mixture
        layouts = [load_layout(f"{cfg.generalist_world}:{s}") for s in range(VALIDATION_SEED, VALIDATION_SEED + n)]
        limit = cfg.env.max_steps  # None: each layout's own (envs.task_plan.slot_max_steps)
        bank = env.bank([lay for lay in layouts for _ in range(tasks)], [t for _ in layouts for t in range(tasks)],
                        limit)
        self.params = view(params.replace(bank=bank), jnp.zeros((), jnp.int32))
        self.recurrent = any(env.plan.recurrent)
        self.rollout = make_rollout(learner, env, cfg.validation_episodes, int(np.max(np.asarray(bank.max_steps))),
                                    with_slot=self.recurrent)
        self.key = jax.random.PRNGKey(cfg.seed + 20_000)
        self.optimum = np.zeros(len(layouts) * tasks)  # per slot: a patrol's route-optimal visits (else 0)
        if self.recurrent:
            limits = np.asarray(bank.max_steps)
            resolved = env.config
            for s, (lay, t) in enumerate((lay, t) for lay in layouts for t in range(tasks)):
                if env.plan.recurrent[t]:
                    task = compile_task(env.plan.automata[t], lay, resolved.label_mode, resolved.robot_radius)
                    self.optimum[s] = task.optimal_visits(int(limits[s]), resolved.dt,
                                                          resolved.v_max * resolved.v_gain)

    def __call__(self, policy) -> dict:
        collided, completed, ret, length, *rest = self.rollout(self.params, policy, self.key)
        out = rates(collided, completed, ret, length, *rest[:2])  # poses, and a Büchi task's visits
        ok = np.asarray(completed) & ~np.asarray(collided)
        steps = float(np.asarray(length)[ok].mean()) if ok.any() else None
        score = ok.astype(float)
        if self.recurrent:  # a patrol's episode: its visits against its slot's optimum
            _, visits, slot = rest
            best = self.optimum[np.asarray(slot)]
            score = np.where(best > 0, visit_scores(visits, best, collided), score)
        return {"success_rate": float(np.mean(score)), "mean_steps_success": steps,
                "completion_rate": out["completion_rate"], "safety_rate": out["safety_rate"]}


class PatrolValidation:
    """A patrol's model selection on one layout (``TrainConfig.patrol_validation``): ``policy ->
    rates`` of that many deterministic episodes on the training layout itself, the same episodes
    (key) every time. A recurrence never completes, and its last policy can make far fewer visits
    than its training episodes did (bench/RESULTS.md, "2026-11-30, late morning": 4.09 of 10 after
    6.97 over the last 2000), so the run keeps the policy that visits most. ``success_rate`` is the
    mean of the episodes' accepting visits as a fraction of the layout's route-optimal count (at
    most 1; 0 for an episode with a collision); ``mean_steps_success`` is None (no episode
    completes), so of equal scores the later policy is kept (``better_validation``)."""

    def __init__(self, cfg: TrainConfig, env, params, learner):
        self.layouts, self.episodes = cfg.layout, cfg.patrol_validation
        self.params = params
        self.rollout = make_rollout(learner, env, cfg.patrol_validation, int(params.max_steps))
        self.key = jax.random.PRNGKey(cfg.seed + 20_000)
        self.optimum = visit_optimum(env.task, params.max_steps, env.config, None).get("route_optimal_visits", 0)

    def __call__(self, policy) -> dict:
        collided, completed, ret, length, _, visits = self.rollout(self.params, policy, self.key)
        out = rates(collided, completed, ret, length, None, visits)
        return {"success_rate": float(np.mean(visit_scores(visits, self.optimum, collided))), "mean_steps_success": None,
                "accepting_visits_per_episode": out["accepting_visits_per_episode"],
                "completion_rate": out["completion_rate"], "safety_rate": out["safety_rate"]}


def validation_for(cfg: TrainConfig, env, params, learner) -> Validation | PatrolValidation | None:
    """The run's model selection: a generalist's on its held-out layouts (``validation_layouts``),
    a patrol's on its one layout (``patrol_validation``), or None (the last policy is the run's)."""
    if cfg.generalist:
        return Validation(cfg, env, params, learner) if cfg.validation_layouts else None
    if cfg.patrol_validation and params.aut.visit is not None and env.task.recurrence:
        return PatrolValidation(cfg, env, params, learner)
    return None
