"""The figures of the sequential layout (the earlier examples' committed runs, ``benchmarks/studies/two_stage_quick``
and ``two_stage_50k``), drawn by ``benchmarks/studies/two_stage_quick/figures.py``: methods and names read from the
directory, every figure readable."""

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from testkit import benchmark_module

FIGURES = benchmark_module("figures")  # benchmarks/studies/two_stage_quick/figures.py
SCRIPT = pathlib.Path(FIGURES.__file__)
draw_figure, experiment_figures, load_experiment = FIGURES.draw_figure, FIGURES.experiment_figures, FIGURES.load_experiment
plot_experiment, source_labels = FIGURES.plot_experiment, FIGURES.source_labels

ENVS = ["Env-A", "Env-B"]


def write_layout(run_dir, names, distilled, switch_at):
    """A seed's ``stages.json`` as the earlier examples wrote it (the committed runs hold such files)."""
    labels = [f"{a} -> {b}" for a, b in zip(names, names[1:])][: len(switch_at)]
    layout = dict(names=list(names), switch_at=list(switch_at), switch_labels=labels, distilled=list(distilled))
    (run_dir / "stages.json").write_text(json.dumps(dict(layout, sources=source_labels(names))))


def write_method(run_dir, method, steps, seed, q_sources=()):
    directory = run_dir / method
    directory.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    rows = [
        dict(timesteps=t, env=env, mean_reward=float(t + rng.normal()), std_reward=0.0, n_episodes=1)
        for t in steps
        for env in ENVS
    ]
    pd.DataFrame(rows).to_csv(directory / "eval.csv", index=False)
    if q_sources:
        rows = [
            dict(timesteps=t, source=i, name=name, q_mean=float(i + rng.normal()), n=10)
            for t in steps
            for i, name in enumerate(q_sources)
        ]
        pd.DataFrame(rows).to_csv(directory / "q_sources.csv", index=False)


@pytest.fixture
def experiment_dir(tmp_path):
    """Two seeds of a two-stage experiment, with method names the plotting code cannot know in advance."""
    for seed in (0, 1):
        run_dir = tmp_path / f"seed_{seed}"
        write_method(run_dir, "collector", range(100, 700, 100), seed, q_sources=("stage_0", "stage_1"))
        write_method(run_dir, "baseline", range(400, 700, 100), seed, q_sources=("stage_0", "stage_1"))
        write_method(run_dir, "student", range(0, 220, 20), seed, q_sources=("stage_0", "stage_1"))
        write_layout(run_dir, ENVS, distilled=["student"], switch_at=[300])
    return tmp_path


def texts(fig):
    """Every title, axis label, legend entry and annotation of a figure."""
    found = [fig._suptitle.get_text()] if fig._suptitle is not None else []
    for ax in fig.axes:
        found += [ax.get_title(), ax.get_xlabel(), ax.get_ylabel()] + [text.get_text() for text in ax.texts]
        if ax.get_legend() is not None:
            found += [text.get_text() for text in ax.get_legend().get_texts()]
    return found


def test_methods_sources_and_switches_come_from_the_directory(experiment_dir):
    experiment = load_experiment(experiment_dir)
    assert experiment.envs == ENVS
    assert experiment.online == ["collector", "baseline"]  # the collector first: it starts at step 0
    assert experiment.distilled == ["student"]
    assert experiment.switches == [(300, "Env-A -> Env-B")]
    assert set(experiment.q["source"]) == set(ENVS)  # stage_<i> named after its environment
    assert experiment.seeds == [0, 1]
    colors = [experiment.color(method) for method in experiment.methods]
    assert len(set(colors)) == len(colors)


def test_every_figure_reads_at_a_glance(experiment_dir):
    specs = {spec.filename: spec for spec in experiment_figures(load_experiment(experiment_dir))}
    assert set(specs) == {"curves_Env-A.png", "curves_Env-B.png", "final_returns.png", "q_sources.png", "distillation.png"}
    for name, spec in specs.items():
        fig = draw_figure(spec)
        found = texts(fig)
        for ax in fig.axes:
            assert ax.get_title() and ax.get_xlabel() and ax.get_ylabel(), name
        assert "2 seeds" in " ".join(found), name
        if name.startswith("curves_"):
            ax = fig.axes[0]
            assert "Env-A -> Env-B" in found  # the change of environment is labelled
            assert any("collector" in text for text in found) and any("student, final" in text for text in found)
            top = max(line.get_ydata().max() for line in ax.get_lines() if len(line.get_xdata()) > 2)
            low, high = ax.get_ylim()
            assert high - top > 0.05 * (high - low)  # the top curve is off the frame
            assert ax.collections, "two seeds: a +- std band"
        if name == "q_sources.png":
            assert {"Env-A data (n=2)", "Env-B data (n=2)"} <= set(found)
            assert not any("stage_" in text for text in found)
            assert [ax.get_title() for ax in fig.axes] == ["collector's critic", "baseline's critic"]
        if name == "final_returns.png":
            assert fig.axes[0].get_xlabel() == "method" and {"Env-A", "Env-B"} <= set(found)
            assert [label.get_text() for label in fig.axes[0].get_xticklabels()] == ["collector", "baseline", "student"]
        if name == "distillation.png":
            assert [ax.get_title() for ax in fig.axes] == ["Evaluated in Env-A", "Evaluated in Env-B"]
            for ax in fig.axes:
                assert all(len(line.get_xdata()) >= 5 for line in ax.get_lines())
    # a method has the same colour in every figure
    curves = draw_figure(specs["curves_Env-A.png"]).axes[0]
    student_level = next(line for line in curves.get_lines() if line.get_label().startswith("student"))
    student_curve = next(line for line in draw_figure(specs["distillation.png"]).axes[0].get_lines())
    assert student_level.get_color() == student_curve.get_color()


