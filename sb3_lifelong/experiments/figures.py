"""
The paper's figures from a two-stage (or three-stage) study (matplotlib's Agg backend, chosen when a figure is drawn:
no display needed). The helpers (a curve with its band over seeds, a labelled change of environment, grouped bars, saving)
also draw the figures of the sequential examples (:mod:`sb3_lifelong.experiments.plots`).
"""

import pathlib
from collections.abc import Callable, Sequence
from typing import Any, Optional

import numpy as np
import pandas as pd

from sb3_lifelong.experiments.report import split_repeat, stage_ends

COLORS = {
    "MPO": "tab:blue",
    "online CRR_indicator": "tab:orange",
    "online CRR_exp_beta1": "tab:green",
    "CRR_exp_beta1": "tab:red",
    "CRR_indicator": "tab:purple",
    "BC": "tab:brown",
}


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # files only: no display, no GL
    import matplotlib.pyplot as plt

    return plt


def _save(plt: Any, fig: Any, path: pathlib.Path) -> pathlib.Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _curves(study: Any, job: str) -> pd.DataFrame:
    frames = []
    for seed in study.seeds:
        path = study.output / f"seed_{seed}" / job / "eval.csv"
        if (study.output / f"seed_{seed}" / job / "done.json").exists() and path.exists():
            frames.append(pd.read_csv(path).assign(seed=seed))
    return pd.concat(frames) if frames else pd.DataFrame()


#: curves with at most this many points are drawn with markers (each evaluation visible)
MARKERS_UP_TO = 12


def _band(ax: Any, frame: pd.DataFrame, env: Optional[str], label: str, color: str, y: str = "mean_reward") -> None:
    """
    One curve: the mean over seeds of ``y`` against ``timesteps``, shaded +- std where there are >= 2 seeds.

    :param ax: the matplotlib axes
    :param frame: rows ``timesteps``, ``env``, ``y`` (and ``seed``), one per seed and point
    :param env: keep only the rows of this ``env`` (None: all rows)
    :param label: legend entry, the number of seeds appended
    :param color: matplotlib colour
    :param y: the column to draw
    """
    rows = (frame if env is None else frame[frame["env"] == env]).groupby("timesteps")[y]
    mean, std, count = rows.mean(), rows.std().fillna(0.0), rows.count()
    marker = "o" if len(mean) <= MARKERS_UP_TO else None
    ax.plot(
        mean.index,
        mean.values,
        color=color,
        label=f"{label} (n={int(count.max())})",
        linewidth=1.8,
        marker=marker,
        markersize=3,
    )
    ax.fill_between(mean.index, (mean - std).values, (mean + std).values, color=color, alpha=0.15, linewidth=0)


def _switch(ax: Any, timestep: float, label: str, row: int = 0) -> None:
    """
    A change of environment: a dashed vertical line, labelled (e.g. ``"Env-A -> Env-B"``) at the top of the axes.

    :param ax: the matplotlib axes
    :param timestep: where the change happens, in the x-axis' units
    :param label: what changes
    :param row: the label's line from the top (successive changes close together would overlap on one line)
    """
    ax.axvline(timestep, color="black", linestyle="--", linewidth=1)
    ax.annotate(
        label,
        xy=(timestep, 0.97 - 0.07 * row),
        xycoords=("data", "axes fraction"),
        ha="left",
        va="top",
        fontsize=9,
        xytext=(4, 0),
        textcoords="offset points",
    )


def _bars(
    ax: Any,
    methods: Sequence[str],
    envs: Sequence[str],
    scores: Callable[[str, str], Sequence[float]],
    colors: Optional[Sequence[str]] = None,
) -> None:
    """
    Grouped bars: for every method, one bar per environment (mean over seeds, error bar +- std).

    :param ax: the matplotlib axes
    :param methods: the groups, along the x axis (tick labels)
    :param envs: the bars of each group (legend entries)
    :param scores: the per-seed values of a method in an environment (empty: no bar)
    :param colors: one colour per environment (default: matplotlib's colour cycle)
    """
    width = 0.8 / len(envs)
    x = np.arange(len(methods))
    for k, env in enumerate(envs):
        means, stds = [], []
        for method in methods:
            values = list(scores(method, env))
            means.append(np.mean(values) if values else np.nan)
            stds.append(np.std(values) if values else 0.0)
        color = colors[k % len(colors)] if colors else None
        ax.bar(x + (k - (len(envs) - 1) / 2) * width, means, width, yerr=stds, capsize=3, label=env, color=color)
    ax.set_xticks(x)
    ax.set_xticklabels(methods, rotation=35, ha="right", fontsize=8)
    ax.grid(axis="y", alpha=0.3)


def plot_online(study: Any, directory: pathlib.Path) -> list[pathlib.Path]:
    """Paper Fig. 2: online curves per environment, each switch labelled, the distilled students dotted."""
    plt = _pyplot()
    envs = study.preset["env_names"]
    ends = stage_ends(study.preset["stage_steps"])[:-1]  # one switch per change of environment
    fig, axes = plt.subplots(1, len(envs), figsize=(6 * len(envs), 4.2), squeeze=False)
    jobs = {"MPO": "collect", "online CRR_indicator": "online_CRR_indicator", "online CRR_exp_beta1": "online_CRR_exp_beta1"}
    for ax, env in zip(axes[0], envs):
        for label, job in jobs.items():
            frame = _curves(study, job)
            if len(frame):
                _band(ax, frame, env, label, COLORS[label])
        for method in ("CRR_exp_beta1", "CRR_indicator"):
            values = list(study.score(method, env).values())
            if values:
                ax.axhline(np.mean(values), color=COLORS[method], linestyle=":", linewidth=2, label=f"distilled {method}")
        for index, end in enumerate(ends):
            _switch(ax, end, f"{envs[index]} -> {envs[index + 1]}", row=index)
        ax.set_title(f"Evaluated in {env}")
        ax.set_xlabel("environment steps")
        ax.set_ylabel("return (deterministic policy)")
        ax.margins(y=0.08)
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # beside the axes: no curve hidden
    change = "change" if len(ends) == 1 else "changes"
    fig.suptitle(f"{study.preset['env_id']}: online learning through the {change} (mean +- std over seeds)")
    return [_save(plt, fig, directory / "fig_online.png")]


