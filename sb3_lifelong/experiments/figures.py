"""
Every figure of the package's experiments, in its one style (:mod:`sb3_lifelong.experiments.style`: one name and one
colour per method in every figure; matplotlib's Agg backend, chosen when a figure is drawn: no display needed).

A study's figures (:func:`plot_study`, from a two-stage or three-stage study read by
:mod:`~sb3_lifelong.experiments.scores`, every example's included): every figure's title names the study's set-up
(its preset, robot and environments), so that the figures of a variant study are not read as another's.
"""

import pathlib
from typing import Any

import numpy as np
import pandas as pd

from sb3_lifelong.experiments.presets import STUDENTS, Job, drift_text, evaluation_stages, preset_name, stage_ends
from sb3_lifelong.experiments.scores import Study, read_log
from sb3_lifelong.experiments.style import (
    band,
    method_color,
    method_label,
    over_seeds,
    pyplot,
    save,
    seed_count,
    seed_lines,
    steps_axis,
    switch,
    value_scale,
)


def _curves(study: Study, job: str) -> pd.DataFrame:
    frames = []
    for seed in study.seeds:
        path = study.output / f"seed_{seed}" / job / "eval.csv"
        if (study.output / f"seed_{seed}" / job / "done.json").exists() and path.exists():
            frames.append(read_log(path, []).assign(seed=seed))  # (malformed rows: refused or named by load_study)
    return pd.concat(frames) if frames else pd.DataFrame()


def _stage_text(stage: Any) -> str:
    if isinstance(stage, str):
        return stage
    return ", ".join(
        f"{key} {value:g}" if isinstance(value, (int, float)) else f"{key} {value}" for key, value in stage.items()
    )


def study_title(study: Study) -> str:
    """
    :param study: a loaded study (:func:`~sb3_lifelong.experiments.scores.load_study`)
    :return: what sets the study apart, for the figures' titles: its preset (or directory), robot, the environments
        after the first (what changes), and the students' critic and repeats when they are not the default
    """
    preset = study.preset
    name = preset_name(preset, study.output) or study.output.name
    changes = [
        f"{env} = {_stage_text(stage) or 'default'}" for env, stage in zip(preset["env_names"][1:], preset["stages"][1:])
    ]
    if preset.get("drift"):  # a drift: what moves over the life, and the robots the stages are evaluated on
        evaluated = evaluation_stages(preset["stages"], preset["drift"], preset.get("drift_eval_at"))
        changes = [f"{drift_text(preset['drift'])} over the life"]
        changes.append("evaluated on " + " | ".join(_stage_text(stage) or "default" for stage in evaluated))
    extras = []
    if preset.get("student_critic", "mse") != "mse":
        extras.append(f"{preset['student_critic']}-critic students")
    if preset.get("student_repeats", 1) > 1:
        extras.append(f"each student trained {preset['student_repeats']}x per seed")
    return f"{name}: {preset['env_id']}, " + "; ".join(changes + extras)


#: the online methods' jobs, by method key
ONLINE_JOBS = {
    "MPO": "collect",
    "MPO agent 2": "collect_agent2",
    "online CRR_indicator": "online_CRR_indicator",
    "online CRR_exp_beta1": "online_CRR_exp_beta1",
}


