"""
Throughput of MPO vs SB3's SAC: environment steps per second with one gradient update per step.

Both use the same networks (256x256 actor and critic), batch size 256 and the same environment. Runs are
interleaved (SAC, MPO, SAC, MPO, ...) in one process so that both see the same machine load; the table reports
medians over rounds and the MPO/SAC ratio. MPO is timed with each scoring precision asked for (float32: exact;
auto: bfloat16 where the CPU has it) and each torso asked for (``--layer-norms off on``: with and without Acme's
LayerNorm after the first hidden layer). A torch profile of each MPO variant's update says where the time goes.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_mpo_throughput.py --envs Walker2d-v5 Hopper-v5 --rounds 5 --steps 1000
"""

import argparse
import datetime
import json
import pathlib
import time
from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import SAC
from torch.profiler import ProfilerActivity, profile

from sb3_lifelong import MPO
from sb3_lifelong.numerics.hardware import machine_description

RESULTS = pathlib.Path(__file__).resolve().parents[1] / "results" / "speed"


def make(
    algo: str,
    env_id: str,
    num_samples: int,
    scoring_dtype: str = "auto",
    layer_norm: bool = False,
    compiled: bool = False,
    train_dtype: str = "float32",
) -> Any:
    # on the CPU even where a GPU is present: this benchmark measures the CPU (its matrix units)
    common = dict(batch_size=256, learning_starts=1000, train_freq=1, gradient_steps=1, seed=0, verbose=0, device="cpu")
    if algo == "SAC":
        return SAC("MlpPolicy", env_id, policy_kwargs=dict(net_arch=[256, 256]), **common)
    return MPO(
        "MlpPolicy",
        env_id,
        policy_kwargs=dict(net_arch=[256, 256], layer_norm=layer_norm),
        num_samples=num_samples,
        compute=dict(scoring_dtype=scoring_dtype, compile_losses=compiled, train_dtype=train_dtype),
        **common,
    )


def timed_learn(model: Any, steps: int) -> float:
    start = time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    return steps / (time.perf_counter() - start)


def profile_mpo(model: MPO, updates: int) -> list[tuple[str, float]]:
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        model.train(updates, model.batch_size)
    rows = []
    total = 0.0
    for event in prof.key_averages():
        if event.key.startswith("mpo/"):
            rows.append((event.key, event.cpu_time_total / 1000.0 / updates))
            total += event.cpu_time_total
    rows.sort(key=lambda row: -row[1])
    return rows


