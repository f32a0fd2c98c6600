"""benchmarks/studies/forgetting_control/control.py: one Stage-1 per seed, a switched and a control branch from it,
measured, and read by the pre-registered rules in both directions."""

import argparse
import csv
import dataclasses
import json
import math

import numpy as np
import pytest
from testkit import benchmark_module


@pytest.fixture
def control():
    return benchmark_module("control")


def test_branches_are_the_screens_collector_and_differ_only_in_stage2(control):
    screen = benchmark_module("screen")  # the study reads its own presets file, equal to the screen's collection
    switched, nominal = control.preset("switched"), control.preset("control")
    theirs = screen.preset(control.CANDIDATE).describe()
    for mine in (switched.describe(), nominal.describe()):
        assert {k: v for k, v in mine.items() if k not in {"stages", "stage_steps", "note"}} == {
            k: v for k, v in theirs.items() if k not in {"stages", "stage_steps", "note"}
        }
    assert switched.stages == ({}, {"leg_motor_scale": -1.0}) and nominal.stages == ({}, {"leg_motor_scale": 1.0})
    assert switched.stage_steps == nominal.stage_steps == (120_000, 120_000)
    assert not set(control.SEEDS) & set(range(0, 22))  # fresh: the screen used 0-3, the pipeline study registered 10-21
    with pytest.raises(ValueError, match="no branch 'other'"):
        control.preset("other")


@pytest.fixture
def tiny(control, monkeypatch):
    """The study at seconds' scale: 600 steps of Env-A, 400 per branch, tiny networks, every Env-A counted learnt."""
    monkeypatch.setattr(control, "ENV_A_STEPS", 600)
    monkeypatch.setattr(control, "STAGE2_STEPS", 400)
    monkeypatch.setattr(control, "SAME_EPISODES", 1)
    monkeypatch.setattr(control, "PART", 400)
    full = control.preset

    def small(branch: str):  # five evaluations before the switch, one episode each, every Env-A counted learnt
        return dataclasses.replace(full(branch), eval_freq=100, eval_episodes=1, env_a_learnt=-1e9,
                                   max_switch_spread=math.inf, net_arch=(16, 16), batch_size=32, num_samples=4,
                                   learning_starts=100, max_episode_steps=100)  # fmt: skip

    monkeypatch.setattr(control, "preset", small)
    # Monte-Carlo returns over 10 steps, so that 100-step episodes give overestimation values to read
    monkeypatch.setattr("sb3_lifelong.evaluation.overestimation.monte_carlo_horizon", lambda gamma: 10)
    return control


