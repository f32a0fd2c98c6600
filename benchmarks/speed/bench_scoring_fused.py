"""
MPO's target pass (``num_samples x batch`` rows through the target critic, no autograd) with the hidden layers as
fused oneDNN products (bias and ReLU as post-ops, weights laid out once per sync:
``sb3_lifelong.numerics.scoring.LowPrecisionCopy(fused=True)``) against the same precision unfused (``addmm`` into a
reused buffer, then an in-place ReLU) and against the exact float32 pass without a copy. With the LayerNorm torso,
each copy also runs with its LayerNorm and tanh as one compiled kernel (``compile_layer_norm``, what a compiled update
uses; compiled in the warm-up round), besides the eager way (converted to float32, normalised, converted back).

A variant this CPU cannot run reads ``n/a`` (oneDNN fuses bfloat16 only with AVX-512 or AMX). Each variant's Q-values
are compared with the exact pass's (largest error over the mean |Q|). One process, one torch thread, the variants
interleaved round by round; the table gives the median milliseconds per pass and the median of the rounds' ratios to
the exact float32 pass.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_scoring_fused.py --env Walker2d-v5 --rounds 7 --calls 20
"""

import argparse
import json
import pathlib
import time
from typing import Any, Optional

import numpy as np
import torch as th

from sb3_lifelong import MPO
from sb3_lifelong.common.policies import sample_gaussian
from sb3_lifelong.numerics.compiling import can_compile
from sb3_lifelong.numerics.hardware import fused_products_supported, machine_description
from sb3_lifelong.numerics.scoring import LowPrecisionCopy, score_actions

RESULTS = pathlib.Path(__file__).resolve().parents[1] / "results" / "speed"


def time_pass(model: MPO, obs: th.Tensor, actions: th.Tensor, copy: Optional[LowPrecisionCopy], calls: int) -> float:
    """:return: milliseconds per scoring pass"""
    start = time.perf_counter()
    for _ in range(calls):
        score_actions(model.critic_target, obs, actions, copy)
    return (time.perf_counter() - start) / calls * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Walker2d-v5")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--calls", type=int, default=20, help="scoring passes per round and variant")
    parser.add_argument("--num-samples", type=int, default=20)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--layer-norm", choices=["on", "off"], default="on", help="MPO's default LayerNorm torso")
    parser.add_argument("--output", type=pathlib.Path, default=RESULTS / "scoring_fused.json")
    args = parser.parse_args()
    th.set_num_threads(1)
    kwargs = dict(net_arch=[256, 256], layer_norm=args.layer_norm == "on")
    model = MPO("MlpPolicy", args.env, policy_kwargs=kwargs, compute=dict(scoring_dtype="float32"), device="cpu", seed=0)
    critic = model.critic_target
    obs_dim = model.observation_space.shape[0]  # type: ignore[index]
    obs = th.randn(args.batch_size, obs_dim, generator=th.Generator().manual_seed(0))
    with th.no_grad():
        mean, std = model.actor_target.distribution_params(obs)
        actions = sample_gaussian(mean, std, args.num_samples)
        exact = score_actions(critic, obs, actions)
    variants: dict[str, Optional[LowPrecisionCopy]] = {"float32, no copy (exact)": None}
    for dtype in (th.float32, th.bfloat16):
        name = str(dtype).removeprefix("torch.")
        for fused in (False, True):
            if fused and not fused_products_supported(dtype):
                continue
            kind = f"{name}, {'fused' if fused else 'unfused'}"
            variants[kind] = LowPrecisionCopy(critic, dtype, fused=fused)
            if args.layer_norm == "on" and can_compile(th.device("cpu")):
                variants[f"{kind}, LayerNorm compiled"] = copy = LowPrecisionCopy(critic, dtype, fused=fused)
                copy.compile_layer_norm = True
    errors: dict[str, float] = {}
    with th.no_grad():
        for name, copy in variants.items():
            errors[name] = float((score_actions(critic, obs, actions, copy) - exact).abs().max() / exact.abs().mean())
    times: dict[str, list[float]] = {name: [] for name in variants}
    with th.no_grad():
        for round_index in range(args.rounds + 1):  # round 0 warms up
            for name, copy in variants.items():
                elapsed = time_pass(model, obs, actions, copy, args.calls)
                if round_index:
                    times[name].append(elapsed)
    reference = np.array(times["float32, no copy (exact)"])
    rows = [
        f"| variant | ms per pass (median of {args.rounds}) | exact / this (median of the rounds' ratios) "
        "| largest Q error / mean abs Q |",
        "| --- | --- | --- | --- |",
    ]
    results: dict[str, Any] = {}
    names = ["float32, no copy (exact)"]
    for dtype_name in ("float32", "bfloat16"):
        for kind in ("unfused", "unfused, LayerNorm compiled", "fused", "fused, LayerNorm compiled"):
            if args.layer_norm == "on" or "LayerNorm" not in kind:
                names.append(f"{dtype_name}, {kind}")
    for name in names:
        if name not in times:
            rows.append(f"| {name} | n/a | n/a | n/a |")
            results[name] = None
            continue
        values = np.array(times[name])
        speed_up = float(np.median(reference / values))
        rows.append(f"| {name} | {np.median(values):.2f} | {speed_up:.2f}x | {errors[name]:.1e} |")
        results[name] = dict(ms=values.tolist(), median_ms=float(np.median(values)), speed_up=speed_up, error=errors[name])
    machine = machine_description()
    torso = "LayerNorm torso" if args.layer_norm == "on" else "plain torso"
    print(f"{machine}\n{args.env}: {args.num_samples} x {args.batch_size} rows, 256x256 critic ({torso}), one thread\n")
    print("\n".join(rows))
    command = (
        f"OMP_NUM_THREADS=1 python benchmarks/speed/bench_scoring_fused.py --env {args.env} --rounds {args.rounds} "
        f"--calls {args.calls} --num-samples {args.num_samples} --batch-size {args.batch_size} --layer-norm {args.layer_norm}"
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(dict(command=command, machine=machine, results=results), indent=2) + "\n")
    print(f"\nwrote {args.output}")


if __name__ == "__main__":
    main()