def run_env(env_id: str, args: argparse.Namespace) -> tuple[list[str], dict[str, Any]]:
    models = {"SAC": make("SAC", env_id, 0)}
    for n in args.num_samples:
        for dtype in args.scoring_dtypes:
            for layer_norm in args.layer_norms:
                for compiled in args.compile_losses:
                    for train_dtype in args.train_dtypes:
                        name = f"MPO (N={n}, {dtype}" + (", LayerNorm" if layer_norm == "on" else "")
                        name += f", {train_dtype} gradient passes" if train_dtype != "float32" else ""
                        name += ", compiled)" if compiled == "on" else ")"
                        models[name] = make("MPO", env_id, n, dtype, layer_norm == "on", compiled == "on", train_dtype)
    for model in models.values():  # warm-up: fill learning_starts and run some updates
        model.learn(1200)
    speeds: dict[str, list[float]] = {name: [] for name in models}
    for round_idx in range(args.rounds):
        for name, model in models.items():
            speeds[name].append(timed_learn(model, args.steps))
        print(f"{env_id} round {round_idx + 1}/{args.rounds}: " + ", ".join(f"{k} {v[-1]:.1f}" for k, v in speeds.items()))

    sac = float(np.median(speeds["SAC"]))
    lines = [
        f"## {env_id}",
        "",
        f"| algorithm | env steps/s (median of {args.rounds}) | ratio to SAC | per round, ratio to SAC: median [min, max] |",
        "| --- | --- | --- | --- |",
    ]
    results: dict[str, Any] = {}
    for name, values in speeds.items():
        median = float(np.median(values))
        # a round's ratio compares two runs next to each other in time, so load that changes between rounds cancels
        per_round = [value / peer for value, peer in zip(values, speeds["SAC"])]
        spread = f"{np.median(per_round):.2f}x [{min(per_round):.2f}, {max(per_round):.2f}]"
        lines.append(f"| {name} | {median:.1f} | {median / sac:.2f}x | {spread} |")
        results[name] = {
            "steps_per_s": values,
            "median": median,
            "ratio_to_sac": median / sac,
            "round_ratios_to_sac": per_round,
        }
        forward = getattr(models[name], "_forward", None)
        if name.endswith("compiled)") and forward is not None:
            # a compiled update refused by its first-call check trains eagerly: a row that says "compiled" but was not
            results[name]["compiled_in_use"] = forward.compiled is not None and not forward.failed
            results[name]["compile_failure"] = forward.failure
    refused = [f"{name}: {results[name]['compile_failure']}" for name in results if results[name].get("compile_failure")]
    if refused:
        lines += ["", "Ran eagerly, the compiled update refused: " + "; ".join(refused)]
    profiles = {name: dict(profile_mpo(model, 100)) for name, model in models.items() if name.startswith("MPO")}
    sections = sorted({key for profile in profiles.values() for key in profile})
    lines += ["", "MPO update, time per section (ms per update, torch profiler, 100 updates):", ""]
    lines += ["| section | " + " | ".join(profiles) + " |", "| --- |" + " --- |" * len(profiles)]
    lines += [f"| {key} | " + " | ".join(f"{p.get(key, 0.0):.2f}" for p in profiles.values()) + " |" for key in sections]
    lines += ["| sum | " + " | ".join(f"{sum(p.values()):.2f}" for p in profiles.values()) + " |", ""]
    return lines, {"results": results, "profile_ms": profiles}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["Walker2d-v5", "Hopper-v5"])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=1000, help="environment steps per timed round")
    parser.add_argument("--num-samples", type=int, nargs="+", default=[20], help="MPO num_samples values to time")
    parser.add_argument("--scoring-dtypes", nargs="+", default=["float32", "auto"], help="MPO scoring precisions to time")
    parser.add_argument("--layer-norms", nargs="+", default=["off"], choices=["off", "on"], help="MPO torsos to time")
    parser.add_argument(
        "--compile-losses",
        nargs="+",
        default=["off"],
        choices=["off", "on"],
        help="MPO eager and/or compiled (compile_losses)",
    )
    parser.add_argument(
        "--train-dtypes",
        nargs="+",
        default=["float32"],
        choices=["float32", "bfloat16", "auto"],
        help="MPO train_dtype values",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a 2-core machine)")
    parser.add_argument("--output", default=str(RESULTS / "mpo_throughput"))
    args = parser.parse_args()
    th.set_num_threads(args.threads)

    lines: list[str] = []
    per_env: dict[str, Any] = {}
    for env_id in args.envs:
        env_lines, per_env[env_id] = run_env(env_id, args)
        lines += env_lines
    table = "\n".join(lines)
    print(table)

    out = pathlib.Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "command": "OMP_NUM_THREADS=1 python benchmarks/speed/bench_mpo_throughput.py "
        + f"--envs {' '.join(args.envs)} --rounds {args.rounds} --steps {args.steps} --num-samples "
        + " ".join(map(str, args.num_samples))
        + f" --scoring-dtypes {' '.join(args.scoring_dtypes)} --layer-norms {' '.join(args.layer_norms)}"
        + f" --compile-losses {' '.join(args.compile_losses)} --train-dtypes {' '.join(args.train_dtypes)}"
        + f" --threads {args.threads}",
        "machine": machine_description(),  # CPU, its matrix flags (AMX, AVX-512 BF16), oneDNN's bf16 kernel, torch
    }
    out.with_suffix(".json").write_text(json.dumps({**meta, "envs": per_env}, indent=2))
    out.with_suffix(".raw.md").write_text(
        f"# MPO vs SAC throughput\n\nCommand: `{meta['command']}`\n\nDate: {meta['date']}; {meta['machine']}\n\n"
        + table
        + "\n"
    )
    print("wrote", out.with_suffix(".raw.md"), "(the commented profile lives in", out.with_suffix(".md"), ")")


if __name__ == "__main__":
    main()
