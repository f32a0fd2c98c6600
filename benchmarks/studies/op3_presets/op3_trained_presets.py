"""
How much each of the paper's OP3 presets hurts a policy trained on the default robot.

Trains PPO on ``sb3_lifelong/OP3Walk-v0`` (default robot) for a wall-clock budget, saving a checkpoint every
``--checkpoint-seconds``; then evaluates the last checkpoint zero-shot on the default robot and on every paper
preset (hip 0.2 / 0.3 rad, feet 1.2 / 1.6, ground 0.1): deterministic return, episode length and distance walked,
mean and standard deviation over ``--eval-episodes`` episodes with the same reset seeds on every robot.

PPO rather than MPO because on this 2-core CPU it turns one core-hour into the most experience (millions of env
steps rather than ~70k); the presets' effect is a property of the robot, not of the learner. The policy starts
with a small action noise (``log_std_init=-1``) so that it starts near the standing pose, and observations and
rewards are normalised (``VecNormalize``, frozen at evaluation).

Usage::

    OMP_NUM_THREADS=1 MENAGERIE_ROOT=../shared/menagerie python benchmarks/studies/op3_presets/op3_trained_presets.py \\
        --train-seconds 6000 --out benchmarks/studies/op3_presets/envs_op3_trained_ppo.md
    # evaluate an existing checkpoint only
    python benchmarks/studies/op3_presets/op3_trained_presets.py --eval-only --workdir benchmarks/studies/op3_presets/op3_ppo
"""

import argparse
import os
import sys
import time
from typing import Dict, List, Tuple

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

import sb3_lifelong.envs  # noqa: F401  (registers the env ids)
from sb3_lifelong.envs import NAMED_STAGES, OP3_WALK_ID, PAPER_STAGES, DynamicsSchedule


class WallClock(BaseCallback):
    """Stop after ``seconds`` of training; checkpoint model + normalisation statistics every ``every`` seconds."""

    def __init__(self, seconds: float, every: float, workdir: str):
        super().__init__()
        self.seconds, self.every, self.workdir = seconds, every, workdir
        self.start = self.last = 0.0

    def _on_training_start(self) -> None:
        self.start = self.last = time.perf_counter()

    def checkpoint(self) -> None:
        self.model.save(os.path.join(self.workdir, "model.zip"))
        env = self.model.get_env()
        assert isinstance(env, VecNormalize)
        env.save(os.path.join(self.workdir, "vecnormalize.pkl"))
        elapsed = time.perf_counter() - self.start
        print(f"checkpoint: {self.num_timesteps} steps after {elapsed:.0f} s", flush=True)

    def _on_step(self) -> bool:
        now = time.perf_counter()
        if now - self.last >= self.every:
            self.checkpoint()
            self.last = now
        return now - self.start < self.seconds

    def _on_training_end(self) -> None:
        self.checkpoint()


def train(args: argparse.Namespace) -> None:
    os.makedirs(args.workdir, exist_ok=True)
    venv = VecNormalize(make_vec_env(OP3_WALK_ID, n_envs=args.n_envs, seed=args.seed), gamma=0.99)
    model = PPO(
        "MlpPolicy",
        venv,
        n_steps=512,
        batch_size=512,
        n_epochs=10,
        learning_rate=3e-4,
        gamma=0.99,
        gae_lambda=0.95,
        clip_range=0.2,
        policy_kwargs=dict(log_std_init=-1.0, net_arch=dict(pi=[128, 128], vf=[128, 128])),
        tensorboard_log=os.path.join(args.workdir, "tensorboard"),
        seed=args.seed,
        verbose=0,
    )
    model.learn(10**9, callback=WallClock(args.train_seconds, args.checkpoint_seconds, args.workdir))


def evaluate(model: PPO, obs_rms: VecNormalize, params: Dict, episodes: int) -> Tuple[List[float], List[int], List[float]]:
    env = DynamicsSchedule(gym.make(OP3_WALK_ID), stages=[params])
    returns, lengths, distances = [], [], []
    for episode in range(episodes):
        obs, info = env.reset(seed=1000 + episode)
        x0 = info["x_position"]
        done, total, length = False, 0.0, 0
        while not done:
            action, _ = model.predict(obs_rms.normalize_obs(obs), deterministic=True)
            obs, reward, terminated, truncated, info = env.step(action)
            total += float(reward)
            length += 1
            done = terminated or truncated
        returns.append(total)
        lengths.append(length)
        distances.append(info["x_position"] - x0)
    env.close()
    return returns, lengths, distances


def report(args: argparse.Namespace) -> List[str]:
    model = PPO.load(os.path.join(args.workdir, "model.zip"), device="cpu")
    stats = VecNormalize.load(os.path.join(args.workdir, "vecnormalize.pkl"), make_vec_env(OP3_WALK_ID, n_envs=1))
    stats.training = False
    lines = [
        "## OP3 presets vs a policy trained on the default robot\n",
        f"PPO, {model.num_timesteps} env steps on the default robot ({args.train_seconds:.0f} s wall-clock budget, "
        f"{args.n_envs} envs in one process, 1 torch thread, seed {args.seed}; hyperparameters in "
        "`benchmarks/studies/op3_presets/op3_trained_presets.py`). Zero-shot on each preset, deterministic actions, "
        f"{args.eval_episodes} episodes with reset seeds 1000+ (the same on every robot); mean ± std.\n",
        "| robot | return | change | episode length | distance walked (m) | change |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    base_r = base_d = None
    for name in ["default", *PAPER_STAGES]:
        r, n, dist = evaluate(model, stats, NAMED_STAGES[name], args.eval_episodes)
        mr, md = float(np.mean(r)), float(np.mean(dist))
        if base_r is None:
            base_r, base_d = mr, md
            rel_r = rel_d = ""
        else:
            rel_r = f"{100 * (mr - base_r) / abs(base_r):+.1f} %"
            rel_d = f"{100 * (md - base_d) / max(abs(base_d), 1e-9):+.1f} %"
        lines.append(
            f"| {name} | {mr:.1f} ± {np.std(r):.1f} | {rel_r} | {np.mean(n):.0f} | {md:.2f} ± {np.std(dist):.2f} | {rel_d} |"
        )
        print(lines[-1], flush=True)
    lines.append(f"\nCommand: `{' '.join(['python', *sys.argv])}`\n")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train-seconds", type=float, default=6000.0)
    parser.add_argument("--checkpoint-seconds", type=float, default=600.0)
    parser.add_argument("--n-envs", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--workdir", type=str, default="benchmarks/studies/op3_presets/op3_ppo")
    parser.add_argument("--eval-only", action="store_true")
    parser.add_argument("--out", type=str, default=None, help="markdown file for the table")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if not args.eval_only:
        train(args)
    lines = report(args)
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)


if __name__ == "__main__":
    main()
