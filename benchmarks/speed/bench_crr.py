"""
CRR benchmark: sb3-lifelong's CRR against d3rlpy's CRR on the same offline dataset, in the same run, with the same
networks (actor and critic 256x256 ReLU), batch (256), number of updates, learning rates (3e-4), advantage
(mean over 4 policy samples), transform (exp, beta=1, clipped at 20), hard target update every 100 updates,
one critic, one torch thread each.

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_crr.py --updates 5000 \
        --data benchmarks/results/speed/crr_hopper_medium_replay.npz --d3rlpy-python /tmp/d3venv/bin/python

The dataset is written by ``benchmarks/speed/crr_collect.py``. d3rlpy is a benchmark-only dependency, installed in its
own virtual environment (``python -m venv --system-site-packages /tmp/d3venv && /tmp/d3venv/bin/pip install
d3rlpy``); each implementation runs in its own process. Throughput is measured on the training loop alone
(data loading and evaluation excluded); the return is the mean over ``--eval-episodes`` deterministic episodes
with seeds 0, 1, ... of the final policy.
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time
from typing import Any

import numpy as np

HIDDEN = [256, 256]
#: where the hand-written notes of a results file begin
NOTES_MARK = "Setup and caveats:"


def evaluate(act, env_id: str, episodes: int) -> tuple[float, float]:
    import gymnasium as gym

    env = gym.make(env_id)
    returns = []
    for seed in range(episodes):
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(act(obs))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    return float(np.mean(returns)), float(np.std(returns))


def make_ours(data: dict, env_id: str, seed: int, compile_losses: bool = False, train_dtype: str = "float32") -> Any:
    """
    :return: sb3-lifelong's CRR on ``data`` with the settings shared with d3rlpy (see the module docstring); with
        ``compile_losses`` its update's forward pass compiled (``compile_losses=True``; eager otherwise, as "auto" is
        for runs this short), and ``train_dtype`` the precision of its gradient passes' hidden products
    """
    import gymnasium as gym

    from sb3_lifelong import CRR

    env = gym.make(env_id)
    return CRR.from_offline_data(
        data,
        env=None,
        observation_space=env.observation_space,
        action_space=env.action_space,
        batch_size=256,
        learning_rate=3e-4,
        gamma=0.99,
        num_samples=4,
        advantage_baseline="mean",
        advantage_transform="exp",
        beta=1.0,
        max_weight=20.0,
        tau=1.0,
        target_update_interval=100,
        policy_kwargs=dict(net_arch=HIDDEN, n_critics=1),
        seed=seed,
        device="cpu",  # as d3rlpy's: the CPU even where a GPU is present
        compute=dict(compile_losses=compile_losses, train_dtype=train_dtype),
    )


def run_ours(args: argparse.Namespace, data: dict) -> dict:
    import torch as th

    th.set_num_threads(1)
    model = make_ours(data, args.env, args.seed, args.compile_losses, args.train_dtype)
    model.learn_offline(20, log_interval=0)  # warm-up (and the compilation), not timed
    start = time.perf_counter()
    model.learn_offline(args.updates, log_interval=0)
    seconds = time.perf_counter() - start
    mean, std = (np.nan, np.nan)
    if args.eval_episodes > 0:
        mean, std = evaluate(lambda obs: model.predict(obs, deterministic=True)[0], args.env, args.eval_episodes)
    return {
        "impl": "sb3-lifelong CRR"
        + (" (compiled)" if args.compile_losses else "")
        + (f" (train_dtype={args.train_dtype})" if args.train_dtype != "float32" else ""),
        "updates": args.updates,
        "seconds": seconds,
        "return": mean,
        "return_std": std,
    }


def run_d3rlpy(args: argparse.Namespace, data: dict) -> dict:
    import d3rlpy
    import torch as th

    th.set_num_threads(1)
    d3rlpy.seed(args.seed)
    timeouts = data["timeouts"].astype(np.float32)
    timeouts[-1] = 0.0 if data["terminals"][-1] else 1.0  # the last trajectory ends with the data
    dataset = d3rlpy.dataset.MDPDataset(
        observations=data["observations"],
        actions=data["actions"],
        rewards=data["rewards"],
        terminals=data["terminals"].astype(np.float32),
        timeouts=timeouts,
    )
    encoder = d3rlpy.models.VectorEncoderFactory(hidden_units=HIDDEN)
    algo = d3rlpy.algos.CRRConfig(
        batch_size=256,
        gamma=0.99,
        actor_learning_rate=3e-4,
        critic_learning_rate=3e-4,
        actor_encoder_factory=encoder,
        critic_encoder_factory=encoder,
        beta=1.0,
        n_action_samples=4,
        advantage_type="mean",
        weight_type="exp",
        max_weight=20.0,
        n_critics=1,
        target_update_type="hard",
        target_update_interval=100,
    ).create(device="cpu:0")
    common = dict(show_progress=False, logger_adapter=d3rlpy.logging.NoopAdapterFactory(), save_interval=10**9)
    algo.fit(dataset, n_steps=20, n_steps_per_epoch=20, **common)  # builds the networks; warm-up, not timed
    start = time.perf_counter()
    algo.fit(dataset, n_steps=args.updates, n_steps_per_epoch=args.updates, **common)
    seconds = time.perf_counter() - start
    mean, std = (np.nan, np.nan)
    if args.eval_episodes > 0:
        mean, std = evaluate(lambda obs: algo.predict(obs[None].astype(np.float32))[0], args.env, args.eval_episodes)
    return {
        "impl": f"d3rlpy {d3rlpy.__version__} CRR",
        "updates": args.updates,
        "seconds": seconds,
        "return": mean,
        "return_std": std,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="benchmarks/results/speed/crr_hopper_medium_replay.npz")
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--updates", type=int, default=5_000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--impl", choices=["ours", "d3rlpy", "both"], default="both")
    parser.add_argument("--d3rlpy-python", default="/tmp/d3venv/bin/python", help="interpreter that has d3rlpy")
    parser.add_argument("--output", default="benchmarks/results/speed/crr_hopper.md")
    parser.add_argument("--speed-rounds", type=int, default=3, help="interleaved throughput-only rounds (0: none)")
    parser.add_argument("--speed-updates", type=int, default=300, help="updates per throughput-only round")
    parser.add_argument("--compile-losses", action="store_true", help="our CRR with compile_losses=True")
    parser.add_argument(
        "--train-dtype",
        default="float32",
        choices=["float32", "bfloat16", "simulated_bfloat16", "auto"],
        help="our CRR's (simulated_bfloat16: bf16's numbers from float32 products, for the return where bf16 is not native)",
    )
    args = parser.parse_args()
    with np.load(args.data) as npz:
        data = {key: npz[key] for key in npz.files}
    if args.impl == "ours":
        print(json.dumps(run_ours(args, data)))
        return
    if args.impl == "d3rlpy":
        print(json.dumps(run_d3rlpy(args, data)))
        return
    results: list[dict[str, Any]] = []
    base = [a for a in sys.argv[1:]]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    pythons = {"ours": sys.executable, "d3rlpy": args.d3rlpy_python}

    def child(impl: str, *extra: str) -> dict[str, Any]:
        command = [pythons[impl], __file__, *base, *extra, "--impl", impl]
        proc = subprocess.run(command, capture_output=True, text=True, env=env)
        if proc.returncode != 0:
            return {"impl": impl, "error": proc.stderr.strip().splitlines()[-1] if proc.stderr else "failed"}
        return json.loads(proc.stdout.strip().splitlines()[-1])

    for impl in pythons:
        results.append(child(impl))
    # Throughput alone, the two implementations alternating, so that both see the same (shared) machine load
    speed: dict[str, list[float]] = {impl: [] for impl in pythons}
    for _ in range(args.speed_rounds):
        for impl in pythons:
            block = child(impl, "--updates", str(args.speed_updates), "--eval-episodes", "0")
            if "error" not in block:
                speed[impl].append(block["updates"] / block["seconds"])
    behaviour = {}
    stats_path = args.data.replace(".npz", ".json")
    if os.path.exists(stats_path):
        with open(stats_path) as file:
            behaviour = json.load(file)
    # the CPU's matrix flags and oneDNN's bf16 kernel decide these ratios (imported here: the d3rlpy child runs this
    # file in an interpreter without the package)
    from sb3_lifelong.numerics.hardware import machine_description

    machine = machine_description()
    print(machine)
    lines = [
        f"# CRR on {args.env}, offline ({len(data['rewards'])} transitions, {os.path.basename(args.data)})",
        "",
        "Command: `OMP_NUM_THREADS=1 python benchmarks/speed/bench_crr.py " + " ".join(base) + "`",
        "",
        f"Machine: {machine}",
        "",
        f"| implementation | updates | updates/s (quality run) | updates/s (best of {args.speed_rounds} interleaved blocks "
        f"of {args.speed_updates}) | final return (mean +- std, {args.eval_episodes} episodes) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for impl_key, result in zip(pythons, results):
        best = f"{max(speed[impl_key]):.1f}" if speed[impl_key] else "-"
        if "error" in result:
            lines.append(f"| {result['impl']} | - | - | {best} | error: {result['error']} |")
        else:
            ups = result["updates"] / result["seconds"]
            score = f"{result['return']:.1f} +- {result['return_std']:.1f}"
            lines.append(f"| {result['impl']} | {result['updates']} | {ups:.1f} | {best} | {score} |")
    if behaviour:
        lines.append(
            f"| behaviour: final collecting policy (deterministic) | - | - | - | {behaviour['behaviour_policy_return']:.1f} |"
        )
        lines.append(f"| behaviour: dataset episodes (mean) | - | - | - | {behaviour['dataset_mean_return']:.1f} |")
    ok = [r for r in results if "error" not in r]
    if len(ok) == 2:
        speedup = (ok[0]["updates"] / ok[0]["seconds"]) / (ok[1]["updates"] / ok[1]["seconds"])
        lines += ["", f"Speed ratio ours / d3rlpy, quality runs (one after the other): {speedup:.2f}x"]
    if speed["ours"] and speed["d3rlpy"]:
        lines += [f"Speed ratio ours / d3rlpy, best interleaved blocks: {max(speed['ours']) / max(speed['d3rlpy']):.2f}x"]
        per_round = [ours / theirs for ours, theirs in zip(speed["ours"], speed["d3rlpy"])]
        lines += [
            f"Speed ratio ours / d3rlpy, median over the rounds of each round's ratio: {float(np.median(per_round)):.2f}x "
            f"(rounds: {', '.join(f'{ratio:.2f}' for ratio in per_round)})"
        ]
    dump = {"results": results, "speed_blocks_updates_per_s": speed, "behaviour": behaviour, "machine": machine}
    # the notes written by hand under the generated table (set-up, readings) are kept when the file is rewritten
    previous = pathlib.Path(args.output).read_text() if os.path.exists(args.output) else ""
    if NOTES_MARK in previous:
        lines += ["", NOTES_MARK + previous.split(NOTES_MARK, 1)[1].split("\n```json\n", 1)[0].rstrip("\n")]
    lines += ["", "```json", json.dumps(dump, indent=2), "```", ""]
    with open(args.output, "w") as file:
        file.write("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
