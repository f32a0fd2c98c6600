"""benchmarks/studies/pipeline_forgetting: its presets are the screen's collection, its claims read both ways and its
three-way reading of an interval, and the Stage-1 rule (no run here)."""

import csv
import math
import pathlib

import pandas as pd
import pytest
from testkit import ROOT, benchmark_module

from sb3_lifelong.experiments import load_claims
from sb3_lifelong.experiments.claims import evaluate_claims
from sb3_lifelong.experiments.presets import load_presets
from sb3_lifelong.experiments.scores import Study

STUDY = ROOT / "benchmarks" / "studies" / "pipeline_forgetting"
#: what a collection is: every setting but the students', the online baselines' and the claims' thresholds
NOT_COLLECTION = {"students", "online", "student_repeats", "note", "env_a_learnt", "max_switch_spread", "value_gap",
                  "min_weight_ess", "student_critic", "student_batch_size", "student_learning_rate", "distill_steps",
                  "distill_eval_freq"}  # fmt: skip


def test_each_preset_collects_what_the_screen_collected():
    screen = benchmark_module("screen")
    pipeline = benchmark_module("pipeline")
    presets = load_presets(STUDY / "presets.py")
    assert sorted(presets) == ["pipeline_cheetah_back_knee_locked", "pipeline_cheetah_back_reversed"]
    for name, preset in presets.items():
        candidate = name.removeprefix("pipeline_")
        mine, theirs = preset.describe(), screen.preset(candidate).describe()
        assert {k: v for k, v in mine.items() if k not in NOT_COLLECTION} == {
            k: v for k, v in theirs.items() if k not in NOT_COLLECTION
        }, candidate
        assert preset.student_repeats == 2 and set(pipeline.REST_JOBS) <= set(preset.jobs())
    # Env-A is the same whichever candidate follows: one Stage-1 per seed serves both
    a, b = presets.values()
    assert a.stages[0] == b.stages[0] == {} and a.stage_steps == b.stage_steps
    assert not set(pipeline.SEEDS) & {0, 1, 2, 3}  # fresh seeds: the screen chose on 0-3


def study(scores: dict, extras: dict, seeds=(10, 11, 12)) -> Study:
    finals = [
        dict(seed=seed, method=method, kind="online", env=env, score=value)
        for (method, env), values in scores.items()
        for seed, value in zip(seeds, values)
    ]
    rows = [
        dict(seed=seed, metric=metric, value=value) for metric, values in extras.items() for seed, value in zip(seeds, values)
    ]
    preset = dict(env_names=["Env-A", "Env-B"], env_a_learnt=1500.0, max_switch_spread=0.2)
    return Study(pathlib.Path("synthetic"), preset, list(seeds), pd.DataFrame(finals), pd.DataFrame(rows))


def verdicts(mpo_a, crr_a, student_a, mpo_b, student_b, switch=(3000.0,) * 3, spread=(0.05,) * 3):
    scores = {
        ("MPO", "Env-A"): mpo_a,
        ("online CRR_exp_beta1", "Env-A"): crr_a,
        ("CRR_exp_beta1", "Env-A"): student_a,
        ("MPO", "Env-B"): mpo_b,
        ("CRR_exp_beta1", "Env-B"): student_b,
    }
    extras = {"MPO|switch|Env-A": switch, "MPO|switch_spread|Env-A": spread}
    rows = evaluate_claims(study(scores, extras), load_claims(STUDY / "claims.py"))
    return {row["claim"]: row["verdict"] for row in rows}


def test_claims_in_both_directions_and_not_testable():
    holds = verdicts((2000, 2100, 2200), (2500, 2600, 2700), (2000, 2100, 2200), (4000, 4000, 4000), (3700, 3700, 3700))
    assert set(holds.values()) == {"reproduced"}
    fails = verdicts((2500, 2600, 2400), (2400, 2500, 2300), (1700, 1800, 1900), (4000, 4000, 4000), (3500, 3500, 3500))
    assert set(fails.values()) == {"not reproduced"}
    # just either side of C1's 0.8 and C3's 0.9
    edge = verdicts((2399,) * 3, (2400,) * 3, (2399 * 0.9 + 1,) * 3, (4000,) * 3, (3599,) * 3)
    assert edge["C1 MPO forgets Env-A"] == "reproduced" and edge["C3b the student is close to MPO's end agent in Env-B"] == (
        "not reproduced"
    )
    assert edge["C3a the student is at least MPO's end agent in Env-A"] == "reproduced"
    # Env-A not learnt, or not steady, on every seed: nothing is testable
    for switch, spread in (((1400.0,) * 3, (0.05,) * 3), ((3000.0,) * 3, (0.3,) * 3)):
        rows = verdicts((2000,) * 3, (2500,) * 3, (2000,) * 3, (4000,) * 3, (3700,) * 3, switch=switch, spread=spread)
        assert set(rows.values()) == {"not testable"}


