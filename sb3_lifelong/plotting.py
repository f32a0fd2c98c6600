"""
Turn an experiment's logs into the paper's figures (PNG).

Reads the layout the example scripts write (``<dir>/seed_<k>/<method>/eval.csv`` and ``q_sources.csv``,
``<dir>/seed_<k>/stages.json``) and writes into ``<dir>``:

- ``curves_<env>.png``: evaluation return in each environment against environment steps, for the online methods
  (mean over seeds, min-max band), stage switches as vertical lines and the distilled policies' final return as
  dotted horizontal lines;
- ``final_returns.png``: bar plot of the final return of every method in every environment (mean +- std over seeds);
- ``q_sources.png``: the collector's average Q-value on each source's data (the overestimation curves);
- ``distillation.png``: the distilled policies' return against offline updates.

Usage::

    python -m sb3_lifelong.plotting runs/two_stage_quick
"""

import argparse
import csv
import json
import pathlib
from collections import defaultdict
from typing import Any, Union

import numpy as np

ONLINE = ("MPO", "CRR_indicator", "CRR_beta1", "SAC", "TD3")
COLORS = {
    "MPO": "tab:blue",
    "CRR_indicator": "tab:orange",
    "CRR_beta1": "tab:green",
    "distilled": "tab:red",
    "distilled_indicator": "tab:purple",
    "distilled_per_source": "tab:brown",
}


def _read_csv(path: pathlib.Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def load_experiment(directory: Union[str, pathlib.Path]) -> dict[str, Any]:
    """
    :param directory: an experiment's output directory
    :return: ``{"eval": {method: {env: {seed: (steps, returns)}}}, "q": {method: {source: {seed: (steps, q)}}},
        "stages": dict or None}``
    """
    root = pathlib.Path(directory)
    evals: dict[str, dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]] = defaultdict(lambda: defaultdict(dict))
    qs: dict[str, dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]] = defaultdict(lambda: defaultdict(dict))
    stages = None
    seed_dirs = sorted(root.glob("seed_*"))
    if not seed_dirs:
        raise FileNotFoundError(f"no seed_<k> directories under {root}: is it an experiment's output directory?")
    for seed_dir in seed_dirs:
        seed = int(seed_dir.name.split("_", 1)[1])
        if (seed_dir / "stages.json").exists() and stages is None:
            stages = json.loads((seed_dir / "stages.json").read_text())
        for method_dir in sorted(p for p in seed_dir.iterdir() if p.is_dir()):
            if (method_dir / "eval.csv").exists():
                per_env: dict[str, list[tuple[float, float]]] = defaultdict(list)
                for row in _read_csv(method_dir / "eval.csv"):
                    per_env[row["env"]].append((float(row["timesteps"]), float(row["mean_reward"])))
                for env, points in per_env.items():
                    array = np.array(sorted(points))
                    evals[method_dir.name][env][seed] = (array[:, 0], array[:, 1])
            if (method_dir / "q_sources.csv").exists():
                per_source: dict[str, list[tuple[float, float]]] = defaultdict(list)
                for row in _read_csv(method_dir / "q_sources.csv"):
                    per_source[row["name"]].append((float(row["timesteps"]), float(row["q_mean"])))
                for source, points in per_source.items():
                    array = np.array(sorted(points))
                    qs[method_dir.name][source][seed] = (array[:, 0], array[:, 1])
    return {"eval": evals, "q": qs, "stages": stages}


def _stack(per_seed: dict[int, tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    length = min(len(steps) for steps, _ in per_seed.values())
    steps = next(iter(per_seed.values()))[0][:length]
    return steps, np.stack([values[:length] for _, values in per_seed.values()])


def plot_experiment(directory: Union[str, pathlib.Path]) -> list[pathlib.Path]:
    """
    Write the figures of an experiment into its directory.

    :param directory: the experiment's output directory
    :return: the paths written
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    root = pathlib.Path(directory)
    data = load_experiment(root)
    evals, qs, stages = data["eval"], data["q"], data["stages"]
    switch_at = stages["switch_at"] if stages else []
    envs = sorted({env for per_env in evals.values() for env in per_env})
    written = []

    for env in envs:
        fig, ax = plt.subplots(figsize=(6.5, 4))
        for method in [m for m in evals if m in ONLINE or not m.startswith("distilled")]:
            if env not in evals[method]:
                continue
            steps, values = _stack(evals[method][env])
            ax.plot(steps, values.mean(0), label=f"{method} ({values.shape[0]} seeds)", color=COLORS.get(method))
            ax.fill_between(steps, values.min(0), values.max(0), alpha=0.15, color=COLORS.get(method))
        for method in [m for m in evals if m.startswith("distilled")]:
            if env in evals[method]:
                finals = [values[-1] for _, values in evals[method][env].values()]
                ax.axhline(np.mean(finals), linestyle=":", linewidth=2, color=COLORS.get(method), label=f"{method} (final)")
        for t in switch_at:
            ax.axvline(t, color="gray", linestyle="--", linewidth=1)
        ax.set_xlabel("environment steps")
        ax.set_ylabel("evaluation return")
        ax.set_title(f"Evaluated in {env}")
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = root / f"curves_{env}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)

    methods = list(evals)
    if methods and envs:
        fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(methods), 4))
        width = 0.8 / len(envs)
        for index, env in enumerate(envs):
            means, stds = [], []
            for method in methods:
                finals = [values[-1] for _, values in evals[method].get(env, {}).values()]
                means.append(np.mean(finals) if finals else np.nan)
                stds.append(np.std(finals) if finals else 0.0)
            positions = np.arange(len(methods)) + (index - (len(envs) - 1) / 2) * width
            ax.bar(positions, means, width, yerr=stds, label=env, capsize=3)
        ax.set_xticks(np.arange(len(methods)))
        ax.set_xticklabels(methods, rotation=20, fontsize=8)
        ax.set_ylabel("final evaluation return")
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = root / "final_returns.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)

    if "MPO" in qs:
        fig, ax = plt.subplots(figsize=(6.5, 4))
        for source, per_seed in sorted(qs["MPO"].items()):
            steps, values = _stack(per_seed)
            ax.plot(steps, values.mean(0), label=f"Q on {source} data")
        for t in switch_at:
            ax.axvline(t, color="gray", linestyle="--", linewidth=1)
        ax.set_xlabel("environment steps")
        ax.set_ylabel("average Q (MPO critic)")
        ax.set_title("Q-values per source of the lifetime buffer")
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = root / "q_sources.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)

    distilled = [m for m in evals if m.startswith("distilled")]
    if distilled:
        fig, axes = plt.subplots(1, len(envs), figsize=(4.5 * len(envs), 3.8), squeeze=False)
        for ax, env in zip(axes[0], envs):
            for method in distilled:
                if env in evals[method]:
                    steps, values = _stack(evals[method][env])
                    ax.plot(steps, values.mean(0), label=method, color=COLORS.get(method))
                    ax.fill_between(steps, values.min(0), values.max(0), alpha=0.15, color=COLORS.get(method))
            ax.set_title(f"Distillation, evaluated in {env}")
            ax.set_xlabel("offline updates")
            ax.set_ylabel("evaluation return")
            ax.legend(fontsize=8)
        fig.tight_layout()
        path = root / "distillation.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("directory", help="an experiment's output directory")
    args = parser.parse_args()
    for path in plot_experiment(args.directory):
        print("wrote", path)


if __name__ == "__main__":
    main()