def plot_online(study: Study, directory: pathlib.Path) -> list[pathlib.Path]:
    """Paper Fig. 2: online curves per environment, each switch labelled, the distilled students' finals dotted."""
    plt = pyplot()
    envs = study.preset["env_names"]
    ends = stage_ends(study.preset["stage_steps"])[:-1]  # one switch per change of environment
    labels = [f"{envs[index]} -> {envs[index + 1]}" for index in range(len(ends))]
    sharing = study.preset.get("sharing")
    if sharing:  # two robots side by side: the first changes once; the copy starts there in Env-C, or the second from 0
        ends = ends[:1]
        labels = [f"{envs[0]} -> {envs[1]}" + (f"; the copy in {envs[2]}" if sharing == "copy" else "")]
    fig, axes = plt.subplots(1, len(envs), figsize=(6 * len(envs), 4.4), squeeze=False)
    for ax, env in zip(axes[0], envs):
        for method, job in ONLINE_JOBS.items():
            frame = _curves(study, job)
            if len(frame):
                band(ax, frame, env, method_label(method), method_color(method))
        for method in ("CRR_exp_beta1", "CRR_indicator"):
            values = list(study.score(method, env).values())
            if values:
                label = f"{method_label(method)}, distilled: final (mean, n={len(values)})"
                ax.axhline(np.mean(values), color=method_color(method), linestyle=":", linewidth=2, label=label)
        for index, (end, label) in enumerate(zip(ends, labels)):
            switch(ax, end, label, row=index)
        ax.set_title(f"Evaluated in {env}")
        steps_axis(ax, "environment steps")
        ax.set_ylabel("return (deterministic policy)")
        ax.margins(y=0.08)
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # beside the axes: no curve hidden
    change = "change" if len(ends) == 1 else "changes"
    fig.suptitle(
        f"{study_title(study)}\nonline learning through the {change} ({over_seeds(len(study.seeds))}; dotted: students)"
    )
    return [save(plt, fig, directory / "fig_online.png")]


def _mpo_references(study: Study, env: str, index: int, last: bool) -> list[tuple[str, float, str]]:
    """:return: (label, value, line style) of MPO's returns in ``env``: at the end, and when it left ``env``"""
    references = []
    final = [v for v in study.score("MPO", env).values() if np.isfinite(v)]
    if final:
        references.append((f"MPO at the end of the collection (online, n={len(final)})", float(np.mean(final)), "--"))
    if not last:
        left = [v for v in study.extra(f"MPO|switch|{env}").values() if np.isfinite(v)]
        if left:
            references.append((f"MPO when it left that environment (n={len(left)})", float(np.mean(left)), ":"))
    return references


def plot_students(study: Study, directory: pathlib.Path) -> list[pathlib.Path]:
    """
    Paper Fig. 4: the final return of every offline student, one panel per environment (a horizontal bar per
    student: the mean over seeds, each seed a dot), with MPO's return at the end of the collection and when it left
    the environment as reference lines.
    """
    envs = study.preset["env_names"]
    present = set(study.finals[study.finals["kind"] == "student"]["method"])
    students = [name for name in STUDENTS if name in present] + sorted(present - set(STUDENTS))
    if not students:
        return []
    plt = pyplot()
    height = 2.2 + 0.42 * len(students)
    fig, axes = plt.subplots(1, len(envs), figsize=(3.2 + 3.6 * len(envs), height), squeeze=False, sharey=True)
    y = np.arange(len(students))
    legend: dict[str, Any] = {}
    for index, (ax, env) in enumerate(zip(axes[0], envs)):
        for row, method in enumerate(students):
            values = [v for v in study.score(method, env).values() if np.isfinite(v)]
            if values:
                ax.barh(row, np.mean(values), height=0.7, color=method_color(method, students), alpha=0.85)
                ax.plot(values, np.full(len(values), row), "o", color="black", markersize=3, zorder=3)
        for label, value, style in _mpo_references(study, env, index, index == len(envs) - 1):
            ax.axvline(value, color=method_color("MPO"), linestyle=style, linewidth=1.8, label=label)
        ax.set_title(f"Evaluated in {env}")
        ax.set_xlabel("final return")
        ax.grid(axis="x", alpha=0.3)
        legend.update({label: handle for handle, label in zip(*ax.get_legend_handles_labels())})
    axes[0][0].set_yticks(y)
    axes[0][0].set_yticklabels([method_label(method) for method in students], fontsize=10)
    axes[0][0].invert_yaxis()  # the pipeline's student first, at the top
    seeds = len(study.seeds)
    what = f"bar: mean over {seeds} seeds, dots: seeds" if seeds > 1 else "1 seed"
    fig.suptitle(
        f"{study_title(study)}\noffline students, {study.preset['distill_steps']:,} updates each ({what})", fontsize=11
    )
    rect = None
    if legend:  # below the panels: no bar hidden
        fig.legend(legend.values(), legend.keys(), loc="lower center", ncol=len(legend), fontsize=9, frameon=False)
        rect = (0.0, 0.45 / height, 1.0, 1.0)
    return [save(plt, fig, directory / "fig_students.png", rect=rect)]