def test_reading_of_an_interval_is_three_way():
    claims = pipeline_claims()
    c1, c2 = "C1 MPO forgets Env-A", "C2 online CRR remembers Env-A better than MPO"
    assert claims.reading(c1, 0.5, 0.75) == "holds"
    assert claims.reading(c1, 0.7, 0.9) == "inconclusive"
    assert claims.reading(c1, 0.85, 1.1) == "fails"
    assert claims.reading(c2, 10.0, 300.0) == "holds"
    assert claims.reading(c2, -10.0, 300.0) == "inconclusive"
    assert claims.reading(c2, -300.0, -10.0) == "fails"
    assert claims.reading(c2, math.nan, 1.0) == "inconclusive"
    assert claims.reading(c2, 10.0, 300.0, verdict="not testable") == "not testable"
    assert set(claims.THRESHOLDS) == {claim.name for claim in claims.CLAIMS}


def pipeline_claims():
    import importlib.util

    spec = importlib.util.spec_from_file_location("pipeline_claims", STUDY / "claims.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    "evals, learnt",
    [
        ([2400, 2900, 2850, 2750, 3150], True),
        ([1400, 1450, 1500, 1480, 1460], False),  # steady, below 1500
        ([1020, 657, 2484, 2548, 2368], False),  # above 1500 on average, spread 0.50 (the screen's seed 3)
    ],
)
def test_stage1_reading_is_the_screen_rule(tmp_path, evals, learnt):
    pipeline = benchmark_module("pipeline")
    path = tmp_path / "eval.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["timesteps", "env", "mean_reward"])
        for k, value in enumerate([100, 200, *evals]):
            writer.writerow([5000 * (k + 1), "Env-A", value])
        writer.writerow([40_000, "Env-B", 5000])
    reading = pipeline.stage1_reading(path, 35_000)
    assert reading["evals"] == [float(v) for v in evals] and reading["learnt"] is learnt


def test_env_b_marks_its_finished_collection_done_for_the_rest(tmp_path, monkeypatch, capsys):
    """The parts run the collector directly; `env-b` then writes the runner's done.json, which `rest` needs."""
    import argparse
    import json

    pipeline = benchmark_module("pipeline")
    runs, results = tmp_path / "runs", tmp_path / "results"
    (results / "stage1").mkdir(parents=True)
    (results / "stage1" / "seed_10.json").write_text(json.dumps({"learnt": True}))
    run_dir = pipeline.study_dir(runs, "cheetah_back_reversed") / "seed_10"
    (run_dir / "collect").mkdir(parents=True)  # adopted already
    parts = []

    def collect_in_parts(settings, seed, directory, stop, part, log):
        parts.append((seed, directory, stop))
        if len(parts) > 1:  # the second call finishes: the collector's final checkpoint
            (directory / "collect" / "final.zip").write_bytes(b"final")

    monkeypatch.setattr(pipeline, "collect_in_parts", collect_in_parts)
    args = argparse.Namespace(runs=str(runs), results=str(results), seed=10, candidate="cheetah_back_reversed")
    with pytest.raises(SystemExit, match="has not finished"):  # a stop before the last step: no done.json
        pipeline.run_env_b(args)
    assert not (run_dir / "collect" / "done.json").exists()
    with pytest.raises(SystemExit, match="the collection is not done"):
        pipeline.run_rest(args)
    pipeline.run_env_b(args)
    done = json.loads((run_dir / "collect" / "done.json").read_text())
    assert done["job"] == "collect" and done["seed"] == 10 and parts[-1] == (10, run_dir, 240_000)
    assert done["preset"] == json.loads(json.dumps(pipeline.study_preset("cheetah_back_reversed").describe()))
    pipeline.run_env_b(args)  # done: nothing runs again
    assert len(parts) == 2 and "the collection is done" in capsys.readouterr().out
    monkeypatch.setattr(pipeline.subprocess, "call", lambda command: parts.append(command) or 0)
    assert pipeline.run_rest(args) == 0 and parts[-1][-len(pipeline.REST_JOBS) :] == list(pipeline.REST_JOBS)
    assert parts[-1][parts[-1].index("--backend") + 1] == "process"  # one worker: no Ray daemons beside it


