"""
The lifelong experiment of ``examples/parallel_sharing.py``: its
configurations (:data:`EXAMPLE_CONFIGS`), environment factories, the collector, its evaluations and the summary.
The paper's protocol (two stages or more, its runner, report and claims) is :mod:`sb3_lifelong.experiments.protocol`
(its presets: :mod:`sb3_lifelong.experiments.presets`); ``examples/three_stage.py`` and
``examples/continuous_drift.py`` run on it (:mod:`sb3_lifelong.experiments.example`).

Layout of an experiment's output directory::

    <output>/seed_<k>/<method>/eval.csv      timesteps, env, mean_reward, std_reward, n_episodes
    <output>/seed_<k>/<method>/q_sources.csv  average Q per source of the buffer
    <output>/seed_<k>/stages.json             the environments' names, the stage switches, the distilled methods
    <output>/tensorboard/                     one run per method and seed (distillation inside the collector's run)
    <output>/summary.csv, summary.md          final return per method, env and seed
    <output>/*.png                            the figures (python -m sb3_lifelong.plotting <output>)

Online methods are evaluated every ``eval_freq`` environment steps; the distilled students every
``distill_eval_freq`` updates, by default :data:`DISTILL_EVALUATIONS` times per distillation (and before the first
update), so that every preset draws distillation curves.

Methods: the collectors (``MPO``; ``MPO_agent1``, ``MPO_agent2`` in parallel sharing), ``distilled`` (CRR, exp
transform, beta=1, on the collected data) and, in parallel sharing, ``distilled_indicator`` (same, indicator
transform: the imbalance baseline).
"""

import argparse
import csv
import json
import pathlib
import shutil
import time
from collections.abc import Mapping, Sequence
from typing import Any, Optional, Union

import gymnasium as gym
import numpy as np
import torch as th

import sb3_lifelong.envs  # noqa: F401  (registers the OP3 task)
from sb3_lifelong import MPO, LifelongReplayBuffer
from sb3_lifelong.core.atomic import atomic_write, write_text_atomic
from sb3_lifelong.envs import DynamicsSchedule
from sb3_lifelong.evaluation.callbacks import EVAL_SEED_OFFSET, MultiEnvEvalCallback, SourceQCallback
from sb3_lifelong.experiments.figures import source_labels

Stage = Union[str, Mapping[str, float]]

#: evaluations of a distilled student over its distillation, whatever the preset (``--distill-eval-freq`` overrides)
DISTILL_EVALUATIONS = 10
#: per seed: what the figures need to know about the experiment (see :func:`write_layout`)
LAYOUT_FILE = "stages.json"

#: the examples' configurations, by name (``--preset``): what :func:`resolve_config` starts from
EXAMPLE_CONFIGS: dict[str, dict[str, Any]] = {
    # minutes on 2 CPU cores: HalfCheetah, small networks
    "quick": dict(
        env_id="HalfCheetah-v5",
        stage_steps=[10_000, 20_000],
        distill_steps=10_000,
        eval_freq=2_500,
        eval_episodes=3,
        seeds=[0],
        net_arch=[64, 64],
        batch_size=128,
        num_samples=10,
        learning_starts=2_000,
        learning_rate=1e-3,
    ),
    # the paper's set-up: OP3 walking, 0.2M steps in Env-A then 1M in Env-B, 3 seeds
    "paper": dict(
        env_id="sb3_lifelong/OP3Walk-v0",
        stage_steps=[200_000, 1_000_000],
        distill_steps=500_000,
        eval_freq=20_000,
        eval_episodes=5,
        seeds=[0, 1, 2],
        net_arch=[256, 256],
        batch_size=256,
        num_samples=20,
        learning_starts=10_000,
        learning_rate=3e-4,
    ),
    # seconds: for the tests
    "tiny": dict(
        env_id="HalfCheetah-v5",
        stage_steps=[300, 300],
        distill_steps=200,
        eval_freq=150,
        eval_episodes=1,
        seeds=[0],
        net_arch=[16, 16],
        batch_size=32,
        num_samples=4,
        learning_starts=100,
        learning_rate=1e-3,
        max_episode_steps=100,
    ),
}


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--preset",
        choices=sorted(EXAMPLE_CONFIGS),
        default="quick",
        help="quick: HalfCheetah, small networks, minutes on a CPU; paper: the OP3 set-up of the paper (GPU-scale); "
        "tiny: seconds, for the tests",
    )
    parser.add_argument("--paper", action="store_const", const="paper", dest="preset", help="same as --preset paper")
    parser.add_argument("--output", default=None, help="output directory (default: runs/<script>_<preset>)")
    parser.add_argument("--env", default=None, help="override the preset's environment id")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="seeds to run one after the other")
    parser.add_argument("--stage-steps", type=int, nargs="+", default=None, help="environment steps of each stage")
    parser.add_argument("--distill-steps", type=int, default=None, help="offline updates of every distilled student")
    parser.add_argument(
        "--eval-freq", type=int, default=None, help="evaluation period of the online methods (environment steps)"
    )
    parser.add_argument(
        "--distill-eval-freq",
        type=int,
        default=None,
        help=f"evaluation period of the distilled students (updates; default: distill steps / {DISTILL_EVALUATIONS})",
    )
    parser.add_argument("--no-baselines", action="store_true", help="skip the online CRR baselines")
    parser.add_argument("--no-plots", action="store_true", help="write the CSV files and the summary, no figures")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="delete the output directory first (without it, a run refuses seeds already there and other settings)",
    )


