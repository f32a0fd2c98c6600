"""benchmarks/studies/imbalance_dose: the collector measured, the students, the claims, adopting a Stage-1."""

import json

import numpy as np
import pandas as pd
import pytest
from testkit import benchmark_module

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.experiments import PRESETS, run_seed


def test_imbalance_dose_study(study, tmp_path):
    """benchmarks/studies/imbalance_dose/imbalance_dose.py: the collector measured, the eight students, preconditions
    and claims."""
    import argparse

    dose = benchmark_module("imbalance_dose")
    output, _ = study
    results = tmp_path / "results"
    args = argparse.Namespace(
        robot="tiny", seed=0, updates=60, students=None, runs=str(tmp_path), study=str(output),
        students_output=str(tmp_path / "students"), results=str(results), student_seed=None,
    )  # fmt: skip
    screen_args = argparse.Namespace(robot="tiny", seed=0, runs=str(tmp_path), study=str(output), results=str(results))
    dose.screen(screen_args)
    screened = json.loads((results / "tiny" / "seed_0" / "screen.json").read_text())
    assert np.isfinite(screened["zero_shot_drop_A_to_B"]) and np.isfinite(screened["stage1_overestimation_Env-A"])
    assert screened["P1_agent"] is True  # the tiny robot has no threshold
    dose.run(args)
    collector = json.loads((results / "tiny" / "seed_0" / "collector.json").read_text())
    for key in ("stage1_last5_Env-A", "end_last5_Env-A", "stage1_same_episodes_Env-A", "final_same_episodes_Env-B"):
        assert np.isfinite(collector[key]), key
    assert collector["mc_return_x3_Env-B"] == pytest.approx(3 * collector["mc_return_x1_Env-B"])  # the reward dose
    assert collector["mc_return_x3_Env-A"] == pytest.approx(collector["mc_return_x1_Env-A"])
    summary = json.loads((results / "tiny" / "seed_0" / "students.json").read_text())
    assert set(summary["students"]) == {"A_only", "B_only", *(f"{t}_{d}" for t in ("ind", "ess") for d in dose.DOSES)}
    ess = summary["students"]["ess_x1_1to5"]
    assert ess["weight_ess"] == pytest.approx(dose.TARGET_ESS, abs=0.01) and ess["beta"] > 0
    assert np.isnan(summary["students"]["ind_x1_1to5"]["beta"])
    # one support for every dose, holding the x3 rewards
    supports = set()
    for name in summary["students"]:
        done = json.loads((tmp_path / "students" / "seed_0" / f"distill_{name}" / "done.json").read_text())
        supports.add(tuple(sorted(done["settings"]["kwargs"]["policy_kwargs"].items())))
    assert len(supports) == 1
    rerun = dose.run(args)  # finished students are skipped
    assert rerun is None
    where = argparse.Namespace(robot="tiny", updates=60, runs=str(tmp_path), study=str(output),
                               students_output=str(tmp_path / "students"))  # fmt: skip
    assert "seed 0: collection finished; students done 8 of 8" in "\n".join(dose.progress(where))
    # a replicate on the same buffer: another student seed, its own directories; the report reads the study's alone
    dose.run(argparse.Namespace(**{**vars(args), "students": ["ess_x1_1to5", "ess_x1_1to20"], "student_seed": 7}))
    replicate = json.loads((results / "tiny" / "replicates" / "seed_0_student7" / "students.json").read_text())
    done = json.loads((tmp_path / "students_student7" / "seed_0" / "distill_ess_x1_1to5" / "done.json").read_text())
    assert set(replicate["students"]) == {"ess_x1_1to5", "ess_x1_1to20"}
    assert (done["student_seed"], done["buffer_seed"]) == (7, 0)
    assert replicate["students"]["ess_x1_1to5"]["evals_Env-A"] != summary["students"]["ess_x1_1to5"]["evals_Env-A"]
    table = dose.replicates(argparse.Namespace(robot="tiny", results=str(results)))
    assert sum(line.startswith("| 0 | 7 | `ess_x1_") for line in table) == 2  # each replicate beside the study's
    (drop,) = [line for line in table if line.startswith("| 0 | 7 | ess, x1_1to20 |")]  # the dose the replicate holds
    study = summary["students"]
    expected = (study["ess_x1_1to5"]["return_Env-A"] - study["ess_x1_1to20"]["return_Env-A"]) / study["A_only"]["return_Env-A"]
    assert f"| {100 * expected:.1f} % |" in drop and (results / "replicates.md").exists()
    dose.report(argparse.Namespace(results=str(results)))
    claims = pd.read_csv(results / "claims.csv")
    assert {"claim", "preconditions_held", "result"} <= set(claims.columns)
    assert set(claims["result"]) <= {"reproduced", "not reproduced", "not testable"}
    assert (claims["result"] == "not testable").all()  # one seed: no claim is testable
    assert (results / "dose_tiny.png").exists() and "P1" in (results / "results.md").read_text()
    q_log = pd.read_csv(results / "tiny" / "seed_0" / "collect_q_sources.csv")  # the collection figure's lower panel
    assert q_log["overestimation"].notna().any() and (results / "collection_tiny.png").exists()


