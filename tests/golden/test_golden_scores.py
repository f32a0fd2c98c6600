"""
Golden values of the study scores (``sb3_lifelong/experiments/scores.py``): each reading computed by hand on a tiny
log written here, for the windows (which evaluations count), the counts (how many), the bounds (a spread at the
limit) and the messages a user reads when a file is malformed.
"""

import dataclasses
import json
import math
import pathlib
import statistics

import pandas as pd
import pytest

from sb3_lifelong.experiments import scores


def evals(env: str, points: dict[int, float]) -> pd.DataFrame:
    return pd.DataFrame({"timesteps": list(points), "env": env, "mean_reward": list(points.values())})


def spread_by_hand(values: list[float]) -> float:
    return statistics.stdev(values) / abs(statistics.fmean(values))


def test_last_returns_leaves_out_the_evaluation_at_after_and_keeps_the_one_at_until() -> None:
    frame = evals("A", {10: 1.0, 20: 2.0, 30: 4.0, 40: 8.0})
    assert scores.last_returns(frame, "A", 10, until=30, after=10).tolist() == [2.0, 4.0]
    assert scores.last_mean(frame, "A", 10, until=40, after=20) == pytest.approx((4.0 + 8.0) / 2)


def test_the_switch_reading_is_the_mean_of_the_last_two_evaluations_of_the_stage() -> None:
    frame = pd.concat([evals("A", {10: 1.0, 20: 2.0, 30: 4.0, 40: 8.0, 50: 100.0}), evals("B", {50: 7.0})])
    rows = {row["metric"]: row["value"] for row in scores.switch_metrics(3, frame, ["A", "B"], [40, 50])}
    assert rows["MPO|switch|A"] == pytest.approx((4.0 + 8.0) / 2)  # at 30 and 40; 50 is Env-B's stage
    assert set(rows) == {"MPO|switch|A", "MPO|switch_spread|A"}


def test_the_switch_spread_reads_the_last_three_evaluations_of_the_second_half() -> None:
    frame = evals("A", {10: 5.0, 20: 50.0, 60: 1.0, 70: 2.0, 80: 3.0, 90: 5.0, 100: 9.0})
    assert scores.switch_spread(frame, "A", 0, 100) == pytest.approx(spread_by_hand([3.0, 5.0, 9.0]))


def test_the_switch_spread_halves_the_stage_it_is_given_not_the_whole_life() -> None:
    # the stage (0, 5]: its second half is (2, 5], so the evaluations at 3, 4 and 5 (a start of 1 would halve (1, 5]
    # into (3, 5] and read two)
    frame = evals("A", {1: 100.0, 2: 10.0, 3: 1.0, 4: 2.0, 5: 4.0})
    assert scores.switch_spread(frame, "A", 0, 5) == pytest.approx(spread_by_hand([1.0, 2.0, 4.0]))
    rows = {row["metric"]: row["value"] for row in scores.switch_metrics(0, frame, ["A", "B"], [5, 10])}
    assert rows["MPO|switch_spread|A"] == pytest.approx(spread_by_hand([1.0, 2.0, 4.0]))


def test_the_switch_spread_of_a_stage_with_two_evaluations_in_its_second_half_reads_those_two() -> None:
    # (50, 100] holds 60 and 100; a window from a third of the stage would also take 40
    frame = evals("A", {20: 3.0, 40: 30.0, 60: 2.0, 100: 6.0})
    assert scores.switch_spread(frame, "A", 0, 100) == pytest.approx(spread_by_hand([2.0, 6.0]))


def test_the_switch_spread_falls_back_on_the_last_two_of_the_stage() -> None:
    frame = evals("A", {10: 1.0, 20: 2.0, 30: 3.0, 100: 9.0})  # one evaluation in (50, 100]
    assert scores.switch_spread(frame, "A", 0, 100) == pytest.approx(spread_by_hand([3.0, 9.0]))
    assert math.isnan(scores.switch_spread(evals("A", {100: 9.0}), "A", 0, 100))


