"""
The bfloat16 scoring pass with Acme's LayerNorm torso: its cost against the plain torso's, with the LayerNorm and
tanh fused in float32 (``sb3_lifelong.common.scoring._layer_norm_no_grad``, the library's path) and unfused (the
modules called one after another, as before the fusion: ``LayerNorm(x.float())``, back to bfloat16, then ``tanh``).

One process, one torch thread, the three passes interleaved round by round so that they see the same machine load;
the table gives the median time per pass and its ratio to the plain torso's.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_scoring_layernorm.py --env Walker2d-v5 --rounds 7 --calls 30
"""

import argparse
import json
import pathlib
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch as th
from torch import nn

from sb3_lifelong import MPO
from sb3_lifelong.common import scoring
from sb3_lifelong.common.policies import sample_gaussian
from sb3_lifelong.common.scoring import score_actions

RESULTS = pathlib.Path(__file__).parent / "results"


def unfused(critic: nn.Module, key: tuple[int, int], module: nn.LayerNorm, x: th.Tensor, then_tanh: bool) -> th.Tensor:
    """The LayerNorm and tanh as separate module calls (the reference the fused path replaced)."""
    out = module(x.float()).to(x.dtype)
    return th.tanh(out) if then_tanh else out


def time_pass(model: MPO, obs: th.Tensor, actions: th.Tensor, calls: int) -> float:
    """:return: milliseconds per scoring pass"""
    start = time.perf_counter()
    for _ in range(calls):
        score_actions(model.critic_target, obs, actions, model._target_scoring_copy)
    return (time.perf_counter() - start) / calls * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Walker2d-v5")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--calls", type=int, default=30, help="scoring passes per round and variant")
    parser.add_argument("--num-samples", type=int, default=20)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--output", type=pathlib.Path, default=RESULTS / "scoring_layernorm.json")
    args = parser.parse_args()
    th.set_num_threads(1)
    models = {
        layer_norm: MPO("MlpPolicy", args.env, policy_kwargs=dict(net_arch=[256, 256], layer_norm=layer_norm), seed=0)
        for layer_norm in (False, True)
    }
    assert models[True]._target_scoring_copy is not None, "this CPU has no native bfloat16: nothing to measure"
    obs_dim = models[False].observation_space.shape[0]  # type: ignore[index]
    generator = th.Generator().manual_seed(0)
    obs = th.randn(args.batch_size, obs_dim, generator=generator)
    with th.no_grad():
        mean, std = models[True].actor_target.distribution_params(obs)
        actions = sample_gaussian(mean, std, args.num_samples)
    fused_path = scoring._layer_norm_no_grad
    variants: dict[str, tuple[MPO, Callable[..., th.Tensor]]] = {
        "plain torso": (models[False], fused_path),
        "LayerNorm, fused (library)": (models[True], fused_path),
        "LayerNorm, unfused (reference)": (models[True], unfused),
    }
    times: dict[str, list[float]] = {name: [] for name in variants}
    with th.no_grad():
        for round_index in range(args.rounds + 1):  # round 0 warms up
            for name, (model, layer_norm_pass) in variants.items():
                scoring._layer_norm_no_grad = layer_norm_pass  # type: ignore[assignment]
                try:
                    elapsed = time_pass(model, obs, actions, args.calls)
                finally:
                    scoring._layer_norm_no_grad = fused_path  # type: ignore[assignment]
                if round_index:
                    times[name].append(elapsed)
    plain = float(np.median(times["plain torso"]))
    rows = [
        f"| variant | ms per pass (median of {args.rounds}) | ratio of medians to the plain torso "
        "| median of the rounds' ratios (each round's own plain pass) |",
        "| --- | --- | --- | --- |",
    ]
    results: dict[str, Any] = {}
    for name, values in times.items():
        median = float(np.median(values))
        paired = float(np.median(np.array(values) / np.array(times["plain torso"])))
        rows.append(f"| {name} | {median:.2f} | {median / plain:.2f}x | {paired:.2f}x |")
        results[name] = dict(ms=values, median_ms=median, ratio_to_plain=median / plain, paired_ratio=paired)
    print(f"{args.env}: {args.num_samples} x {args.batch_size} rows, 256x256 critic, bfloat16 scoring, one thread\n")
    print("\n".join(rows))
    command = (
        f"OMP_NUM_THREADS=1 python benchmarks/bench_scoring_layernorm.py --env {args.env} --rounds {args.rounds} "
        f"--calls {args.calls}"
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(dict(command=command, torch=th.__version__, results=results), indent=2) + "\n")
    print(f"\nwrote {args.output}")


if __name__ == "__main__":
    main()
