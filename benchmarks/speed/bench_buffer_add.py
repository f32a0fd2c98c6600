"""
add() cost of an in-memory LifelongReplayBuffer: repeats of 20,000 single-env adds (60-float observations, 20-float
actions), microseconds per transition. A quick check for regressions: run it against an older commit with
``git worktree add /tmp/old <commit> && PYTHONPATH=/tmp/old python benchmarks/speed/bench_buffer_add.py``.
"""

import argparse
import time

import gymnasium as gym
import numpy as np

import sb3_lifelong
from sb3_lifelong import LifelongReplayBuffer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--adds", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    obs_space = gym.spaces.Box(-1, 1, (60,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (20,), np.float32)
    rng = np.random.default_rng(0)
    obs, action = rng.random((1, 60), dtype=np.float32), rng.random((1, 20), dtype=np.float32)
    results = []
    for _ in range(args.repeats):
        buffer = LifelongReplayBuffer(100_000, obs_space, action_space, device="cpu")
        start = time.perf_counter()
        for _ in range(args.adds):
            buffer.add(obs, obs, action, np.ones(1), np.zeros(1), [{}])
        results.append((time.perf_counter() - start) / args.adds * 1e6)
    print(f"{sb3_lifelong.__file__}: us per add {[round(r, 1) for r in results]}")


if __name__ == "__main__":
    main()
