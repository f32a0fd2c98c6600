"""Studies of more stages, student repeats and value supports; a collection reused by another study."""

import dataclasses
import json
import pathlib

import numpy as np
import pandas as pd
import pytest
from testkit import THREE_STAGE_CLAIMS

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.experiments import PRESETS, job_names, load_claims, load_study, run_seed, write_report
from sb3_lifelong.experiments.__main__ import main
from sb3_lifelong.experiments.claims import evaluate_claims
from sb3_lifelong.experiments.jobs import NotOwnedError
from sb3_lifelong.experiments.presets import load_presets


def test_three_stage_study_end_to_end(tmp_path):
    """The three-stage preset's shape at a tiny budget: one buffer of three sources, switch scores, its own claims."""

    own = load_presets(THREE_STAGE_CLAIMS.parent / "presets.py")  # the three-stage study's presets
    three = own["cpu_three"]
    assert three.stages[0] == {} and len(three.stages) == len(three.stage_steps) == len(three.env_names) == 3
    assert three.stage_steps[0] == three.stage_steps[1] and three.stage_steps[2] == 5 * three.stage_steps[0]  # 0.2:0.2:1
    assert three.jobs() == ["collect", "distill_CRR_exp_beta1", "distill_CRR_indicator", "distill_BC"]
    for number in (1, 2, 3):  # the paper's own environment combinations, at its scale
        paper = own[f"paper_three_{number}"]
        assert paper.stages[0] == "default" and paper.stages[2].startswith(paper.stages[1] + "+")
        assert paper.stage_steps == (200_000, 200_000, 1_000_000) and paper.jobs() == three.jobs()
    tiny = dataclasses.replace(
        PRESETS["tiny"],
        stages=three.stages,
        stage_steps=(200, 200, 400),
        env_names=three.env_names,
        students=three.students,
        online=False,
    )
    output = tmp_path / "three"
    assert run_seed(tiny, 0, output, log=lambda message: None) == tiny.jobs()
    run_dir = output / "seed_0"
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        assert buffer.size() == 800
        assert {v["name"] for v in buffer.sources.values()} == {"Env-A", "Env-B", "Env-C"}
        counts = buffer.source_counts()
        assert set(counts) == {0, 1, 2} and 200 <= counts[0] < 250 and counts[2] > 300
    evals = pd.read_csv(run_dir / "distill_CRR_exp_beta1" / "eval.csv")
    assert set(evals["env"]) == {"Env-A", "Env-B", "Env-C"}
    write_report(output, claims=THREE_STAGE_CLAIMS)
    study = load_study(output)
    assert set(study.extra("MPO|switch|Env-A")) == {0} and set(study.extra("MPO|switch|Env-B")) == {0}
    assert not study.extra("MPO|switch|Env-C")  # MPO never leaves the last environment
    collect = pd.read_csv(run_dir / "collect" / "eval.csv")
    at_switch_b = collect[(collect["env"] == "Env-B") & (collect["timesteps"] <= 400)].sort_values("timesteps")
    assert study.extra("MPO|switch|Env-B")[0] == pytest.approx(at_switch_b["mean_reward"].tail(2).mean())
    stage2_b = collect[(collect["env"] == "Env-B") & (collect["timesteps"] > 200) & (collect["timesteps"] <= 400)]
    assert study.extra("MPO|stage2_area|Env-B")[0] == pytest.approx(stage2_b["mean_reward"].mean())  # not Stage 3's
    # how steadily MPO left Env-B: from Stage 2's evaluations alone (its second half holds one: the stage's last two)
    assert study.extra("MPO|switch_spread|Env-B")[0] == pytest.approx(
        np.std(stage2_b.sort_values("timesteps")["mean_reward"].tail(2), ddof=1)
        / abs(stage2_b.sort_values("timesteps")["mean_reward"].tail(2).mean())
    )
    study.preset = {**study.preset, "max_switch_spread": -1.0}  # no seed steady: T1a and T1b not testable, T2a as before
    three_stage = load_claims(THREE_STAGE_CLAIMS)
    checked = {r["claim"]: r["verdict"] for r in evaluate_claims(study, three_stage)}
    assert checked["T1a forgetting Env-A"] == checked["T1b forgetting Env-B"] == "not testable"
    claims = pd.read_csv(output / "claims.csv")
    recorded = claims.set_index("claim")["verdict"]
    assert (
        checked["T2a distillation recovers the earlier environments"]
        == recorded["T2a distillation recovers the earlier environments"]
    )
    assert list(claims["claim"]) == [claim.name for claim in three_stage]
    assert "no data" not in set(claims["verdict"])  # every student and score these claims need ran
    assert (output / "fig_online.png").stat().st_size > 0
    assert not (output / "fig_sampling_ratio.png").exists()  # Env-A : Env-B ratios mean nothing here
    write_report(output, plots=False)  # no claims given, none beside the seeds: the report says so
    assert "No claims were given" in (output / "report.md").read_text()


