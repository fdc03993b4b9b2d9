"""ZoneEnv's six finite-horizon tasks and its infinite-horizon ones (DeepLTL's tables), zero-shot, for d2spo generalists.

    python bench/zones.py --runs RUNS                    # train seeds 0, 1, 2 (defaults) unless there, then evaluate
    python bench/zones.py --runs RUNS --seeds 0 --episodes 100 --out /tmp/zones
    python bench/zones.py --quick --runs /tmp/zq         # a check of the script: a tiny training, 8 episodes

Beside the generalists, ``PathFollower``: a controller with no learning that steers along the
observation's path direction, on the same layouts, limits and key. It scores about as the
generalists do (bench/RESULTS.md, "2026-12-02, evening"): the observation carries a planner's answer,
so these tables show what d2spo's task shaping solves, not a policy that reads formulas better
than DeepLTL's, whose agent plans for itself (README, "What these ZoneEnv figures measure").

For each seed, one generalist trained with the defaults (``d2spo train --algo d2spo --generalist
--task phi1 --seed S``; RUNS/gen-sS, reused when its summary.json is there) is evaluated on each
task for ``--episodes`` episodes, each on a zones layout of its own (``zones:SEED`` for SEED =
1000000 + i: ZoneEnv's conventions, docs/layouts.md), π_Ω alone and with the runtime filter,
seeing a forbidden zone as ``d2spo eval`` does by default (within the robot's lidar range for a
generalist trained without ``--forbidden-range``; the default since 2026-12-03, docs/config.md).
Per task and seed: success (completed without a collision), mean steps of the successful episodes,
collision rate. The episode limit is d2spo's time rule (the longest a specialist would get on the
first 20 layouts, and at least the generalist's own slot limit), never more than ZoneEnv's 1000.

Writes OUT/zones.json (every figure), OUT/zones.md (the table beside the published success rates),
OUT/zones-success.png (success per task beside DeepLTL, GCRL-LTL, LTL2Action) and
OUT/zones-trajectories.png (episodes on four drawn layouts).

The infinite-horizon tasks (``INFINITE``) run ZoneEnv's full 1000 steps per episode and are scored
as DeepLTL scores them, by accepting visits per episode, and against what a perfect robot of ours
could make on each drawn layout in those steps (the route-optimal visits, ``CompiledTask.optimal_visits``):
DeepLTL's point robot and d2spo's unicycle cover different distances in a step, so the visit counts
alone do not compare; the fraction of the route-optimal count is ours, robot for robot. ``FG blue``
(DeepLTL's persistence task, no deterministic Büchi automaton) is tried and reported as d2spo
answers it (refused in one line: docs/ltl.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

TASKS = (
    "F (green & (!blue U yellow)) & F magenta",
    "(F blue) & (!blue U (green & F yellow))",
    "F (blue | green) & F yellow & F magenta",
    "!(magenta | yellow) U (blue & F green)",
    "!green U ((blue | magenta) & (!green U yellow))",
    "((green | blue) => (!yellow U magenta)) U yellow",
)
REFERENCE = {  # success rates: DeepLTL, GCRL-LTL, LTL2Action (ZoneEnv, finite-horizon tasks)
    TASKS[0]: (0.922, 0.852, 0.595),
    TASKS[1]: (0.912, 0.847, 0.142),
    TASKS[2]: (0.962, 0.892, 0.667),
    TASKS[3]: (0.901, 0.872, 0.690),
    TASKS[4]: (0.912, 0.851, 0.660),
    TASKS[5]: (0.978, 0.894, 0.930),
}
METHODS = ("DeepLTL", "GCRL-LTL", "LTL2Action")
INFINITE = ("GF blue & GF green", "GF blue & GF green & GF yellow & G !magenta")
REFERENCE_VISITS = {  # accepting visits per 1000-step episode: DeepLTL, GCRL-LTL (SOURCE_INFINITE)
    INFINITE[0]: (4.16, 3.14),
    INFINITE[1]: (1.71, 1.31),
}
PERSISTENCE = "FG blue"
REFERENCE_PERSISTENCE = (562.8, 265.5)
"""``FG blue``: steps in the accepting set per 1000-step episode, DeepLTL and GCRL-LTL."""
SOURCE_INFINITE = ("DeepLTL (ICLR 2025), its table of ZoneEnv's infinite-horizon tasks, as d2spo's issue 34 "
                   "quotes it (no results file of these was in the copy of the repository searched)")
SOURCE = ("DeepLTL's results file results/PointLtl2-v0.csv (columns method, task, seed, success_rate, "
          "mean_steps; 5 seeds x 500 episodes, 1000-step episodes), read in the copy of the DeepLTL "
          "repository at github.com/mattiagiuri/ltl_gnn, commit d72036752a47576bbe7c45e3e015d51015c35791 "
          "(the original repository was not in the index searched); the rates are the means of its 5 seeds")
ZONE_SEED = 1_000_000
"""First ``zones:SEED`` of the evaluation (training draws its zones from ``world:SEED``'s own stream)."""
ZONE_ENV_LIMIT = 1000
"""ZoneEnv's episode limit: ours is never more."""
LIMIT_SAMPLE = 20
"""Layouts whose specialist step limit sets the episode limit."""


def train_seed(runs: Path, seed: int, quick: bool) -> Path:
    from d2spo.config import TrainConfig
    from d2spo.progress import train_with_progress

    out = runs / f"gen-s{seed}"
    if (out / "summary.json").is_file():
        return out
    extra = dict(episodes=64, generalist_layouts=8, validation_layouts=0, eval_episodes=0) if quick else {}
    cfg = TrainConfig(algo="d2spo", generalist=True, task="phi1", seed=seed, **extra)
    resume = out if (out / "checkpoint.json").is_file() else None  # an interrupted training goes on
    train_with_progress(cfg, out, resume, show=True)
    return out


def _on_layouts(cfg, task: str, filt: bool, layouts: list, limit: int, bank=None):
    """(env, params viewing the bank of ``layouts``, learner, bank): the generalist trained with
    ``cfg``, built for ``task`` alone (one task, pairings 1, as ``zero_shot`` builds it) with the
    runtime filter on or off; ``bank`` (that of another mode) is reused when given."""
    from d2spo.algos.generalist import build_generalist
    from d2spo.envs.generalist import view
    from d2spo.zero_shot import seen_forbidden_range

    c = dataclasses.replace(cfg, task=task, generalist_tasks=0, generalist_patrols=0, generalist_pairings=1,
                            env=seen_forbidden_range(cfg.env),  # as d2spo eval sees a forbidden area
                            d2spo=dataclasses.replace(cfg.d2spo, runtime_filter=filt))
    env, params, learner = build_generalist(c, layouts[:1], limit)
    bank = env.bank(layouts, max_steps=limit) if bank is None else bank
    return env, view(params.replace(bank=bank), jnp.zeros((), jnp.int32)), learner, bank


class PathFollower:
    """The reference with no learning: a controller that reads only the observation's ``target``
    (the direction, in the robot's frame, in which the path to the nearest area that makes progress
    falls fastest: docs/env.md, "The generalist") and steers along it, turn rate twice the angle to
    it, clipped; full speed ahead, or backwards at 0.6 while the direction is more than 1 rad off.
    What the observation alone solves: the learned policy is worth what it adds to this. Acts where
    a learner does (``rollout.make_rollout``); its ``policy`` argument is unused."""

    def __init__(self, env):
        sl = env.observation_slices["target"]
        self.forward, self.left = sl.start + 1, sl.start + 2  # (path length, forward, left, any)
        self.params = None

    def act(self, policy, obs, env_state, key):
        angle = jnp.arctan2(obs[self.left], obs[self.forward])
        speed = jnp.where(jnp.abs(angle) > 1.0, -0.6, 1.0)
        return jnp.stack([speed, jnp.clip(2.0 * angle, -1.0, 1.0)])


def _follow(env, episodes: int, limit: int, params) -> tuple:
    """``make_rollout``'s arrays for the ``PathFollower`` on ``params`` (key 7, as the policy's)."""
    from d2spo.rollout import make_rollout

    return tuple(np.asarray(a) for a in make_rollout(PathFollower(env), env, episodes, limit, slot_per_episode=True)(
        params, None, jax.random.PRNGKey(7)))


def evaluate_seed(run: Path, episodes: int, keep_paths: int) -> dict:
    from d2spo.envs import layout_bank
    from d2spo.envs.task_plan import slot_max_steps
    from d2spo.envs.zones import zones_layout
    from d2spo.rollout import make_rollout
    from d2spo.run import load_policy
    from d2spo.zero_shot import generalist_layout

    cfg, _, policy, meta = load_policy(run)
    layouts = [zones_layout(ZONE_SEED + i) for i in range(episodes)]
    for lay in layouts:
        layout_bank.check_fits(lay)
    out = {"policy": meta["policy"], "tasks": {}}
    for task in TASKS:
        needs = [generalist_layout(cfg.env, lay.name, task)[1] for lay in layouts[:LIMIT_SAMPLE]]
        limit = min(ZONE_ENV_LIMIT, max([cfg.env.max_steps or slot_max_steps(layouts[0])] + needs))
        per, bank = {"max_steps": limit}, None
        for filt in (False, True):
            env, params, learner, bank = _on_layouts(cfg, task, filt, layouts, limit, bank)  # one bank for both modes
            run = make_rollout(learner, env, episodes, limit, slot_per_episode=True)
            t = time.perf_counter()
            collided, completed, _, length, poses = (np.asarray(a) for a in run(params, policy, jax.random.PRNGKey(7)))
            ok = completed & ~collided
            per["filter" if filt else "pi_omega"] = {
                "success_rate": float(ok.mean()), "collision_rate": float(collided.mean()),
                "completion_rate": float(completed.mean()),
                "mean_steps_to_success": float(length[ok].mean()) if ok.any() else None,
                "episodes": int(episodes), "seconds": round(time.perf_counter() - t, 1)}
            if filt and keep_paths:
                per["paths"] = [(layouts[i], poses[i:i + 1], collided[i:i + 1], completed[i:i + 1])
                                for i in range(keep_paths)]
        collided, completed, _, length, _ = _follow(env, episodes, limit, params)
        ok = completed & ~collided
        per["path_follower"] = {"success_rate": float(ok.mean()), "collision_rate": float(collided.mean()),
                                "mean_steps_to_success": float(length[ok].mean()) if ok.any() else None}
        out["tasks"][task] = per
    return out


def evaluate_infinite(run: Path, episodes: int) -> dict:
    """The ``INFINITE`` tasks over ZoneEnv's 1000 steps, one drawn zones layout per episode, π_Ω
    alone and with the filter: accepting visits per episode, and the route-optimal visits on the
    same layouts; then how d2spo answers ``PERSISTENCE``."""
    from d2spo.envs.compiled_task import compile_task
    from d2spo.envs.zones import zones_layout
    from d2spo.errors import UserError
    from d2spo.rollout import make_rollout, visit_optimum
    from d2spo.run import load_policy
    from d2spo.zero_shot import generalist_layout

    cfg, _, policy, meta = load_policy(run)
    layouts = [zones_layout(ZONE_SEED + i) for i in range(episodes)]
    limit = ZONE_ENV_LIMIT
    out = {"policy": meta["policy"], "max_steps": limit, "tasks": {}}
    for task in INFINITE:
        per, bank, optimum = {}, None, None
        for filt in (False, True):
            env, params, learner, bank = _on_layouts(cfg, task, filt, layouts, limit, bank)
            if optimum is None:
                res = env.config
                optimum = np.array([visit_optimum(compile_task(env.automaton, lay, res.label_mode, res.robot_radius),
                                                  limit, res, None)["route_optimal_visits"] for lay in layouts], float)
            t = time.perf_counter()
            collided, *_, visits = (np.asarray(a) for a in make_rollout(learner, env, episodes, limit,
                                                                          slot_per_episode=True)(
                params, policy, jax.random.PRNGKey(7)))
            per["filter" if filt else "pi_omega"] = {
                "visits_per_episode": float(visits.mean()), "collision_rate": float(collided.mean()),
                "visit_fraction": float(visits.sum() / optimum.sum()),
                "episodes": int(episodes), "seconds": round(time.perf_counter() - t, 1)}
        collided, *_, visits = _follow(env, episodes, limit, params)
        per["path_follower"] = {"visits_per_episode": float(visits.mean()), "collision_rate": float(collided.mean()),
                                "visit_fraction": float(visits.sum() / optimum.sum())}
        per["route_optimal_visits"] = float(optimum.mean())
        out["tasks"][task] = per
    try:
        generalist_layout(cfg.env, layouts[0].name, PERSISTENCE)
        out[PERSISTENCE] = "accepted"
    except UserError as e:
        out[PERSISTENCE] = f"refused: {e}"
    return out


def infinite_table(results: dict, seeds: list[int]) -> str:
    """The markdown table of the ``INFINITE`` tasks (means over seeds) and the ``PERSISTENCE`` row."""
    lines = ["| task | visits π_Ω | visits + filter | no learning (`PathFollower`) | route-optimal | "
             "of the route-optimal (filter) | collisions π_Ω / filter | DeepLTL | GCRL-LTL |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]

    def mean(task, mode, key):
        return float(np.mean([results[s]["tasks"][task][mode][key] for s in seeds]))

    for task in INFINITE:
        best = float(np.mean([results[s]["tasks"][task]["route_optimal_visits"] for s in seeds]))
        lines.append(f"| `{task}` | {mean(task, 'pi_omega', 'visits_per_episode'):.2f} | "
                     f"{mean(task, 'filter', 'visits_per_episode'):.2f} | "
                     f"{mean(task, 'path_follower', 'visits_per_episode'):.2f} | {best:.2f} | "
                     f"{mean(task, 'filter', 'visit_fraction'):.1%} | {mean(task, 'pi_omega', 'collision_rate'):.1%} / "
                     f"{mean(task, 'filter', 'collision_rate'):.1%} | "
                     + " | ".join(f"{r:.2f}" for r in REFERENCE_VISITS[task]) + " |")
    answer = results[seeds[0]][PERSISTENCE]
    lines.append(f"| `{PERSISTENCE}` (steps in the accepting set) | {answer} | | | | | | "
                 + " | ".join(f"{r:.1f}" for r in REFERENCE_PERSISTENCE) + " |")
    return "\n".join(lines)


def table(results: dict, seeds: list[int]) -> tuple[str, dict]:
    """The markdown table (mean over seeds, min-max in brackets) and the means per task and mode."""
    lines = ["| task | d2spo π_Ω | d2spo + filter | steps (filter) | collisions π_Ω / filter | no learning "
             "(`PathFollower`), steps | " + " | ".join(METHODS) + " |", "|---|---:|---:|---:|---:|---:|" + "---:|" * len(METHODS)]
    means = {}
    for task in TASKS:
        row = {}
        for mode in ("pi_omega", "filter"):
            vals = [results[s]["tasks"][task][mode] for s in seeds]
            row[mode] = {k: float(np.mean([v[k] for v in vals])) for k in ("success_rate", "collision_rate")}
            row[mode]["range"] = (min(v["success_rate"] for v in vals), max(v["success_rate"] for v in vals))
            steps = [v["mean_steps_to_success"] for v in vals if v["mean_steps_to_success"] is not None]
            row[mode]["steps"] = float(np.mean(steps)) if steps else None
        means[task] = row

        def cell(mode):
            m, (lo, hi) = row[mode]["success_rate"], row[mode]["range"]
            return f"{m:.3f}" + (f" [{lo:.3f}-{hi:.3f}]" if len(seeds) > 1 else "")

        steps = row["filter"]["steps"]
        follow = [results[s]["tasks"][task]["path_follower"] for s in seeds]  # the same layouts for every seed
        f_steps = follow[0]["mean_steps_to_success"]
        lines.append(f"| `{task.replace('|', chr(92) + '|')}` | {cell('pi_omega')} | {cell('filter')} | "
                     f"{'—' if steps is None else f'{steps:.0f}'} | {row['pi_omega']['collision_rate']:.1%} / "
                     f"{row['filter']['collision_rate']:.1%} | {follow[0]['success_rate']:.3f}, "
                     f"{'—' if f_steps is None else f'{f_steps:.0f}'} | "
                     + " | ".join(f"{r:.3f}" for r in REFERENCE[task]) + " |")
    return "\n".join(lines), means


def success_figure(means: dict, path: Path) -> None:
    from matplotlib.figure import Figure

    from d2spo.plotstyle import PALETTE, save_figure

    fig = Figure(figsize=(10.0, 4.4), layout="constrained")
    ax = fig.subplots()
    names = ["d2spo π_Ω", "d2spo + filter", *METHODS]
    x = np.arange(len(TASKS))
    w = 0.8 / len(names)
    for k, name in enumerate(names):
        vals = ([means[t]["pi_omega"]["success_rate"] for t in TASKS] if k == 0 else
                [means[t]["filter"]["success_rate"] for t in TASKS] if k == 1 else
                [REFERENCE[t][k - 2] for t in TASKS])
        ax.bar(x + (k - (len(names) - 1) / 2) * w, vals, w, label=name, color=PALETTE[k % len(PALETTE)])
    ax.set_xticks(x, [f"task {i + 1}" for i in range(len(TASKS))])
    ax.set_ylabel("success rate (completed, no collision)")
    ax.set_ylim(0.0, 1.05)
    ax.set_title("ZoneEnv's six finite tasks, zones drawn anew every episode (references: published rates)")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncols=len(names))
    save_figure(fig, path, "figure")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, required=True, help="where the generalists are (or are trained)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--episodes", type=int, default=500, help="episodes per task, seed and mode (one layout each)")
    ap.add_argument("--out", type=Path, default=Path("bench/zones"))
    ap.add_argument("--quick", action="store_true", help="a tiny training and 8 episodes: a check of the script")
    args = ap.parse_args()
    from d2spo import compile_cache

    compile_cache.enable()  # the commands' cache: a second seed or mode of the same program compiles nothing
    if args.quick:
        args.seeds, args.episodes = args.seeds[:1], 8
    args.out.mkdir(parents=True, exist_ok=True)
    results, paths = {}, None
    for seed in args.seeds:
        run = train_seed(args.runs, seed, args.quick)
        res = evaluate_seed(run, args.episodes, keep_paths=4 if paths is None else 0)
        if paths is None:
            paths = res["tasks"][TASKS[0]].pop("paths")
        for task in TASKS:
            res["tasks"][task].pop("paths", None)
        res["infinite"] = evaluate_infinite(run, args.episodes)
        results[seed] = res
        print(json.dumps({"seed": seed, **{t: res["tasks"][t] for t in TASKS}, "infinite": res["infinite"]}))
    text, means = table(results, args.seeds)
    machine = f"{platform.machine()}, {platform.processor() or 'cpu'}, jax {jax.__version__} on {jax.default_backend()}"
    head = (f"{datetime.date.today()}, {machine}; seeds {args.seeds}, {args.episodes} episodes per task, seed and "
            f"mode, zones:{ZONE_SEED}.. (one layout per episode). References: {SOURCE}.")
    inf = infinite_table({s: r["infinite"] for s, r in results.items()}, args.seeds)
    head_inf = (f"ZoneEnv's infinite-horizon tasks: {ZONE_ENV_LIMIT}-step episodes, the same layouts; visits are "
                f"accepting visits per episode (means over seeds). References: {SOURCE_INFINITE}.")
    (args.out / "zones.md").write_text(head + "\n\n" + text + "\n\n" + head_inf + "\n\n" + inf + "\n")
    (args.out / "zones.json").write_text(json.dumps({"seeds": args.seeds, "episodes": args.episodes,
                                                     "results": {str(s): r for s, r in results.items()},
                                                     "reference": REFERENCE, "source": SOURCE}, indent=1))
    success_figure(means, args.out / "zones-success.png")
    from d2spo.plots import evaluation_figure

    evaluation_figure(args.out / "zones-trajectories.png", paths,
                      [{"completion_rate": float(c[0]), "safety_rate": float(1 - k[0]), "episodes": 1}
                       for _, _, k, c in paths], f"d2spo generalist (seed {args.seeds[0]}) + filter on "
                      f"task 1: {TASKS[0]}")
    print(head)
    print(text)
    print(head_inf)
    print(inf)


if __name__ == "__main__":
    main()
