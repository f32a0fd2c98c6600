"""
Choose Env-A / Env-B pairs the paper's way: Env-B is a change that causes a clear drop under zero-shot transfer.

For one robot and a list of candidate changes, an MPO policy is trained in each environment (the default robot,
Env-A, and every candidate Env-B) with the collector settings of the CPU protocol, then every policy is evaluated
in every environment. A good pair drops in both directions: the Env-A policy fails in Env-B *and* the Env-B policy
fails in Env-A (otherwise the later environment's data would simply transfer back and there is nothing to forget).

The true physical parameters of all candidates are appended to the observation (zeros = nominal), as in the
paper, so one observation layout serves every policy.

One robot and seed is one command; trained policies are kept in ``--work`` and re-used when the command is
re-run (a crashed run continues where it stopped)::

    OMP_NUM_THREADS=1 python benchmarks/studies/env_pairs/env_pairs.py --env Hopper-v5 --steps 50000 --seed 0 \
        --changes hip_deformation=0.3 foot_scale=2.0 mass_scale=1.75 friction=0.2
    python benchmarks/studies/env_pairs/env_pairs.py --report benchmarks/studies/env_pairs/results   # the table over \
        robots and seeds
"""

import argparse
import json
import pathlib
import time
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_lifelong import MPO
from sb3_lifelong.envs import DynamicsSchedule

RESULTS = pathlib.Path(__file__).parent / "results"

# the collector of the CPU protocol (sb3_lifelong.experiments, preset "cpu")
COLLECTOR = dict(
    policy_kwargs=dict(net_arch=[128, 128], layer_norm=False),
    num_samples=10,
    batch_size=128,
    learning_rate=1e-3,
    learning_starts=2000,
)


def parse_change(text: str) -> dict[str, float]:
    name, _, value = text.partition("=")
    if not value:
        raise argparse.ArgumentTypeError(f"a change is name=value (e.g. hip_deformation=0.3), got {text!r}")
    return {name: float(value)}


def label(stage: dict[str, float]) -> str:
    return "default" if not stage else ",".join(f"{k}={v:g}" for k, v in stage.items())


def make_env(env_id: str, stages: list[dict[str, float]], index: int) -> DynamicsSchedule:
    env = DynamicsSchedule(gym.make(env_id), stages=stages, append_params=True)
    env.set_stage(index, immediate=True)
    return env


def run(args: argparse.Namespace) -> None:
    stages: list[dict[str, float]] = [{}, *args.changes]
    names = [label(stage) for stage in stages]
    work = pathlib.Path(args.work) / f"{args.env}_s{args.seed}"
    work.mkdir(parents=True, exist_ok=True)
    out = pathlib.Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    result_path = out / f"{args.env}_s{args.seed}.json"
    result: dict[str, Any] = dict(
        env=args.env, seed=args.seed, steps=args.steps, envs=names, eval_episodes=args.eval_episodes, collector=COLLECTOR
    )
    result["returns"] = {}
    result["train_seconds"] = {}
    for index in range(len(stages)):
        policy_path = work / f"policy_{index}.zip"
        if policy_path.exists():
            model = MPO.load(policy_path, device="cpu")
            print(f"[{args.env} s{args.seed}] re-using the policy trained in {names[index]}", flush=True)
        else:
            print(f"[{args.env} s{args.seed}] training in {names[index]} for {args.steps} steps", flush=True)
            start = time.perf_counter()
            model = MPO("MlpPolicy", make_env(args.env, stages, index), seed=args.seed, **COLLECTOR)  # type: ignore[arg-type]
            model.learn(args.steps)
            model.save(policy_path)
            result["train_seconds"][names[index]] = time.perf_counter() - start
        row = {}
        for target, target_name in enumerate(names):
            eval_env = Monitor(make_env(args.env, stages, target))
            eval_env.reset(seed=10_000 + args.seed)
            mean, std = evaluate_policy(model, eval_env, n_eval_episodes=args.eval_episodes, deterministic=True)
            row[target_name] = dict(mean=float(mean), std=float(std))
        result["returns"][names[index]] = row
        print(
            f"[{args.env} s{args.seed}] policy of {names[index]}: " + ", ".join(f"{k} {v['mean']:.0f}" for k, v in row.items())
        )
        result_path.write_text(json.dumps(result, indent=1))
    print("wrote", result_path)


def report(directory: pathlib.Path) -> str:
    """Markdown table of the drops, from every ``<env>_s<seed>.json`` in ``directory``."""
    by_env: dict[str, list[dict[str, Any]]] = {}
    for path in sorted(directory.glob("*_s*.json")):
        data = json.loads(path.read_text())
        by_env.setdefault(data["env"], []).append(data)
    lines = [
        "| robot | Env-B | seeds | A-policy in A | A-policy in B | drop A->B | B-policy in B | B-policy in A | drop B->A |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]

    def cell(values: list[float]) -> str:
        return f"{np.mean(values):.0f} +- {np.std(values):.0f}"

    for env_id, runs in by_env.items():
        complete = [run for run in runs if "default" in run["returns"]]
        for name in runs[0]["envs"][1:]:
            pairs = [run for run in complete if name in run["returns"]]
            if not pairs:
                continue
            aa = [run["returns"]["default"]["default"]["mean"] for run in pairs]
            ab = [run["returns"]["default"][name]["mean"] for run in pairs]
            bb = [run["returns"][name][name]["mean"] for run in pairs]
            ba = [run["returns"][name]["default"]["mean"] for run in pairs]
            drop_ab = 100 * (1 - np.mean(ab) / np.mean(aa))
            drop_ba = 100 * (1 - np.mean(ba) / np.mean(bb))
            lines.append(
                f"| {env_id} | {name} | {len(pairs)} | {cell(aa)} | {cell(ab)} | {drop_ab:.0f} % | {cell(bb)} | {cell(ba)} "
                f"| {drop_ba:.0f} % |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5", help="MuJoCo robot (gymnasium id)")
    parser.add_argument("--changes", type=parse_change, nargs="+", default=[], help="candidate Env-Bs, name=value each")
    parser.add_argument("--steps", type=int, default=50_000, help="training steps per environment")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--work", default="runs/env_pairs", help="where the trained policies are kept (not committed)")
    parser.add_argument("--output", default=str(RESULTS), help="where the per-run JSON goes")
    parser.add_argument("--report", default=None, help="only print and write the table of the JSON files in this directory")
    args = parser.parse_args()
    th.set_num_threads(1)
    if args.report:
        table = report(pathlib.Path(args.report))
        print(table)
        (pathlib.Path(args.report) / "README.md").write_text(
            "# Env-A / Env-B candidates: zero-shot drops in both directions\n\n"
            "Deterministic evaluation, mean +- std over seeds of the per-seed mean return.\n\n" + table + "\n"
        )
        return
    if not args.changes:
        parser.error("give at least one candidate change (--changes name=value ...)")
    run(args)


if __name__ == "__main__":
    main()