def test_the_later_stage_of_three_reads_its_own_window() -> None:
    frame = pd.concat(
        [
            evals("A", {60: 1.0, 80: 2.0, 100: 4.0}),
            evals("B", {110: 50.0, 160: 1.0, 180: 3.0, 200: 5.0}),
            evals("C", {300: 9.0}),
        ]
    )
    rows = {row["metric"]: row["value"] for row in scores.switch_metrics(0, frame, ["A", "B", "C"], [100, 200, 300])}
    assert rows["MPO|switch|B"] == pytest.approx((3.0 + 5.0) / 2)
    assert rows["MPO|switch_spread|B"] == pytest.approx(spread_by_hand([1.0, 3.0, 5.0]))
    assert rows["MPO|switch_spread|A"] == pytest.approx(spread_by_hand([1.0, 2.0, 4.0]))


def test_a_level_whose_spread_is_exactly_the_limit_is_learnt() -> None:
    values = [90.0, 110.0, 100.0]
    spread = spread_by_hand(values)
    mean, measured, learnt = scores.learnt_level(values, threshold=100.0, max_spread=spread)
    assert (mean, learnt) == (100.0, True)
    assert measured == pytest.approx(spread)
    assert not scores.learnt_level(values, threshold=100.0, max_spread=spread * 0.999)[2]
    assert not scores.learnt_level(values, threshold=100.5, max_spread=1.0)[2]


def write(path: pathlib.Path, text: str) -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_the_overestimation_of_each_environment_left_in_a_three_stage_life(tmp_path: pathlib.Path) -> None:
    q_log = write(
        tmp_path / "q_sources.csv",
        "timesteps,name,source,q_mean,overestimation\n"
        "100,A,0,1.0,0.5\n300,A,0,1.0,2.5\n"
        "200,B,1,1.0,1.5\n300,B,1,1.0,3.5\n300,C,2,1.0,9.0\n",
    )
    measured = scores.collector_overestimation(1, q_log, ["A", "B", "C"], [100, 200, 300])
    extras = {row["metric"]: row["value"] for row in measured}
    assert extras == {
        "MPO|overestimation_switch|A": 0.5,
        "MPO|overestimation_end|A": 2.5,
        "MPO|overestimation_switch|B": 1.5,
        "MPO|overestimation_end|B": 3.5,
    }


def test_a_q_log_without_monte_carlo_returns_has_no_data_values(tmp_path: pathlib.Path) -> None:
    q_log = write(tmp_path / "q_sources.csv", "timesteps,name,q_mean\n100,A,1.0\n")
    assert scores.data_values(0, q_log) == []
    q_log = write(tmp_path / "measured" / "q_sources.csv", "timesteps,name,q_mean,mc_return\n100,A,1.0,4.0\n200,A,1.0,6.0\n")
    assert scores.data_values(0, q_log) == [dict(seed=0, metric="data|mc_return|A", value=6.0)]


def test_a_students_weights_are_the_mean_of_their_last_five_logged_values(tmp_path: pathlib.Path) -> None:
    ess = [100.0, 1.0, 2.0, None, 3.0, 4.0, 5.0]  # the empty cell is not a value
    lines = ["timesteps,weight_ess"] + [f"{10 * (i + 1)},{'' if value is None else value}" for i, value in enumerate(ess)]
    train_log = write(tmp_path / "train.csv", "\n".join(lines) + "\n")
    assert scores.student_weights(0, "CRR", train_log) == [dict(seed=0, metric="CRR|weight_ess", value=3.0)]


def test_read_eval_reads_only_a_finished_job(tmp_path: pathlib.Path) -> None:
    job = tmp_path / "seed_0" / "collect"
    write(job / "eval.csv", "timesteps,env,mean_reward\n10,A,1.0\n")
    assert scores.read_eval(tmp_path, 0, "collect") is None  # no done.json: still running
    write(job / "done.json", json.dumps({}))
    assert scores.read_eval(tmp_path, 0, "collect")["mean_reward"].tolist() == [1.0]
    (job / "eval.csv").unlink()
    assert scores.read_eval(tmp_path, 0, "collect") is None


def test_a_log_without_a_required_column_says_none_of_its_rows_is_used(tmp_path: pathlib.Path) -> None:
    path = write(tmp_path / "eval.csv", "timesteps,mean_reward\n10,1.0\n")
    problems: list[scores.MalformedRow] = []
    scores.read_log(path, problems)
    assert [str(problem) for problem in problems] == [
        f"{path}:1: no column 'env' (its columns: timesteps, mean_reward): none of its rows is used"
    ]


