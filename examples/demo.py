"""
End-to-end demo: train MPO on a small MuJoCo task, evaluate it along the way, and leave behind
tensorboard logs, an evaluation CSV, a learning-curve plot and the trained model.

Usage::

    python examples/demo.py --output demo_output            # a few minutes on 2 CPU cores
    tensorboard --logdir demo_output/tensorboard
"""

import argparse
import csv
import pathlib
import time

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_lifelong import MPO


class EvalToCSV(BaseCallback):
    """Evaluate the deterministic policy every ``eval_freq`` steps; log to tensorboard and a CSV file."""

    def __init__(self, eval_env: gym.Env, eval_freq: int, csv_path: pathlib.Path, n_eval_episodes: int = 5):
        super().__init__()
        self.eval_env = eval_env
        self.eval_freq = eval_freq
        self.csv_path = csv_path
        self.n_eval_episodes = n_eval_episodes
        self.rows: list[tuple[int, float, float]] = []

    def _on_step(self) -> bool:
        if self.num_timesteps % self.eval_freq == 0:
            mean, std = evaluate_policy(self.model, self.eval_env, n_eval_episodes=self.n_eval_episodes, deterministic=True)
            self.rows.append((self.num_timesteps, float(mean), float(std)))
            self.logger.record("eval/mean_reward", mean)
            with open(self.csv_path, "w", newline="") as handle:
                writer = csv.writer(handle)
                writer.writerow(["timesteps", "mean_reward", "std_reward"])
                writer.writerows(self.rows)
        return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--output", default="demo_output", help="directory for the logs, the plot and the model")
    parser.add_argument("--env", default="InvertedPendulum-v5", help="gymnasium id of the task")
    parser.add_argument("--steps", type=int, default=8000, help="environment steps of training")
    parser.add_argument("--eval-freq", type=int, default=1000, help="evaluation period, in environment steps")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    args = parser.parse_args()
    th.set_num_threads(1)
    out = pathlib.Path(args.output)
    out.mkdir(parents=True, exist_ok=True)

    model = MPO(
        "MlpPolicy",
        args.env,
        learning_starts=1000,
        batch_size=128,
        policy_kwargs=dict(net_arch=[128, 128]),
        tensorboard_log=str(out / "tensorboard"),
        seed=args.seed,
        verbose=0,
    )
    callback = EvalToCSV(Monitor(gym.make(args.env)), args.eval_freq, out / "eval.csv")
    start = time.perf_counter()
    model.learn(args.steps, callback=callback, tb_log_name="MPO_demo", progress_bar=True)
    elapsed = time.perf_counter() - start
    model.save(out / "mpo_demo")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps, means, stds = (np.array(column) for column in zip(*callback.rows))
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(steps, means, marker="o", label="MPO")
    ax.fill_between(steps, means - stds, means + stds, alpha=0.2)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("evaluation return")
    ax.set_title(f"MPO on {args.env}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "learning_curve.png", dpi=100)

    print(f"\n| steps | eval return (mean +- std, {callback.n_eval_episodes} episodes) |")
    print("| --- | --- |")
    for step, mean, std in callback.rows:
        print(f"| {step} | {mean:.1f} +- {std:.1f} |")
    print(f"\ntrained {args.steps} steps in {elapsed:.0f} s ({args.steps / elapsed:.0f} steps/s)")
    print(f"outputs in {out}/: learning_curve.png, eval.csv, mpo_demo.zip, tensorboard/")


if __name__ == "__main__":
    main()
