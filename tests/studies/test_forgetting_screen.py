"""benchmarks/studies/forgetting_screen/screen.py: one Stage-1 per robot and seed, each candidate continued from it,
measured, and read by the pre-registered rule."""

import argparse
import csv
import importlib.util
import json
import pathlib
import types

import pytest
from testkit import shrink_screen

SCRIPT = pathlib.Path(__file__).resolve().parents[2] / "benchmarks" / "studies" / "forgetting_screen" / "screen.py"


def load_screen() -> types.ModuleType:
    spec = importlib.util.spec_from_file_location("forgetting_screen", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def tiny_screen(monkeypatch):
    """The screen at seconds' scale: one robot, two candidates, 600 steps of Env-A, tiny networks."""
    screen = load_screen()
    shrink_screen(screen, monkeypatch, eval_freq=200)
    monkeypatch.setattr(screen, "CANDIDATES", {
        "cheetah_back_reversed": ("cheetah", {"leg_motor_scale": -1.0}),
        "cheetah_back_knee_locked": ("cheetah", {"joint_lock": 1.0}),
    })  # fmt: skip
    monkeypatch.setattr(screen, "ENV_B_FACTOR", 2)
    return screen


def test_screen_shares_stage1_measures_and_reports(tiny_screen, tmp_path):
    screen = tiny_screen
    runs, results = tmp_path / "runs", tmp_path / "results"
    screen.queue(argparse.Namespace(runs=str(runs), results=str(results), seed=0, candidates=None))
    stage1 = runs / "forgetting_screen" / "cheetah" / "stage1" / "seed_0"
    assert (stage1 / "collect" / "stage1.zip").exists()
    for candidate in screen.CANDIDATES:
        measured = json.loads((results / candidate / "seed_0" / "measure.json").read_text())
        run_dir = runs / "forgetting_screen" / candidate / "seed_0"
        assert json.loads((run_dir / "adopted.json").read_text())["stage1_from"] == str(stage1)
        # both candidates continued from the same Stage-1: the same Env-A evaluations up to the switch
        evals = [r for r in csv.DictReader(open(results / candidate / "seed_0" / "eval.csv")) if r["env"] == "Env-A"]
        assert [int(r["timesteps"]) for r in evals] == list(range(200, 1801, 200))
        assert measured["stage1_evals_env_a"] == [float(r["mean_reward"]) for r in evals if int(r["timesteps"]) <= 600][-5:]
        assert measured["forgetting_ratio"] == pytest.approx(measured["end_env_a"] / measured["stage1_env_a"])
        assert measured["switch"] == 600 and measured["end"] == 1800
        for key in ("same_episode_ratio", "zero_shot_env_b", "overestimation_env_a_switch", "overestimation_env_a_end"):
            assert isinstance(measured[key], float)
    first = json.loads((results / "cheetah_back_reversed" / "seed_0" / "measure.json").read_text())
    second = json.loads((results / "cheetah_back_knee_locked" / "seed_0" / "measure.json").read_text())
    assert first["stage1_evals_env_a"] == second["stage1_evals_env_a"]
    assert first["stage1_same_episodes_Env-A"] == second["stage1_same_episodes_Env-A"]  # the same frozen agent
    # a second call skips what is measured
    screen.queue(argparse.Namespace(runs=str(runs), results=str(results), seed=0, candidates=None))
    screen.report(argparse.Namespace(results=str(results)))
    rows = list(csv.DictReader(open(results / "screen.csv")))
    assert [r["candidate"] for r in rows] == list(screen.CANDIDATES)
    assert {"candidate", "seed", "env_a_learnt", "forgetting_ratio"} <= set(rows[0])
    text = (results / "results.md").read_text()
    assert "pending" in text and (results / "screen.png").exists()


def _row(ratio, learnt=True, seed=None):
    return dict(forgetting_ratio=ratio, env_a_learnt=learnt, forgets=(ratio <= 0.8) if learnt else None, seed=seed)


@pytest.mark.parametrize(
    "rows, verdict",
    [
        ([_row(0.79, seed=0), _row(0.5, seed=1)], "forgets"),
        ([_row(0.81, seed=0), _row(0.5, seed=1)], "mixed"),
        ([_row(0.81, seed=0), _row(1.2, seed=1)], "does not forget"),
        ([_row(0.5, seed=0), _row(0.5, learnt=False, seed=1)], "not testable"),
        ([_row(0.5, seed=0)], "pending"),
        ([_row(0.5, learnt=False, seed=0)], "not testable"),  # one seed left: two learnt seeds are out of reach
    ],
)
def test_candidate_verdict_in_both_directions(rows, verdict):
    assert load_screen().candidate_verdict(rows)[0] == verdict


def test_selection_prefers_forgetting_then_the_cheaper_robot_then_the_closest():
    screen = load_screen()
    verdicts = {name: ("does not forget", 1.0) for name in screen.CANDIDATES}
    verdicts["walker_right_reversed"] = ("forgets", 0.50)
    verdicts["cheetah_back_weak"] = ("forgets", 0.52)  # within 0.05 of the walker's: the cheaper robot wins
    verdicts["hopper_feet"] = ("forgets", 0.70)
    assert screen.select(verdicts) == ("cheetah_back_weak", "forgets")
    verdicts = {name: ("does not forget", 1.1) for name in screen.CANDIDATES}
    verdicts["hopper_reversed"] = ("does not forget", 0.9)
    verdicts["cheetah_hip"] = ("not testable", 0.1)
    assert screen.select(verdicts) == ("hopper_reversed", "closest (no candidate forgets)")
    verdicts["cheetah_hip"] = ("pending", 0.1)
    assert screen.select(verdicts)[0] is None


def test_amended_candidates_are_read_on_four_seeds():
    screen = load_screen()
    seeds = screen.candidate_seeds("cheetah_back_reversed")
    assert seeds == (0, 1, 2, 3) and screen.candidate_seeds("walker_soft_ground") == (0, 1)

    def row(learnt: bool, ratio: float, seed: int) -> dict:
        return dict(env_a_learnt=learnt, forgetting_ratio=ratio, forgets=learnt and ratio <= 0.8, seed=seed)

    two = [row(True, 0.75, 0), row(False, 1.85, 1)]
    assert screen.candidate_verdict(two, seeds)[0] == "pending"  # seeds 2 and 3 not measured yet
    assert screen.candidate_verdict(two)[0] == "not testable"  # as registered for two seeds
    four = [*two, row(True, 0.7, 2), row(False, 1.2, 3)]
    verdict, mean = screen.candidate_verdict(four, seeds)
    assert verdict == "forgets" and mean == pytest.approx(0.725)  # learnt on two of four, both forget
    assert screen.candidate_verdict([*two, row(True, 0.9, 2), row(False, 1.2, 3)], seeds)[0] == "mixed"
    assert screen.candidate_verdict([*two, row(False, 0.5, 2), row(False, 1.2, 3)], seeds)[0] == "not testable"
    # seed 3's Stage-1 did not learn Env-A: it cannot count, so the verdict does not wait for its Env-B
    three = [*two, row(True, 0.7, 2)]
    assert screen.candidate_verdict(three, seeds)[0] == "pending"
    assert screen.candidate_verdict(three, seeds, {0: True, 1: False, 2: True, 3: False})[0] == "forgets"
    assert screen.candidate_verdict(three, seeds, {3: True})[0] == "pending"
    # unmeasured seeds whose Stage-1s did not learn Env-A: not testable before any Env-B run
    assert screen.candidate_verdict([], (0, 1), {0: True, 1: False})[0] == "not testable"
    assert screen.candidate_verdict([], (0, 1), {0: True})[0] == "pending"


def test_stage1_records_are_read_by_robot_and_seed(tmp_path):
    screen = load_screen()
    for robot, seed, learnt in (("cheetah", 0, True), ("cheetah", 3, False), ("hopper", 1, False)):
        (tmp_path / "stage1" / robot).mkdir(parents=True, exist_ok=True)
        (tmp_path / "stage1" / robot / f"seed_{seed}.json").write_text(f'{{"seed": {seed}, "learnt": {str(learnt).lower()}}}')
    assert screen.stage1_readings(tmp_path) == {"cheetah": {0: True, 3: False}, "hopper": {1: False}}


def test_field_terms_of_a_learnt_seed_hand_computed(tmp_path):
    screen = load_screen()
    row = dict(candidate="cheetah_back_reversed", seed=0, stage1_env_a=2000.0, zero_shot_env_b=0.0, end_env_a=1500.0,
               end_env_b=3000.0, env_a_learnt=True)  # fmt: skip
    terms = screen.field_terms(row, {"Env-A": -300.0, "Env-B": -300.0})
    # reference: A 2000 (the switch), B 3000 (the end); s0 = [1, 300 / 3300], s1 = [1800 / 2300, 1]
    assert terms["forgetting_env_a"] == pytest.approx(1 - 1800 / 2300)
    assert terms["backward_transfer"] == pytest.approx(-(1 - 1800 / 2300))
    assert terms["average_performance"] == pytest.approx((1800 / 2300 + 1) / 2)
    assert terms["forward_transfer"] == pytest.approx(300 / 3300)
    # the section lists learnt seeds only, with the random policy's returns read from the candidate's folder
    (tmp_path / "cheetah_back_reversed").mkdir()
    record = dict(
        env_names=["Env-A", "Env-B"], stages=[{}, {"leg_motor_scale": -1.0}], returns={"Env-A": -300.0, "Env-B": -300.0}
    )
    (tmp_path / "cheetah_back_reversed" / "random_returns.json").write_text(json.dumps(record))
    lines = screen.field_terms_lines([row, {**row, "seed": 1, "env_a_learnt": False}], tmp_path)
    assert lines[-1].startswith("| cheetah_back_reversed | 0 | -300, -300 | +0.89 | +0.22 | -0.22 | +0.09 |")
    assert not any(line.startswith("| cheetah_back_reversed | 1 ") for line in lines)
    assert screen.field_terms_lines([{**row, "env_a_learnt": False}], tmp_path) == []
