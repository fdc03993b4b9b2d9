"""``--label-radius``: a fixed relaxed labelling radius for a learner that does not anneal, used in
training only; evaluation reads the task with the areas' true radii; refused where it would change
nothing (an annealing learner, the generalist)."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from test_train import tiny

from d2spo.errors import ConfigError
from d2spo.rollout import make_rollout, rates
from d2spo.run import build

WIDE = 50.0  # covers the whole arena from any start: every area is "reached" at once under it


def _wide(algo: str, **kw):
    env = dataclasses.replace(tiny().env, label_radius=WIDE)
    return tiny(algo=algo, task="F A1", env=env, **kw)


def test_a_learner_without_annealing_trains_with_the_fixed_radius():
    _, params, learner = build(_wide("td3"))
    seen = learner.schedule.env_params(params, jax.numpy.int32(0)).label_radius
    assert np.allclose(np.asarray(seen), WIDE)


def test_an_annealing_learner_turned_off_trains_with_it_too():
    cfg = tiny(algo="tlgrl", task="F A1", env=dataclasses.replace(tiny().env, label_radius=WIDE),
               anneal=dataclasses.replace(tiny().anneal, enabled=False))
    _, params, learner = build(cfg)
    assert np.allclose(np.asarray(learner.schedule.env_params(params, jax.numpy.int32(5)).label_radius), WIDE)


@pytest.mark.parametrize("kw, words", [({"algo": "tlgrl"}, "anneals its labelling radius"),
                                       ({"algo": "d2spo", "generalist": True}, "no effect with --generalist")])
def test_it_is_refused_where_it_would_change_nothing(kw, words):
    with pytest.raises(ConfigError, match=words):
        _wide(**kw)


def test_an_evaluation_reads_the_task_with_the_true_radii():
    env, params, learner = build(_wide("td3"))
    key = jax.random.PRNGKey(0)
    # the env itself, with these params, ends an episode at its first step (A1 "reached" at once) ...
    state, _ = env.reset(key, params)
    *_, done, info = env.step(key, state, np.zeros(env.action_size, np.float32), params)
    assert bool(done) and bool(info["completed_relaxed"]) and not bool(info["completed"])
    # ... an evaluation does not: it is neither a completion nor a rejection there
    out = make_rollout(learner, env, 4, 40)(params, learner.policy(jax.jit(learner.init)(key)), key)
    collided, completed, _, length = (np.asarray(x) for x in out[:4])
    assert (length > 1).all()
    r = rates(*out, max_steps=40)
    assert r["rejection_rate"] == float(np.mean((length < 40) & ~collided.astype(bool) & ~completed.astype(bool)))
    assert r["rejection_rate"] == 0.0  # F A1 forbids nothing


def test_the_refusal_names_a_flag_the_command_line_takes():
    """The refusal's way out parses: `--anneal.no-enabled` (it said `--anneal.enabled False`, which the
    command line refuses: a boolean flag takes no value)."""
    from d2spo.cli import parse

    with pytest.raises(ConfigError) as refused:
        _wide("tlgrl")
    assert "--anneal.no-enabled" in str(refused.value) and "--anneal.enabled False" not in str(refused.value)
    cfg = parse(["train", "--algo", "tlgrl", "--anneal.no-enabled", "--label-radius", "1.0"]).config()
    assert not cfg.anneal.enabled and cfg.env.label_radius == 1.0
