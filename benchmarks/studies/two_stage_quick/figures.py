"""
The figures of an experiment in the sequential layout of the package's earlier examples: the committed
``benchmarks/studies/two_stage_quick`` and ``two_stage_50k``, the only outputs in that layout (this script serves
both), drawn in the package's one style (``sb3_lifelong.experiments.style``: the methods the examples share with the
studies have the studies' names and colours, e.g. ``distilled`` is "CRR exp β=1", red, as in every figure). The
examples (``examples/three_stage.py``, ``continuous_drift.py``, ``parallel_sharing.py``) now write a study of the
protocol instead, whose figures
``python -m sb3_lifelong.experiments report <dir>`` draws.

Reads the layout those examples wrote (``<dir>/seed_<k>/<method>/eval.csv`` and ``q_sources.csv``,
``<dir>/seed_<k>/stages.json``) and writes into ``<dir>``:

- ``curves_<env>.png``: evaluation return in each environment against environment steps, for the online methods
  (mean over seeds, +- std band with two seeds or more), the environment changes as labelled vertical lines and the
  distilled policies' final return as dotted horizontal lines;
- ``final_returns.png``: the final return of every method in every environment (mean +- std over seeds);
- ``q_sources.png``: each online method's average Q-value on each environment's data (the overestimation curves),
  one line per seed (and from three seeds on their median and interquartile range, which no diverging seed drags);
- ``distillation.png``: the distilled policies' return against offline updates, one panel per environment.

The methods are read from the directory: the distilled ones are those named in ``stages.json`` (outputs written
before it named them: the methods whose name starts with ``distilled``), the online ones all the others. A method
keeps its name and colour in every figure. Usage::

    python benchmarks/studies/two_stage_quick/figures.py benchmarks/studies/two_stage_quick
"""

import argparse
import functools
import json
import pathlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Optional, Union

import numpy as np
import pandas as pd

from sb3_lifelong.core.cli import plain_text
from sb3_lifelong.core.contract import stage_name
from sb3_lifelong.experiments.style import (
    band,
    method_color,
    method_label,
    over_seeds,
    pyplot,
    save,
    seed_lines,
    steps_axis,
    switch,
    value_scale,
)

#: one colour per environment or source of data, in the order of the stages (matplotlib's "Dark2")
ENV_COLORS = ["#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d", "#666666"]


def env_color(index: int) -> str:
    """:return: the colour of the environment (or source of data) of stage ``index``"""
    return ENV_COLORS[index % len(ENV_COLORS)]


def grouped_bars(
    ax: Any,
    groups: Sequence[str],
    bars: Sequence[str],
    scores: Callable[[str, str], Sequence[float]],
    colors: Optional[Sequence[str]] = None,
    labels: Optional[Sequence[str]] = None,
) -> None:
    """
    Grouped bars: for every group, one bar per entry of ``bars`` (the mean over seeds), error bar +- std, and each
    seed's value as a dot (so that the number of seeds is seen).

    :param ax: the matplotlib axes
    :param groups: the groups, along the x axis
    :param bars: the bars of each group (legend entries)
    :param scores: the per-seed values of (group, bar) (empty: no bar)
    :param colors: one colour per bar (default: ``ENV_COLORS``)
    :param labels: the groups' tick labels (default: ``groups``)
    """
    colors = list(colors) if colors else ENV_COLORS
    width = 0.8 / len(bars)
    x = np.arange(len(groups))
    for k, bar in enumerate(bars):
        offset = (k - (len(bars) - 1) / 2) * width
        means, stds = [], []
        for index, group in enumerate(groups):
            values = [float(v) for v in scores(group, bar)]
            means.append(np.mean(values) if values else np.nan)
            stds.append(np.std(values) if values else 0.0)
            ax.plot(np.full(len(values), x[index] + offset), values, "o", color="black", markersize=2.5, zorder=3)
        ax.bar(x + offset, means, width, yerr=stds, capsize=3, label=bar, color=colors[k % len(colors)])
    names = list(labels) if labels is not None else list(groups)
    long = max((len(name) for name in names), default=0) > 12
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=25 if long else 0, ha="right" if long else "center", fontsize=9)
    ax.grid(axis="y", alpha=0.3)


#: the method directories of the sequential layout (the earlier examples' committed runs) by the study method each is
SEQUENTIAL_METHODS: dict[str, str] = {
    "MPO": "MPO",
    "CRR_indicator": "online CRR_indicator",
    "CRR_beta1": "online CRR_exp_beta1",
    "distilled": "CRR_exp_beta1",
    "distilled_indicator": "CRR_indicator",
    "distilled_per_source": "CRR_exp_beta1_two_actors",
}

#: the name prefix of the distilled methods, for outputs whose ``stages.json`` does not list them
DISTILLED_PREFIX = "distilled"


