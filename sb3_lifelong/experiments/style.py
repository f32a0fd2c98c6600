"""
One look for every figure of the package: one name and one colour per method, and the drawing helpers (curves over
seeds, a labelled change of environment, saving) that the figures of the studies
(:mod:`sb3_lifelong.experiments.figures`) and the benchmarks share.

A method is known by its key in the protocol (:data:`sb3_lifelong.experiments.protocol.STUDENTS`, ``"MPO"`` for the
collector, ``"online <name>"`` for the online baselines), so that "CRR exp β=1" is red and called so in every figure.
A method this module does not know keeps its own name and gets a colour of :data:`OTHER_COLORS`.
"""

import pathlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import pandas as pd

from sb3_lifelong.core.atomic import atomic_write


@dataclass(frozen=True)
class MethodStyle:
    """
    How a method appears in every figure.

    :param label: its name in legends and on axes
    :param color: its colour (matplotlib colour string)
    """

    label: str
    color: str


#: every method of the studies by its key: the collector, the online baselines and the offline students
METHODS: dict[str, MethodStyle] = {
    "MPO": MethodStyle("MPO", "#1f77b4"),
    "MPO agent 2": MethodStyle("MPO, the second robot", "#aec7e8"),
    "online CRR_indicator": MethodStyle("online CRR indicator", "#ff7f0e"),
    "online CRR_exp_beta1": MethodStyle("online CRR exp β=1", "#2ca02c"),
    "CRR_exp_beta1": MethodStyle("CRR exp β=1", "#d62728"),
    "CRR_indicator": MethodStyle("CRR indicator", "#9467bd"),
    "BC": MethodStyle("BC", "#8c564b"),
    "CRR_indicator_A_only": MethodStyle("CRR indicator, Env-A data only", "#e377c2"),
    "CRR_indicator_B_only": MethodStyle("CRR indicator, Env-B data only", "#7f7f7f"),
    "CRR_exp_beta1_A_only": MethodStyle("CRR exp β=1, Env-A data only", "#bcbd22"),
    "CRR_indicator_scale_rwd_B": MethodStyle("CRR indicator, Env-B rewards x0.5", "#17becf"),
    "CRR_indicator_two_actors": MethodStyle("CRR indicator, one actor per env", "#393b79"),
    "CRR_exp_beta1_two_actors": MethodStyle("CRR exp β=1, one actor per env", "#5254a3"),
    "CRR_indicator_ratio_1to1": MethodStyle("CRR indicator, sampled 1:1", "#637939"),
    "CRR_indicator_ratio_1to10": MethodStyle("CRR indicator, sampled 1:10", "#8c6d31"),
    "CRR_exp_beta1_ratio_1to1": MethodStyle("CRR exp β=1, sampled 1:1", "#843c39"),
    "CRR_exp_beta1_ratio_1to10": MethodStyle("CRR exp β=1, sampled 1:10", "#7b4173"),
    "SAC": MethodStyle("SAC", "#222222"),
}

#: colours for the methods :data:`METHODS` does not know, in order (none of them a known method's)
OTHER_COLORS = ["#000075", "#469990", "#9a6324", "#f58231", "#911eb4", "#42d4f4", "#808000", "#e6194b", "#3cb44b"]


#: curves with at most this many points are drawn with markers (each evaluation visible)
MARKERS_UP_TO = 12

#: from this many seeds on, :func:`seed_lines` draws the median and the interquartile range over the seed lines
MEDIAN_FROM = 3


def method_label(method: str) -> str:
    """:return: the name of a method in figures (its key when it is not a known method)"""
    return METHODS[method].label if method in METHODS else method


def method_color(method: str, others: Sequence[str] = ()) -> str:
    """
    :param method: a method's key
    :param others: the unknown methods of the figure, in order: an unknown method gets the colour of its position
    :return: the method's colour
    """
    if method in METHODS:
        return METHODS[method].color
    unknown = [name for name in others if name not in METHODS]
    position = unknown.index(method) if method in unknown else 0
    return OTHER_COLORS[position % len(OTHER_COLORS)]


def over_seeds(count: int, what: str = "mean ± std") -> str:
    """:return: e.g. ``"mean ± std over 4 seeds"``, or ``"1 seed"``"""
    return f"{what} over {count} seeds" if count > 1 else seed_count(count)


def seed_count(count: int) -> str:
    """:return: ``"no seed"``, ``"1 seed"`` or e.g. ``"4 seeds"``"""
    return "no seed" if count == 0 else "1 seed" if count == 1 else f"{count} seeds"


