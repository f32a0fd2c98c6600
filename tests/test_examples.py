"""The example scripts run end to end at a tiny budget (same code path as their quick and paper presets)."""

import csv
import json
import os
import pathlib
import re
import subprocess
import sys

import numpy as np
import pytest

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"


def run_example(script: str, output: pathlib.Path, *extra: str) -> str:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    command = [sys.executable, str(EXAMPLES / script), "--preset", "tiny", "--output", str(output), *extra]
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result.stdout


def summary_rows(output: pathlib.Path) -> list[dict[str, str]]:
    with open(output / "summary.csv") as handle:
        return list(csv.DictReader(handle))


def score_rows(output: pathlib.Path) -> list[dict[str, str]]:
    with open(output / "scores.csv") as handle:
        return list(csv.DictReader(handle))


THREE_ENVS = {"Env-A", "Env-B", "Env-C"}


def test_three_stage_with_baselines_and_plots(tmp_path):
    """The protocol's layout: its runner's jobs, its scores, report and figures, for three stages."""
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.experiments.presets import stage_ends

    stdout = run_example("three_stage.py", tmp_path, "--backend", "process")
    rows = score_rows(tmp_path)
    online = {"MPO", "online CRR_indicator", "online CRR_exp_beta1"}
    assert {row["method"] for row in rows} == online | {"CRR_exp_beta1", "CRR_indicator"}
    for method in {row["method"] for row in rows}:
        assert {row["env"] for row in rows if row["method"] == method} == THREE_ENVS, method
    assert {row["kind"] for row in rows if row["method"] in online} == {"online"}
    for name in ("fig_online.png", "fig_students.png", "fig_q_sources.png"):
        assert (tmp_path / name).stat().st_size > 10_000, name
    assert "| MPO | online |" in stdout and (tmp_path / "report.md").read_text().startswith("# 3-stage study")
    # what the figures name: the environments and their changes
    preset = json.loads((tmp_path / "preset.json").read_text())
    assert preset["env_names"] == ["Env-A", "Env-B", "Env-C"] and stage_ends(preset["stage_steps"])[:-1] == [200, 400]
    # the students are evaluated often enough to draw a curve
    with open(tmp_path / "seed_0" / "distill_CRR_exp_beta1" / "eval.csv") as handle:
        assert len({row["timesteps"] for row in csv.DictReader(handle) if row["env"] == "Env-A"}) >= 5
    # the collector's buffer holds every environment's data, tagged by source
    with LifelongReplayBuffer.open(tmp_path / "seed_0" / "buffer", read_only=True) as buffer:
        assert buffer.size() == 600 and {v["name"] for v in buffer.sources.values()} == THREE_ENVS
        assert set(buffer.source_counts()) == {0, 1, 2}
    with open(tmp_path / "seed_0" / "collect" / "q_sources.csv") as handle:
        assert {row["name"] for row in csv.DictReader(handle)} == THREE_ENVS


def test_three_stage_without_baselines_with_the_per_source_student(tmp_path):
    extra = ["--no-baselines", "--no-plots", "--per-source-actors", "--seeds", "1", "--backend", "process"]
    run_example("three_stage.py", tmp_path, *extra)
    rows = score_rows(tmp_path)
    assert {row["method"] for row in rows} == {"MPO", "CRR_exp_beta1", "CRR_indicator", "CRR_indicator_two_actors"}
    assert {row["env"] for row in rows if row["method"] == "CRR_indicator_two_actors"} == THREE_ENVS
    assert {row["seed"] for row in rows} == {"1"} and not list(tmp_path.glob("*.png"))
    assert not list((tmp_path / "seed_1").glob("online_*"))


def test_continuous_drift_runs_on_the_protocol_and_evaluates_the_robots_of_its_life(tmp_path):
    """One drifting life through the runner: its thirds evaluated on the robot of the first, middle and last step."""
    from sb3_lifelong import LifelongReplayBuffer

    run_example("continuous_drift.py", tmp_path, "--no-baselines", "--no-plots", "--backend", "process")
    hips = {"hip_0.00": 0.0, "hip_0.15": 0.15, "hip_0.30": 0.3}
    rows = score_rows(tmp_path)
    assert {row["method"] for row in rows} == {"MPO", "CRR_exp_beta1", "CRR_indicator"}
    assert {row["env"] for row in rows} == set(hips)
    # the random policy's baseline was measured on the same pinned robots
    measured = json.loads((tmp_path / "random_returns.json").read_text())
    assert measured["stages"] == [{"hip_deformation": hip} for hip in hips.values()]
    assert "drifting over the whole life: hip_deformation 0 -> 0.3" in (tmp_path / "report.md").read_text()
    with LifelongReplayBuffer.open(tmp_path / "seed_0" / "buffer", read_only=True) as buffer:
        hip = buffer.read_range("observations", 0, buffer.size())[:, -1] * 0.5  # the hip over its observation scale
    assert buffer.size() == 600 and hip[0] == 0.0 and 0.25 < hip[-1] <= 0.3 and np.all(np.diff(hip) >= -1e-6)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--stage-steps", "10", "10"], "--stage-steps: expected 3 arguments"),
        (["--workers", "0"], "--workers: .*must be at least 1"),
        (["--seeds", "-1"], "--seeds: .*seeds are ints"),
        (["--device", "gpu"], "--device: device 'gpu' is not a torch device"),
    ],
)
def test_three_stage_refuses_bad_arguments_before_it_runs(tmp_path, extra, message):
    command = [sys.executable, str(EXAMPLES / "three_stage.py"), "--preset", "tiny", "--output", str(tmp_path / "out")]
    result = subprocess.run([*command, *extra], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and re.search(message, result.stderr), result.stderr
    assert not (tmp_path / "out").exists()


def test_examples_are_programs_with_documented_flags():
    for script in EXAMPLES.glob("*.py"):
        text = script.read_text()
        assert "sys.path" not in text, script.name
        result = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120)
        assert result.returncode == 0, result.stderr
        lines = result.stdout.splitlines()
        options = [(i, line.strip()) for i, line in enumerate(lines) if line.strip().startswith("--")]
        assert options, script.name
        for i, option in options:
            helped_here = "  " in option  # argparse puts the help after two spaces, or on the next lines
            helped_below = i + 1 < len(lines) and lines[i + 1].startswith("    ") and not lines[i + 1].strip().startswith("-")
            assert helped_here or helped_below, f"{script.name}: {option} has no help text"