def test_the_error_names_twenty_rows_and_counts_the_rest(tmp_path: pathlib.Path) -> None:
    rows = [scores.MalformedRow(tmp_path / "eval.csv", line, "bad") for line in range(2, 27)]
    message = str(scores.MalformedResultsError(rows))
    assert message.startswith("25 malformed row(s)")
    assert sum(f"eval.csv:{line}: bad" in message for line in range(2, 27)) == 20
    assert "... and 5 more" in message
    assert "... and" not in str(scores.MalformedResultsError(rows[:20]))
    assert "... and 1 more" in str(scores.MalformedResultsError(rows[:21]))


def test_a_malformed_row_is_a_fixed_record() -> None:
    row = scores.MalformedRow(pathlib.Path("eval.csv"), 3, "bad")
    with pytest.raises(dataclasses.FrozenInstanceError):
        row.line = 4  # type: ignore[misc]
    assert len({row, scores.MalformedRow(pathlib.Path("eval.csv"), 3, "bad")}) == 1


def test_a_life_of_five_stages_reads_every_switch() -> None:
    names = ["A", "B", "C", "D", "E"]
    frame = pd.concat([evals(env, {10 * i + 5: float(i), 10 * (i + 1): float(i + 1)}) for i, env in enumerate(names)])
    rows = {row["metric"]: row["value"] for row in scores.switch_metrics(0, frame, names, [10, 20, 30, 40, 50])}
    assert {metric for metric in rows if metric.startswith("MPO|switch|")} == {f"MPO|switch|{env}" for env in names[:-1]}
    assert rows["MPO|switch|D"] == pytest.approx((3.0 + 4.0) / 2)
    assert rows["MPO|switch_spread|D"] == pytest.approx(spread_by_hand([3.0, 4.0]))  # its own stage, (30, 40]


def test_a_students_score_is_the_mean_of_its_last_two_evaluations(tmp_path: pathlib.Path) -> None:
    preset = dict(env_names=["A", "B"], stage_steps=[100, 100])
    write(tmp_path / "preset.json", json.dumps(preset))
    run = tmp_path / "seed_0"
    write(run / "collect" / "done.json", json.dumps({}))
    write(run / "collect" / "eval.csv", "timesteps,env,mean_reward\n100,A,1.0\n100,B,1.0\n200,A,1.0\n200,B,1.0\n")
    write(run / "distill_BC" / "done.json", json.dumps({}))
    student = "timesteps,env,mean_reward\n" + "".join(
        f"{t},{env},{r}\n" for t, r in ((10, 1.0), (20, 2.0), (30, 4.0)) for env in "AB"
    )
    write(run / "distill_BC" / "eval.csv", student)
    study = scores.load_study(tmp_path)
    assert study.score("BC", "A") == {0: 3.0}  # (2 + 4) / 2, not the first evaluation too


def stored(path: pathlib.Path, rows: int):
    import gymnasium as gym
    import numpy as np

    from sb3_lifelong import LifelongReplayBuffer

    buffer = LifelongReplayBuffer(0, gym.spaces.Box(-1, 1, (2,)), gym.spaces.Box(-1, 1, (1,)), device="cpu", path=path)
    buffer.set_source(0, name="Env-A")
    for i in range(rows):
        obs = np.full((1, 2), i, dtype=np.float32)
        buffer.add(obs, obs, np.zeros((1, 1)), np.array([1.0]), np.array([False]), [{}])
    buffer.flush()
    return buffer


def test_the_rows_of_a_buffer_are_counted_while_its_writer_holds_it(tmp_path: pathlib.Path) -> None:
    writer = stored(tmp_path / "buffer", 7)  # a collection still writing: only a read-only open may count
    try:
        assert scores.count_source_rows(tmp_path / "buffer") == {"Env-A": 7}
    finally:
        writer.close()


def test_an_unreadable_buffer_leaves_the_report_without_its_rows_and_says_so_where_it_was_asked(tmp_path) -> None:
    run = tmp_path / "seed_0"
    write(run / "collect" / "done.json", json.dumps({}))  # no record of the rows: they are counted in the buffer
    write(run / "buffer" / "manifest.json", "{not json")
    with pytest.warns(UserWarning, match="its rows per source could not be counted") as caught:
        assert scores.source_rows(run) == {}
    assert caught[0].filename == __file__  # the caller's line, not the module's
    assert str(run / "buffer") in str(caught[0].message)


