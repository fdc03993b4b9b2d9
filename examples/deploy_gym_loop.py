"""Drive an exported policy (`d2spo export`) from a Gymnasium loop, as a robot's control loop would.

    d2spo export runs/d2spo-phi1-paper-s0 --out exported/phi1
    python examples/deploy_gym_loop.py exported/phi1 --episodes 3            # or a run directory

The policy acts through ``d2spo.deploy`` (numpy only): each step it is given what a robot has, the
lidar ranges, the pose and the automaton state it keeps itself (``TaskTracker``), never the
simulator's state. The simulator here is d2spo's Gymnasium env (``d2spo/Nav-v0``, docs/env.md);
its observation stands in for the robot's sensors: its lidar part times H is the scan, and its
pose part gives the pose (on a robot: the localisation's, in the layout's frame). The comments
marked ROS 2 say where a node would make each call (docs/deploy.md, "A ROS 2 node").
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np

import d2spo.envs  # noqa: F401  registers d2spo/Nav-v0
from d2spo.config import config_from_dict
from d2spo.deploy import Policy
from d2spo.errors import ArtefactError, UserError


def load_policy(path: Path) -> Policy:
    """The policy of an export directory, or of a run directory exported into a temporary directory
    that is removed once the policy is loaded (it reads its weights into memory)."""
    if (path / "manifest.json").is_file():
        return Policy.load(path)
    if not path.exists():  # an export not written yet (e.g. robot/phi1, or RUN/export): say how to write it
        run = next((p for p in path.parents if (p / "config.json").is_file()), None)  # RUN/export: RUN
        raise ArtefactError(f"{path}: no such export or run directory; "
                            + (f"the run {run} has no export there: `d2spo export {run} --out {path}` writes one"
                               if run else f"`d2spo export RUN --out {path}` writes one from the run directory RUN")
                            + " (or give the run directory itself)")
    from d2spo.export import export_run  # a run directory: export it first (this needs JAX; a robot does not)

    with tempfile.TemporaryDirectory(prefix="d2spo-export-") as tmp:
        out = Path(tmp) / path.name
        export_run(path, out)
        return Policy.load(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", type=Path, help="an export directory (d2spo export) or a run directory")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--filter", choices=("default", "on", "off"), default="default",
                        help="the runtime filter (D²SPO): as exported, on, or off")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.episodes < 1:
        parser.exit(2, f"{parser.prog}: error: --episodes must be >= 1, got {args.episodes}\n")

    # ROS 2: in the node's __init__: load the policy once and make the tracker of the task's state.
    try:
        policy = load_policy(args.path)
    except UserError as e:  # not an export nor a run, damaged, ...: one line, as the d2spo commands say it
        parser.exit(2, f"{parser.prog}: error: {e}\n")
    task = policy.task_tracker()
    use_filter = None if args.filter == "default" else args.filter == "on"
    if use_filter and policy.runtime_filter is None:
        parser.exit(2, f"{parser.prog}: error: --filter on: this policy has no runtime filter (only D²SPO's has one)\n")
    m = policy.manifest
    cfg = config_from_dict(m["config"])
    # max_episode_steps=-1: no TimeLimit of the spec's 300 steps; the env ends an episode at its own
    # limit, which a long route or a patrol raises (docs/env.md), as d2spo eval does
    env = gym.make("d2spo/Nav-v0", task=cfg.task, config=cfg.env_config(), max_episode_steps=-1)
    patrol = policy.automaton.visit is not None  # a Büchi task: never finished, scored by its visits
    lidar = policy.parts["lidar"]  # where the observation holds the scan (the manifest's observation.parts)

    def sensors(obs):
        """What the robot measures: the ranges (m) and the pose. ROS 2: the /scan callback keeps the
        latest LaserScan, resampled to the K rays of the manifest's ``sensor`` (ray k at heading +
        2πk/K, counter-clockwise), and the pose comes from tf (map -> base_link) in the layout's frame."""
        return obs[lidar] * policy.H, policy.pose_of_observation(obs)

    results = []
    for episode in range(args.episodes):
        obs, _ = env.reset(seed=args.seed + episode)
        ranges, pose = sensors(obs)
        task.reset(pose[0], pose[1])  # ROS 2: when the mission starts, at the robot's pose
        steps, done, collided, completed, mismatches, env_visits = 0, False, False, False, 0, 0
        while not done:
            # ROS 2: a timer at 1/dt (the manifest's action.dt) runs these three lines and publishes
            # Twist(linear.x=v, angular.z=omega) on /cmd_vel.
            u = policy.act(ranges, pose, task.q, filter=use_filter)
            v, omega = policy.command(u)
            obs, _, terminated, truncated, info = env.step(u)  # the robot moves
            ranges, pose = sensors(obs)
            task.update(pose[0], pose[1])  # ROS 2: after each step, from the new pose
            mismatches += task.q != info["q_next"]  # the env's own automaton state, for this check only
            env_visits += info.get("accepting_visit", False)  # and its own count of a patrol's visits
            steps += 1
            done = terminated or truncated
            collided, completed = collided or info["collided"], completed or info["completed"]
        results.append((collided, completed, steps, task.visits))
        outcome = (f"{task.visits} accepting visits" + ("" if task.visits == env_visits else f" (the env counted {env_visits})")
                   if patrol else "completed" if completed else "not completed")
        print(f"episode {episode}: {steps} steps, {'collided' if collided else 'safe'}, "
              f"{outcome} (last command v={v:.2f} m/s, omega={omega:.2f} rad/s"
              f"{'' if not mismatches else f'; automaton state differed from the env in {mismatches} steps'})")
    collided, completed, steps, visits = map(np.array, zip(*results))
    filt = "none" if policy.runtime_filter is None else ("on" if (policy.filter_on if use_filter is None else use_filter)
                                                 else "off")
    scores = {"visits_per_episode": float(visits.mean())} if patrol else {"completion_rate": float(completed.mean())}
    print(json.dumps({"episodes": len(results), "safety_rate": float(1 - collided.mean()), **scores,
                      "mean_length": float(steps.mean()), "runtime_filter": filt}))


if __name__ == "__main__":
    main()