@pytest.mark.parametrize(
    "script, extra, envs",
    [
        ("parallel_sharing.py", ["--setup", "copy", "--no-plots"], {"Env-A", "Env-B", "Env-C"}),
        ("parallel_sharing.py", ["--setup", "independent", "--backend", "process", "--no-plots"], {"Env-A", "Env-B", "Env-C"}),
    ],
)
def test_other_examples(tmp_path, script, extra, envs):
    stdout = run_example(script, tmp_path, *extra)
    rows = summary_rows(tmp_path)
    assert {row["env"] for row in rows} == envs
    assert any(row["method"] == "distilled" for row in rows)
    layout = json.loads((tmp_path / "seed_0" / "stages.json").read_text())
    assert "distilled" in layout["distilled"] and set(layout["names"]) == envs
    if script == "parallel_sharing.py":
        # the merged data holds every environment once: Env-A's part of the copied buffer is not duplicated
        assert "900 transitions shared, per source {0: 300, 1: 300, 2: 300}" in stdout
        timing = json.loads((tmp_path / "seed_0" / "collectors.json").read_text())
        assert timing["workers"] == 2 and len(timing["collector_seconds"]) == 2


def test_two_stage_example_reads_top_to_bottom_and_writes_its_results(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    out = tmp_path / "two_stage"
    args = ["--steps-a", "150", "--steps-b", "150", "--updates", "40", "--episodes", "1", "--output", str(out)]
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / "two_stage.py"), *args], capture_output=True, text=True, env=env, timeout=600
    )
    assert result.returncode == 0, result.stderr
    with open(out / "returns.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert {(row["agent"], row["env"]) for row in rows} == {
        (agent, env) for agent in ("mpo_switch", "mpo_end", "student") for env in ("Env-A", "Env-B")
    }
    assert all(float(row["mean_return"]) == float(row["mean_return"]) for row in rows)  # finite numbers, no NaN
    for name in ("curves.csv", "two_stage.png", "mpo_switch.zip", "mpo_end.zip", "student.zip"):
        assert (out / name).is_file(), name
    assert "Env-A, MPO end / at switch" in result.stdout
    # an output that holds results is refused, and nothing in it is touched
    before = (out / "returns.csv").read_bytes()
    again = subprocess.run(
        [sys.executable, str(EXAMPLES / "two_stage.py"), *args], capture_output=True, text=True, timeout=120
    )
    assert again.returncode == 2 and "not empty" in again.stderr and (out / "returns.csv").read_bytes() == before


def test_seeds_of_separate_runs_are_summarised_together(tmp_path):
    from sb3_lifelong.experiments.sequential import finish

    config = dict(eval_episodes=1)
    first = [
        dict(seed=0, method="MPO", env="Env-A", final_return=1.0),
        dict(seed=1, method="MPO", env="Env-A", final_return=5.0),
    ]
    finish(tmp_path, first, config, 1.0, plots=False)
    # a later run redoes seed 1 and adds seed 2: seed 0 is kept, seed 1 replaced
    finish(tmp_path, [dict(seed=s, method="MPO", env="Env-A", final_return=3.0) for s in (1, 2)], config, 1.0, plots=False)
    rows = summary_rows(tmp_path)
    assert [(row["seed"], float(row["final_return"])) for row in rows] == [("0", 1.0), ("1", 3.0), ("2", 3.0)]
    assert "seeds [0, 1, 2]" in (tmp_path / "summary.md").read_text()
    assert "| MPO | 2 +- 1 |" in (tmp_path / "summary.md").read_text()


def test_a_rerun_never_mixes_runs_silently(tmp_path):
    from sb3_lifelong.experiments.sequential import EXAMPLE_CONFIGS, prepare_output

    config = dict(EXAMPLE_CONFIGS["tiny"], seeds=[0], preset="tiny")
    prepare_output(tmp_path, config)
    (tmp_path / "seed_0").mkdir()
    with pytest.raises(FileExistsError, match=r"seed\(s\) \[0\] already in .*--overwrite"):
        prepare_output(tmp_path, config)
    prepare_output(tmp_path, {**config, "seeds": [1]})  # another seed, same settings: summarised together
    with pytest.raises(FileExistsError, match="other settings"):
        prepare_output(tmp_path, {**config, "seeds": [2], "distill_steps": 7})
    with pytest.raises(FileExistsError, match="other settings"):
        prepare_output(tmp_path, {**config, "seeds": [2]}, setup="copy")
    prepare_output(tmp_path, {**config, "distill_steps": 7}, overwrite=True)
    assert not (tmp_path / "seed_0").exists() and (tmp_path / "config.json").exists()