def resolve_config(args: argparse.Namespace) -> dict[str, Any]:
    config = dict(EXAMPLE_CONFIGS[args.preset])
    overrides = dict(
        env_id=args.env,
        seeds=args.seeds,
        stage_steps=args.stage_steps,
        distill_steps=args.distill_steps,
        eval_freq=args.eval_freq,
    )
    config.update({key: value for key, value in overrides.items() if value is not None})
    config["distill_eval_freq"] = getattr(args, "distill_eval_freq", None) or distill_eval_freq(config["distill_steps"])
    config["preset"] = args.preset
    return config


def prepare_output(output: pathlib.Path, config: dict[str, Any], overwrite: bool = False, **extra: Any) -> None:
    """
    Make the output directory of a run, never mixing runs silently: seeds of separate runs may share a directory
    (they are summarised together) only when their settings are the same, and a seed already there is not redone.

    :param output: the output directory
    :param config: the run's settings (:func:`resolve_config`); recorded in ``<output>/config.json``
    :param overwrite: delete the directory first
    :param extra: further settings of the example (e.g. its set-up), recorded and compared with the others
    :raises FileExistsError: when a seed of this run is already in ``output``, or ``output`` holds a run with
        other settings
    """
    if overwrite and output.exists():
        shutil.rmtree(output)
    settings = json.loads(json.dumps({**{k: v for k, v in config.items() if k != "seeds"}, **extra}, default=str))
    recorded = output / "config.json"
    if recorded.exists() and json.loads(recorded.read_text()) != settings:
        raise FileExistsError(
            f"{output} holds a run with other settings ({recorded}); their seeds would be summarised together. "
            "Choose another --output, or pass --overwrite to delete it and start again."
        )
    there = [seed for seed in config["seeds"] if (output / f"seed_{seed}").exists()]
    if there:
        raise FileExistsError(
            f"seed(s) {there} already in {output} from an earlier run. Run other --seeds to add them to the summary, "
            "choose another --output, or pass --overwrite to delete the directory and start again."
        )
    output.mkdir(parents=True, exist_ok=True)
    write_text_atomic(recorded, json.dumps(settings, indent=1))


