"""
Learning curves of MPO vs SB3's SAC on MuJoCo locomotion (Gymnasium v5 tasks).

Each (env, algorithm, seed) run trains with one gradient step per environment step, evaluates the deterministic
policy every ``--eval-freq`` steps on a separate environment, and appends a row to
``benchmarks/studies/mpo_quality/quality/<budget>/<env>__<algo>__s<seed>.csv`` after every evaluation (a stopped run keeps its
curve; ``<budget>`` is the step budget, e.g. ``30k``, so runs of different lengths never overwrite each other).
``--summarise`` turns the CSV files into a table (markdown, one block of rows per budget) and one plot per
environment and budget.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/studies/mpo_quality/bench_mpo_quality.py --envs Hopper-v5 Walker2d-v5 --seeds 0 \
        1 --steps 30000 --jobs 2
    OMP_NUM_THREADS=1 python benchmarks/studies/mpo_quality/bench_mpo_quality.py --envs Hopper-v5 --algos MPO_n5 \
        MPO_penalty --steps 30000
    python benchmarks/studies/mpo_quality/bench_mpo_quality.py --summarise

``--algos`` takes SAC and the MPO variants of :data:`MPO_VARIANTS` (the reference MPOs' options: n-step returns,
the action penalty, observation normalisation, Acme's LayerNorm torso), each with the same networks, batch and
update rate. Each evaluation also records the collecting policy's exploration std on its latest 1,024 states
(percentiles 10 / 50 / 90 of the std averaged over the action dimensions; runs from 2026-11-25 on).
"""

import argparse
import csv
import itertools
import json
import multiprocessing as mp
import pathlib
import time
from typing import Any

import numpy as np

RESULTS = pathlib.Path(__file__).parent

NOTES_MARK = "## Runs and notes"

#: MPO variants by name: constructor settings, and whether observations are normalised (SB3's VecNormalize)
MPO_VARIANTS: dict[str, tuple[dict[str, Any], bool]] = {
    "MPO": ({}, False),
    "MPO_n5": ({"n_steps": 5}, False),
    "MPO_penalty": ({"policy_loss": {"action_penalty": True}}, False),
    "MPO_n5_penalty": ({"n_steps": 5, "policy_loss": {"action_penalty": True}}, False),
    "MPO_obsnorm": ({}, True),
    "MPO_bf16": ({"compute": {"train_dtype": "bfloat16"}}, False),  # bf16 hidden products in the gradient passes
    "MPO_layernorm": ({"policy_kwargs": {"layer_norm": True}}, False),
    "MPO_layernorm_obsnorm": ({"policy_kwargs": {"layer_norm": True}}, True),  # MPO's default since 2026-11-25, normalised
    # the default torso with bf16 hidden products in the gradient passes: native (its pair: MPO_layernorm), and
    # simulated from float32 products (the same numbers at float32's speed, always eager; its pair: MPO_layernorm_eager)
    "MPO_layernorm_bf16": ({"policy_kwargs": {"layer_norm": True}, "compute": {"train_dtype": "bfloat16"}}, False),
    # MPO_layernorm_bf16's pair run beside it on the same code and CPU (MPO_layernorm's own files are older code's)
    "MPO_layernorm_fp32": ({"policy_kwargs": {"layer_norm": True}, "compute": {"train_dtype": "float32"}}, False),
    "MPO_layernorm_bf16sim": (
        {"policy_kwargs": {"layer_norm": True}, "compute": {"train_dtype": "simulated_bfloat16"}},
        False,
    ),
    "MPO_layernorm_eager": ({"policy_kwargs": {"layer_norm": True}, "compute": {"compile_losses": False}}, False),
}
CURVES = RESULTS / "quality"