def test_value_support_holds_every_return():
    from sb3_lifelong.experiments.jobs import value_support

    support = value_support((-2.0, 5.0), 0.9)
    assert support == pytest.approx(dict(v_min=-20.0, v_max=50.0))
    assert value_support((1.0, 3.0), 0.5) == pytest.approx(dict(v_min=0.0, v_max=6.0))  # 0 always inside
    assert value_support((-1.0, 3.0), 0.5, scales=[0.5, 4.0]) == pytest.approx(dict(v_min=-8.0, v_max=24.0))
    assert value_support((0.0, 0.0), 0.9)["v_max"] > 0  # never an empty support
    with pytest.raises(ValueError, match="gamma"):
        value_support((0.0, 1.0), 1.0)


def test_job_names_with_student_repeats():
    from sb3_lifelong.experiments.presets import split_repeat

    jobs = job_names(["CRR_exp_beta1", "BC"], online=False, student_repeats=3)
    assert jobs == [
        "collect",
        "distill_CRR_exp_beta1",
        "distill_BC",
        "distill_CRR_exp_beta1__r1",
        "distill_BC__r1",
        "distill_CRR_exp_beta1__r2",
        "distill_BC__r2",
    ]
    assert job_names(["BC"], online=False) == ["collect", "distill_BC"]
    assert split_repeat("CRR_exp_beta1__r2") == ("CRR_exp_beta1", 2)
    assert split_repeat("CRR_indicator_ratio_1to10") == ("CRR_indicator_ratio_1to10", 0)
    assert split_repeat("BC__rx") == ("BC__rx", 0)
    with pytest.raises(ValueError, match="student_repeats"):
        job_names(student_repeats=0)
    with pytest.raises(SystemExit):  # a usage error before anything is written (test_cli_counts.py)
        main(["run", "--preset", "tiny", "--seed", "0", "--output", "unused", "--student-repeats", "0"])


def test_student_repeats_are_scored_by_their_mean(study, tmp_path):
    """A preset with ``student_repeats``: each repeat its own student seed, the report scores their mean."""
    import shutil

    from sb3_lifelong.experiments.presets import REPEAT_SEED_STRIDE
    from sb3_lifelong.experiments.scores import STUDENT_LAST, last_mean

    source, _ = study
    preset = dataclasses.replace(PRESETS["tiny"], students=("CRR_exp_beta1",), online=False, student_repeats=2)
    output = tmp_path / "repeats"
    for part in ("collect", "buffer"):  # the fixture's finished collection: no need to collect again
        shutil.copytree(source / "seed_0" / part, output / "seed_0" / part)
    assert preset.jobs() == ["collect", "distill_CRR_exp_beta1", "distill_CRR_exp_beta1__r1"]
    assert run_seed(preset, 0, output, log=lambda line: None) == preset.jobs()[1:]
    scores = []
    for job, repeat in (("distill_CRR_exp_beta1", 0), ("distill_CRR_exp_beta1__r1", 1)):
        done = json.loads((output / "seed_0" / job / "done.json").read_text())
        assert done["repeat"] == repeat and done["student_seed"] == repeat * REPEAT_SEED_STRIDE
        scores.append(last_mean(pd.read_csv(output / "seed_0" / job / "eval.csv"), "Env-A", STUDENT_LAST))
    assert scores[0] == load_study(source).score("CRR_exp_beta1", "Env-A")[0]  # repeat 0 is the plain study's student
    loaded = load_study(output)
    assert loaded.score("CRR_exp_beta1", "Env-A") == {0: pytest.approx(np.mean(scores))}
    assert len(loaded.finals[loaded.finals["method"] == "CRR_exp_beta1"]) == 2  # one row per environment, not per repeat
    with pytest.raises(ValueError, match="unknown jobs"):  # a preset without repeats has no repeat jobs
        run_seed(PRESETS["tiny"], 0, tmp_path / "plain", jobs=["distill_CRR_exp_beta1__r1"], log=lambda line: None)


