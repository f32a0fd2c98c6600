"""The cost log and the progress lines a person plans with: each job's time, the seed's estimate, honest counts."""

import json

import pytest
from testkit import small_preset

from sb3_lifelong.experiments import costs, run_seed
from sb3_lifelong.experiments.__main__ import main


@pytest.fixture
def cost_log(tmp_path, monkeypatch):
    path = tmp_path / "costs.jsonl"
    monkeypatch.setenv(costs.COSTS_VARIABLE, str(path))
    return path


def test_the_log_files_each_job_under_its_settings_and_this_cpu(cost_log):
    settings = small_preset().describe()
    assert costs.record(settings, "collect", 30.0) and costs.record(settings, "collect", 50.0)
    assert costs.record(settings, "distill_BC__r1", 6.0)  # a repeat is filed under its first run
    assert costs.record(dict(settings, distill_steps=999), "collect", 1000.0)  # other settings
    with open(cost_log, "a") as handle:
        handle.write('{"preset": "torn')  # a line cut short by a crash is skipped
        handle.write("\n" + json.dumps({"preset": costs.fingerprint(settings), "job": "collect", "seconds": 1, "cpu": "x"}))
    times = costs.measured(settings)
    assert times == {"collect": [30.0, 50.0], "distill_BC": [6.0]}  # the other CPU's line and the torn one left out
    assert costs.estimate("collect", times) == 40.0  # the median
    assert costs.estimate("distill_BC__r2", times) == 6.0
    assert costs.estimate("distill_CRR_exp_beta1", times) == 6.0  # another student: as the students measured
    assert costs.estimate("online_CRR_indicator", times) is None
    assert costs.remaining(["collect", "distill_BC"], times) == "about 46 s left for 2 job(s)"
    assert costs.remaining(["collect", "online_x"], times) == ("about 40 s left for 1 of 2 job(s); not measured yet: online_x")
    assert costs.remaining(["online_x"], times) == "1 job(s) left, no measured time for them yet"
    assert costs.remaining([], times) == ""
    assert costs.minutes(90) == "1.5 min" and costs.minutes(3 * 3600) == "3.0 h"


def test_an_empty_variable_switches_the_log_off(monkeypatch, tmp_path):
    monkeypatch.setenv(costs.COSTS_VARIABLE, "")
    assert costs.costs_file() is None
    assert not costs.record({"a": 1}, "collect", 1.0) and costs.measured({"a": 1}) == {}
    monkeypatch.setenv(costs.COSTS_VARIABLE, str(tmp_path / "a_file" / "below_a_file.jsonl"))
    (tmp_path / "a_file").write_text("not a directory")
    assert not costs.record({"a": 1}, "collect", 1.0)  # cannot be written: skipped, no error


def test_a_run_numbers_its_jobs_over_all_of_them_and_estimates_the_rest(tmp_path, cost_log):
    preset = small_preset()
    jobs = ["distill_BC", "distill_CRR_exp_beta1"]
    messages: list[str] = []
    run_seed(preset, 0, tmp_path / "study", jobs=jobs, log=messages.append)
    starts = [m for m in messages if " ..." in m]
    assert [m.split(" ...")[0] for m in starts] == [
        "seed 0: job 1/3 collect",  # collect runs first, and is counted
        "seed 0: job 2/3 distill_CRR_exp_beta1",  # in the protocol's order, not the order given
        "seed 0: job 3/3 distill_BC",
    ]
    assert messages[0] == "seed 0: 3 job(s) left, no measured time for them yet"
    assert "as measured before" not in starts[1] and "(about " in starts[2]  # the second student: from the first
    assert [m.split("; ")[1] for m in messages if "job collect done in " in m] == [
        "2 job(s) left, no measured time for them yet"
    ]
    assert messages[-1].endswith("; the seed is done")
    assert any(
        "distill_CRR_exp_beta1: checkpoint at 10 of 20 updates" in m and "a stopped run continues from here" in m
        for m in messages
    )
    assert set(costs.measured(preset.describe())) == {"collect", "distill_BC", "distill_CRR_exp_beta1"}

    again: list[str] = []  # seed 1: every job estimated from the log of seed 0
    run_seed(preset, 1, tmp_path / "study", jobs=jobs, log=again.append)
    assert again[0].startswith("seed 1: about ") and again[0].endswith(" left for 3 job(s)")
    assert all("as measured before" in m for m in again if " ..." in m)

    rerun: list[str] = []  # seed 0 again: nothing to do
    run_seed(preset, 0, tmp_path / "study", jobs=jobs, log=rerun.append)
    assert rerun == ["seed 0: 3 of 3 job(s) already done, skipped: collect, distill_CRR_exp_beta1, distill_BC"]


def test_list_shows_what_a_job_and_a_seed_took(cost_log, capsys):
    from sb3_lifelong.experiments import PRESETS

    assert main(["list", "--preset", "tiny"]) == 0
    assert "No cost measured yet for these settings on this CPU" in capsys.readouterr().out
    settings = PRESETS["tiny"].describe()
    costs.record(settings, "collect", 120.0)
    costs.record(settings, "distill_BC", 30.0)
    assert main(["list", "--preset", "tiny"]) == 0
    out = capsys.readouterr().out
    assert "  collect                            [2.0 min] MPO through every stage" in out
    assert "[30 s]" in out.split("distill_CRR_exp_beta1 ")[1].splitlines()[0]  # as the other students
    assert f"{cost_log}). A seed: about " in out and "not measured yet: online_CRR_indicator" in out