@dataclass
class Experiment:
    """
    An experiment's logs.

    :param evals: one row per seed, method, environment and evaluation: ``seed, method, env, timesteps, mean_reward``
    :param q: one row per seed, method, source and measurement: ``seed, method, source, timesteps, q_mean``, the
        source named after its environment
    :param envs: the evaluation environments, in the experiment's order
    :param online: the methods that learn by acting (``timesteps``: environment steps), by first evaluation
    :param distilled: the methods trained offline (``timesteps``: updates)
    :param switches: ``(environment step, what changes)`` at every change of environment
    """

    evals: pd.DataFrame
    q: pd.DataFrame
    envs: list[str]
    online: list[str]
    distilled: list[str]
    switches: list[tuple[int, str]]

    @property
    def methods(self) -> list[str]:
        """The online methods, then the distilled ones."""
        return self.online + self.distilled

    @property
    def seeds(self) -> list[int]:
        """The seeds that have evaluations."""
        return sorted(set(self.evals["seed"]))

    def color(self, method: str) -> str:
        """:return: the colour of a method, the same in every figure (a study method's colour, as in the package's style)"""
        return method_color(SEQUENTIAL_METHODS.get(method, method), [SEQUENTIAL_METHODS.get(m, m) for m in self.methods])

    def label(self, method: str) -> str:
        """:return: the name of a method in the figures (a study method's name, as in the package's style)"""
        return method_label(SEQUENTIAL_METHODS.get(method, method))

    def finals(self, method: str, env: str) -> list[float]:
        """:return: a method's last evaluation in an environment, one value per seed"""
        rows = self.evals[(self.evals["method"] == method) & (self.evals["env"] == env)]
        return [float(value) for value in _last(rows, "mean_reward")]


def source_labels(names: Sequence[str]) -> dict[str, str]:
    """
    :param names: the environments' names, in stage order
    :return: the name a buffer gives stage ``i``'s source -> ``names[i]``: ``Env-A``, ``Env-B``, ... (and the
        ``stage_<i>`` of buffers written before sources took the environments' names)
    """
    labels = {f"stage_{index}": name for index, name in enumerate(names)}
    labels.update({stage_name(index): name for index, name in enumerate(names)})
    return labels


def _last(frame: pd.DataFrame, y: str) -> pd.Series:
    """:return: the value of ``y`` at each seed's last ``timesteps``"""
    return frame.sort_values("timesteps").groupby("seed")[y].last()


def load_experiment(directory: Union[str, pathlib.Path]) -> Experiment:
    """
    Read an experiment's output directory.

    :param directory: the directory (with ``seed_<k>`` sub-directories)
    :return: its evaluations, Q-values, environments, methods and environment changes
    """
    root = pathlib.Path(directory)
    seed_dirs = sorted(
        (path for path in root.glob("seed_*") if path.is_dir() and path.name[5:].isdigit()),
        key=lambda path: int(path.name[5:]),
    )
    if not seed_dirs:
        raise FileNotFoundError(f"no seed_<k> directories under {root}: is it an experiment's output directory?")
    layout: dict[str, Any] = {}
    evals, qs = [], []
    for seed_dir in seed_dirs:
        seed = int(seed_dir.name[5:])
        if not layout and (seed_dir / "stages.json").exists():
            layout = json.loads((seed_dir / "stages.json").read_text())
        for method_dir in sorted(path for path in seed_dir.iterdir() if path.is_dir()):
            if (method_dir / "eval.csv").exists():
                evals.append(pd.read_csv(method_dir / "eval.csv").assign(seed=seed, method=method_dir.name))
            if (method_dir / "q_sources.csv").exists():
                qs.append(pd.read_csv(method_dir / "q_sources.csv").assign(seed=seed, method=method_dir.name))
    columns = ["seed", "method", "env", "timesteps", "mean_reward"]
    eval_frame = pd.concat(evals)[columns] if evals else pd.DataFrame(columns=columns)
    names = list(layout.get("names", []))
    envs = names + sorted(set(eval_frame["env"]) - set(names))
    # a buffer names stage i's source Env-A, Env-B, ... (older buffers: stage_<i>): the figures use the environments' names
    labels = layout.get("sources", source_labels(names))
    q_frame = pd.concat(qs) if qs else pd.DataFrame(columns=["seed", "method", "name", "timesteps", "q_mean"])
    q_frame = q_frame.assign(source=[labels.get(name, name) for name in q_frame["name"]])
    methods = list(dict.fromkeys(eval_frame["method"]))
    if "distilled" in layout:
        distilled = [method for method in layout["distilled"] if method in methods]
    else:
        distilled = [method for method in methods if method.startswith(DISTILLED_PREFIX)]
    first_step = eval_frame.groupby("method")["timesteps"].min()
    switch_at = [int(t) for t in layout.get("switch_at", [])]
    switch_labels = layout.get("switch_labels", [f"{a} -> {b}" for a, b in zip(names, names[1:])])
    switch_labels = list(switch_labels) + ["environment change"] * (len(switch_at) - len(switch_labels))
    return Experiment(
        evals=eval_frame,
        q=q_frame[["seed", "method", "source", "timesteps", "q_mean"]],
        envs=envs,
        # the collector first: it starts at step 0, the methods continuing from it later
        online=sorted((m for m in methods if m not in distilled), key=lambda m: (first_step[m], m)),
        distilled=distilled,
        switches=list(zip(switch_at, switch_labels)),
    )


