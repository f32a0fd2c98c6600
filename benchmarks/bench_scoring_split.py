"""
The bf16 scoring pass with the first layer split into a per-state and a per-sample product, against the stacked
product and the exact float32 pass, interleaved in one process (20 samples x 256 states, 256x256 critic).

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_scoring_split.py --rounds 7
    OMP_NUM_THREADS=1 python benchmarks/bench_scoring_split.py --rounds 7 --layer-norm   # MPO's default torso
"""

import argparse
import pathlib
import time

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.torch_layers import FlattenExtractor

from sb3_lifelong.common import scoring
from sb3_lifelong.common.policies import QCritic
from sb3_lifelong.common.scoring import LowPrecisionCopy, score_actions

RESULTS = pathlib.Path(__file__).parent / "results"
#: (name, observation width, action width)
SHAPES = [("OP3 walking", 68, 20), ("Walker2d", 17, 6), ("Hopper", 11, 3)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--calls", type=int, default=20, help="scoring passes per timed round")
    parser.add_argument("--layer-norm", action="store_true", help="the LayerNorm torso (MPO's default) instead of ReLU")
    args = parser.parse_args()
    th.set_num_threads(1)
    threshold = scoring.SPLIT_MIN_FEATURES
    lines = [
        "| robot (obs + action) | split used | split (ms) | stacked bf16 (ms) | float32 (ms) | stacked / split "
        "| float32 / split |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, width, action_dim in SHAPES:
        obs_space, act_space = gym.spaces.Box(-1, 1, (width,)), gym.spaces.Box(-1, 1, (action_dim,))
        critic = QCritic(
            obs_space, act_space, [256, 256], FlattenExtractor(obs_space), width, n_critics=1, layer_norm=args.layer_norm
        )
        copy = LowPrecisionCopy(critic)
        obs, actions = th.rand(256, width) * 2 - 1, th.rand(20, 256, action_dim) * 2 - 1
        times: dict[str, list[float]] = {"split": [], "stacked": [], "float32": []}
        with th.no_grad():
            for _ in range(args.rounds):
                for mode in times:
                    scoring.SPLIT_MIN_FEATURES = threshold if mode == "split" else 10**9
                    low = None if mode == "float32" else copy
                    for _ in range(3):
                        score_actions(critic, obs, actions, low)
                    start = time.perf_counter()
                    for _ in range(args.calls):
                        score_actions(critic, obs, actions, low)
                    times[mode].append((time.perf_counter() - start) / args.calls * 1e3)
        scoring.SPLIT_MIN_FEATURES = threshold
        med = {mode: float(np.median(values)) for mode, values in times.items()}
        used = scoring._splits_first_layer(critic.q_networks[0], width, action_dim, copy)
        lines.append(
            f"| {name} ({width} + {action_dim}) | {'yes' if used else 'no'} | {med['split']:.2f} | {med['stacked']:.2f} | "
            f"{med['float32']:.2f} | {med['stacked'] / med['split']:.2f}x | {med['float32'] / med['split']:.2f}x |"
        )
    table = "\n".join(lines)
    print(table)
    RESULTS.mkdir(exist_ok=True)
    torso = " --layer-norm" if args.layer_norm else ""
    (RESULTS / f"scoring_split{'_layernorm' if args.layer_norm else ''}.md").write_text(
        f"# bf16 scoring pass: first layer split per state / per sample{' (LayerNorm torso)' if args.layer_norm else ''}\n\n"
        "Command: `OMP_NUM_THREADS=1 python benchmarks/bench_scoring_split.py --rounds "
        f"{args.rounds}{torso}` (medians of the rounds; the three variants interleaved in one process).\n\n" + table + "\n"
    )


if __name__ == "__main__":
    main()
