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


def read_rows(path: pathlib.Path, start: int = 0, stop=None) -> np.ndarray:
    from sb3_lifelong import LifelongReplayBuffer

    with LifelongReplayBuffer.open(path, read_only=True) as buffer:
        stop = buffer.size() if stop is None else stop
        return np.concatenate(
            [
                buffer.read_range(field, start, stop).reshape(stop - start, -1)
                for field in ("observations", "actions", "rewards")
            ],
            axis=1,
        )


def test_parallel_sharing_copy_runs_the_copy_beside_the_first_robot_and_shares_env_a_once(tmp_path):
    """The copy set-up on the protocol's runner: Stage 1, then the two robots side by side, the merge, the students."""
    from sb3_lifelong import LifelongReplayBuffer

    stdout = run_example("parallel_sharing.py", tmp_path, "--setup", "copy", "--no-plots", "--backend", "process")
    rows = score_rows(tmp_path)
    assert {row["method"] for row in rows} == {"MPO", "MPO agent 2", "CRR_exp_beta1", "CRR_indicator"}
    assert {row["env"] for row in rows} == THREE_ENVS
    # the collection runs to the switch, then the first robot and its copy start together (two workers)
    lines = stdout.splitlines()
    position = {line: i for i, line in enumerate(lines)}
    first_done = min(
        i for i, line in enumerate(lines) if line.startswith(("[done] seed_0/collect ", "[done] seed_0/collect_agent2"))
    )
    assert position["[start] seed_0/collect@200"] < position["[start] seed_0/collect"] < first_done
    assert position["[start] seed_0/collect_agent2"] < first_done
    run = tmp_path / "seed_0"
    # the copy starts from the first robot's Stage-1 buffer, and its clock from the switch
    copy, stage1 = read_rows(run / "buffer_agent2", 0, 200), read_rows(run / "buffer_stage1")
    np.testing.assert_array_equal(copy, stage1)
    with open(run / "collect_agent2" / "eval.csv") as handle:
        assert min(int(row["timesteps"]) for row in csv.DictReader(handle)) > 200
    # the merged buffer: the first robot's 400 transitions, then the copy's own 200 (Env-A once)
    shared = read_rows(run / "buffer_shared")
    np.testing.assert_array_equal(shared[:400], read_rows(run / "buffer"))
    np.testing.assert_array_equal(shared[400:], read_rows(run / "buffer_agent2", 200))
    with LifelongReplayBuffer.open(run / "buffer_shared", read_only=True) as buffer:
        assert buffer.source_counts() == {0: 200, 1: 200, 2: 200}
    assert json.loads((run / "share" / "done.json").read_text())["source_rows"] == {"Env-A": 200, "Env-B": 200, "Env-C": 200}
    assert "two robots side by side (copy)" in (tmp_path / "report.md").read_text()


def test_parallel_sharing_independent_merges_a_second_robot_of_its_own(tmp_path):
    from sb3_lifelong import LifelongReplayBuffer

    stdout = run_example("parallel_sharing.py", tmp_path, "--setup", "independent", "--workers", "1", "--no-plots")
    assert "collect@" not in stdout  # no Stage 1 to wait for
    run = tmp_path / "seed_0"
    with LifelongReplayBuffer.open(run / "buffer_agent2", read_only=True) as buffer:
        assert buffer.source_counts() == {2: 200}
    with open(run / "collect_agent2" / "eval.csv") as handle:
        assert min(int(row["timesteps"]) for row in csv.DictReader(handle)) <= 200  # its own clock, from 0
    shared = read_rows(run / "buffer_shared")
    np.testing.assert_array_equal(shared, np.concatenate([read_rows(run / "buffer"), read_rows(run / "buffer_agent2")]))
    assert {row["method"] for row in score_rows(tmp_path)} == {"MPO", "MPO agent 2", "CRR_exp_beta1", "CRR_indicator"}
    assert "a second robot learns Env-C from scratch" in (tmp_path / "report.md").read_text()


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
