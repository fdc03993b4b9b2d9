"""D²SPO end to end: safe exploration from the first episode, and learning on `relaxed`."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import pytest
from _reproduce import short_run_config

from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.rollout import random_proposal_safety
from d2spo.run import build
from d2spo.train import learner_program


def test_short_run_on_relaxed_learns_to_reach_a1_safely(short_d2spo_run):
    """250 episodes of D²SPO on the `relaxed` layout, task F A1 (its first leg; the two-area task
    needs thousands of episodes; tests/conftest.py trains it, tests/test_plots.py draws Figs. 4-5
    from it too). The final policy must reach A1 far more often than the untrained
    one and never collide; training itself stays mostly collision-free (seeds 0, 1, 2 under the
    suite's flags: final completion 1.0, collisions in 0-0.4% of the 250 episodes; 500 episodes
    were asked before, 2026-11-27). The run compiles its task
    onto the layout once (envs/compiled_task.py): one distance computation, route and set of fields."""
    run, summary, calls = short_d2spo_run
    # the grid search for the robot twice: make_env's feasibility check and the barrier's margin d
    assert calls == {"distances": 1, "route_length": 1, "reachable_states": 2, "state_fields": 1}
    untrained = summary["eval_untrained"]
    assert untrained["completion_rate"] <= 0.1
    assert summary["eval"]["completion_rate"] >= 0.8
    assert summary["eval"]["safety_rate"] == 1.0
    import csv

    with open(run / "episodes.csv") as f:
        collided = [int(r["collided"]) for r in csv.DictReader(f)]
    assert len(collided) == 250 and sum(collided) / 250 <= 0.1
    # `d2spo eval --runtime-filter True --filter-alpha A --filter-iters N` on the same run
    from d2spo.errors import ConfigError
    from d2spo.evaluate import EvalConfig, evaluate_run

    res = evaluate_run(run, EvalConfig(episodes=16, runtime_filter=True, filter_alpha=1.5, filter_iters=5))
    assert res["runtime_filter"] is True and res["filter_alpha"] == 1.5 and res["filter_iters"] == 5
    assert res["safety_rate"] == 1.0
    with pytest.raises(ConfigError):
        EvalConfig(episodes=4, runtime_filter=True, filter_alpha=0.0)
    # the demo's picture of it: named, with units, legends and a colourbar label, and no title clipped
    from d2spo.plots import draw_policy_figure
    from d2spo.run import load_policy

    _, learner, policy, _ = load_policy(run)
    # as many episodes as the run's final evaluation: its compiled rollout serves (58.9 s -> 51.8 s)
    fig, rates = draw_policy_figure(learner, policy, learner.env, learner.params, episodes=32,
                                    suptitle="D²SPO: layout 'relaxed', task 'F A1'")
    traj, cbf, bar = fig.axes
    assert {ax.get_xlabel() for ax in (traj, cbf)} == {"x (m)"} and {ax.get_ylabel() for ax in (traj, cbf)} == {"y (m)"}
    assert bar.get_ylabel() == "h, the learned CBF (h ≥ 0: safe set)"
    legend = [t.get_text() for t in traj.get_legend().get_texts()]
    assert "start; arrow: initial heading" in legend and "sensing radius H = 1.2 m (around the start)" in legend
    assert "trajectory: collision (x: end)" in legend
    fig.canvas.draw()
    box = fig.bbox
    for text in (fig._suptitle, traj.title, cbf.title):
        ext = text.get_window_extent()
        assert box.x0 <= ext.x0 and ext.x1 <= box.x1 and box.y0 <= ext.y0 and ext.y1 <= box.y1, text.get_text()
    assert rates["safety_rate"] == 1.0


def test_cautious_start_makes_random_exploration_safe():
    """Before any env step, π_Ω (pre-trained on synthetic sensed data only) turns uniform random
    proposals, which crash in most episodes, into mostly safe ones (2026-12-01: 34% of episodes
    safe without it and 100% with it on `relaxed`; 33% and 100% for ϕ1 on `paper`). The learner is the short
    run's: placed after that test, it finds the init program the run compiled (d2spo.memo)."""
    env, params, learner = build(short_run_config())
    carry = learner_program(learner, "init")(jax.random.PRNGKey(0))
    raw = random_proposal_safety(learner, carry, env, params, shielded=False)
    safe = random_proposal_safety(learner, carry, env, params, shielded=True)
    assert raw < 0.6, raw
    assert safe >= 0.9, (raw, safe)
    # The override is a correction, not a new policy: far from obstacles π_Ω follows the proposal.
    obs = jnp.zeros((1, env.observation_size)).at[:, env.observation_slices["lidar"]].set(1.0)
    u_rl = jnp.array([[0.5, -0.3]])
    u = learner.execute(carry.safety, obs, u_rl, jnp.zeros((1, 3)))
    assert float(jnp.linalg.norm(u - u_rl)) < 0.2