def test_both_branches_continue_one_stage1_and_report(tiny, tmp_path):
    control = tiny
    runs, results = tmp_path / "runs", tmp_path / "results"
    control.queue(argparse.Namespace(runs=str(runs), results=str(results), seeds=[30]))
    stage1 = runs / "forgetting_control" / "stage1" / "seed_30"
    assert json.loads((results / "stage1" / "seed_30.json").read_text())["learnt"]
    measured = {}
    for branch in control.BRANCHES:
        run_dir = runs / "forgetting_control" / branch / "seed_30"
        assert json.loads((run_dir / "adopted.json").read_text())["stage1_from"] == str(stage1)
        measured[branch] = json.loads((results / branch / "seed_30" / "measure.json").read_text())
        evals = [r for r in csv.DictReader(open(results / branch / "seed_30" / "eval.csv")) if r["env"] == "Env-A"]
        assert [int(r["timesteps"]) for r in evals] == list(range(100, 1001, 100))
        assert measured[branch]["switch"] == 600 and measured[branch]["end"] == 1000
    # the same frozen Stage-1 agent on the same seeded episodes in both branches
    assert measured["switched"]["stage1_same_episodes_Env-A"] == measured["control"]["stage1_same_episodes_Env-A"]
    # the control's Stage 2 is the nominal robot: its frozen agent scores the same in "Env-B" as in Env-A
    assert measured["control"]["stage1_same_episodes_Env-B"] == pytest.approx(
        measured["control"]["stage1_same_episodes_Env-A"]
    )
    assert measured["switched"]["stage1_same_episodes_Env-B"] != measured["switched"]["stage1_same_episodes_Env-A"]
    lines = control.progress(argparse.Namespace(runs=str(runs), results=str(results)))
    assert lines[0] == "seed 30: switched measured, control measured" and lines[1] == "seed 31: Stage 1 not started"
    # K4: the frozen and both end agents against their own policy's return from the restored Env-A states
    control.run_true_error(argparse.Namespace(runs=str(runs), results=str(results), seeds=[30], rows=4))
    true = json.loads((results / "true_error" / "seed_30.json").read_text())
    assert true["rows"] == 4 and set(true) >= {"stage1", "final_switched", "final_control"}
    for agent in ("stage1", "final_switched", "final_control"):
        assert true[agent]["true_error"] == pytest.approx(true[agent]["q"] - true[agent]["g"])
    assert true["true_offline_error"] == true["final_switched"]["true_error"] - true["final_control"]["true_error"]
    assert control.collected(results)[0]["true_offline_error"] == true["true_offline_error"]
    text = control.report(argparse.Namespace(results=str(results)))
    rows = list(csv.DictReader(open(results / "control.csv")))
    assert [int(r["seed"]) for r in rows] == [30] and float(rows[0]["true_offline_error"]) == true["true_offline_error"]
    control_end = measured["control"]["end_env_a"]
    expected = measured["switched"]["end_env_a"] / control_end if control_end > 0 else math.nan
    assert float(rows[0]["cost_ratio"]) == pytest.approx(expected, nan_ok=True)
    assert text.count("**pending**") == 4 and (results / "control.png").exists()
    for name, branch in measured.items():  # the end's evaluations are the last five; the overestimation was measured
        evals = [r for r in csv.DictReader(open(results / name / "seed_30" / "eval.csv")) if r["env"] == "Env-A"]
        assert branch["end_evals_env_a"] == [float(r["mean_reward"]) for r in evals][-5:]
        assert all(math.isfinite(branch[k]) for k in ("final_overestimation_Env-A", "overestimation_env_a_end"))
    # a second call skips what is measured; a seed outside the registration is refused
    control.queue(argparse.Namespace(runs=str(runs), results=str(results), seeds=[30]))
    with pytest.raises(SystemExit, match="not one of the registered seeds"):
        control.queue(argparse.Namespace(runs=str(runs), results=str(results), seeds=[3]))


def _branch(**values):
    out = {
        "end_env_a": 1500.0, "overestimation_env_a_switch": 40.0, "overestimation_env_a_end": 100.0,
        "stage1_overestimation_Env-A": 45.0, "final_overestimation_Env-A": 105.0, "stage1_same_episodes_Env-A": 2100.0,
        "stage1_same_episodes_Env-B": 200.0, "final_same_episodes_Env-A": 1400.0,
    }  # fmt: skip
    out.update({key.replace("__", "-"): value for key, value in values.items()})
    return out


def test_seed_values(control):
    stage1 = dict(seed=30, mean=2000.0)
    switched = _branch()
    nominal = _branch(end_env_a=3000.0, overestimation_env_a_end=70.0, final_overestimation_Env__A=75.0,
                      final_same_episodes_Env__A=2800.0)  # fmt: skip
    values = control.seed_values(stage1, switched, nominal)
    assert values["cost_ratio"] == 0.5 and values["forgetting_ratio"] == 0.75 and values["control_ratio"] == 1.5
    assert values["same_episode_cost"] == 0.5 and values["same_episode_forgetting"] == pytest.approx(1400 / 2100)
    # K3 reads the agents' overestimation on the same rows (measure_agent), the logged curves are reported beside
    assert (values["growth_switched"], values["growth_control"], values["offline_growth"]) == (60.0, 30.0, 30.0)
    assert (values["logged_growth_switched"], values["logged_growth_control"]) == (60.0, 30.0)
    assert values["change_is_real"] and values["zero_shot_share"] == pytest.approx(200 / 2100)
    assert not control.seed_values(stage1, _branch(stage1_same_episodes_Env__B=1900.0), nominal)["change_is_real"]
    # a non-positive denominator gives no ratio (and no real change), never a flipped sign
    broken = control.seed_values(stage1, _branch(stage1_same_episodes_Env__A=-5.0), _branch(end_env_a=-10.0))
    assert math.isnan(broken["cost_ratio"]) and math.isnan(broken["zero_shot_share"]) and not broken["change_is_real"]
    with pytest.raises(ValueError, match="seed 30, control: final_overestimation_Env-A is missing or not finite"):
        control.seed_values(stage1, switched, _branch(final_overestimation_Env__A=float("nan")))