def plot_students(study: Any, directory: pathlib.Path) -> list[pathlib.Path]:
    """Paper Fig. 4: final return of every offline student per environment, error bars over seeds."""
    plt = _pyplot()
    envs = study.preset["env_names"]
    from sb3_lifelong.experiments.protocol import STUDENTS

    present = set(study.finals[study.finals["kind"] == "student"]["method"])
    students = [name for name in STUDENTS if name in present]
    if not students:
        return []
    fig, ax = plt.subplots(figsize=(max(8, 0.8 * len(students) * len(envs)), 4.8))
    _bars(ax, students, envs, lambda method, env: list(study.score(method, env).values()))
    ax.set_xlabel("offline student (same number of updates)")
    ax.set_ylabel("final return")
    seeds = len(study.seeds)
    over = f"mean +- std over {seeds} seeds" if seeds > 1 else "1 seed"
    ax.set_title(f"Distillation variants, {study.preset['distill_steps']:,} updates ({over})")
    ax.legend()
    return [_save(plt, fig, directory / "fig_students.png")]


def plot_q(study: Any, directory: pathlib.Path) -> list[pathlib.Path]:
    """Paper Fig. 5: average Q per source during distillation, sources named by environment."""
    plt = _pyplot()
    methods = ["CRR_indicator", "CRR_indicator_A_only", "CRR_indicator_B_only", "CRR_exp_beta1"]
    envs = study.preset["env_names"]
    fig, axes = plt.subplots(1, len(envs), figsize=(6 * len(envs), 4.2), squeeze=False)
    drawn = False
    for ax, env in zip(axes[0], envs):
        for index, method in enumerate(methods):
            frames = []
            for seed in study.seeds:
                run_dir = study.output / f"seed_{seed}"
                for path in sorted(run_dir.glob(f"distill_{method}*/q_sources.csv")):  # with the student's repeats
                    finished = (path.parent / "done.json").exists()  # a repeat still running: not yet
                    if finished and split_repeat(path.parent.name[len("distill_") :])[0] == method:
                        frames.append(pd.read_csv(path).assign(seed=seed))
            if not frames:
                continue
            frame = pd.concat(frames).rename(columns={"name": "env"})
            frame = frame.groupby(["seed", "timesteps", "env"], as_index=False)["q_mean"].mean()  # repeats: one per seed
            if len(frame[frame["env"] == env]):
                _band(ax, frame, env, method, f"C{index}", y="q_mean")
                drawn = True
        ax.set_title(f"Average Q over {env} data")
        ax.set_xlabel("distillation updates")
        low, high = ax.get_ylim()
        if low < 0 or high > 10 * max(low, 1.0):
            # symmetric log: a diverging critic (e.g. a student that never saw this data) would flatten the others
            ax.set_yscale("symlog", linthresh=100)
            ax.set_ylabel("Q (symmetric log scale)")
        else:  # within one decade a log axis has no labelled tick: linear
            ax.set_ylabel("Q")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if not drawn:
        plt.close(fig)
        return []
    return [_save(plt, fig, directory / "fig_q_sources.png")]


def plot_ratios(study: Any, directory: pathlib.Path) -> list[pathlib.Path]:
    """Paper Fig. 6: Env-A return against the Env-A : Env-B sampling ratio."""
    env = study.preset["env_names"][0]
    ratios = [("1:1", "_ratio_1to1"), ("1:5 (raw)", ""), ("1:10", "_ratio_1to10")]
    if len(study.preset["env_names"]) != 2 or not any(
        study.score(base + suffix, env) for base in ("CRR_indicator", "CRR_exp_beta1") for _, suffix in ratios if suffix
    ):
        return []  # the ratios are Env-A : Env-B of a two-stage study; without a re-weighted student there is no curve
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.2))
    drawn = False
    for base, label in (("CRR_indicator", "indicator"), ("CRR_exp_beta1", "exp, beta=1")):
        means, stds = [], []
        for _, suffix in ratios:
            values = list(study.score(base + suffix, env).values())
            means.append(np.mean(values) if values else np.nan)
            stds.append(np.std(values) if values else 0.0)
        if np.isfinite(means).any():
            ax.errorbar(range(len(ratios)), means, yerr=stds, marker="o", capsize=4, label=label)
            drawn = True
    if not drawn:
        plt.close(fig)
        return []
    ax.set_xticks(range(len(ratios)))
    ax.set_xticklabels([r for r, _ in ratios])
    ax.set_xlabel("Env-A : Env-B sampling ratio")
    ax.set_ylabel(f"final return in {env}")
    ax.set_title(f"{env} return vs sampling ratio (mean +- std over seeds)")
    ax.margins(x=0.15)
    ax.grid(alpha=0.3)
    ax.legend()
    return [_save(plt, fig, directory / "fig_sampling_ratio.png")]


def plot_study(study: Any) -> list[pathlib.Path]:
    """:return: the paths of every figure written into the study's directory"""
    paths = []
    for plot in (plot_online, plot_students, plot_q, plot_ratios):
        paths += plot(study, study.output)
    return paths
