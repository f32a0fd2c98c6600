"""
Would bf16 autocast of MPO's batch passes pay? The online critic's and actor's forward passes on the batch (and so
their backward) under ``torch.autocast(bfloat16)``, against the same model in float32, interleaved in one process.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_mpo_autocast.py --env Walker2d-v5 --blocks 8 --updates 100
"""

import argparse
import statistics
import time
from typing import Any

import gymnasium as gym
import torch as th

from sb3_lifelong import MPO


def with_autocast(model: MPO) -> None:
    """Run the online critic's forward and the online actor's distribution under bf16 autocast (float32 out)."""
    critic_forward, actor_params = model.critic.forward, model.actor.distribution_params

    def critic(obs: Any, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        with th.autocast("cpu", dtype=th.bfloat16):
            values = critic_forward(obs, actions)
        return tuple(value.float() for value in values)

    def actor(obs: Any) -> tuple[th.Tensor, th.Tensor]:
        with th.autocast("cpu", dtype=th.bfloat16):
            mean, std = actor_params(obs)
        return mean.float(), std.float()

    model.critic.forward = critic  # type: ignore[method-assign]
    model.actor.distribution_params = actor  # type: ignore[method-assign]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Walker2d-v5")
    parser.add_argument("--blocks", type=int, default=8, help="interleaved blocks per variant")
    parser.add_argument("--updates", type=int, default=100, help="updates per block")
    args = parser.parse_args()
    th.set_num_threads(1)
    models = {}
    for name in ("float32", "autocast bf16"):
        model = MPO(
            "MlpPolicy", gym.make(args.env), learning_starts=0, batch_size=256, seed=0, policy_kwargs=dict(layer_norm=False)
        )
        model.learn(600)  # some data to sample
        if name != "float32":
            with_autocast(model)
        models[name] = model
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.blocks):
        for name, model in models.items():
            start = time.perf_counter()
            model.train(args.updates, 256)
            times[name].append((time.perf_counter() - start) * 1e3 / args.updates)
    print("| variant | ms per update (median) | blocks |\n| --- | --- | --- |")
    for name, values in times.items():
        print(f"| {name} | {statistics.median(values):.1f} | {', '.join(f'{v:.1f}' for v in values)} |")
    print(f"\nfloat32 / autocast: {statistics.median(times['float32']) / statistics.median(times['autocast bf16']):.2f}x")


if __name__ == "__main__":
    main()
