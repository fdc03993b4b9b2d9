"""`make demo`: the paper's tasks as automata, then a short D²SPO training that ends with a
summary table and a picture (trajectories of the trained policy and its learned barrier).

The short run is D²SPO on the `relaxed` layout with the task F A1 ("eventually reach A1"), 500
episodes, `--fast` (32 envs, 64-64 TD3 networks) and two TD3 updates per vectorised step: under a
minute on 2 CPU cores (under 20 s once the compilation cache holds its programs), and the policy
reaches A1 without a collision. The full tasks (relaxed ϕ1, ϕ1) need the paper's 20000 episodes:
`d2spo reproduce table2 table3`.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from rich.console import Console
from rich.table import Table

from d2spo.algos.td3 import TD3Config
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig, layouts, make_env
from d2spo.errors import RunInUseError
from d2spo.ltl import TASKS, translate
from d2spo.ltl.tasks import BUCHI_SUITE
from d2spo.progress import train_with_progress
from d2spo.run import load_policy
from d2spo.runio import make_run_dir, run_holder


def random_rollout(layout: str, steps: int, seed: int, task: str | None = None,
                   label_mode: str = "event") -> np.ndarray:
    """Positions [T, 2] of one env driven by uniform random actions until its first episode ends.

    The default task is to reach the layout's last area's label, which every layout can express;
    ``label_mode`` is the labelling whose letters the task reads (``EnvConfig.label_mode``).
    """

    if task is None:
        task = f"F {layouts.load(layout).areas[-1].label}"
    env, params = make_env(EnvConfig(layout=layout, label_mode=label_mode), task=task)

    def body(carry, key):
        state, alive = carry
        k_act, k_step = jax.random.split(key)
        action = jax.random.uniform(k_act, (env.action_size,), minval=-1.0, maxval=1.0)
        state, _, _, _, done, info = env.step(k_step, state, action, params)
        return (state, alive & ~done), (info["next_pose"], alive)

    key = jax.random.PRNGKey(seed)
    state, _ = env.reset(key, params)
    keys = jax.random.split(jax.random.fold_in(key, 1), steps)
    _, (poses, alive) = jax.jit(lambda s, k: jax.lax.scan(body, (s, jnp.bool_(True)), k))(state, keys)
    poses, alive = np.asarray(poses), np.asarray(alive)
    start = np.asarray(state.pose)[None, :2]
    return np.concatenate([start, poses[alive, :2]], axis=0)


DEMO_TASK = "F A1"


def run_demo(out: Path, seed: int = 0, episodes: int = 500) -> int:
    """The paper's tasks as automata, then a short D²SPO training (see the module docstring), a
    summary table and a picture of the trained policy with its learned barrier function."""


    console = Console()
    out = Path(out)
    make_run_dir(out)  # a file in the way: one line, exit 2
    paper = layouts.load("paper")
    table = Table(title="The paper's tasks as automata (distances on the 'paper' layout)")
    for col in ("task", "formula", "states", "area visits needed"):
        table.add_column(col)
    for name, formula in TASKS.items():
        if name in BUCHI_SUITE:  # no good prefix: not monitors (docs/ltl.md)
            continue
        aut = translate(formula)
        dist = aut.distances(layouts.feasible_letters(paper, aut.aps, "event"))
        table.add_row(name, formula, str(len(aut.delta)), str(dist[aut.initial]))
    console.print(table)

    run = out / "d2spo-relaxed"
    if run.exists():  # the last demo's run, unless a demo is training it now
        holder = run_holder(run)
        if holder is not None:
            raise RunInUseError(f"{run}: in use by another training ({holder}); wait for it to end, or use another --out")
        shutil.rmtree(run)
    cfg = TrainConfig(algo="d2spo", task=DEMO_TASK, episodes=episodes, seed=seed, window=min(200, episodes),
                      eval_episodes=50, env=EnvConfig(layout="relaxed"), fast=True,
                      td3=dataclasses.replace(TD3Config(), updates_per_step=2))
    console.print(f"[bold]Training D²SPO on layout 'relaxed', task {DEMO_TASK!r}, for {episodes} episodes[/bold] "
                  "(the paper's protocol is 20000 episodes; `d2spo reproduce table3` runs it)")
    rc = train_with_progress(cfg, run, None, show=True)
    if rc != 0:
        return rc
    cfg, learner, policy, _ = load_policy(run)
    env, params = learner.env, learner.params  # the run's env, as load_policy built it
    picture = out / "d2spo_relaxed.png"
    from d2spo.plots import policy_figure  # matplotlib: imported only to draw

    policy_figure(picture, learner, policy, env, params, episodes=8, seed=seed,
                  suptitle=f"D²SPO after {episodes} episodes: layout {env.layout.name!r}, task {DEMO_TASK!r}")
    console.print(f"picture: {picture}")
    return 0