def distill_eval_freq(distill_steps: int) -> int:
    """
    :param distill_steps: offline updates of a distillation
    :return: the evaluation period that evaluates a student :data:`DISTILL_EVALUATIONS` times
    """
    return max(1, int(distill_steps) // DISTILL_EVALUATIONS)


def write_layout(
    run_dir: pathlib.Path,
    names: Sequence[str],
    distilled: Sequence[str],
    switch_at: Sequence[int] = (),
    switch_labels: Optional[Sequence[str]] = None,
    sources: Optional[Mapping[str, str]] = None,
    stages: Optional[Sequence[Stage]] = None,
) -> pathlib.Path:
    """
    Write what the figures need to know about one seed's experiment (``<run_dir>/stages.json``).

    :param run_dir: the seed's directory
    :param names: the evaluation environments' names (the stages', in order, for the sequential experiments)
    :param distilled: the methods trained offline (their ``eval.csv`` counts updates, not environment steps)
    :param switch_at: the environment steps at which the environment changes
    :param switch_labels: what changes at each switch (default ``"<names[i]> -> <names[i + 1]>"``)
    :param sources: legend label of each source of the buffers, by source name (default: source ``stage_<i>`` is
        ``names[i]``)
    :param stages: the stages' dynamics, for the record
    :return: the file written
    """
    labels = list(switch_labels) if switch_labels is not None else [f"{a} -> {b}" for a, b in zip(names, names[1:])]
    if len(labels) < len(switch_at):
        raise ValueError(f"{len(switch_at)} switches need {len(switch_at)} labels, got {labels}")
    layout: dict[str, Any] = dict(
        names=list(names),
        switch_at=[int(t) for t in switch_at],
        switch_labels=labels[: len(switch_at)],
        distilled=list(distilled),
        sources=dict(sources) if sources is not None else source_labels(names),
    )
    if stages is not None:
        layout["stages"] = [stage if isinstance(stage, str) else dict(stage) for stage in stages]
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LAYOUT_FILE
    write_text_atomic(path, json.dumps(layout))
    return path


def make_schedule(
    env_id: str,
    stages: Sequence[Stage],
    switch_at: Optional[Sequence[int]] = None,
    max_episode_steps: Optional[int] = None,
    **kwargs: Any,
) -> Any:
    """The robot with its lifetime of stages; the true physical parameters are appended to the observation."""
    return DynamicsSchedule(
        gym.make(env_id, **episode_limit(max_episode_steps)),
        stages=list(stages),
        switch_at=switch_at,
        append_params=True,
        **kwargs,
    )


def episode_limit(max_episode_steps: Optional[int]) -> dict[str, Any]:
    """:return: the keyword arguments of ``gym.make`` that cut episodes at ``max_episode_steps`` (None: the env's own)"""
    return {} if max_episode_steps is None else dict(max_episode_steps=max_episode_steps)


def algo_kwargs(config: dict[str, Any], seed: int) -> dict[str, Any]:
    return dict(
        # the same torso for MPO and CRR (the online CRR starts from MPO's weights); the configs ran without LayerNorm
        policy_kwargs=dict(net_arch=list(config["net_arch"]), layer_norm=config.get("layer_norm", False)),
        batch_size=config["batch_size"],
        learning_rate=config["learning_rate"],
        seed=seed,
    )


def eval_callbacks(
    directory: pathlib.Path,
    eval_envs: dict[str, Any],
    config: dict[str, Any],
    source_q: bool = True,
    sources: Optional[dict[str, int]] = None,
    offline: bool = False,
    seed: Optional[int] = None,
) -> list[Any]:
    """
    The evaluation (``eval.csv``) and Q-per-source (``q_sources.csv``) callbacks of one method.

    :param directory: the method's directory
    :param eval_envs: the evaluation environments, by name
    :param config: the experiment's configuration (``eval_freq``, ``distill_eval_freq``, ``eval_episodes``)
    :param source_q: also log the critic's average Q on each source of the buffer
    :param sources: the source whose actor acts in each environment (one actor per source), or None
    :param offline: a distillation: evaluate every ``distill_eval_freq`` updates and before the first one
    :param seed: the run's seed: the evaluation environments are seeded from ``EVAL_SEED_OFFSET + seed`` (None:
        unseeded)
    :return: the callbacks
    """
    directory.mkdir(parents=True, exist_ok=True)
    if offline:
        freq = config.get("distill_eval_freq") or distill_eval_freq(config["distill_steps"])
    else:
        freq = config["eval_freq"]
    callbacks: list[Any] = [
        MultiEnvEvalCallback(
            eval_envs,
            eval_freq=freq,
            n_eval_episodes=config["eval_episodes"],
            log_path=directory / "eval.csv",
            eval_at_start=offline,
            sources=sources,
            seed=None if seed is None else EVAL_SEED_OFFSET + seed,
        )
    ]
    if source_q:
        callbacks.append(SourceQCallback(log_freq=freq, log_path=directory / "q_sources.csv"))
    return callbacks


def make_collector(
    env: Any, config: dict[str, Any], seed: int, tensorboard_log: Optional[str], buffer_path: Optional[str] = None
) -> MPO:
    """MPO with a lifetime buffer (in memory, or on disk at ``buffer_path``)."""
    return MPO(
        "MlpPolicy",
        env,
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=buffer_path) if buffer_path is not None else None,
        learning_starts=config["learning_starts"],
        num_samples=config["num_samples"],
        tensorboard_log=tensorboard_log,
        **algo_kwargs(config, seed),
    )