#: how the figures name each run's algorithm: the plain torso was MPO's default until 2026-11-25, the LayerNorm one since
LABELS = {
    "MPO": "MPO, plain torso (old default)",
    "MPO_n5": "MPO, plain torso, n-step 5",
    "MPO_penalty": "MPO, plain torso, action penalty",
    "MPO_n5_penalty": "MPO, plain torso, n-step 5, action penalty",
    "MPO_obsnorm": "MPO, plain torso, VecNormalize",
    "MPO_layernorm": "MPO, LayerNorm torso (the default)",
    "MPO_layernorm_obsnorm": "MPO, LayerNorm torso (the default), VecNormalize",
    "MPO_layernorm_bf16": "MPO, LayerNorm torso, bf16 gradient passes",
    "MPO_layernorm_fp32": "MPO, LayerNorm torso, float32 gradient passes",
    "MPO_layernorm_bf16sim": "MPO, LayerNorm torso, bf16 gradient passes (simulated)",
    "MPO_layernorm_eager": "MPO, LayerNorm torso, eager",
    "SAC": "SAC",
}
#: their colours: the default MPO and SAC as in every figure of the package (sb3_lifelong.experiments.style)
COLORS = {
    "MPO": "#e6ab02",
    "MPO_n5": "#8c564b",
    "MPO_penalty": "#e377c2",
    "MPO_n5_penalty": "#bcbd22",
    "MPO_obsnorm": "#9467bd",
    "MPO_layernorm": "#1f77b4",
    "MPO_layernorm_obsnorm": "#17becf",
    "MPO_layernorm_fp32": "#2ca02c",
    "MPO_layernorm_bf16": "#d62728",
    "SAC": "#222222",
}


def budget_name(steps: int) -> str:
    """The folder of a step budget's curves: ``30000`` -> ``"30k"``."""
    return f"{steps // 1000}k" if steps % 1000 == 0 else str(steps)


def policy_std(model: Any, count: int = 1024) -> np.ndarray:
    """
    The exploration noise of the collecting policy on the latest ``count`` observations of its replay buffer (read in
    place: no random number is drawn, so a run is the same with or without this probe).

    :param model: an MPO (its Gaussian's std, in action units) or a SAC (the std before its tanh squashing)
    :param count: how many of the latest observations
    :return: the 10th, 50th and 90th percentiles over those states of the std averaged over the action dimensions
    """
    import torch as th

    buffer = model.replay_buffer
    end = buffer.pos if buffer.pos > 0 else buffer.buffer_size  # the latest rows are just before the write position
    observations = buffer.observations[max(0, end - count) : end].reshape(-1, *buffer.obs_shape)
    if model.get_vec_normalize_env() is not None:
        observations = model.get_vec_normalize_env().normalize_obs(observations)
    with th.no_grad():
        obs = th.as_tensor(observations, dtype=th.float32, device=model.device)
        if hasattr(model.actor, "distribution_params"):
            _, std = model.actor.distribution_params(obs)
        else:
            _, log_std, _ = model.actor.get_action_dist_params(obs)
            std = log_std.exp()
    return np.percentile(std.mean(dim=-1).cpu().numpy(), [10, 50, 90])


def run_one(config: tuple[str, str, int, int, int, int, int]) -> str:
    env_id, algo, seed, steps, eval_freq, eval_episodes, learning_starts = config
    import gymnasium as gym
    import torch as th
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.monitor import Monitor

    from sb3_lifelong import MPO

    th.set_num_threads(1)
    folder = CURVES / budget_name(steps)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{env_id}__{algo}__s{seed}.csv"
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    common: dict[str, Any] = dict(batch_size=256, learning_starts=learning_starts, seed=seed, verbose=0)
    policy_kwargs = dict(net_arch=[256, 256])
    settings, normalise = MPO_VARIANTS.get(algo, ({}, False))
    env: Any = env_id
    eval_env: Any = Monitor(gym.make(env_id))
    eval_env.reset(seed=10_000 + seed)
    if normalise:  # statistics from the training env, frozen copies for evaluation
        env = VecNormalize(DummyVecEnv([lambda: gym.make(env_id)]), norm_reward=False)
        eval_env = VecNormalize(DummyVecEnv([lambda: Monitor(gym.make(env_id))]), norm_reward=False, training=False)
        eval_env.seed(10_000 + seed)
    model: Any
    if algo == "SAC":
        model = SAC("MlpPolicy", env, policy_kwargs=policy_kwargs, **common)
    else:
        settings = dict(settings)
        # same sizes, the variant's options; the variants without "layernorm" in their name without it (as they ran)
        network = {**policy_kwargs, "layer_norm": False, **settings.pop("policy_kwargs", {})}
        model = MPO("MlpPolicy", env, policy_kwargs=network, **settings, **common)
    start = time.perf_counter()

    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(
            ["timesteps", "mean_return", "std_return", "wall_s", "policy_std_p10", "policy_std_median", "policy_std_p90"]
        )

        class Evaluate(BaseCallback):
            def _on_step(self) -> bool:
                if self.num_timesteps % eval_freq == 0:
                    if normalise:
                        eval_env.obs_rms = model.get_vec_normalize_env().obs_rms  # type: ignore[union-attr]
                    mean, std = evaluate_policy(self.model, eval_env, n_eval_episodes=eval_episodes, deterministic=True)
                    spread = [f"{value:.3f}" for value in policy_std(model)]
                    wall = f"{time.perf_counter() - start:.1f}"
                    writer.writerow([self.num_timesteps, f"{mean:.2f}", f"{std:.2f}", wall, *spread])
                    handle.flush()
                return True

        model.learn(steps, callback=Evaluate())
    return str(path)


