"""
Collect the offline dataset of the CRR benchmark: the replay buffer of a partly trained SB3 SAC run on Hopper-v5
(a "medium-replay" style dataset: every transition the learner saw, from random to medium quality).

    OMP_NUM_THREADS=1 python benchmarks/speed/crr_collect.py --env Hopper-v5 --steps 40000 --max-minutes 13 \
        --output benchmarks/results/speed/crr_hopper_medium_replay.npz

Writes a d4rl-style ``.npz`` (actions in environment units) and a ``.json`` with the behaviour statistics:
mean return of the dataset's episodes and of the final SAC policy (deterministic, 10 episodes).
"""

import argparse
import json
import time

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_lifelong.core.datasets import replay_buffer_to_d4rl


class TimeLimit(BaseCallback):
    def __init__(self, seconds: float):
        super().__init__()
        self.deadline = time.time() + seconds

    def _on_step(self) -> bool:
        return time.time() < self.deadline


def episode_returns(data: dict) -> list[float]:
    ends = np.flatnonzero(data["terminals"] | data["timeouts"])
    returns: list[float] = []
    start = 0
    for end in ends:
        returns.append(float(data["rewards"][start : end + 1].sum()))
        start = int(end) + 1
    return returns


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--steps", type=int, default=40_000)
    parser.add_argument("--max-minutes", type=float, default=13.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default="benchmarks/results/speed/crr_hopper_medium_replay.npz")
    args = parser.parse_args()
    th.set_num_threads(1)
    start = time.time()
    env = Monitor(gym.make(args.env))
    model = SAC("MlpPolicy", env, learning_starts=5_000, seed=args.seed, verbose=0)
    model.learn(args.steps, callback=TimeLimit(args.max_minutes * 60 - 60))
    assert model.replay_buffer is not None and isinstance(env.action_space, gym.spaces.Box)
    assert model.replay_buffer is not None and isinstance(env.action_space, gym.spaces.Box)
    data = replay_buffer_to_d4rl(model.replay_buffer)
    low, high = env.action_space.low, env.action_space.high
    data["actions"] = low + (data["actions"] + 1.0) * 0.5 * (high - low)  # SB3 stores normalised actions
    np.savez_compressed(args.output, **data)  # type: ignore[arg-type]
    returns = episode_returns(data)
    result = evaluate_policy(model, Monitor(gym.make(args.env)), n_eval_episodes=10, deterministic=True)
    policy_mean, policy_std = float(result[0]), float(result[1])  # type: ignore[arg-type]
    stats = {
        "env": args.env,
        "collector": "SB3 SAC, default hyperparameters (256x256, batch 256)",
        "env_steps": int(model.num_timesteps),
        "transitions": len(data["rewards"]),
        "dataset_episodes": len(returns),
        "dataset_mean_return": float(np.mean(returns)),
        "dataset_last10_mean_return": float(np.mean(returns[-10:])),
        "behaviour_policy_return": float(policy_mean),
        "behaviour_policy_return_std": float(policy_std),
        "seconds": time.time() - start,
    }
    with open(args.output.replace(".npz", ".json"), "w") as file:
        json.dump(stats, file, indent=2)
    print(json.dumps(stats, indent=2))


if __name__ == "__main__":
    main()