def test_recorded_settings_predating_new_preset_fields(tmp_path):
    """A study recorded before a Preset field existed resumes; more student repeats may be added; nothing else."""

    from sb3_lifelong.experiments.presets import LATER_SETTINGS, REPORT_THRESHOLDS
    from sb3_lifelong.experiments.protocol import record_settings

    preset = PRESETS["cpu"]  # a preset whose report thresholds are set now: an old study of it had none
    assert preset.env_a_learnt is not None
    old = json.loads(json.dumps(preset.describe()))
    for key in LATER_SETTINGS:
        old.pop(key)
    (tmp_path / "preset.json").write_text(json.dumps(old))
    record_settings(preset, tmp_path)  # the defaults are what the old study ran with
    assert json.loads((tmp_path / "preset.json").read_text()) == old  # left as it was
    record_settings(dataclasses.replace(preset, student_repeats=3), tmp_path)  # repeats added on the same buffers
    recorded = json.loads((tmp_path / "preset.json").read_text())
    assert recorded["student_repeats"] == 3
    # the old study keeps its report as it was: no thresholds it did not record
    assert all(recorded[key] is None for key in REPORT_THRESHOLDS)
    record_settings(preset, tmp_path)  # fewer repeats asked: the record keeps 3
    assert json.loads((tmp_path / "preset.json").read_text())["student_repeats"] == 3
    changes = (
        dict(layer_norm=True),
        dict(distill_steps=7),
        dict(student_critic="categorical"),
        dict(drift={"friction": (1, 2)}),
    )
    for changed in changes:
        with pytest.raises(ValueError, match="other settings"):
            record_settings(dataclasses.replace(preset, **changed), tmp_path)


def test_collection_reused_by_a_study_of_other_students(study, tmp_path):
    """``--collection-from``: another study's buffers, linked; only the students run, with a categorical critic."""

    from sb3_lifelong import CRR
    from sb3_lifelong.experiments.jobs import value_support
    from sb3_lifelong.experiments.presets import Preset
    from sb3_lifelong.experiments.report import incomplete_repeats

    source, _ = study
    preset = dataclasses.replace(
        PRESETS["tiny"], students=("CRR_indicator",), online=False, student_critic="categorical", student_repeats=2
    )
    output = tmp_path / "c51"
    lines: list[str] = []
    assert run_seed(preset, 0, output, log=lines.append, collection_from=source) == preset.jobs()[1:]  # no collect
    run_dir = output / "seed_0"
    assert (run_dir / "buffer").is_symlink() and (run_dir / "buffer").resolve() == (source / "seed_0" / "buffer").resolve()
    done = json.loads((run_dir / "collect" / "done.json").read_text())
    assert done["adopted_from"] == str((source / "seed_0").resolve()) and any("reused" in line for line in lines)
    assert (run_dir / "collect" / "eval.csv").read_bytes() == (source / "seed_0" / "collect" / "eval.csv").read_bytes()
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        support = value_support(buffer.reward_range(), 0.99)
    critic = CRR.load(run_dir / "distill_CRR_indicator__r1" / "student.zip").critic
    assert type(critic).__name__ == "CategoricalCritic" and critic.v_max == pytest.approx(support["v_max"])
    assert run_seed(preset, 0, output, log=lambda line: None, collection_from=source) == []  # all done: nothing again
    # the MPO scores are the source study's; a student still running is named in the report
    assert load_study(output).score("MPO", "Env-A") == load_study(source, seeds=[0]).score("MPO", "Env-A")
    (run_dir / "distill_CRR_indicator__r1" / "done.json").unlink()
    assert incomplete_repeats(load_study(output)) == ["seed 0: CRR_indicator on 1 of 2 repeats"]
    assert "1 of 2 repeats" in write_report(output, plots=False, seeds=[0])
    (run_dir / "distill_CRR_indicator" / "done.json").unlink()
    assert incomplete_repeats(load_study(output)) == ["seed 0: CRR_indicator on 0 of 2 repeats"]
    assert (output / "report_seeds_0.md").exists() and (output / "claims_seeds_0.csv").exists()
    with pytest.raises(ValueError, match=r"seeds \[5\]"):
        load_study(output, seeds=[5])
    # what cannot be reused, named
    with pytest.raises(ValueError, match="other settings \\(stage_steps\\)"):
        run_seed(dataclasses.replace(preset, stage_steps=(300, 400)), 0, tmp_path / "other", collection_from=source)
    with pytest.raises(ValueError, match="no finished collection"):
        run_seed(preset, 7, output, collection_from=source)
    with pytest.raises(ValueError, match="not a study"):
        run_seed(preset, 1, output, collection_from=tmp_path)
    with pytest.raises(ValueError, match="student_critic must be one of"):
        Preset(**{**PRESETS["tiny"].__dict__, "student_critic": "huber"})
    assert load_study(output, seeds=[0, 0]).seeds == [0]