@dataclass
class Curve:
    """
    One line of a panel: the mean over seeds of ``y`` against ``timesteps``, shaded +- std with two seeds or more.

    :param label: the legend entry
    :param frame: rows ``seed, timesteps, <y>``
    :param y: the column drawn
    :param color: matplotlib colour
    :param final: draw only the final value (mean over seeds), as a dotted horizontal line
    :param per_seed: draw one line per seed (and their median and interquartile range from three seeds on) instead
        of the mean +- std, for values that one seed can drag far (a diverging critic's Q)
    """

    label: str
    frame: pd.DataFrame
    y: str
    color: str
    final: bool = False
    per_seed: bool = False


@dataclass
class Panel:
    """
    One axes of a figure: curves against timesteps, or grouped bars.

    :param title: the axes' title
    :param xlabel: the x axis' label
    :param ylabel: the y axis' label
    :param curves: the lines
    :param switches: ``(x, label)`` of every change of environment
    :param bars: ``(groups, bars of each group, values per seed of (group, bar))`` for a bar chart
    :param group_labels: the tick labels of the bar chart's groups (default: the groups)
    """

    title: str
    xlabel: str
    ylabel: str
    curves: list[Curve] = field(default_factory=list)
    switches: list[tuple[int, str]] = field(default_factory=list)
    bars: Optional[tuple[list[str], list[str], dict[tuple[str, str], list[float]]]] = None
    group_labels: Optional[list[str]] = None


@dataclass
class FigureSpec:
    """
    What a figure shows, before drawing.

    :param filename: the PNG's name in the experiment's directory
    :param title: the figure's title
    :param panels: its axes, side by side
    """

    filename: str
    title: str
    panels: list[Panel]


def _over_seeds(experiment: Experiment) -> str:
    return over_seeds(len(experiment.seeds))


def online_curves(experiment: Experiment, env: str) -> FigureSpec:
    """
    :param experiment: the logs
    :param env: the evaluation environment
    :return: the online methods' return in ``env`` against environment steps, the distilled finals dotted
    """
    rows = experiment.evals[experiment.evals["env"] == env]
    curves = [
        Curve(experiment.label(method), rows[rows["method"] == method], "mean_reward", experiment.color(method))
        for method in experiment.online
        if (rows["method"] == method).any()
    ]
    curves += [
        Curve(
            f"{experiment.label(method)}, final",
            rows[rows["method"] == method],
            "mean_reward",
            experiment.color(method),
            final=True,
        )
        for method in experiment.distilled
        if (rows["method"] == method).any()
    ]
    panel = Panel(f"Evaluated in {env}", "environment steps", "evaluation return", curves, experiment.switches)
    return FigureSpec(f"curves_{env}.png", f"Online learning ({_over_seeds(experiment)})", [panel])


def final_returns(experiment: Experiment) -> FigureSpec:
    """
    :param experiment: the logs
    :return: every method's final return in every environment, as grouped bars
    """
    values = {(method, env): experiment.finals(method, env) for method in experiment.methods for env in experiment.envs}
    panel = Panel("Every method in every environment", "method", "return at the last evaluation")
    panel.bars = (experiment.methods, experiment.envs, values)
    panel.group_labels = [experiment.label(method) for method in experiment.methods]
    return FigureSpec("final_returns.png", f"Final return ({_over_seeds(experiment)})", [panel])


def q_sources(experiment: Experiment) -> FigureSpec:
    """
    :param experiment: the logs
    :return: each online method's average Q on each environment's data, one panel per method
    """
    q = experiment.q
    sources = [env for env in experiment.envs if (q["source"] == env).any()]
    sources += sorted(set(q["source"]) - set(sources))
    panels = []
    for method in experiment.online:
        rows = q[q["method"] == method]
        if len(rows):
            curves = [
                Curve(f"{source} data", rows[rows["source"] == source], "q_mean", env_color(index), per_seed=True)
                for index, source in enumerate(sources)
                if (rows["source"] == source).any()
            ]
            title = f"{experiment.label(method)}'s critic"
            panels.append(Panel(title, "environment steps", "average Q", curves, experiment.switches))
    count = len(experiment.seeds)
    what = f"{count} seeds, one line each" if count > 1 else "1 seed"
    what += "; thick: median, band: interquartile range" if count >= 3 else ""
    title = f"Average Q on each environment's data\n({what})"
    return FigureSpec("q_sources.png", title, panels)


