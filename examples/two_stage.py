"""
The two-stage experiment, top to bottom, with the package's public API only: a robot learns Env-A, its hip is bent
(Env-B) and it learns on; the whole lifetime buffer is then distilled offline into one policy, and the three agents
(frozen at the switch, at the end of MPO, the student) are evaluated on the same seeded episodes of both environments.

Usage::

    python examples/two_stage.py --output two_stage          # the defaults: about 15 min on one CPU core
    python examples/two_stage.py --steps-a 1000 --steps-b 2000 --updates 500 --output /tmp/t   # a smoke run

It writes ``returns.csv`` (agent, environment, mean and std of the return), ``curves.csv`` (every evaluation during
collection and distillation), ``two_stage.png`` and the three models. The defaults show the pipeline, not the paper's
findings: a robot needs far more steps to learn a gait (the study presets: ``python -m sb3_lifelong.experiments``).
"""

import argparse
import csv
import pathlib

import gymnasium as gym
import numpy as np
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_lifelong import CRR, MPO, LifelongReplayBuffer
from sb3_lifelong.envs import DynamicsSchedule, stage_envs
from sb3_lifelong.evaluation import MultiEnvEvalCallback

ENV_ID = "Hopper-v5"
STAGES = [{}, {"hip_deformation": 0.3}]  # Env-A: the robot as built; Env-B: the right hip bent by 0.3 rad
NAMES = ["Env-A", "Env-B"]


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps-a", type=int, default=20_000, help="environment steps in Env-A")
    parser.add_argument("--steps-b", type=int, default=60_000, help="environment steps in Env-B")
    parser.add_argument("--updates", type=int, default=10_000, help="gradient updates of the offline student")
    parser.add_argument("--episodes", type=int, default=5, help="evaluation episodes per environment")
    parser.add_argument("--seed", type=int, default=0, help="seed of the collector, the student and the evaluations")
    parser.add_argument("--output", default="two_stage", help="directory of the results (must be new or empty)")
    args = parser.parse_args()
    if min(args.steps_a, args.steps_b, args.updates, args.episodes) < 1:
        parser.error("--steps-a, --steps-b, --updates and --episodes must be >= 1")
    output = pathlib.Path(args.output)
    if output.exists() and any(output.iterdir()):
        parser.error(f"--output {output} is not empty: give a new directory")
    return args


def evaluate(model, envs: dict, episodes: int, seed: int) -> dict[str, tuple[float, float]]:
    """Mean and std of the return on every environment, on the same seeded episodes for every agent."""
    out = {}
    for name, env in envs.items():
        env.reset(seed=seed)  # the next episodes are the same ones for each agent evaluated here
        mean, std = evaluate_policy(model, env, n_eval_episodes=episodes, deterministic=True)
        out[name] = (float(mean), float(std))
    return out


def main() -> None:
    args = parse_args()
    output = pathlib.Path(args.output)
    output.mkdir(parents=True, exist_ok=True)

    # 1. the robot through its life: Env-A until the switch, Env-B after it; the true physical parameters are appended
    #    to the observation (as in the paper), so one policy can tell the environments apart
    env = DynamicsSchedule(gym.make(ENV_ID), stages=STAGES, switch_at=[args.steps_a], append_params=True)
    eval_envs = {name: Monitor(e) for name, e in stage_envs(ENV_ID, STAGES, NAMES, append_params=True).items()}
    episode_seed = 10_000 + args.seed

    # 2. the online collector keeps every transition in a lifetime buffer on disk, each tagged with its environment
    model = MPO(
        "MlpPolicy",
        env,
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=output / "buffer"),
        policy_kwargs=dict(net_arch=[128, 128]),
        learning_starts=1_000,
        seed=args.seed,
    )
    every = max((args.steps_a + args.steps_b) // 10, 1)
    collecting = MultiEnvEvalCallback(eval_envs, eval_freq=every, n_eval_episodes=args.episodes, seed=args.seed)

    # 3. Env-A, then freeze a copy of the agent at the switch, then Env-B
    model.learn(args.steps_a, callback=collecting)
    model.save(output / "mpo_switch")
    at_switch = evaluate(model, eval_envs, args.episodes, episode_seed)
    model.learn(args.steps_b, callback=collecting, reset_num_timesteps=False)
    model.save(output / "mpo_end")
    at_end = evaluate(model, eval_envs, args.episodes, episode_seed)

    # 4. distil the whole lifetime buffer, offline, with no task boundaries (the paper's choice under imbalance:
    #    the exponential advantage transform with beta = 1)
    distilling = MultiEnvEvalCallback(eval_envs, eval_freq=max(args.updates // 10, 1), n_eval_episodes=args.episodes)
    student = model.distill(CRR, total_updates=args.updates, advantage_transform="exp", beta=1.0, callback=distilling)
    student.save(output / "student")
    distilled = evaluate(student, eval_envs, args.episodes, episode_seed)

    # 5. the numbers: forgetting is the end agent against the frozen one in Env-A; the student should keep both
    with open(output / "returns.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["agent", "env", "mean_return", "std_return", "episodes"])
        for agent, returns in (("mpo_switch", at_switch), ("mpo_end", at_end), ("student", distilled)):
            for name, (mean, std) in returns.items():
                writer.writerow([agent, name, f"{mean:.2f}", f"{std:.2f}", args.episodes])
    with open(output / "curves.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["phase", "step", "env", "mean_return"])
        writer.writeheader()
        for phase, callback in (("collection", collecting), ("distillation", distilling)):
            for row in callback.results:
                writer.writerow(dict(phase=phase, step=row["timesteps"], env=row["env"], mean_return=row["mean_reward"]))
    ratio = at_end["Env-A"][0] / at_switch["Env-A"][0] if at_switch["Env-A"][0] > 0 else float("nan")
    print(f"{'':12}" + "".join(f"{name:>16}" for name in NAMES))
    for agent, returns in (("at switch", at_switch), ("MPO end", at_end), ("student", distilled)):
        print(f"{agent:12}" + "".join(f"{returns[name][0]:16.1f}" for name in NAMES))
    print(f"Env-A, MPO end / at switch: {ratio:.2f} (below 1: forgetting)")

    # 6. the figure: learning curves of the collector per environment, then the three agents side by side
    import matplotlib

    matplotlib.use("Agg")  # files only: no display needed
    import matplotlib.pyplot as plt

    figure, (curves, bars) = plt.subplots(1, 2, figsize=(11, 4))
    for name in NAMES:
        rows = [row for row in collecting.results if row["env"] == name]
        curves.plot([r["timesteps"] for r in rows], [r["mean_reward"] for r in rows], marker="o", label=name)
    curves.axvline(args.steps_a, color="grey", linestyle="--", label="switch to Env-B")
    curves.set(xlabel="environment steps", ylabel="mean return", title="MPO, evaluated in both environments")
    curves.legend()
    width = 0.25
    for k, (agent, returns) in enumerate((("MPO at switch", at_switch), ("MPO end", at_end), ("student", distilled))):
        bars.bar(np.arange(len(NAMES)) + (k - 1) * width, [returns[name][0] for name in NAMES], width, label=agent)
    bars.set_xticks(np.arange(len(NAMES)), NAMES)
    bars.set(ylabel="mean return (same seeded episodes)", title="frozen, end and distilled agents")
    bars.legend()
    figure.tight_layout()
    figure.savefig(output / "two_stage.png", dpi=120)
    print(f"wrote {output}/returns.csv, curves.csv, two_stage.png and the models")


if __name__ == "__main__":
    main()