def test_eval_switches_the_runtime_filter_on_away_from_the_training_layout():
    from d2spo.evaluate import filter_choice

    d2 = TrainConfig(algo="d2spo", env=EnvConfig(layout="paper", preset="default"))
    assert filter_choice(d2, None, None, None) is None  # as trained
    assert filter_choice(d2, "paper", "default", None) is None
    assert filter_choice(d2, "random:3", None, None) is True
    assert filter_choice(d2, None, "turtlebot", None) is True
    assert filter_choice(d2, None, None, None, {"slip": 0.2}) is True  # a per-field change of the dynamics
    assert filter_choice(d2, None, None, None, {"slip": 0.05}) is None  # the trained value: nothing changes
    assert filter_choice(d2, "random:3", None, False) is False  # asked for: the paper's π_Ω alone
    assert filter_choice(TrainConfig(algo="td3-lag"), "random:3", None, None) is None  # no filter to switch
    # a generalist never trained on its config's default layout (`paper`): on there too
    gen = dataclasses.replace(d2, generalist=True)
    assert filter_choice(gen, "paper", None, None) is True and filter_choice(gen, "random:3", None, None) is True
    assert filter_choice(gen, "paper", None, False) is False


def test_one_compiled_rollout_serves_every_random_layout():
    """Evaluation compiles the rollout once for layouts of the same shapes, passing each layout's
    params as an argument: D²SPO's π_Ω must then see *that* layout's obstacles,
    (through the nearest-obstacle feature of x), exactly as a rollout compiled for it alone does."""
    import dataclasses

    from d2spo.evaluate import learner_on
    from d2spo.rollout import make_rollout

    cfg = TrainConfig(algo="d2spo", task="phi1", episodes=10, num_envs=2)
    cfg = dataclasses.replace(cfg, d2spo=dataclasses.replace(cfg.d2spo, pretrain=False))
    env0, params0, learner0 = learner_on(cfg, "random5:0", None)
    policy = jax.jit(lambda k: learner0.policy(learner0.init(k)))(jax.random.PRNGKey(0))  # jit: eager init is slow
    shared = make_rollout(learner0, env0, 2, 40)
    key = jax.random.PRNGKey(1)
    env4, params4, learner4 = learner_on(cfg, "random5:4", None)
    alone = make_rollout(learner4, env4, 2, 40)(params4, policy, key)
    for a, b in zip(alone, shared(params4, policy, key)):
        assert jnp.array_equal(a, b, equal_nan=True)
    # and the layouts really differ (else the check above could not fail)
    assert not jnp.array_equal(params0.geom.box_lo, params4.geom.box_lo)
    assert not jnp.array_equal(shared(params0, policy, key)[4], alone[4], equal_nan=True)


def test_the_carry_template_has_the_shapes_of_the_pretraining_init():
    """``run.carry_template`` traces ``init_template`` (no cautious start) for speed: it must give
    exactly the structure, shapes and dtypes of the ``init`` that pre-trains, or a checkpoint or a
    snapshot would load into the wrong template."""
    from d2spo.run import carry_template

    cfg = TrainConfig(algo="d2spo", task="F A1", env=EnvConfig(layout="relaxed"), episodes=10, num_envs=2).check()
    _, _, learner = build(cfg)
    assert learner.d2.pretrain
    full = jax.eval_shape(learner.init, jax.random.PRNGKey(3))
    template = carry_template(learner)
    assert jax.tree_util.tree_structure(template) == jax.tree_util.tree_structure(full)
    assert [(x.shape, x.dtype) for x in jax.tree_util.tree_leaves(template)] == \
        [(x.shape, x.dtype) for x in jax.tree_util.tree_leaves(full)]
    assert carry_template(learner) is template  # traced once per learner


def test_a_checkpoint_holds_the_d2spo_carry_as_one_flat_dict():
    """``D2SPOCarry`` holds a ``TD3Carry``; its checkpoint keeps the flat layout, in the order that
    older checkpoints hold it, and restores to the nested carry."""
    import numpy as np
    from flax import serialization

    cfg = TrainConfig(algo="d2spo", task="F A1", env=EnvConfig(layout="relaxed"), episodes=10, num_envs=2).check()
    _, _, learner = build(cfg)
    shapes = jax.eval_shape(learner.init, jax.random.PRNGKey(0))
    # numpy leaves: the check is about structure and bytes, and eager jnp would compile per leaf shape
    carry = jax.tree_util.tree_map(lambda s: (np.arange(s.size).reshape(s.shape) % 7).astype(s.dtype), shapes)
    state = serialization.to_state_dict(carry)
    assert list(state) == ["key", "env_state", "obs", "agent", "buffer", "safety", "data", "steps", "episodes"]
    assert list(state["agent"]) == list(serialization.to_state_dict(carry.td3.agent))
    back = serialization.from_bytes(jax.tree_util.tree_map(np.zeros_like, carry), serialization.to_bytes(carry))
    assert jax.tree_util.tree_structure(back) == jax.tree_util.tree_structure(carry)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(carry)))
    assert learner.policy(back)[0] is back.td3.agent.actor