def distillation(experiment: Experiment) -> FigureSpec:
    """
    :param experiment: the logs
    :return: the distilled methods' return against offline updates, one panel per environment
    """
    rows = experiment.evals[experiment.evals["method"].isin(experiment.distilled)]
    panels = []
    for env in experiment.envs:
        in_env = rows[rows["env"] == env]
        curves = [
            Curve(experiment.label(method), in_env[in_env["method"] == method], "mean_reward", experiment.color(method))
            for method in experiment.distilled
            if (in_env["method"] == method).any()
        ]
        if curves:
            panels.append(Panel(f"Evaluated in {env}", "offline updates", "evaluation return", curves))
    title = f"Distillation of the lifetime buffer ({_over_seeds(experiment)})"
    return FigureSpec("distillation.png", title, panels)


def experiment_figures(experiment: Experiment) -> list[FigureSpec]:
    """
    :param experiment: the logs
    :return: every figure that has something to show
    """
    specs = [online_curves(experiment, env) for env in experiment.envs]
    specs += [final_returns(experiment), q_sources(experiment), distillation(experiment)]
    return [spec for spec in specs if any(panel.curves or panel.bars for panel in spec.panels)]


def _lookup(table: dict[tuple[str, str], list[float]], group: str, bar: str) -> list[float]:
    return table[(group, bar)]


def draw_figure(spec: FigureSpec) -> Any:
    """
    Draw a figure (matplotlib's Agg backend, no display). One legend, right of the last panel, so that no line is
    hidden behind it.

    :param spec: what it shows
    :return: the matplotlib figure
    """
    plt = pyplot()
    first = spec.panels[0]
    width = 6.0 if first.bars is None else max(6.0, 0.5 * len(first.bars[0]) * len(first.bars[1]))
    fig, axes = plt.subplots(1, len(spec.panels), figsize=(width * len(spec.panels) + 2.0, 4.5), squeeze=False)
    legend: dict[str, Any] = {}
    for ax, panel in zip(axes[0], spec.panels):
        if panel.bars is not None:
            groups, bars, table = panel.bars
            grouped_bars(ax, groups, bars, functools.partial(_lookup, table), labels=panel.group_labels)
            ax.use_sticky_edges = False  # margins on the bars' side of 0 too
        for curve in panel.curves:
            if curve.final:
                last = _last(curve.frame, curve.y)
                label = f"{curve.label} (n={len(last)})"
                ax.axhline(last.mean(), color=curve.color, linestyle=":", linewidth=2, label=label)
            elif curve.per_seed:
                seed_lines(ax, curve.frame, curve.label, curve.color, y=curve.y)
            else:
                band(ax, curve.frame, None, curve.label, curve.color, y=curve.y)
        values = pd.concat([curve.frame[curve.y] for curve in panel.curves]) if panel.curves else pd.Series(dtype=float)
        if len(values) and values.abs().max() > 1e4:  # a diverging critic would flatten the others
            value_scale(ax, list(values), panel.ylabel)
        else:
            ax.set_ylabel(panel.ylabel)
        for timestep, label in panel.switches:
            switch(ax, timestep, label)
        ax.margins(y=0.15)  # room above the top curve, where the changes are labelled
        ax.set_title(panel.title)
        if panel.bars is None:
            steps_axis(ax, panel.xlabel)
        else:
            ax.set_xlabel(panel.xlabel)
        ax.grid(axis="both" if panel.bars is None else "y", alpha=0.3)
        legend.update({label: handle for handle, label in zip(*ax.get_legend_handles_labels())})
    axes[0][-1].legend(legend.values(), legend.keys(), fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.suptitle(spec.title)
    return fig


def plot_experiment(directory: Union[str, pathlib.Path]) -> list[pathlib.Path]:
    """
    Write the figures of an experiment into its directory.

    :param directory: the experiment's output directory
    :return: the paths written
    """
    root = pathlib.Path(directory)
    plt = pyplot()
    return [save(plt, draw_figure(spec), root / spec.filename) for spec in experiment_figures(load_experiment(root))]


def main(argv: Optional[list[str]] = None) -> None:
    """
    The command line: ``python benchmarks/studies/two_stage_quick/figures.py <dir>``.

    :param argv: the arguments (default: ``sys.argv[1:]``)
    """
    parser = argparse.ArgumentParser(
        prog="python benchmarks/studies/two_stage_quick/figures.py",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("directory", help="an experiment's output directory")
    args = parser.parse_args(argv)
    for path in plot_experiment(args.directory):
        print("wrote", path)


if __name__ == "__main__":
    main()