def _tree_digest(folder: pathlib.Path) -> dict[str, bytes]:
    return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def test_a_reused_collection_never_touches_its_source(study, tmp_path):
    """Linked buffers: collecting again unlinks them; a source moved away is named; another source is refused."""
    import shutil

    source, _ = study
    copy = tmp_path / "source"  # a study of our own to move and delete
    shutil.copytree(source, copy, symlinks=True)
    before = {name: _tree_digest(copy / "seed_0" / name) for name in ("buffer", "buffer_stage1")}
    preset = dataclasses.replace(PRESETS["tiny"], students=("BC",), online=False)
    output = tmp_path / "reuse"
    run_seed(preset, 0, output, log=lambda line: None, collection_from=copy)
    for name in ("buffer", "buffer_stage1"):
        assert (output / "seed_0" / name).resolve() == (copy / "seed_0" / name).resolve()
    with pytest.raises(ValueError, match="reuses the collection of"):  # one seed, one collection
        run_seed(preset, 0, output, log=lambda line: None, collection_from=source)
    # the source moved: the next student names what is gone and what to do
    copy.rename(tmp_path / "moved")
    (output / "seed_0" / "distill_BC" / "done.json").unlink()
    with pytest.raises(FileNotFoundError, match="which is gone"):
        run_seed(preset, 0, output, log=lambda line: None)
    (tmp_path / "moved").rename(copy)
    # a reused collection whose done.json is lost is refused (it holds the collector's final checkpoint), nothing deleted
    (output / "seed_0" / "collect" / "done.json").unlink()
    with pytest.raises(NotOwnedError, match="a finished collection is there"):
        run_seed(preset, 0, output, jobs=["collect"], log=lambda line: None)
    assert (output / "seed_0" / "collect" / "final.zip").exists() and (output / "seed_0" / "buffer").is_symlink()
    # collecting again once it is moved away replaces the links by buffers of its own; the source's stay as they were
    (output / "seed_0" / "collect").rename(tmp_path / "reused_collect")
    run_seed(preset, 0, output, jobs=["collect"], log=lambda line: None)
    assert not (output / "seed_0" / "buffer").is_symlink() and (output / "seed_0" / "buffer" / "manifest.json").exists()
    assert {name: _tree_digest(copy / "seed_0" / name) for name in before} == before
    with pytest.raises(ValueError, match="has a collection of its own"):
        run_seed(preset, 0, output, log=lambda line: None, collection_from=copy)
    # a source seed without its Stage-1 buffer is not a collection to reuse
    shutil.rmtree(copy / "seed_1" / "buffer_stage1")
    with pytest.raises(ValueError, match="not a whole collection"):
        run_seed(preset, 1, output, log=lambda line: None, collection_from=copy)