#: the students whose average Q per source Fig. 5 draws
Q_STUDENTS = ("CRR_indicator", "CRR_indicator_A_only", "CRR_indicator_B_only", "CRR_exp_beta1")


def _q_frame(study: Study, method: str) -> pd.DataFrame:
    """:return: rows ``seed, timesteps, env, q_mean`` of a student's finished runs (its repeats averaged per seed)"""
    frames = []
    for seed in study.seeds:
        run_dir = study.output / f"seed_{seed}"
        for path in sorted(run_dir.glob(f"distill_{method}*/q_sources.csv")):  # with the student's repeats
            finished = (path.parent / "done.json").exists()  # a repeat still running: not yet
            if finished and Job.parse(path.parent.name).name == method:
                frames.append(read_log(path, []).assign(seed=seed))  # (malformed rows: as in load_study)
    if not frames:
        return pd.DataFrame(columns=["seed", "timesteps", "env", "q_mean"])
    frame = pd.concat(frames).rename(columns={"name": "env"})
    return frame.groupby(["seed", "timesteps", "env"], as_index=False)["q_mean"].mean()  # repeats: one per seed


def plot_q(study: Study, directory: pathlib.Path) -> list[pathlib.Path]:
    """
    Paper Fig. 5: average Q per source during distillation, sources named by environment: one thin line per seed
    (and the median with its interquartile range from three seeds on), so that one diverging seed shows as itself.
    """
    envs = study.preset["env_names"]
    frames = {method: _q_frame(study, method) for method in Q_STUDENTS}
    frames = {method: frame for method, frame in frames.items() if len(frame)}
    if not frames:
        return []
    plt = pyplot()
    fig, axes = plt.subplots(1, len(envs), figsize=(6 * len(envs), 4.6), squeeze=False)
    counts = set()
    for ax, env in zip(axes[0], envs):
        drawn: list[float] = []
        for method, frame in frames.items():
            rows = frame[frame["env"] == env]
            if len(rows):
                counts.add(seed_lines(ax, rows, method_label(method), method_color(method), y="q_mean"))
                drawn += list(rows["q_mean"])
        ax.set_title(f"Average Q over {env} data")
        steps_axis(ax, "distillation updates")
        value_scale(ax, drawn, "average Q")
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    seeds = max(counts) if counts else 0
    what = f"{seeds} seeds, one line each" if seeds > 1 else "1 seed"
    what += "; thick: median, band: interquartile range" if seeds >= 3 else ""
    fig.suptitle(f"{study_title(study)}\nthe students' average Q on each environment's data ({what})", fontsize=11)
    return [save(plt, fig, directory / "fig_q_sources.png")]


#: Fig. 6's re-weighted sampling ratios: (Env-B rows drawn per Env-A row, the suffix of the students that sample
#: them); the students without a suffix sample the raw share, the buffer's own (:func:`raw_share_label`)
RATIOS = ((1.0, "_ratio_1to1"), (10.0, "_ratio_1to10"))


def share_text(b_per_a: float) -> str:
    """:return: a share Env-A : Env-B with its smaller side 1, e.g. ``"1:1.8"``, ``"1:10"``, ``"2.5:1"``"""

    def number(value: float) -> str:
        return f"{value:.0f}" if value >= 10 else f"{value:.1f}".removesuffix(".0")

    return f"1:{number(b_per_a)}" if b_per_a >= 1 else f"{number(1 / b_per_a)}:1"


def raw_shares(study: Study) -> dict[int, float]:
    """
    :param study: a loaded two-stage study
    :return: seed -> the Env-B rows per Env-A row of its lifetime buffer (``buffer|rows|<env>``, as the collection
        recorded them: :func:`~sb3_lifelong.experiments.scores.source_rows`), for the seeds that have both
    """
    first, second = study.preset["env_names"][:2]
    rows_a, rows_b = study.extra(f"buffer|rows|{first}"), study.extra(f"buffer|rows|{second}")
    return {seed: rows_b[seed] / rows_a[seed] for seed in sorted(rows_a) if seed in rows_b and rows_a[seed] > 0}