# ------------------------------------------------------------------------------------------------- drawing
def pyplot() -> Any:
    """:return: ``matplotlib.pyplot`` on the Agg backend (files only: no display, no GL)"""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(
    plt: Any, fig: Any, path: pathlib.Path, dpi: int = 110, rect: Optional[tuple[float, float, float, float]] = None
) -> pathlib.Path:
    """
    Lay out, write and close a figure.

    :param plt: ``matplotlib.pyplot``
    :param fig: the figure
    :param path: the PNG file
    :param dpi: resolution
    :param rect: the part of the figure the axes are laid out in (``tight_layout``'s; None: all of it), e.g. to
        leave room for a legend below
    :return: ``path``
    """
    fig.tight_layout(rect=rect)
    with atomic_write(path) as handle:  # a failed write leaves the previous figure
        fig.savefig(handle, dpi=dpi, format=pathlib.Path(path).suffix.lstrip(".") or "png")
    plt.close(fig)
    return path


def band(ax: Any, frame: pd.DataFrame, env: Optional[str], label: str, color: str, y: str = "mean_reward") -> None:
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


def seed_lines(ax: Any, frame: pd.DataFrame, label: str, color: str, y: str) -> int:
    """
    A method's curves over seeds that no single seed can drag: one thin line per seed, and from
    :data:`MEDIAN_FROM` seeds on the median over seeds with its interquartile range (quartiles of nearest rank; a
    mean +- std band is pulled by one diverging seed, and on a log axis reaches below zero for a positive quantity).

    :param ax: the matplotlib axes
    :param frame: rows ``seed``, ``timesteps``, ``y``
    :param label: the method's legend entry (the number of seeds and what is drawn are appended)
    :param color: its colour
    :param y: the column to draw
    :return: the number of seeds
    """
    seeds = sorted(set(frame["seed"]))
    summary = len(seeds) >= MEDIAN_FROM
    width, alpha = (0.8, 0.4) if summary else (1.4, 0.9)  # with a median drawn, the seeds' lines step back
    for seed in seeds:
        rows = frame[frame["seed"] == seed].sort_values("timesteps")
        marker = "o" if len(rows) <= MARKERS_UP_TO else None
        ax.plot(rows["timesteps"], rows[y], color=color, linewidth=width, alpha=alpha, marker=marker, markersize=2.5)
    if summary:
        by_step = frame.groupby("timesteps")[y]
        # quartiles of nearest rank: the band joins seeds' own values, never a point pulled towards a diverging seed
        median = by_step.median()
        low, high = by_step.quantile(0.25, interpolation="nearest"), by_step.quantile(0.75, interpolation="nearest")
        ax.plot(median.index, median.values, color=color, linewidth=2.4, label=f"{label} (n={len(seeds)})")
        ax.fill_between(median.index, low.values, high.values, color=color, alpha=0.15, linewidth=0)
    else:
        ax.plot([], [], color=color, linewidth=width, label=f"{label} (n={len(seeds)})")
    return len(seeds)


def value_scale(ax: Any, values: Sequence[float], ylabel: str) -> str:
    """
    Set a y axis that shows values spanning decades: logarithmic for positive values over more than a decade and a
    half, symmetric-log (linear within +- 100) when values of both signs reach beyond 1,000, else linear.

    :param ax: the matplotlib axes
    :param values: the values drawn
    :param ylabel: the axis' label
    :return: the label with the scale named (set on ``ax`` too)
    """
    data = np.asarray([v for v in values if np.isfinite(v)], dtype=float)
    if len(data) and data.min() > 0 and data.max() / data.min() > 30:
        from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))  # 100, 200, 500, 1000: read without powers of 10
        ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:,.0f}" if value >= 1 else f"{value:g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ylabel += " (log scale)"
    elif len(data) and data.min() <= 0 and np.abs(data).max() > 1e3:
        ax.set_yscale("symlog", linthresh=100)
        ylabel += " (symmetric log scale, linear within ±100)"
    ax.set_ylabel(ylabel)
    return ylabel


def steps_axis(ax: Any, label: str) -> None:
    """
    Label an x axis of steps or updates, its ticks in thousands (``50k``) when they reach 10,000, so that long runs'
    ticks do not run into each other.

    :param ax: the matplotlib axes
    :param label: the axis' label
    """
    from matplotlib.ticker import FuncFormatter

    if max(abs(value) for value in ax.get_xlim()) >= 10_000:
        ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value / 1000:g}k"))
    ax.set_xlabel(label)


def switch(ax: Any, timestep: float, label: str, row: int = 0) -> None:
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