def summarise() -> None:
    from sb3_lifelong.experiments.statistics import bootstrap_ci, paired_difference
    from sb3_lifelong.experiments.style import method_color, pyplot, save, steps_axis

    plt = pyplot()

    curves: dict[tuple[str, str, str], list[np.ndarray]] = {}
    seeds: dict[tuple[str, str, str], list[int]] = {}
    for path in sorted(CURVES.glob("*/*.csv"), key=lambda p: (int(p.parent.name.rstrip("k")), p.name)):
        env_id, algo, seed = path.stem.split("__")
        data = np.genfromtxt(path, delimiter=",", skip_header=1, ndmin=2)
        budget = path.parent.name
        steps = int(budget[:-1]) * 1000 if budget.endswith("k") else int(budget)
        if data.size and data[-1, 0] >= steps:  # a run still going (or stopped) is left out of the table
            curves.setdefault((budget, env_id, algo), []).append(data)
            seeds.setdefault((budget, env_id, algo), []).append(int(seed.lstrip("s")))
    scores: dict[tuple[str, str, str], dict[int, tuple[float, float]]] = {}  # seed -> (final, mean of the last 3)
    lines = [
        "| budget | env | algorithm | seeds | steps reached | final return (mean +- std over seeds, ddof=0) "
        "| 95 % BCa bootstrap CI | per seed | last 3 evals (mean +- std over seeds) | best eval (mean over seeds) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for (budget, env_id, algo), runs in curves.items():
        reached = min(int(run[-1, 0]) for run in runs)
        finals = [run[run[:, 0] <= reached][-1, 1] for run in runs]
        bests = [run[:, 1].max() for run in runs]
        lasts = [run[run[:, 0] <= reached][-3:, 1].mean() for run in runs]  # one evaluation swings; three less
        low, high = bootstrap_ci(finals)
        scores[(budget, env_id, algo)] = dict(zip(seeds[(budget, env_id, algo)], zip(finals, lasts)))
        lines.append(
            f"| {budget} | {env_id} | {algo} | {len(runs)} | {reached} | {np.mean(finals):.0f} +- {np.std(finals):.0f} | "
            f"[{low:.0f}, {high:.0f}] | {', '.join(f'{value:.0f}' for value in finals)} | "
            f"{np.mean(lasts):.0f} +- {np.std(lasts):.0f} | {np.mean(bests):.0f} |"
        )
    lines += [
        "",
        "Each MPO variant against SAC, paired by seed (the same seed's runs: first minus second; 95 % BCa bootstrap "
        "interval of the mean difference; on how many of the paired seeds MPO is higher):",
        "",
        "| budget | env | algorithm | seeds paired | final return: MPO - SAC [95 % BCa CI] | MPO higher on "
        "| last 3 evals: MPO - SAC [95 % BCa CI] | MPO higher on |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for (budget, env_id, algo), mine in scores.items():
        sac = scores.get((budget, env_id, "SAC"))
        if algo == "SAC" or sac is None:
            continue
        final = paired_difference({s: v[0] for s, v in mine.items()}, {s: v[0] for s, v in sac.items()})
        last = paired_difference({s: v[1] for s, v in mine.items()}, {s: v[1] for s, v in sac.items()})
        if final["n"] < 2:
            continue
        lines.append(
            f"| {budget} | {env_id} | {algo} | {final['n']} "
            f"| {final['mean']:+.0f} [{final['low']:+.0f}, {final['high']:+.0f}] "
            f"| {final['wins']:g} of {final['n']} | {last['mean']:+.0f} [{last['low']:+.0f}, {last['high']:+.0f}] "
            f"| {last['wins']:g} of {last['n']} |"
        )
    table = "\n".join(lines)
    print(table)
    # the notes written under the table (how the runs were made, what they show) are kept when it is redrawn
    path = RESULTS / "mpo_quality.md"
    notes = path.read_text().split(NOTES_MARK, 1)[1] if path.exists() and NOTES_MARK in path.read_text() else ""
    path.write_text(
        "# MPO vs SAC: evaluation return (deterministic policy, 5 episodes per evaluation)\n\n"
        "All runs: 256x256 networks, batch 256, one update per step, SB3 defaults otherwise (MPO: N=20, hard target "
        "copy every 100 updates; its variants change only what their name says, see `MPO_VARIANTS`). Per-run curves: "
        "`quality/`. Table redrawn by `python benchmarks/studies/mpo_quality/bench_mpo_quality.py --summarise`.\n\n"
        + table
        + "\n\n"
        + NOTES_MARK
        + notes
    )
    for budget, env_id in dict.fromkeys((budget, env) for budget, env, _ in curves):
        fig, ax = plt.subplots(figsize=(9.5, 4.2))
        for (run_budget, env, algo), runs in sorted(curves.items()):
            if (run_budget, env) != (budget, env_id):
                continue
            length = min(len(run) for run in runs)
            steps = runs[0][:length, 0]
            returns = np.stack([run[:length, 1] for run in runs])
            color = COLORS.get(algo) or method_color(algo)
            ax.plot(steps, returns.mean(0), color=color, linewidth=1.8, label=f"{LABELS.get(algo, algo)} ({len(runs)} seeds)")
            ax.fill_between(steps, returns.min(0), returns.max(0), color=color, alpha=0.15, linewidth=0)
        steps_axis(ax, "environment steps")
        ax.set_ylabel("evaluation return (deterministic policy)")
        ax.set_title(f"MPO vs SAC on {env_id}, {budget} steps (256x256 networks)")
        ax.grid(alpha=0.3)
        ax.legend(
            title="line: mean; band: min to max over seeds",
            fontsize=8,
            title_fontsize=8,
            loc="upper left",
            bbox_to_anchor=(1.02, 1.0),
        )
        save(plt, fig, RESULTS / f"mpo_quality_{env_id}_{budget}.png", dpi=100)


def paired_verdict(base: dict[int, float], other: dict[int, float]) -> dict[str, Any]:
    """
    The rule pre-registered for bf16 gradient passes (``benchmarks/results/speed/fast_paths.md``, "Still open for goal 4"),
    per robot, on the final evaluation's return paired by seed: **pass** where the whole 95 % t interval of the
    difference (other minus base) lies within one standard deviation of the base seeds' returns, **fail** where it
    excludes 0, **inconclusive** otherwise; where both of the first two hold (a difference shown, smaller than the
    spread), ``"within the spread, a difference shown"``.

    :param base: final return by seed of the float32 runs
    :param other: final return by seed of the runs compared with them
    :return: the statistics and ``verdict`` (``"too few seeds"`` under 2 paired, ``"non-finite return"`` where a
        paired return is NaN or infinite, e.g. a diverged run)
    """
    from sb3_lifelong.experiments.statistics import t_interval

    seeds = sorted(set(base) & set(other))
    if len(seeds) < 2:
        return {"seeds": seeds, "verdict": "too few seeds"}
    if not all(np.isfinite([base[seed] for seed in seeds] + [other[seed] for seed in seeds])):
        return {"seeds": seeds, "verdict": "non-finite return"}
    base_mean, spread, _, _ = t_interval([base[seed] for seed in seeds])
    other_mean, other_std, _, _ = t_interval([other[seed] for seed in seeds])
    difference, _, low, high = t_interval([other[seed] - base[seed] for seed in seeds])
    within, shown = -spread <= low and high <= spread, high < 0.0 or low > 0.0
    # the rule did not say which reading wins where both hold; settled before the first pair's verdict was computed
    # (2026-11-26, 23:32 UTC): both are reported, neither is called a plain pass or fail
    if within:
        verdict = "within the spread, a difference shown" if shown else "pass"
    else:
        verdict = "fail" if shown else "inconclusive"
    return {
        "seeds": seeds,
        "base_mean": base_mean,
        "base_std": spread,
        "other_mean": other_mean,
        "other_std": other_std,
        "difference_mean": difference,
        "difference_ci95": [low, high],
        "verdict": verdict,
    }


def final_returns(env_id: str, algo: str, budget: str = "100k") -> dict[int, float]:
    """
    :param env_id: the environment
    :param algo: the variant
    :param budget: the step budget's folder under ``results/quality``
    :return: the final evaluation's return by seed, of the runs that reached the budget (a run still going is left out)
    """
    steps = int(budget[:-1]) * 1000
    finals = {}
    for path in sorted((CURVES / budget).glob(f"{env_id}__{algo}__s*.csv")):
        data = np.genfromtxt(path, delimiter=",", skip_header=1, ndmin=2)
        if data.size and data[-1, 0] >= steps:
            finals[int(path.stem.split("__s")[-1])] = float(data[-1, 1])
    return finals


def report_pair(envs: list[str], base: str, other: str) -> dict[str, dict[str, Any]]:
    """
    Print the paired verdict per robot, and write it to ``results/quality/paired_<base>_<other>.json``.

    :param envs: the robots
    :param base: the float32 variant
    :param other: the variant compared with it
    :return: by robot, the final returns per seed and :func:`paired_verdict`'s result
    """
    if base == other:
        raise ValueError(f"--paired needs two different variants, got {base} twice")
    results = {}
    for env_id in envs:
        finals = {algo: final_returns(env_id, algo) for algo in (base, other)}
        results[env_id] = {"per_seed": finals, **paired_verdict(finals[base], finals[other])}
        r = results[env_id]
        if "difference_ci95" in r:
            low, high = r["difference_ci95"]
            print(
                f"{env_id}: seeds {r['seeds']}; {base} {r['base_mean']:.1f} +- {r['base_std']:.1f}, {other} "
                f"{r['other_mean']:.1f} +- {r['other_std']:.1f}; difference {r['difference_mean']:+.1f} "
                f"[{low:+.1f}, {high:+.1f}]: {r['verdict']}"
            )
        else:
            print(f"{env_id}: seeds {r['seeds']}: {r['verdict']}")
    path = CURVES / f"paired_{base}_{other}.json"
    path.write_text(json.dumps(results, indent=2) + "\n")
    print("->", path)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["Hopper-v5", "Walker2d-v5"])
    parser.add_argument("--algos", nargs="+", default=["MPO", "SAC"], choices=["SAC", *MPO_VARIANTS])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--eval-freq", type=int, default=5000)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--learning-starts", type=int, default=5000)
    parser.add_argument("--jobs", type=int, default=1, help="runs in parallel (one torch thread each)")
    parser.add_argument("--summarise", action="store_true", help="only summarise the existing CSV files")
    parser.add_argument(
        "--paired", nargs=2, metavar=("BASE", "OTHER"), help="only the pre-registered paired verdict of two variants at 100k"
    )
    args = parser.parse_args()
    if args.paired:
        report_pair(args.envs, *args.paired)
        return
    if not args.summarise:
        # seed-major order: with --jobs 2 the MPO and SAC runs of one (seed, env) run side by side
        configs = [
            (env, algo, seed, args.steps, args.eval_freq, args.eval_episodes, args.learning_starts)
            for seed, env, algo in itertools.product(args.seeds, args.envs, args.algos)
        ]
        with mp.get_context("spawn").Pool(args.jobs) as pool:
            for path in pool.imap_unordered(run_one, configs):
                print("done:", path, flush=True)
    summarise()


if __name__ == "__main__":
    main()
