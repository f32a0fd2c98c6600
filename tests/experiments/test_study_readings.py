"""What studies share, as runner features: a collection in parts, and the readings of its eval.csv and q_sources.csv."""

import csv
import json
import math

import pytest
from testkit import small_preset

from sb3_lifelong.experiments.collection import collect_in_parts, paused_at
from sb3_lifelong.experiments.scores import last_evaluations, learnt_level, overestimation_at, switch_reading


def test_a_collection_in_parts_pauses_at_each_part_and_finishes(tmp_path):
    preset = small_preset()  # 60 + 60 steps
    run_dir = tmp_path / "seed_0"
    messages: list[str] = []
    assert not collect_in_parts(preset, 0, run_dir, 60, part=25, log=messages.append)  # Stage 1 alone: 25, 50, 60
    assert paused_at(run_dir) == 60 and (run_dir / "collect" / "stage1.zip").exists()
    assert [m.split(" in ")[0] for m in messages if m.startswith(f"{run_dir}: to step ")] == [
        f"{run_dir}: to step {n}" for n in (25, 50, 60)
    ]
    messages.clear()
    assert collect_in_parts(preset, 0, run_dir, 120, part=25, log=messages.append)  # 75, 100, 120: finished
    assert [m.split(" in ")[0] for m in messages if m.startswith(f"{run_dir}: to step ")] == [
        f"{run_dir}: to step {n}" for n in (75, 100, 120)
    ]
    assert (run_dir / "collect" / "final.zip").exists()
    with pytest.raises(ValueError, match="part must be at least 1"):
        collect_in_parts(preset, 0, tmp_path / "other", 60, part=0)
    assert paused_at(tmp_path / "never_started") == 0


def write_evals(path, rows):
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["timesteps", "env", "mean_reward"])
        writer.writerows(rows)


@pytest.mark.parametrize(
    "evals, learnt",
    [
        ([2400, 2900, 2850, 2750, 3150], True),  # mean 2810, spread 0.101
        ([1400, 1450, 1500, 1480, 1460], False),  # steady, below 1500
        ([1020, 657, 2484, 2548, 2368], False),  # mean 1815.4 above 1500, spread 0.50
    ],
)
def test_the_switch_reading_by_hand(tmp_path, evals, learnt):
    path = tmp_path / "eval.csv"
    rows = [(5000 * (k + 1), "Env-A", value) for k, value in enumerate([100, 200, *evals])]
    write_evals(path, [*rows[::-1], (40_000, "Env-A", 9999), (30_000, "Env-B", 5000)])  # any order; later and Env-B rows
    reading = switch_reading(path, 35_000, 1500.0, 0.2, 5)
    mean = sum(evals) / 5
    spread = math.sqrt(sum((v - mean) ** 2 for v in evals) / 4) / mean
    assert reading["evals"] == [float(v) for v in evals] and reading["learnt"] is learnt
    assert reading["mean"] == pytest.approx(mean) and reading["spread"] == pytest.approx(spread)
    assert (reading["threshold"], reading["max_spread"]) == (1500.0, 0.2)
    assert last_evaluations(path, "Env-A", None, 2) == [float(evals[-1]), 9999.0]


def test_too_few_evaluations_or_a_zero_mean_are_not_learnt(tmp_path):
    path = tmp_path / "eval.csv"
    write_evals(path, [(5000, "Env-A", 3000), (10_000, "Env-A", 3000)])
    assert not switch_reading(path, 10_000, 1500.0, 0.2, 5)["learnt"]  # two evaluations of five
    assert learnt_level([0.0, 0.0], -1.0, 0.2) == (0.0, math.inf, False)


def test_overestimation_at_reads_one_logged_value(tmp_path):
    path = tmp_path / "q_sources.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["timesteps", "name", "overestimation"])
        writer.writerows([(100, "Env-A", 3.5), (100, "Env-B", -1.0), (200, "Env-A", "")])
    assert overestimation_at(path, "Env-A", 100) == 3.5 and overestimation_at(path, "Env-B", 100) == -1.0
    assert math.isnan(overestimation_at(path, "Env-A", 200)) and math.isnan(overestimation_at(path, "Env-A", 300))
    assert json.dumps(overestimation_at(path, "Env-B", 100)) == "-1.0"