def test_the_return_matrix_starts_at_the_first_stage_by_default() -> None:
    frame = pd.concat([evals("A", {100: 1.0, 200: 3.0}), evals("B", {100: 2.0, 200: 4.0})])
    rows = {row["metric"]: row["value"] for row in scores.return_matrix(0, "MPO", frame, ["A", "B"], [100, 200])}
    assert rows == {"MPO|R|0|A": 1.0, "MPO|R|0|B": 2.0, "MPO|R|1|A": 2.0, "MPO|R|1|B": 3.0}
    later = scores.return_matrix(0, "online X", frame, ["A", "B"], [100, 200], first=1)
    assert {row["metric"] for row in later} == {"online X|R|1|A", "online X|R|1|B"}


def test_the_stage_2_area_is_the_mean_of_every_evaluation_of_stage_2(tmp_path: pathlib.Path) -> None:
    write(tmp_path / "preset.json", json.dumps(dict(env_names=["A", "B"], stage_steps=[100, 1000])))
    run = tmp_path / "seed_0"
    write(run / "collect" / "done.json", json.dumps({"source_rows": {"A": 100, "B": 1000}}))
    stage2 = {100 + 10 * k: float(k) for k in range(1, 101)}  # 100 evaluations in (100, 1100]
    points = {50: 1000.0, 100: 2000.0, **stage2}  # Stage 1's two are not in the area
    lines = "".join(f"{t},{env},{r}\n" for t, r in points.items() for env in "AB")
    write(run / "collect" / "eval.csv", "timesteps,env,mean_reward\n" + lines)
    study = scores.load_study(tmp_path)
    assert study.extra("MPO|stage2_area|A") == {0: pytest.approx(sum(range(1, 101)) / 100)}
    assert study.extra("buffer|rows|B") == {0: 1000.0}


def test_a_students_extras_are_its_last_q_per_source_and_its_weights(tmp_path: pathlib.Path) -> None:
    q = "timesteps,source,name,q_mean\n10,0,A,1.0\n10,1,B,2.0\n20,0,A,5.0\n20,1,B,7.0\n"
    write(tmp_path / "q_sources.csv", q)
    write(tmp_path / "train.csv", "timesteps,weight_ess\n10,0.5\n20,0.7\n")
    extras = {row["metric"]: row["value"] for row in scores.student_extras(0, "BC", tmp_path, [])}
    assert extras == {"BC|q|A": 5.0, "BC|q|B": 7.0, "BC|weight_ess": pytest.approx(0.6)}


def two_repeats_study(path: pathlib.Path, malformed_row: bool = False) -> None:
    write(path / "preset.json", json.dumps(dict(env_names=["A", "B"], stage_steps=[100, 100])))
    run = path / "seed_0"
    write(run / "collect" / "done.json", json.dumps({"source_rows": {"A": 100, "B": 100}}))
    write(run / "collect" / "eval.csv", "timesteps,env,mean_reward\n200,A,1.0\n200,B,1.0\n")
    for job, ess, reward in (("distill_BC", 0.4, 2.0), ("distill_BC__r1", 0.8, 4.0)):
        write(run / job / "done.json", json.dumps({}))
        write(run / job / "eval.csv", f"timesteps,env,mean_reward\n10,A,{reward}\n10,B,{reward}\n")
        write(run / job / "train.csv", f"timesteps,weight_ess\n10,{ess}\n" + ("x,1\n" if malformed_row else ""))


def test_a_students_repeats_score_and_weigh_as_their_mean_in_the_order_of_the_jobs(tmp_path: pathlib.Path) -> None:
    two_repeats_study(tmp_path)
    study = scores.load_study(tmp_path)
    assert study.score("BC", "A") == {0: 3.0} and study.extra("BC|weight_ess") == {0: pytest.approx(0.6)}
    assert list(study.finals["method"]) == ["MPO", "MPO", "BC", "BC"]  # the collector first, as the jobs run
    assert list(study.finals["repeats"]) == [1, 1, 2, 2]
    metrics = list(study.extras["metric"])
    assert metrics.index("MPO|stage2_area|A") < metrics.index("buffer|rows|A") < metrics.index("BC|weight_ess")


def test_a_dropped_malformed_row_is_named_at_the_callers_line(tmp_path: pathlib.Path) -> None:
    two_repeats_study(tmp_path, malformed_row=True)
    with pytest.warns(scores.MalformedRowWarning, match="timesteps is .x., not a number") as caught:
        study = scores.load_study(tmp_path, malformed="drop")
    assert {warning.filename for warning in caught} == {__file__} and len(study.dropped) == 2