def test_outputs_without_the_new_layout_fields(experiment_dir):
    # stages.json as written before it named the distilled methods and the sources
    (experiment_dir / "seed_0" / "distilled_indicator").mkdir()
    (experiment_dir / "seed_0" / "student" / "eval.csv").rename(experiment_dir / "seed_0" / "distilled_indicator" / "eval.csv")
    for seed in (0, 1):
        layout = dict(stages=[{}, {"hip_deformation": 0.3}], names=ENVS, switch_at=[300])
        (experiment_dir / f"seed_{seed}" / "stages.json").write_text(json.dumps(layout))
    experiment = load_experiment(experiment_dir)
    assert experiment.distilled == ["distilled_indicator"]  # by the prefix
    assert "student" in experiment.online
    assert experiment.switches == [(300, "Env-A -> Env-B")]
    assert set(experiment.q["source"]) == set(ENVS)


def test_command_line_writes_the_figures_without_a_display(experiment_dir):
    env = {key: value for key, value in os.environ.items() if key not in ("DISPLAY", "MPLBACKEND")}
    result = subprocess.run(
        [sys.executable, str(SCRIPT), str(experiment_dir)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    for name in ("curves_Env-A.png", "curves_Env-B.png", "final_returns.png", "q_sources.png", "distillation.png"):
        assert (experiment_dir / name).stat().st_size > 1000
        assert f"wrote {experiment_dir / name}" in result.stdout
    written = plot_experiment(experiment_dir)  # and from Python, after the command line: the same files
    assert sorted(path.name for path in written) == sorted(path.name for path in experiment_dir.glob("*.png"))


def test_the_examples_name_methods_as_the_studies(tmp_path):
    from sb3_lifelong.experiments.style import METHODS

    for seed in (0, 1):
        run_dir = tmp_path / f"seed_{seed}"
        write_method(run_dir, "MPO", range(100, 700, 100), seed, q_sources=("stage_0", "stage_1"))
        write_method(run_dir, "distilled", range(0, 220, 20), seed)
        write_method(run_dir, "distilled_indicator", range(0, 220, 20), seed)
        write_layout(run_dir, ENVS, distilled=["distilled", "distilled_indicator"], switch_at=[300])
    experiment = load_experiment(tmp_path)
    assert experiment.color("distilled") == METHODS["CRR_exp_beta1"].color
    assert experiment.color("distilled_indicator") == METHODS["CRR_indicator"].color
    specs = {spec.filename: spec for spec in experiment_figures(experiment)}
    found = texts(draw_figure(specs["distillation.png"]))
    assert f"{METHODS['CRR_exp_beta1'].label} (n=2)" in found and not any("distilled" in text for text in found)
    ticks = [t.get_text() for t in draw_figure(specs["final_returns.png"]).axes[0].get_xticklabels()]
    assert ticks == ["MPO", METHODS["CRR_exp_beta1"].label, METHODS["CRR_indicator"].label]


def test_every_study_method_has_the_studies_style():
    from sb3_lifelong.experiments.style import METHODS

    assert set(FIGURES.SEQUENTIAL_METHODS.values()) <= set(METHODS)


def test_the_committed_figures_are_redrawn_byte_for_byte(tmp_path):
    """The committed run in this layout: its figures, drawn again from its logs, are the committed PNGs (byte for byte
    with the matplotlib that drew them, which each PNG names; another draws other bytes)."""
    import shutil

    import matplotlib
    from PIL import Image

    study = SCRIPT.parent
    drawn_by = Image.open(study / "q_sources.png").info.get("Software", "")
    if f"Matplotlib version{matplotlib.__version__}," not in drawn_by:
        pytest.skip(f"the committed PNGs were drawn by {drawn_by!r}, not matplotlib {matplotlib.__version__}")
    copy = tmp_path / study.name
    shutil.copytree(study, copy, ignore=shutil.ignore_patterns("*.png", "*.py"))
    written = plot_experiment(copy)
    assert sorted(path.name for path in written) == sorted(path.name for path in study.glob("*.png"))
    for path in written:
        assert path.read_bytes() == (study / path.name).read_bytes(), path.name