def raw_share_label(study: Study) -> str:
    """
    :param study: a loaded two-stage study
    :return: the tick label of the students that sample the whole buffer: its share Env-A : Env-B, e.g.
        ``"raw (1:1.8)"`` (``"raw (1:1.8 to 1:1.9)"`` when the seeds' buffers differ), or ``"raw (share not
        recorded)"`` when no seed's rows per source are known
    """
    shares = raw_shares(study)
    if not shares:
        return "raw (share not recorded)"
    low, high = share_text(min(shares.values())), share_text(max(shares.values()))
    return f"raw ({low})" if low == high else f"raw ({low} to {high})"


def plot_ratios(study: Study, directory: pathlib.Path) -> list[pathlib.Path]:
    """
    Paper Fig. 6: Env-A return against the Env-A : Env-B sampling ratio (the two series side by side), the raw share
    labelled with what the seeds' buffers hold.
    """
    env = study.preset["env_names"][0]
    bases = ("CRR_indicator", "CRR_exp_beta1")
    reweighted = any(study.score(base + suffix, env) for base in bases for _, suffix in RATIOS)
    if len(study.preset["env_names"]) != 2 or not reweighted:
        return []  # the ratios are Env-A : Env-B of a two-stage study; without a re-weighted student there is no curve
    shares = raw_shares(study)
    raw = float(np.mean(list(shares.values()))) if shares else float(np.sqrt(np.prod([r for r, _ in RATIOS])))
    ratios = sorted([*RATIOS, (raw, "")])  # in the order of Env-B's share (unknown: between the others)
    labels = [raw_share_label(study) if not suffix else share_text(share) for share, suffix in ratios]
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    x = np.arange(len(ratios))
    counts = set()
    for offset, base in zip((-0.09, 0.09), bases):
        per_ratio = [[v for v in study.score(base + suffix, env).values() if np.isfinite(v)] for _, suffix in ratios]
        means = [float(np.mean(values)) if values else np.nan for values in per_ratio]
        stds = [float(np.std(values)) if values else 0.0 for values in per_ratio]
        if not np.isfinite(means).any():
            continue
        n = max(len(values) for values in per_ratio)
        counts.add(n)
        color = method_color(base)
        label = f"{method_label(base)} ({'mean ± std, ' if n > 1 else ''}n={n})"
        ax.errorbar(x + offset, means, yerr=stds, marker="o", capsize=4, color=color, label=label)
        seed_values = per_ratio if n > 1 else []  # one seed: its dot is the mean's
        for position, values in zip(x + 1.7 * offset, seed_values):  # beside the error bar (two seeds sit on its ends)
            ax.plot(np.full(len(values), position), values, "o", color=color, markersize=3.5, alpha=0.6, markeredgewidth=0)
    ax.set_xticks(x)
    ax.set_xticklabels(labels)
    ax.set_xlabel("Env-A : Env-B share of the student's batches (raw: the buffer's own rows)")
    ax.set_ylabel(f"final return in {env}")
    seeds = max(counts) if counts else 0
    dots = "; small dots: seeds" if seeds > 1 else ""
    ax.set_title(f"{study_title(study)}\n{env} return vs sampling ratio ({seed_count(seeds)}{dots})", fontsize=10)
    ax.margins(x=0.12)
    ax.grid(alpha=0.3)
    handles, names = ax.get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=len(names), fontsize=9, frameon=False)  # below: no curve hidden
    return [save(plt, fig, directory / "fig_sampling_ratio.png", rect=(0.0, 0.07, 1.0, 1.0))]


def plot_study(study: Study) -> list[pathlib.Path]:
    """:return: the paths of every figure written into the study's directory"""
    paths = []
    for plot in (plot_online, plot_students, plot_q, plot_ratios):
        paths += plot(study, study.output)
    return paths