@pytest.mark.parametrize(
    "claim, values, reading",
    [
        ("K1", [0.6, 0.65, 0.7, 0.62, 0.68], "costs at least a fifth"),
        ("K1", [0.85, 0.9, 0.88, 0.92, 0.87], "costs"),
        ("K1", [0.98, 1.0, 1.02, 0.99, 1.01], "no cost"),
        ("K1", [0.93, 0.95, 0.94, 0.96, 0.95], "costs, within the margin"),
        ("K1", [1.03, 1.05, 1.04, 1.06, 1.05], "helps, within the margin"),
        ("K1", [0.6, 0.65, 0.7, 0.62, 0.68, 5.0, 5.0], "costs at least a fifth"),  # the first five are read
        ("K1", [1.3, 1.4, 1.5, 1.35, 1.45], "helps"),
        ("K1", [0.5, 1.5, 0.7, 1.3, 1.0], "inconclusive"),
        ("K1", [0.5, 0.5, 0.5, 0.5], "pending"),
        ("K2", [0.5, 0.6, 0.55, 0.65, 0.6], "holds"),
        ("K2", [1.1, 1.2, 1.3, 1.0, 1.15], "fails"),
        ("K2", [0.5, 1.2, 0.7, 1.0, 0.8], "inconclusive"),
        ("K3", [20.0, 30.0, 25.0, 35.0, 28.0], "holds"),
        ("K3", [-2.0, 3.0, 1.0, -1.0, 0.5], "no difference"),
        ("K3", [4.0, 6.0, 5.0, 7.0, 5.5], "holds, within the margin"),
        ("K3", [-20.0, -30.0, -25.0, -35.0, -28.0], "reversed"),
        ("K3", [-40.0, 50.0, 10.0, -30.0, 20.0], "inconclusive"),
    ],
)
def test_readings_in_every_direction(control, claim, values, reading):
    assert control.read_claim(claim, values) == reading


def test_not_testable_once_every_stage1_ended_with_too_few_learnt(control):
    row = dict(cost_ratio=0.5, forgetting_ratio=0.5, offline_growth=10.0, change_is_real=True)
    rows = [dict(row, seed=seed) for seed in (30, 31, 32, 33)]
    stage1 = {seed: seed < 34 for seed in control.SEEDS}
    assert {claim: reading for claim, (reading, _) in control.readings(rows, stage1).items()} == dict.fromkeys(
        ("K1", "K2", "K3", "K4"), "not testable"
    )
    # while seeds are left to start, or a learnt seed is still running, it waits
    assert control.readings(rows, {30: True})["K1"][0] == "pending"
    assert control.readings(rows[:3], stage1)["K1"][0] == "pending"
    # K1 counts only seeds where the change is a change; each claim reads its first five counted seeds
    more = [*rows, dict(row, seed=34, cost_ratio=2.0, change_is_real=False), dict(row, seed=35), dict(row, seed=36)]
    read = control.readings(more, {seed: True for seed in control.SEEDS})
    assert read["K1"][1] == [0.5] * 5 and read["K2"][1] == [0.5] * 5 and read["K1"][0] == "costs at least a fifth"
    # with every seed ended, a real change on only four seeds leaves K1 not testable while K2 reads
    four = [*rows, dict(row, seed=34, change_is_real=False)]
    read = control.readings(four, {seed: seed < 35 for seed in control.SEEDS})
    assert read["K1"][0] == "not testable" and read["K2"][0] == "holds"
    with pytest.raises(ValueError, match="no claim 'K5'"):
        control.read_claim("K5", [1.0] * 5)


def test_an_interrupted_adoption_is_refused(tiny, tmp_path):
    runs, results = tmp_path / "runs", tmp_path / "results"
    partial = runs / "forgetting_control" / "switched" / "seed_30" / "collect"
    partial.mkdir(parents=True)
    (partial / "eval.csv").write_text("")
    with pytest.raises(SystemExit, match="unfinished adoption"):
        tiny.run_branch("switched", 30, runs, results)
    assert (partial / "eval.csv").exists()  # nothing is deleted


def test_a_restored_state_steps_as_the_original(control):
    import gymnasium as gym

    original, copy = gym.make("HalfCheetah-v5"), gym.make("HalfCheetah-v5")
    obs, _ = original.reset(seed=0)
    for _ in range(20):
        obs, *_ = original.step(original.action_space.sample())
    copy.reset(seed=1)
    control.restore(copy, obs)
    action = original.action_space.sample()
    np.testing.assert_allclose(copy.step(action)[0], original.step(action)[0], atol=1e-5)
    with pytest.raises(ValueError, match="did not give it back"):
        control.restore(copy, obs[:10])
