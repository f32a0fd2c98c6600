"""The example scripts run end to end at a tiny budget (same code path as their quick and paper presets)."""

import csv
import json
import os
import pathlib
import subprocess
import sys

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


def test_three_stage_with_baselines_and_plots(tmp_path):
    stdout = run_example("three_stage.py", tmp_path)
    rows = summary_rows(tmp_path)
    methods = {row["method"] for row in rows}
    assert methods == {"MPO", "CRR_indicator", "CRR_beta1", "distilled", "distilled_indicator"}
    assert {row["env"] for row in rows} == {"Env-A", "Env-B", "Env-C"}
    for name in ("curves_Env-A.png", "curves_Env-B.png", "curves_Env-C.png", "final_returns.png", "q_sources.png"):
        assert (tmp_path / name).stat().st_size > 1000, name
    assert (tmp_path / "distillation.png").stat().st_size > 1000
    # what the figures name: the changes of environment and the distilled methods
    layout = json.loads((tmp_path / "seed_0" / "stages.json").read_text())
    assert layout["switch_labels"] == ["Env-A -> Env-B", "Env-B -> Env-C"]
    assert layout["distilled"] == ["distilled", "distilled_indicator"]
    # the students are evaluated often enough to draw a curve (before the first update, then every tenth)
    with open(tmp_path / "seed_0" / "distilled" / "eval.csv") as handle:
        assert len({row["timesteps"] for row in csv.DictReader(handle) if row["env"] == "Env-A"}) >= 5
    assert "| MPO |" in stdout
    # the collector's buffer holds every environment's data, tagged by stage
    with open(tmp_path / "seed_0" / "MPO" / "q_sources.csv") as handle:
        assert {row["name"] for row in csv.DictReader(handle)} == {"Env-A", "Env-B", "Env-C"}


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
        (
            "three_stage.py",
            ["--no-baselines", "--no-plots", "--per-source-actors", "--seeds", "1"],
            {"Env-A", "Env-B", "Env-C"},
        ),
        ("parallel_sharing.py", ["--setup", "copy", "--no-plots"], {"Env-A", "Env-B", "Env-C"}),
        ("parallel_sharing.py", ["--setup", "independent", "--backend", "process", "--no-plots"], {"Env-A", "Env-B", "Env-C"}),
        ("continuous_drift.py", ["--no-plots"], {"hip_0.00", "hip_0.15", "hip_0.30"}),
    ],
)
def test_other_examples(tmp_path, script, extra, envs):
    stdout = run_example(script, tmp_path, *extra)
    rows = summary_rows(tmp_path)
    assert {row["env"] for row in rows} == envs
    assert any(row["method"] == "distilled" for row in rows)
    layout = json.loads((tmp_path / ("seed_1" if "--seeds" in extra else "seed_0") / "stages.json").read_text())
    assert "distilled" in layout["distilled"] and set(layout["names"]) == envs
    if "--per-source-actors" in extra:
        assert {row["env"] for row in rows if row["method"] == "distilled_per_source"} == envs
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