def test_progress_names_each_seeds_collection_state(tmp_path, monkeypatch):
    import argparse
    import json

    pipeline = benchmark_module("pipeline")
    runs, results = tmp_path / "runs", tmp_path / "results"
    (results / "stage1").mkdir(parents=True)
    for seed in (10, 13, 15):
        (results / "stage1" / f"seed_{seed}.json").write_text(json.dumps({"learnt": True}))
    (results / "stage1" / "seed_11.json").write_text(json.dumps({"learnt": False}))
    study = pipeline.study_dir(runs, "cheetah_back_reversed")
    (study / "seed_10" / "collect").mkdir(parents=True)  # finished: its done.json, and a pause record left behind
    (study / "seed_10" / "collect" / "done.json").write_text(json.dumps({"job": "collect"}))
    (study / "seed_10" / "collect" / "paused.json").write_text(json.dumps({"timesteps": 220_000}))
    (study / "seed_13" / "collect").mkdir(parents=True)
    (study / "seed_13" / "collect" / "paused.json").write_text(json.dumps({"timesteps": 120_000}))
    (study / "seed_15" / "collect").mkdir(parents=True)
    lines = pipeline.progress(argparse.Namespace(runs=str(runs), results=str(results)))
    by_seed = {line.split(":")[0]: line for line in lines}
    assert "cheetah_back_reversed: collected, done: collect" in by_seed["seed 10"]
    assert "cheetah_back_reversed: collection paused at 120,000, done: -" in by_seed["seed 13"]
    assert "cheetah_back_reversed: collection not started" in by_seed["seed 15"]
    assert by_seed["seed 11"] == "seed 11: Env-A not learnt (stops here)"


def test_summary_reads_each_claim_from_its_interval_on_the_testable_seeds():
    """The registered three-way reading, on the testable seeds only: a seed whose Env-A was not learnt is left out."""
    pipeline = benchmark_module("pipeline")
    seeds = (10, 11, 12, 13)
    scores = {
        ("MPO", "Env-A"): (1000, 1100, 1200, 5000),  # seed 13 did not learn Env-A: its 5000 must not count
        ("online CRR_exp_beta1", "Env-A"): (1500, 1700, 1650, 100),
        ("CRR_exp_beta1", "Env-A"): (1800, 1900, 2000, 100),
        ("CRR_indicator", "Env-A"): (900, 1000, 1100, 100),
        ("MPO", "Env-B"): (4000, 4000, 4000, 4000),
        ("CRR_exp_beta1", "Env-B"): (2000, 3900, 4100, 4000),
        ("CRR_indicator", "Env-B"): (3000, 3100, 3200, 4000),
    }
    extras = {"MPO|switch|Env-A": (3000, 3000, 3000, 1000), "MPO|switch_spread|Env-A": (0.05,) * 4}
    readings = {row["claim"][:3]: row for row in pipeline.claim_readings(study(scores, extras, seeds))}
    assert set(readings["C1 "]["values"]) == {10, 11, 12}
    assert readings["C1 "]["mean"] == pytest.approx(1100 / 3000) and readings["C1 "]["reading"] == "holds"
    assert readings["C2 "]["reading"] == "holds" and readings["C2 "]["verdict"] == "reproduced"
    assert readings["C3a"]["reading"] == "holds"
    assert readings["C3b"]["reading"] == "inconclusive"  # 0.5, 0.975, 1.025: the interval holds 0.9
    beside = {row["series"]: row for row in pipeline.students_beside(study(scores, extras, seeds))}
    assert beside["CRR_indicator / MPO (Env-A)"]["values"] == {10: 0.9, 11: 1000 / 1100, 12: 1100 / 1200, 13: 100 / 5000}
    assert beside["exp - indicator (Env-A)"]["mean"] == pytest.approx((900 + 900 + 900 + 0) / 4)
    assert beside["exp - indicator (Env-A)"]["reading"] == "-"


def test_summary_separates_the_student_noise_from_the_buffers():
    pipeline = benchmark_module("pipeline")
    rows = [
        dict(seed=seed, student="CRR_exp_beta1", repeat=repeat, env="Env-A", score=base + delta)
        for seed, base in ((10, 1000.0), (11, 2000.0), (12, 3000.0))
        for repeat, delta in ((0, -100.0), (1, 100.0))
    ]
    rows.append(dict(seed=13, student="CRR_exp_beta1", repeat=0, env="Env-A", score=9000.0))  # one training only: left out
    (noise,) = pipeline.student_noise(pd.DataFrame(rows))
    assert noise["seeds"] == 3
    assert noise["within_sd"] == pytest.approx(200 / math.sqrt(2))  # two values 200 apart: sd 141
    assert noise["between_sd"] == pytest.approx(1000.0)
