"""
What one student of the imbalance dose study costs on this machine: CRR at the study's settings (256x256 LayerNorm torso,
categorical critic, batch 256, HalfCheetah-sized input and action), with the indicator and with ``target_ess``,
timed in interleaved blocks of updates in one process; the time of a 200k-update student and of the paper's 5M.

    OMP_NUM_THREADS=1 python benchmarks/bench_student_cost.py      # -> benchmarks/results/student_cost.json
"""

import argparse
import json
import pathlib
import time

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_lifelong import CRR
from sb3_lifelong.common.hardware import machine_description

RESULTS = pathlib.Path(__file__).parent / "results" / "student_cost.json"
VARIANTS = {
    "indicator": dict(advantage_transform="indicator"),
    "target_ess=0.9": dict(advantage_transform="exp", target_ess=0.9),
}


def random_data(rows: int, obs_dim: int, action_dim: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return dict(
        observations=rng.normal(size=(rows, obs_dim)).astype(np.float32),
        actions=rng.uniform(-1, 1, (rows, action_dim)).astype(np.float32),
        rewards=rng.normal(size=rows).astype(np.float32),
        next_observations=rng.normal(size=(rows, obs_dim)).astype(np.float32),
        terminals=np.zeros(rows, bool),
        timeouts=np.zeros(rows, bool),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--blocks", type=int, default=5, help="interleaved blocks per variant")
    parser.add_argument("--updates", type=int, default=200, help="updates per block")
    parser.add_argument("--output", default=str(RESULTS))
    args = parser.parse_args()
    th.set_num_threads(1)
    data = random_data(50_000, 19, 6)  # HalfCheetah with its 2 physical parameters appended
    policy_kwargs = dict(net_arch=[256, 256], layer_norm=True, distributional_critic=True, v_min=-500.0, v_max=3000.0)
    space = spaces.Box(-1, 1, (6,))
    models = {
        name: CRR.from_offline_data(
            data, env=None, action_space=space, policy_kwargs=policy_kwargs, batch_size=256, seed=0, **kw
        )
        for name, kw in VARIANTS.items()
    }
    for model in models.values():
        model.learn_offline(50, log_interval=0)  # warm-up
    seconds: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.blocks):
        for name, model in models.items():
            start = time.perf_counter()
            model.learn_offline(args.updates, log_interval=0, reset_num_timesteps=False)
            seconds[name].append((time.perf_counter() - start) / args.updates)
    result = {"machine": machine_description(), "command": "OMP_NUM_THREADS=1 python benchmarks/bench_student_cost.py"}
    lines = [
        result["machine"],
        "",
        "| student | ms per update (median block) | 200k updates | 5M updates (the paper) |",
        "| --- | --- | --- | --- |",
    ]
    for name, values in seconds.items():
        ms = float(np.median(values)) * 1e3
        result[name] = dict(
            ms_per_update=ms, blocks_ms=[v * 1e3 for v in values], minutes_200k=ms * 2e5 / 6e4, hours_5M=ms * 5e6 / 3.6e6
        )
        lines.append(f"| {name} | {ms:.1f} | {ms * 2e5 / 6e4:.0f} min | {ms * 5e6 / 3.6e6:.1f} h |")
    pathlib.Path(args.output).write_text(json.dumps(result, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