def test_imbalance_dose_adopts_a_stage1_and_branches(study, tmp_path):
    """imbalance_dose.py: another change's collection, paused at the switch from a finished Stage-1, continues in parts;
    ``branch`` runs another Env-B from it; the change screen reports both."""
    import argparse

    dose = benchmark_module("imbalance_dose")
    output, _ = study
    adopted = tmp_path / "adopted"
    dose.adopt_stage1(argparse.Namespace(robot="tiny", seed=0, source=str(output), output=str(adopted)))
    preset = PRESETS["tiny"]
    switch = preset.stage_steps[0]
    record = json.loads((adopted / "seed_0" / "collect" / "paused.json").read_text())
    assert record == dict(timesteps=switch, transitions=switch)
    with pytest.raises(FileExistsError):  # written once
        dose.adopt_stage1(argparse.Namespace(robot="tiny", seed=0, source=str(output), output=str(adopted)))
    assert run_seed(preset, 0, adopted, jobs=["collect"], log=lambda m: None, until=switch + 100) == []
    assert run_seed(preset, 0, adopted, jobs=["collect"], log=lambda m: None) == ["collect"]
    with LifelongReplayBuffer.open(adopted / "seed_0" / "buffer", read_only=True) as buffer, LifelongReplayBuffer.open(
        output / "seed_0" / "buffer_stage1", read_only=True
    ) as stage1:
        assert buffer.size() == sum(preset.stage_steps)
        np.testing.assert_array_equal(
            buffer.store.read_range("observations", 0, switch), stage1.store.read_range("observations", 0, switch)
        )
    evals = pd.read_csv(adopted / "seed_0" / "collect" / "eval.csv")
    assert (evals[evals["timesteps"] <= switch]["env"] == "Env-A").all()  # the other Env-B's evaluations are not kept
    results = tmp_path / "results"
    dose.branch(argparse.Namespace(robot="tiny", seed=0, change='{"hip_deformation": -0.3}', steps=200, runs=str(tmp_path),
                                   study=str(output), output=str(tmp_path / "branched"), results=str(results)))  # fmt: skip
    curve = results / "tiny" / "changes" / "branched" / "seed_0" / "collect_eval.csv"
    assert pd.read_csv(curve)["timesteps"].max() == switch + 200
    dose.report(argparse.Namespace(results=str(results)))
    assert "change screen" in (results / "results.md").read_text() and (results / "change_screen_tiny.png").exists()


