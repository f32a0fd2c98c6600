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


def test_a_level_exactly_at_the_threshold_is_learnt():
    assert learnt_level([1500.0, 1500.0, 1500.0], 1500.0, 0.2) == (1500.0, 0.0, True)
    assert learnt_level([1499.0, 1499.0], 1500.0, 0.2)[2] is False
    assert learnt_level([1000.0, 2000.0], 1500.0, math.sqrt(2) / 3)[2] is True  # spread exactly at its bound


def test_the_switch_metrics_of_three_stages_by_hand():
    """Each environment left (Env-A at 100, Env-B at 200) has its return and its spread over its own stage."""
    import pandas as pd

    from sb3_lifelong.experiments.scores import switch_metrics

    values = {"Env-A": [10, 20, 30, 40, 50, 60, 70, 80, 90, 100], "Env-B": [1, 2, 3, 4, 5, 6, 7, 8, 9, 10]}
    rows = []
    for k in range(1, 31):  # an evaluation every 10 steps of three 100-step stages
        rows.append(dict(timesteps=10 * k, env="Env-A", mean_reward=float(values["Env-A"][(k - 1) % 10] + 1000 * (k > 10))))
        rows.append(dict(timesteps=10 * k, env="Env-B", mean_reward=float(values["Env-B"][(k - 1) % 10] * (1 + (k > 10)))))
        rows.append(dict(timesteps=10 * k, env="Env-C", mean_reward=0.0))
    frame = pd.DataFrame(rows)
    got = {row["metric"]: row["value"] for row in switch_metrics(7, frame, ["Env-A", "Env-B", "Env-C"], [100, 200, 300])}
    assert sorted(got) == ["MPO|switch_spread|Env-A", "MPO|switch_spread|Env-B", "MPO|switch|Env-A", "MPO|switch|Env-B"]
    assert got["MPO|switch|Env-A"] == (90 + 100) / 2  # the last two evaluations up to 100
    assert got["MPO|switch|Env-B"] == (18 + 20) / 2  # the last two up to 200 (Env-B doubled after 100)

    def spread(xs):
        mean = sum(xs) / len(xs)
        return math.sqrt(sum((x - mean) ** 2 for x in xs) / (len(xs) - 1)) / mean

    assert got["MPO|switch_spread|Env-A"] == pytest.approx(spread([80, 90, 100]))  # the second half of (0, 100]
    assert got["MPO|switch_spread|Env-B"] == pytest.approx(spread([16, 18, 20]))  # the second half of (100, 200]
