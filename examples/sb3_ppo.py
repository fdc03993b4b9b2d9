"""Stable-Baselines3 trains on d2spo/Nav-v0 with no glue code (torch is not a d2spo dependency).

    pip install d2spo stable-baselines3        # brings torch
    python examples/sb3_ppo.py --timesteps 30000

The env is made with ``gymnasium.make`` exactly as SB3 expects; the cost of each step is in
``info["cost"]`` (SB3 ignores it; a safe-RL learner would read it), and SB3's ``Monitor`` writes
its ``info["episode"]`` (r, l, t) without colliding with the env's own ``info["episode_stats"]``.
"""

from __future__ import annotations

import argparse
import sys

import gymnasium as gym
import numpy as np

try:
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
except ImportError:  # not a d2spo dependency: one line, not a traceback
    sys.exit("examples/sb3_ppo.py needs Stable-Baselines3 (and torch): pip install stable-baselines3")

import d2spo.envs  # noqa: F401  registers d2spo/Nav-v0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=30_000)
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes")
    args = parser.parse_args()

    env_kwargs = {"task": "F A1", "layout": "open", "max_steps": 80}
    vec_env = make_vec_env("d2spo/Nav-v0", n_envs=8, seed=0, env_kwargs=env_kwargs)
    model = PPO("MlpPolicy", vec_env, n_steps=128, batch_size=256, learning_rate=1e-3, seed=0, verbose=0)
    model.learn(total_timesteps=args.timesteps)

    env = gym.make("d2spo/Nav-v0", **env_kwargs)
    completed, costs = [], []
    for episode in range(args.episodes):
        obs, _ = env.reset(seed=episode)
        done, cost = False, 0.0
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            cost += info["cost"]
            done = terminated or truncated
        completed.append(info["completed"])
        costs.append(cost)
    print(f"task 'F A1' on 'open' after {args.timesteps} steps: completed {np.mean(completed):.0%} of "
          f"{args.episodes} episodes, mean cost {np.mean(costs):.2f}")


if __name__ == "__main__":
    main()