def test_imbalance_dose_claims_wait_for_missing_seeds_and_students():
    """A claim is pending while a seed could still make it testable, not testable when none can, decided when due."""
    dose = benchmark_module("imbalance_dose")

    def collector(end_a: float) -> dict:
        out = {"stage1_last5_Env-A": 4000.0, "end_last5_Env-A": end_a, "stage1_overestimation_Env-A": 90.0}
        out["final_overestimation_Env-A"] = 200.0
        for scale in (1, 3):
            out.update({f"mc_return_x{scale}_Env-A": 170.0, f"mc_return_x{scale}_Env-B": 330.0 * scale})
        return out

    def students(drop: float, b_only: float = 1000.0) -> dict:
        ind = {"x1_1to5": 3000.0, "x3_1to5": 3000.0 - drop, "x1_1to20": 3000.0 - drop}
        rows = {"A_only": {"return_Env-A": 3500.0}, "B_only": {"return_Env-A": b_only}}
        for name, value in ind.items():
            rows[f"ind_{name}"] = {"return_Env-A": value, "overestimation_Env-A": 100.0 + (3000.0 - value) / 10}
            rows[f"ess_{name}"] = {"return_Env-A": 3000.0, "weight_ess": 0.9, "weight_clip_frac": 0.0}
        return rows

    def verdicts(data: dict) -> dict:
        pre = {seed: dose.seed_preconditions("cheetah_hip", *data[seed]) for seed in data}
        return {row["claim"]: row["result"] for row in dose.claims("cheetah_hip", data, pre)}

    # seed 0 did not forget (P2 failed) and has no student: every claim waits for seeds 1 and 2 (one seed decides none)
    one = verdicts({0: (collector(4700.0), {})})
    assert one["C1 MPO forgets Env-A"] == "pending"
    assert one["C2 indicator drops in A at x3_1to5"] == "pending" and one["C3 ESS student flat at x3_1to5"] == "pending"
    assert one["C5 MPO's overestimation on A grows after the switch"] == "pending"
    pre = dose.seed_preconditions("cheetah_hip", collector(4700.0), {})
    assert pre["P1"] is None and pre["P4"] is None and pre["P2"] is False
    # seed 1 forgot, its students are in, seed 2 failed P2: two seeds cannot hold C2's preconditions
    done = verdicts({0: (collector(4700.0), {}), 1: (collector(2000.0), students(800.0)), 2: (collector(4500.0), {})})
    assert done["C2 indicator drops in A at x3_1to5"] == "not testable"
    assert done["C4 overestimation on A rises at x1_1to20"] == "not testable"
    assert done["C1 MPO forgets Env-A"] == "not reproduced"  # two testable seeds, and seed 0 is not lower: decided
    assert done["C5 MPO's overestimation on A grows after the switch"] == "pending"  # P1 waits for the A_only students
    # three forgetting seeds with students: the indicator drops, the conservative student does not
    full = verdicts({seed: (collector(2000.0), students(800.0)) for seed in (0, 1, 2)})
    assert full["C1 MPO forgets Env-A"] == "reproduced"
    assert (
        full["C2 indicator drops in A at x3_1to5"] == "reproduced" and full["C3 ESS student flat at x3_1to5"] == "reproduced"
    )
    assert full["C4 overestimation on A rises at x3_1to5"] == "reproduced"
    flat = verdicts({seed: (collector(2000.0), students(0.0)) for seed in (0, 1, 2)})
    assert flat["C2 indicator drops in A at x1_1to20"] == "not reproduced"
    assert flat["C3 ESS student flat at x1_1to20"] == "not testable"
    waiting = verdicts({0: (collector(2000.0), students(800.0)), 1: (collector(2000.0), {})})  # seed 1's students run
    assert waiting["C2 indicator drops in A at x3_1to5"] == "pending"

    # the secondary design: P2s (the B_only student fails in Env-A) in place of P2, so collectors that did not forget
    # test the student claims where the Env-B data alone does not teach Env-A
    kept = verdicts({seed: (collector(4700.0), students(800.0)) for seed in (0, 1, 2)})
    assert kept["C2 indicator drops in A at x3_1to5"] == "not testable"  # P2 failed everywhere
    assert (
        kept["S2 indicator drops in A at x3_1to5"] == "reproduced" and kept["S3 ESS student flat at x3_1to5"] == "reproduced"
    )
    assert kept["S4 overestimation on A rises at x1_1to20"] == "reproduced"
    transfers = verdicts({seed: (collector(4700.0), students(800.0, b_only=3400.0)) for seed in (0, 1, 2)})
    assert transfers["S2 indicator drops in A at x1_1to20"] == "not testable"  # 3400 > 0.8 x 3500: Env-B data teaches A
    pre = dose.seed_preconditions("cheetah_hip", collector(4700.0), {"A_only": {"return_Env-A": 3500.0}})
    assert pre["P2s"] is None  # B_only has not finished
    assert (
        verdicts({0: (collector(4700.0), {"A_only": {"return_Env-A": 3500.0}})})["S2 indicator drops in A at x3_1to5"]
        == "pending"
    )


def test_imbalance_dose_merge_students_adds_and_keeps(tmp_path):
    """imbalance_dose.py merge-students: the other directory's students are added, none is removed, the support must
    be the same."""
    import argparse

    dose = benchmark_module("imbalance_dose")
    target = tmp_path / "results" / "cheetah_hip" / "seed_0" / "students.json"
    source = tmp_path / "scratch" / "cheetah_hip" / "seed_0" / "students.json"
    target.parent.mkdir(parents=True)
    source.parent.mkdir(parents=True)
    support = {"v_min": -1.0, "v_max": 5.0}
    target.write_text(json.dumps(dict(support=support, students={"A_only": {"r": 1}, "ind_x1_1to5": {"r": 2}})))
    source.write_text(json.dumps(dict(support=support, students={"ess_x1_1to20": {"r": 3}})))
    args = argparse.Namespace(robot="cheetah_hip", seed=0, source=str(tmp_path / "scratch"), results=str(tmp_path / "results"))
    merged = dose.merge_students(args)
    assert merged["students"] == {"A_only": {"r": 1}, "ind_x1_1to5": {"r": 2}, "ess_x1_1to20": {"r": 3}}
    assert json.loads(target.read_text()) == merged
    source.write_text(json.dumps(dict(support={"v_min": -2.0, "v_max": 5.0}, students={"B_only": {}})))
    with pytest.raises(SystemExit, match="another support"):
        dose.merge_students(args)
    assert json.loads(target.read_text()) == merged  # nothing lost