def final_returns(callback: MultiEnvEvalCallback) -> dict[str, float]:
    """:return: the mean reward of the last evaluation, per environment"""
    if not callback.results:
        callback.evaluate()
    last = max(row["timesteps"] for row in callback.results)
    return {row["env"]: row["mean_reward"] for row in callback.results if row["timesteps"] == last}


def write_summary(output: pathlib.Path, rows: list[dict[str, Any]], config: dict[str, Any], elapsed: float) -> str:
    """Write ``summary.csv`` / ``summary.md`` (mean +- std over seeds) and return the markdown table."""
    with atomic_write(output / "summary.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["seed", "method", "env", "final_return"])
        writer.writeheader()
        writer.writerows(rows)
    methods = list(dict.fromkeys(row["method"] for row in rows))
    envs = list(dict.fromkeys(row["env"] for row in rows))
    header = "| method | " + " | ".join(envs) + " | mean over envs |"
    lines = [header, "|" + " --- |" * (len(envs) + 2)]
    for method in methods:
        cells = []
        per_seed_means: dict[int, list[float]] = {}
        for env in envs:
            values = [row["final_return"] for row in rows if row["method"] == method and row["env"] == env]
            for row in rows:
                if row["method"] == method and row["env"] == env:
                    per_seed_means.setdefault(row["seed"], []).append(row["final_return"])
            cells.append(f"{np.mean(values):.0f} +- {np.std(values):.0f}" if values else "-")
        overall = [float(np.mean(v)) for v in per_seed_means.values()]
        lines.append(f"| {method} | " + " | ".join(cells) + f" | {np.mean(overall):.0f} +- {np.std(overall):.0f} |")
    table = "\n".join(lines)
    seeds = sorted({row["seed"] for row in rows})
    write_text_atomic(
        output / "summary.md",
        f"# {output.name}\n\nFinal evaluation return (mean +- std over seeds {seeds}; deterministic policy, "
        f"{config['eval_episodes']} episodes per env).\n\n{table}\n\nConfig: `{json.dumps(config)}`\n\n"
        f"Wall clock (of the last invocation): {elapsed:.0f} s\n",
    )
    return table


def merge_previous_seeds(output: pathlib.Path, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """
    Seeds run by separate invocations into the same output directory are summarised together: the rows of
    ``summary.csv`` from earlier runs are kept for the seeds that this run did not redo.

    :return: all rows, sorted by seed
    """
    previous = output / "summary.csv"
    if not previous.exists():
        return rows
    redone = {row["seed"] for row in rows}
    with open(previous, newline="") as handle:
        kept = [
            dict(seed=int(row["seed"]), method=row["method"], env=row["env"], final_return=float(row["final_return"]))
            for row in csv.DictReader(handle)
            if int(row["seed"]) not in redone
        ]
    if kept:
        print(f"summary: keeping the results of seeds {sorted({row['seed'] for row in kept})} from {previous}")
    return sorted(kept + rows, key=lambda row: row["seed"])


def finish(output: pathlib.Path, rows: list[dict[str, Any]], config: dict[str, Any], elapsed: float, plots: bool) -> None:
    """Write and print the summary table (with earlier seeds of the same directory), then the figures."""
    print(write_summary(output, merge_previous_seeds(output, rows), config, elapsed))
    if plots:
        from sb3_lifelong.experiments.figures import plot_experiment

        for path in plot_experiment(output):
            print("wrote", path)


def set_threads() -> None:
    th.set_num_threads(1)


def now() -> float:
    return time.perf_counter()