def test_imbalance_dose_same_collection_compares_the_q_logs(tmp_path, capsys):
    """imbalance_dose.py same-collection: equal where every common measurement is equal, else where it first differs."""
    import argparse

    dose = benchmark_module("imbalance_dose")
    results, runs = tmp_path / "results", tmp_path / "runs"
    committed = results / "cheetah_hip" / "seed_0" / "collect_q_sources.csv"
    rerun = runs / "imbalance_dose_cheetah_hip" / "seed_0" / "collect" / "q_sources.csv"
    committed.parent.mkdir(parents=True)
    rerun.parent.mkdir(parents=True)
    committed.write_text("timesteps,source,name,q_mean,n\n10000,0,Env-A,6.5,4096\n20000,0,Env-A,32.25,4096\n"
                         "30000,0,Env-A,76.0,4096\n")  # fmt: skip
    args = argparse.Namespace(robot="cheetah_hip", seed=0, runs=str(runs), study=None, results=str(results))
    header = "timesteps,source,name,q_mean,n,q_probe,mc_return,overestimation,n_mc\n"
    rerun.write_text(header + "10000,0,Env-A,6.5,4096,1,2,-1,10\n20000,0,Env-A,32.25,4096,1,2,-1,10\n")
    assert dose.same_collection(args)  # a run still going: equal so far, the later committed row not compared yet
    assert "2 measurements equal, up to 20,000 steps" in capsys.readouterr().out
    rerun.write_text(header + "10000,0,Env-A,6.5,4096,,,,\n20000,0,Env-A,32.25000001,4096,,,,\n30000,0,Env-A,75.0,4096,,,,\n")
    assert not dose.same_collection(args)
    assert "differs first at 20,000 steps, source 0: 32.25000001 here, 32.25 committed (2 of 3" in capsys.readouterr().out
    rerun.unlink()
    with pytest.raises(SystemExit, match="does not exist"):
        dose.same_collection(args)


def test_imbalance_dose_progress_counts_committed_students(tmp_path, monkeypatch):
    """imbalance_dose.py progress: students committed in the results need no run; the missing ones are named."""
    import argparse

    dose = benchmark_module("imbalance_dose")
    study, results = tmp_path / "runs" / "study", tmp_path / "results"
    (study / "seed_0" / "collect").mkdir(parents=True)
    (study / "seed_0" / "collect" / "done.json").write_text("{}")
    names = list(dose.student_settings({}))
    (results / "tiny" / "seed_0").mkdir(parents=True)
    (results / "tiny" / "seed_0" / "students.json").write_text(json.dumps({"students": {n: {} for n in names[:-1]}}))
    where = argparse.Namespace(robot="tiny", updates=60, runs=str(tmp_path / "runs"), study=str(study),
                               students_output=str(tmp_path / "students"), results=str(results))  # fmt: skip
    text = "\n".join(dose.progress(where))
    assert f"committed in {results}: {len(names) - 1}" in text
    # only the missing student, into a scratch directory (run rewrites students.json), then merged; absolute paths
    assert f"--students {names[-1]} --results <scratch>" in text and "merge-students --robot tiny --seed 0" in text
    assert f"--runs {(tmp_path / 'runs').resolve()} --study {study.resolve()}" in text
    (results / "tiny" / "seed_0" / "students.json").write_text(json.dumps({"students": {n: {} for n in names}}))
    assert "nothing to run" in "\n".join(dose.progress(where))
    monkeypatch.setitem(dose.PINNED, "tiny", ("aaaaaaa", "bbbbbbb"))  # a pinned study names its snapshots
    (study / "seed_0" / "collect" / "done.json").unlink()
    (results / "tiny" / "seed_0" / "students.json").write_text(json.dumps({"students": {n: {} for n in names[:-1]}}))
    text = "\n".join(dose.progress(where))
    assert "aaaaaaa" in text and "bbbbbbb" in text
    assert "PYTHONPATH=<collect-tree>:<repo>/benchmarks/studies/imbalance_dose/study_float32" in text
