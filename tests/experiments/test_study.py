"""The paper's protocol as jobs: one seed end to end at a tiny budget, skip-finished, re-run, report, claims."""

import dataclasses
import json
import pathlib
import re
import shutil

import numpy as np
import pandas as pd
import pytest
from testkit import JOBS, PAPER_CLAIMS, THREE_STAGE_CLAIMS

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.experiments import PRESETS, STUDENTS, job_names, load_claims, load_study, run_seed, write_report
from sb3_lifelong.experiments.__main__ import main
from sb3_lifelong.experiments.claims import evaluate_claims
from sb3_lifelong.experiments.jobs import job_lock
from sb3_lifelong.experiments.protocol import sampling_weights
from sb3_lifelong.experiments.statistics import bootstrap_ci

CLAIMS = load_claims(PAPER_CLAIMS)  # the paper's two-stage claims, as the paper_cpu study declares them


def test_a_seed_writes_every_job(study):
    output, messages = study
    run_dir = output / "seed_0"
    for job in JOBS:
        done = json.loads((run_dir / job / "done.json").read_text())
        assert done["job"] == job and done["seconds"] > 0
        evals = pd.read_csv(run_dir / job / "eval.csv")
        assert set(evals["env"]) == {"Env-A", "Env-B"}
    collect = pd.read_csv(run_dir / "collect" / "eval.csv")
    assert collect["timesteps"].max() == sum(PRESETS["tiny"].stage_steps)  # evaluated at the very end
    # one lifetime buffer with both stages, sources named after the environments
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        assert buffer.size() == sum(PRESETS["tiny"].stage_steps)
        assert {v["name"] for v in buffer.sources.values()} == {"Env-A", "Env-B"}
        counts = buffer.source_counts()  # the change takes effect at the first episode start of Stage 2
        assert counts[0] + counts[1] == 600 and 200 <= counts[0] < 250
        # the collection records what its buffer holds, for a report that has no buffer (an exported study)
        assert json.loads((run_dir / "collect" / "done.json").read_text())["source_rows"] == buffer.source_counts(by_name=True)
    with LifelongReplayBuffer.open(run_dir / "buffer_stage1", read_only=True) as stage1:
        assert stage1.size() == 200 and set(stage1.source_counts()) == {0}
    # the online baseline starts where Stage 1 ended and runs through Stage 2
    online = pd.read_csv(run_dir / "online_CRR_exp_beta1" / "eval.csv")
    assert online["timesteps"].min() > 200 and online["timesteps"].max() == 600
    # students log Q per source on the whole lifetime, even the one that samples Env-A only
    q = pd.read_csv(run_dir / "distill_CRR_indicator_A_only" / "q_sources.csv")
    assert set(q["name"]) == {"Env-A", "Env-B"}
    assert any("job 1/" in m and "collect" in m for m in messages)


def test_every_job_writes_a_tensorboard_run(study):
    """A study is browsable in tensorboard like any SB3 run: one run per job, with a curve per environment."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    output, _ = study
    expected = {"collect": "MPO", "online_CRR_exp_beta1": "CRR", "distill_BC": "BC", "distill_CRR_exp_beta1": "CRR"}
    for job in JOBS:
        runs = sorted((output / "seed_0" / job / "tb").glob("*_*"))
        assert len(runs) == 1, f"{job}: one tensorboard run, got {runs}"  # the collection's two stages: one run
        assert runs[0].name.startswith(expected.get(job, "CRR") + "_") and list(runs[0].glob("events.out.tfevents.*"))
        events = EventAccumulator(str(runs[0]))
        events.Reload()
        evals = pd.read_csv(output / "seed_0" / job / "eval.csv")
        for env in ("Env-A", "Env-B"):
            logged = {event.step: event.value for event in events.Scalars(f"eval/{env}/mean_reward")}
            in_csv = evals[evals["env"] == env].set_index("timesteps")["mean_reward"]
            assert sorted(logged) == sorted(in_csv.index), job  # every evaluation, at its timestep
            assert np.allclose([logged[t] for t in in_csv.index], in_csv.values, rtol=1e-4), job
        if job != "distill_BC":  # a critic: the Q-value diagnostic per source
            assert {"diagnostics/q_mean/Env-A", "diagnostics/q_mean/Env-B"} <= set(events.Tags()["scalars"]), job


def test_finished_jobs_are_skipped_and_a_lost_job_reruns(study):
    output, _ = study
    messages: list[str] = []
    assert run_seed(PRESETS["tiny"], 0, output, jobs=JOBS, log=messages.append) == []
    assert any("already done" in m for m in messages)
    (output / "seed_0" / "distill_BC" / "done.json").unlink()  # as if the job had crashed
    assert run_seed(PRESETS["tiny"], 0, output, jobs=JOBS, log=messages.append) == ["distill_BC"]


def test_a_job_another_process_runs_is_skipped(study):
    output, _ = study
    run_dir = output / "seed_1"
    (run_dir / "distill_BC" / "done.json").unlink()
    messages: list[str] = []
    with job_lock(run_dir, "distill_BC") as ours:  # as if another command of this seed were running the job
        assert ours
        with job_lock(run_dir, "distill_BC") as again:  # a second open file, as another process would have
            assert not again
        assert run_seed(PRESETS["tiny"], 1, output, jobs=["distill_BC"], log=messages.append) == []
    assert any("distill_BC is running in another process" in m for m in messages)
    assert not (run_dir / "distill_BC" / "done.json").exists()  # its directory was left alone
    with job_lock(run_dir, "collect"):
        (run_dir / "collect" / "done.json").rename(run_dir / "collect" / "done.bak")
        try:
            with pytest.raises(RuntimeError, match="collect job"):
                run_seed(PRESETS["tiny"], 1, output, jobs=["distill_BC"], log=messages.append)
        finally:
            (run_dir / "collect" / "done.bak").rename(run_dir / "collect" / "done.json")
    assert run_seed(PRESETS["tiny"], 1, output, jobs=["distill_BC"], log=messages.append) == ["distill_BC"]


def test_report_claims_and_figures(study):
    output, _ = study
    text = write_report(output, claims=PAPER_CLAIMS)
    assert "## Claims" in text
    # the students' weights, per seed (the CRR students log them; BC has none)
    weights = text.split("## The students' weights")[1].split("## Claims")[0]
    assert "| CRR_exp_beta1 |" in weights and "s1: " in weights and "| BC |" not in weights
    for name in ("fig_online.png", "fig_students.png", "fig_q_sources.png", "fig_sampling_ratio.png", "report.md"):
        assert (output / name).stat().st_size > 0
    scores = pd.read_csv(output / "scores.csv")
    assert set(scores["seed"]) == {0, 1}
    claims = pd.read_csv(output / "claims.csv")
    assert list(claims["claim"]) == [claim.name for claim in CLAIMS]
    assert set(claims["verdict"]) <= {"reproduced", "not reproduced", "no data"}
    verdicts = dict(zip(claims["claim"], claims["verdict"]))
    assert verdicts["C5a reward scale"] == "no data"  # its student did not run
    assert verdicts["C1 forgetting"] != "no data"
    paired = dict(zip(claims["claim"], claims["paired"].fillna("")))
    pattern = r"CRR beta=1 - MPO: [+-][\d.]+ \[[+-][\d.]+, [+-][\d.]+\], CRR beta=1 higher on [\d.]+ of 2 seeds"
    assert re.fullmatch(pattern, paired["C2a conservative online CRR remembers"])
    assert paired["C1 forgetting"] == ""  # a per-seed ratio: paired already
    assert "paired by seed" in text


def test_the_study_figures_read_as_they_should(study, monkeypatch):
    """Titles name the set-up, one name and colour per method, no rotated code names, seeds and n shown, a reference."""
    from sb3_lifelong.experiments import figures
    from sb3_lifelong.experiments.style import METHODS

    output, _ = study
    drawn = {}

    def keep(plt, fig, path, **kwargs):
        drawn[path.name] = fig
        return path

    monkeypatch.setattr(figures, "save", keep)
    figures.plot_study(load_study(output))
    assert set(drawn) == {"fig_online.png", "fig_students.png", "fig_q_sources.png", "fig_sampling_ratio.png"}
    for name, fig in drawn.items():  # the preset and what changes, in every title
        title = fig._suptitle.get_text() if fig._suptitle is not None else fig.axes[0].get_title()
        assert title.startswith("tiny: Hopper-v5, Env-B = hip_deformation 0.3"), name

    students = drawn["fig_students.png"]
    assert [ax.get_title() for ax in students.axes] == ["Evaluated in Env-A", "Evaluated in Env-B"]
    ticks = students.axes[0].get_yticklabels()
    assert [t.get_text() for t in ticks][:2] == [METHODS["CRR_exp_beta1"].label, METHODS["CRR_indicator"].label]
    assert all(t.get_rotation() == 0 and t.get_fontsize() >= 9 for t in ticks)
    references = [line for line in students.axes[0].get_lines() if line.get_label().startswith("MPO at the end")]
    assert references and references[0].get_color() == METHODS["MPO"].color  # MPO's final return, as a reference
    bars = {round(patch.get_y() + patch.get_height() / 2): patch.get_facecolor() for patch in students.axes[0].patches}
    assert len(set(bars.values())) == len(bars)  # one colour per student

    ratio = drawn["fig_sampling_ratio.png"].axes[0]
    series = ratio.containers  # one error-bar series per student kind
    assert len(series) == 2 and all("n=2" in container.get_label() for container in series)
    # the raw share is the one the seeds' buffers hold, not the paper's 1:5
    shares = []
    for seed in (0, 1):
        with LifelongReplayBuffer.open(output / f"seed_{seed}" / "buffer", read_only=True) as buffer:
            rows = buffer.source_counts(by_name=True)
        shares.append(f"1:{rows['Env-B'] / rows['Env-A']:.1f}".removesuffix(".0"))
    raw = f"raw ({shares[0]})" if shares[0] == shares[1] else f"raw ({min(shares)} to {max(shares)})"
    ticks = [tick.get_text() for tick in ratio.get_xticklabels()]
    assert ticks == ["1:1", raw, "1:10"] and not any("1:5" in tick for tick in ticks)
    assert ratio.get_legend() is None and drawn["fig_sampling_ratio.png"].legends  # below the axes, not on the curves
    first, second = (np.asarray(container.lines[0].get_xdata(), dtype=float) for container in series)
    assert np.all(np.abs(first - second) > 0.1)  # the two series side by side, not on top of each other

    q = drawn["fig_q_sources.png"]
    assert "2 seeds, one line each" in q._suptitle.get_text()
    seeds_lines = [line for line in q.axes[0].get_lines() if len(line.get_xdata()) > 0]
    methods = [text.get_text() for text in q.axes[-1].get_legend().get_texts()]
    assert len(seeds_lines) == 2 * len(methods)  # one line per seed and student, no mean +- std band
    assert not q.axes[0].collections


def test_the_raw_share_reads_the_rows_of_each_source():
    """Fig. 6's raw share: the Env-A : Env-B rows of the seeds' buffers, whatever they are; none known: said so."""
    from sb3_lifelong.experiments.figures import raw_share_label, share_text
    from sb3_lifelong.experiments.scores import Study

    def study_of(rows: dict) -> Study:
        extras = [
            dict(seed=seed, metric=f"buffer|rows|{env}", value=float(n)) for seed, r in rows.items() for env, n in r.items()
        ]
        preset = {"env_names": ["Env-A", "Env-B"]}
        return Study(
            pathlib.Path("."), preset, sorted(rows), pd.DataFrame(), pd.DataFrame(extras, columns=["seed", "metric", "value"])
        )

    assert raw_share_label(study_of({0: {"Env-A": 211, "Env-B": 389}})) == "raw (1:1.8)"  # the tiny preset's
    assert raw_share_label(study_of({0: {"Env-A": 60_000, "Env-B": 180_000}})) == "raw (1:3)"  # the cpu preset's
    assert raw_share_label(study_of({0: {"Env-A": 100, "Env-B": 300}, 1: {"Env-A": 100, "Env-B": 500}})) == "raw (1:3 to 1:5)"
    assert raw_share_label(study_of({})) == "raw (share not recorded)"
    assert share_text(0.4) == "2.5:1" and share_text(12.0) == "1:12"


def test_the_rows_per_source_of_a_study_recorded_before_the_record(study, tmp_path):
    """A collection recorded before ``source_rows`` existed: counted in its buffer; without the buffer: not known."""
    from sb3_lifelong.experiments.scores import source_rows

    output, _ = study
    run_dir = tmp_path / "seed_0"
    (run_dir / "collect").mkdir(parents=True)
    done = json.loads((output / "seed_0" / "collect" / "done.json").read_text())
    expected = done.pop("source_rows")
    (run_dir / "collect" / "done.json").write_text(json.dumps(done))
    assert source_rows(run_dir) == {}  # no record, no buffer
    shutil.copytree(output / "seed_0" / "buffer", run_dir / "buffer")
    assert source_rows(run_dir) == expected


def test_a_one_seed_report_gives_values_not_intervals(study, monkeypatch):
    """At one seed: each value alone, "1 seed" (never "1 seeds"), no interval in the tables or the claims."""
    from sb3_lifelong.experiments import figures

    output, _ = study
    text = write_report(output, plots=False, seeds=[0], claims=PAPER_CLAIMS)
    assert "1 seeds" not in text and "1 seed" in text
    table = text.split("## Final returns")[1].split("\n## ")[0]
    rows = [line for line in table.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert rows and not any("[" in row or "+-" in row for row in rows)
    at_a = load_study(output, seeds=[0]).score("CRR_exp_beta1", "Env-A")[0]
    assert next(row for row in rows if row.startswith("| CRR_exp_beta1 |")).split("|")[3].strip() == f"{at_a:.0f}"
    claims = [line for line in text.split("## Claims")[1].splitlines() if line.startswith("| C")]
    assert len(claims) == len(CLAIMS) and not any("[" in row for row in claims)  # no "45 [45, 45]"
    drawn = {}

    def keep(plt, fig, path, **kwargs):
        drawn[path.name] = fig
        return path

    monkeypatch.setattr(figures, "save", keep)
    figures.plot_study(load_study(output, seeds=[0]))
    titles = [fig._suptitle.get_text() if fig._suptitle is not None else fig.axes[0].get_title() for fig in drawn.values()]
    assert len(titles) == 4 and all("1 seed" in title and "1 seeds" not in title for title in titles)


def test_the_report_opens_with_what_the_run_showed(study, tmp_path):
    """Its first lines: the toy budget's warning (the tiny preset), then three lines: the pipeline's student against
    MPO, what MPO kept, the claims counted; a study that is no toy has no warning."""
    from sb3_lifelong.experiments.presets import toy_budget
    from sb3_lifelong.experiments.report import export_results

    output, _ = study
    text = write_report(output, plots=False, claims=PAPER_CLAIMS)
    lines = [line for line in text.splitlines() if line]
    assert lines[0].startswith("# 2-stage study") and lines[1].startswith("> **A toy budget** (preset `tiny`)")
    assert "Env-A is not learnt" in lines[1] and "not the paper's findings" in lines[1]
    summary = lines[2:5]
    assert all(line.startswith("- **") for line in summary) and lines[5].startswith("Stages:")
    data = load_study(output)
    for env in ("Env-A", "Env-B"):
        for method in ("CRR_exp_beta1", "MPO"):
            values = list(data.score(method, env).values())
            assert f"{env} {np.mean(values):.0f} +- {np.std(values):.0f}" in summary[0], (method, env)
    assert "CRR_exp_beta1" in summary[0] and "mean +- std over 2 seeds" in summary[0]
    at_switch = list(data.extra("MPO|switch|Env-A").values())
    assert summary[1].startswith("- **What MPO kept") and f"against {np.mean(at_switch):.0f}" in summary[1]
    verdicts = pd.read_csv(output / "claims.csv")["verdict"].value_counts()
    assert summary[2].startswith(f"- **The {len(CLAIMS)} pre-registered claims**")
    assert all(f"{count} {verdict}" in summary[2] for verdict, count in verdicts.items())

    # a preset that is no toy: no warning (a copy of the study's results, recorded as such)
    export_results(output, tmp_path / "cpu_like")
    recorded = json.loads((tmp_path / "cpu_like" / "preset.json").read_text())
    assert toy_budget(recorded) and not toy_budget(PRESETS["cpu"].describe())
    recorded.pop("toy", None)
    assert toy_budget(recorded)  # recorded before presets were marked: read from the preset it matches
    assert toy_budget(json.loads(json.dumps(PRESETS["demo"].describe())))
    (tmp_path / "cpu_like" / "preset.json").write_text(json.dumps({**recorded, "toy": False}))
    plain = write_report(tmp_path / "cpu_like", plots=False)
    assert "toy budget" not in plain
    assert [line for line in plain.splitlines() if line][1].startswith("- **The pipeline's student**")


def test_export_keeps_results_not_data(study, tmp_path):
    from sb3_lifelong.experiments.report import export_results

    output, _ = study
    write_report(output, plots=False, claims=PAPER_CLAIMS)
    copied = export_results(output, tmp_path / "export")
    assert (tmp_path / "export" / "seed_0" / "collect" / "eval.csv").exists() and (tmp_path / "export" / "report.md").exists()
    assert not any("buffer" in str(p.relative_to(tmp_path)) or p.suffix == ".zip" for p in copied)
    (output / "seed_1" / "distill_BC" / "done.json").rename(output / "seed_1" / "distill_BC" / "done.later")
    try:  # an unfinished job's files are not results
        again = export_results(output, tmp_path / "export2")
        assert not any("distill_BC" in str(p) and "seed_1" in str(p) for p in again)
    finally:
        (output / "seed_1" / "distill_BC" / "done.later").rename(output / "seed_1" / "distill_BC" / "done.json")


def test_claims_follow_the_numbers(study):
    output, _ = study
    study_data = load_study(output)
    finals = study_data.finals
    # make the indicator student exactly half of the A-only student in Env-A: C4a must hold, then must fail
    for factor, expected in ((0.5, "reproduced"), (1.0, "not reproduced")):
        edited = finals.copy()
        a_only = edited[(edited["method"] == "CRR_indicator_A_only") & (edited["env"] == "Env-A")].set_index("seed")["score"]
        mask = (edited["method"] == "CRR_indicator") & (edited["env"] == "Env-A")
        edited.loc[mask, "score"] = edited.loc[mask, "seed"].map(a_only).abs() * factor + (0 if factor < 1 else 1)
        edited.loc[edited["method"] == "CRR_indicator_A_only", "score"] = edited.loc[
            edited["method"] == "CRR_indicator_A_only", "score"
        ].abs()
        study_data.finals = edited
        rows = {r["claim"]: r["verdict"] for r in evaluate_claims(study_data, CLAIMS)}
        assert rows["C4a the imbalance drop"] == expected


def test_report_shows_what_mpo_kept_beside_its_overestimation(study):
    """The report's forgetting table: per seed, MPO in Env-A when it left (and how steadily), at the end, their ratio,
    and the collector's overestimation of Env-A data when it left and at the end, from its ``q_sources.csv``."""
    from sb3_lifelong.experiments.presets import stage_ends
    from sb3_lifelong.experiments.report import forgetting_table

    output, _ = study
    study_data = load_study(output)
    switch = stage_ends(study_data.preset["stage_steps"])[0]
    for seed in (0, 1):
        q = pd.read_csv(output / f"seed_{seed}" / "collect" / "q_sources.csv").dropna(subset=["overestimation"])
        env_a = q[q["name"] == "Env-A"].sort_values("timesteps")
        assert study_data.extra("MPO|overestimation_switch|Env-A")[seed] == pytest.approx(
            env_a[env_a["timesteps"] <= switch]["overestimation"].iloc[-1]
        )
        assert study_data.extra("MPO|overestimation_end|Env-A")[seed] == pytest.approx(env_a["overestimation"].iloc[-1])
        assert env_a["timesteps"].iloc[-1] > switch  # the end is measured after the switch
    assert not study_data.extra("MPO|overestimation_end|Env-B")  # MPO never left Env-B
    table = forgetting_table(study_data).splitlines()
    assert len(table) == 2 + 2 and "overestimation" in table[0]  # a row per seed
    at_switch, at_end = study_data.extra("MPO|switch|Env-A"), study_data.score("MPO", "Env-A")
    for seed, row in zip((0, 1), table[2:]):
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[:2] == [str(seed), "Env-A"] and cells[2] == f"{at_switch[seed]:.0f}" and cells[4] == f"{at_end[seed]:.0f}"
        over = (
            study_data.extra("MPO|overestimation_switch|Env-A")[seed],
            study_data.extra("MPO|overestimation_end|Env-A")[seed],
        )
        assert cells[6] == f"{over[0]:+.1f} -> {over[1]:+.1f}"
        assert cells[5] == (f"{at_end[seed] / at_switch[seed]:.2f}" if at_switch[seed] > 0 else "-")  # C1's ratio
    assert "## What MPO kept of the environments it left" in write_report(output, plots=False, claims=PAPER_CLAIMS)


def test_switch_spread_reads_the_end_of_the_stage():
    """The spread MPO left an environment with: its last 3 evaluations in the second half of the stage (not the climb
    before, not the next stage), the stage's last two where that half has fewer; no level, no spread."""
    from sb3_lifelong.experiments.scores import relative_spread, switch_spread

    steps = list(range(10, 201, 10))  # a stage from 100 to 200 (evaluations at 110 ... 200), then the next one
    returns = [float(t) for t in steps]  # a climb: 10, 20, ...
    frame = pd.DataFrame(dict(timesteps=steps, env="Env-B", mean_reward=returns))
    expected = relative_spread(pd.Series([180.0, 190.0, 200.0]))
    assert switch_spread(frame, "Env-B", 0, 200) == pytest.approx(expected)
    assert expected == pytest.approx(np.std([180, 190, 200], ddof=1) / 190)
    assert switch_spread(frame, "Env-B", 100, 170) == pytest.approx(relative_spread(pd.Series([150.0, 160.0, 170.0])))
    sparse = frame[frame["timesteps"].isin([120, 140, 200])]  # second half (150, 200] holds one: the stage's last two
    assert switch_spread(sparse, "Env-B", 100, 200) == pytest.approx(relative_spread(pd.Series([140.0, 200.0])))
    assert np.isnan(switch_spread(sparse, "Env-B", 150, 200))  # one evaluation in the whole stage: not measured
    assert np.isnan(switch_spread(frame, "Env-A", 0, 200))  # never evaluated there
    assert relative_spread(pd.Series([-10.0, 10.0])) == np.inf  # a mean of 0: no level to drop from
    assert relative_spread(pd.Series([-100.0, -120.0])) == pytest.approx(np.std([100, 120], ddof=1) / 110)  # |mean|


def test_forgetting_needs_a_steady_switch(study):
    """``max_switch_spread``: the forgetting claims are tested only where MPO's last Env-A evaluations before the switch
    were steady (their spread, std / mean, measured from ``eval.csv``); the other claims are untouched."""
    from sb3_lifelong.experiments.presets import stage_ends
    from sb3_lifelong.experiments.scores import switch_spread

    output, _ = study
    study_data = load_study(output)
    unchecked = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    spread = study_data.extra("MPO|switch_spread|Env-A")
    switch = stage_ends(study_data.preset["stage_steps"])[0]
    assert sorted(spread) == [0, 1]
    for seed in (0, 1):
        evals = pd.read_csv(output / f"seed_{seed}" / "collect" / "eval.csv")
        assert spread[seed] == switch_spread(evals, "Env-A", 0, switch) and np.isfinite(spread[seed])
    # an upper bound: no seed as steady as asked, C1 is not testable, with each seed's spread; the rest as before
    study_data.preset = {**study_data.preset, "max_switch_spread": min(spread.values()) / 2}
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert rows["C1 forgetting"]["verdict"] == "not testable"
    assert (
        "std / mean" in rows["C1 forgetting"]["precondition"]
        and "held on 0 of 2 measured seeds" in rows["C1 forgetting"]["precondition"]
    )
    for claim in set(unchecked) - {"C1 forgetting"}:
        assert rows[claim]["verdict"] == unchecked[claim]["verdict"], claim
    # every seed steady enough: C1 reads as without the check
    study_data.preset = {**study_data.preset, "max_switch_spread": max(spread.values())}
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert rows["C1 forgetting"]["verdict"] == unchecked["C1 forgetting"]["verdict"]
    assert "held on 2 of 2" in rows["C1 forgetting"]["precondition"]
    # the three-stage claims: forgetting Env-B asks for a steady Env-B at its switch (the end of Stage 2)
    from sb3_lifelong.experiments.claims import PRECONDITIONS

    needs = {claim.name: claim.needs for claim in load_claims(THREE_STAGE_CLAIMS)}
    assert "steady" in needs["T1a forgetting Env-A"] and "steady_b" in needs["T1b forgetting Env-B"]
    assert PRECONDITIONS["steady_b"].values(study_data) == {}  # in two stages MPO never leaves Env-B
    # a spread of infinity (a mean return of 0) is a measured failure, not a missing measurement
    study_data.extras = study_data.extras.copy()
    study_data.extras.loc[study_data.extras["metric"] == "MPO|switch_spread|Env-A", "value"] = np.inf
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert rows["C1 forgetting"]["verdict"] == "not testable" and "s0: inf" in rows["C1 forgetting"]["precondition"]


def test_claims_are_tested_where_their_preconditions_hold(study):
    """A preset's thresholds (``env_a_learnt``, ``value_gap``, ``min_weight_ess``): a claim is tested on the seeds where
    its preconditions hold, reads *not testable* where they hold on none, and the other claims are untouched;
    without thresholds nothing is checked."""
    from sb3_lifelong.experiments.claims import PRECONDITIONS
    from sb3_lifelong.experiments.report import claims_table

    output, _ = study
    study_data = load_study(output)
    unchecked = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert all(p.check(study_data) is None for p in PRECONDITIONS.values())
    assert all("precondition" not in r for r in unchecked.values())
    # what the preconditions measure is in the scores: MPO at the switch, the data's value, the student's weights
    at_switch = study_data.extra("MPO|switch|Env-A")
    assert sorted(at_switch) == [0, 1]
    gap = PRECONDITIONS["value_gap"].values(study_data)
    assert sorted(gap) == [0, 1] and all(np.isfinite(v) and v != 0 for v in gap.values())
    for seed in (0, 1):  # Env-B's data over Env-A's, from the collector's last Monte-Carlo measurement
        q = pd.read_csv(output / f"seed_{seed}" / "collect" / "q_sources.csv").dropna(subset=["mc_return"])
        last = q[q["timesteps"] == q["timesteps"].max()].set_index("name")["mc_return"]
        assert gap[seed] == pytest.approx(last["Env-B"] / last["Env-A"])
    ess = study_data.extra("CRR_exp_beta1|weight_ess")
    assert sorted(ess) == [0, 1] and all(0 < v <= 1 for v in ess.values())
    needs = {"C1 forgetting", "C2a conservative online CRR remembers", "C4a the imbalance drop", "C4b beta=1 fixes it"}
    # a threshold no seed reached: every claim about Env-A is not testable, with the measured values
    study_data.preset = {**study_data.preset, "env_a_learnt": max(at_switch.values()) + 1.0}
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    for claim in needs:
        assert rows[claim]["verdict"] == "not testable", claim
        note = rows[claim]["precondition"]
        assert "held on 0 of 2 measured seeds" in note and "s0: " in note and "s1: " in note
    assert rows["C3 the pipeline is best"]["verdict"] == unchecked["C3 the pipeline is best"]["verdict"]
    assert rows["C3 the pipeline is best"]["precondition"] == "-"
    assert "| precondition |" in claims_table(list(rows.values())).splitlines()[0]
    # a threshold one seed reached: the claims about Env-A are tested on that seed alone
    best = max(at_switch, key=at_switch.get)
    study_data.preset = {**study_data.preset, "env_a_learnt": at_switch[best]}
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert rows["C1 forgetting"]["verdict"] in ("reproduced", "not reproduced")
    assert f"s{best}: " in rows["C1 forgetting"]["values"] and f"s{1 - best}: n/a" in rows["C1 forgetting"]["values"]
    assert "held on 1 of 2 measured seeds" in rows["C1 forgetting"]["precondition"]
    # every seed learnt Env-A, but no seed's exp beta=1 student is conservative enough: only the claims calling it so
    study_data.preset = {**study_data.preset, "env_a_learnt": min(at_switch.values()) - 1.0, "min_weight_ess": 1.01}
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert rows["C4b beta=1 fixes it"]["verdict"] == "not testable"
    assert rows["C4a the imbalance drop"]["verdict"] == unchecked["C4a the imbalance drop"]["verdict"]
    assert "effective sample size >= 1.01" in rows["C4b beta=1 fixes it"]["precondition"]
    # no value gap on any seed: the imbalance claims are not testable, forgetting still is
    study_data.preset = {**study_data.preset, "min_weight_ess": None, "value_gap": max(gap.values()) + 1.0}
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert rows["C4a the imbalance drop"]["verdict"] == "not testable"
    assert rows["C1 forgetting"]["verdict"] == unchecked["C1 forgetting"]["verdict"]
    # a precondition not measured (no Monte-Carlo columns): no data, not "not testable"; one seed measured failing and
    # the other not measured: still no data (the other seed may yet hold it)
    measured_extras = study_data.extras
    study_data.extras = measured_extras[~measured_extras["metric"].str.startswith("data|mc_return|")]
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert rows["C4a the imbalance drop"]["verdict"] == "no data"
    assert "not measured on s0, s1" in rows["C4a the imbalance drop"]["precondition"]
    study_data.extras = measured_extras[
        ~measured_extras["metric"].isin(["data|mc_return|Env-A"]) | (measured_extras["seed"] == 0)
    ]
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert rows["C4a the imbalance drop"]["verdict"] == "no data"
    study_data.extras = measured_extras
    # thresholds every seed reached: the verdicts are those of the unchecked report
    study_data.preset = {**study_data.preset, "value_gap": min(gap.values()) - 1.0, "min_weight_ess": 0.0}
    rows = {r["claim"]: r for r in evaluate_claims(study_data, CLAIMS)}
    assert {c: r["verdict"] for c, r in rows.items()} == {c: r["verdict"] for c, r in unchecked.items()}


def test_sampling_weights_give_the_ratio():
    counts = {0: 1000, 1: 5000}
    for ratio in ((1, 1), (1, 10), (1, 0), (0, 1)):
        weights = sampling_weights(ratio, counts)
        mass = {s: weights[s] * counts[s] for s in counts}
        total = sum(mass.values())
        assert mass[0] / total == pytest.approx(ratio[0] / sum(ratio))
    with pytest.raises(ValueError, match="no data"):
        sampling_weights((1, 1), {0: 10})
    with pytest.raises(ValueError, match="non-negative"):
        sampling_weights((0, 0), counts)


def test_bootstrap_interval():
    from scipy import stats

    low, high = bootstrap_ci([1.0, 2.0, 3.0])
    assert 1.0 <= low < 2.0 < high <= 3.0
    assert bootstrap_ci([5.0]) == (5.0, 5.0) and bootstrap_ci([4.0, 4.0]) == (4.0, 4.0)
    assert all(np.isnan(bootstrap_ci([])))
    # scipy's BCa interval, not a percentile one: on skewed data (one seed far above the others) BCa reaches further
    # towards the outlier than the percentile interval of the same resamples does
    skewed = np.array([100.0, 120.0, 130.0, 110.0, 125.0, 900.0])
    expected = stats.bootstrap((skewed,), np.mean, n_resamples=10_000, method="BCa", rng=np.random.default_rng(0))
    assert bootstrap_ci(list(skewed)) == pytest.approx(tuple(expected.confidence_interval))
    percentile = stats.bootstrap((skewed,), np.mean, n_resamples=10_000, method="percentile", rng=np.random.default_rng(0))
    assert bootstrap_ci(list(skewed))[1] > percentile.confidence_interval.high


def test_claims_pair_the_compared_series_by_seed():
    from sb3_lifelong.experiments.claims import describe_pair
    from sb3_lifelong.experiments.statistics import paired_difference

    # seeds differ a lot, the first method is 8-12 above the second on every seed: paired, the difference is sure
    second = {0: 100.0, 1: 500.0, 2: 900.0, 3: 1300.0, 4: 1700.0}
    first = {seed: value + offset for (seed, value), offset in zip(second.items(), (10.0, 12.0, 8.0, 11.0, 9.0))}
    difference = paired_difference(first, {**second, 9: 5.0})  # a seed of one side only is left out
    assert difference["n"] == 5 and difference["wins"] == 5 and difference["mean"] == pytest.approx(10.0)
    assert 8.0 <= difference["low"] < 10.0 < difference["high"] <= 12.0
    unpaired_low, unpaired_high = bootstrap_ci(list(first.values()))
    assert unpaired_high - unpaired_low > 100 * (difference["high"] - difference["low"])  # each mean's own: no verdict
    text = describe_pair("A", "B", difference)
    assert re.fullmatch(r"A - B: \+10 \[\+[89], \+1[01]\], A higher on 5 of 5 seeds", text), text
    tie = paired_difference({0: 1.0, 1: 2.0}, {0: 1.0, 1: 1.0})
    assert tie["wins"] == 1.5  # a tie counts one half
    pairs = {claim.name: claim.compared(["x", "y", "z"]) for claim in CLAIMS}
    assert pairs["C5d sampling ratio hurts the indicator"] == [("1:1", "1:5"), ("1:5", "1:10")]
    assert all(first == "CRR_exp_beta1" for first, _ in pairs["C3 the pipeline is best"])
    assert pairs["C2a conservative online CRR remembers"] == [("x", "y"), ("x", "z")]  # default: the first vs the others


def test_a_study_keeps_one_set_of_settings(study):
    output, _ = study
    other = PRESETS["tiny"].__class__(**{**PRESETS["tiny"].__dict__, "distill_steps": 7})
    with pytest.raises(ValueError, match="other settings"):
        run_seed(other, 0, output)


def test_demo_preset_jobs():
    demo = PRESETS["demo"]
    assert demo.jobs()[0] == "collect" and not any(job.startswith("online_") for job in demo.jobs())
    assert all(job[len("distill_") :] in STUDENTS for job in demo.jobs()[1:])
    assert demo.note and sum(demo.stage_steps) % demo.eval_freq == 0


def test_cli_list_and_errors(capsys, tmp_path):

    assert main(["list", "--preset", "cpu"]) == 0
    out = capsys.readouterr().out
    for job in job_names():
        assert job in out
    assert PRESETS["cpu"].jobs() == job_names()
    assert len(STUDENTS) >= 10
    with pytest.raises(ValueError, match="unknown jobs"):
        run_seed(PRESETS["tiny"], 0, tmp_path, jobs=["distill_nothing"])
    with pytest.raises(SystemExit):
        main(["run", "--preset", "tiny", "--output", str(tmp_path)])  # --seed is required
    with pytest.raises(SystemExit):
        main(["run", "--preset", "tiny", "--seed", "0", "--output", str(tmp_path), "--stage-steps", "100"])
    assert "one value per stage" in capsys.readouterr().err
    with pytest.raises(ValueError, match="one step count and one name per stage"):
        dataclasses.replace(PRESETS["tiny"], env_names=("Env-A", "Env-B", "Env-C"))


def test_a_ratio_with_a_non_positive_denominator_is_left_out():
    from sb3_lifelong.experiments.claims import ratio, undefined_ratios

    numerator, denominator = {0: 180.0, 1: 630.0, 2: 360.0}, {0: 480.0, 1: 0.0, 2: -2.3}
    assert ratio(numerator, denominator) == {0: 0.375}  # not 360 / -2.3 = -157, which would swamp the mean
    assert undefined_ratios(numerator, denominator) == {1: 0.0, 2: -2.3}


def continual_study(online_end_a=90.0):
    """Two seeds; MPO forgets Env-A (100 -> 60) and learns Env-B (20 -> 120); online CRR keeps more of Env-A."""
    from sb3_lifelong.experiments.scores import Study

    values = {
        "MPO|R|0|Env-A": 100.0, "MPO|R|0|Env-B": 20.0, "MPO|R|1|Env-A": 60.0, "MPO|R|1|Env-B": 120.0,
        "online CRR_exp_beta1|R|1|Env-A": online_end_a, "online CRR_exp_beta1|R|1|Env-B": 100.0,
    }  # fmt: skip
    extras = pd.DataFrame([dict(seed=s, metric=m, value=v) for s in (0, 1) for m, v in values.items()])
    preset = dict(env_names=["Env-A", "Env-B"], stage_steps=[10, 20])
    return Study(pathlib.Path("synthetic"), preset, [0, 1], pd.DataFrame(), extras)


def test_continual_metrics_of_the_report_hand_computed():
    from sb3_lifelong.experiments.report import continual_table

    table = continual_table(continual_study(), {"Env-A": 0.0, "Env-B": 20.0})
    rows = {tuple(c.strip() for c in line.strip("|").split("|"))[:2]: line for line in table.splitlines()[2:]}
    cells = lambda key: [c.strip() for c in rows[key].strip("|").split("|")][2:]  # noqa: E731
    # MPO: reference (best end of stage) A 100, B 120; s0 = [1, 0], s1 = [0.6, 1]: A = 0.8, F_A = 0.4, BWT -0.4, FWT 0
    assert cells(("MPO", "0")) == ["+0.80", "+0.40", "-0.40", "+0.00"]
    # online CRR shares MPO's Stage 1: reference A 100, B 100; s1 = [0.9, 1.0]: A = 0.95, F_A = 0.1
    assert cells(("online CRR_exp_beta1", "1")) == ["+0.95", "+0.10", "-0.10", "+0.00"]
    assert cells(("MPO", "mean +- std")) == ["+0.80 +- 0.00", "+0.40 +- 0.00", "-0.40 +- 0.00", "+0.00 +- 0.00"]
    assert "forgetting of Env-A" in table.splitlines()[0] and "forgetting of Env-B" not in table
    # Env-B not evaluated before its stage (a Stage 1 run alone, adopted): forward transfer is not measured
    unseen = continual_study()
    unseen.extras.loc[unseen.extras["metric"] == "MPO|R|0|Env-B", "value"] = np.nan
    rows = continual_table(unseen, {"Env-A": 0.0, "Env-B": 20.0}).splitlines()
    assert rows[2] == "| MPO | 0 | +0.80 | +0.40 | -0.40 | n/a |" and rows[4].endswith("| n/a |")
    # a seed that learnt nothing above the random policy in an environment has no normalised scores
    flat = continual_table(continual_study(), {"Env-A": 0.0, "Env-B": 500.0})
    assert "not defined: no return above the random policy's" in flat


def test_the_report_gives_the_field_metrics_from_each_run_and_measures_the_random_policy_once(study, tmp_path, monkeypatch):
    import shutil

    from sb3_lifelong.experiments import report

    output = tmp_path / "study"
    shutil.copytree(study[0], output, ignore=shutil.ignore_patterns("buffer*", "random_returns.json"))  # (other reports')
    data = load_study(output)
    frame = pd.read_csv(output / "seed_0" / "collect" / "eval.csv")
    end = data.preset["stage_steps"][0]
    switch_rows = frame[(frame["env"] == "Env-B") & (frame["timesteps"] <= end)].sort_values("timesteps")
    assert data.extra("MPO|R|0|Env-B")[0] == pytest.approx(switch_rows["mean_reward"].tail(2).mean())
    assert data.extra("MPO|R|1|Env-A")[0] == pytest.approx(data.score("MPO", "Env-A")[0])
    assert not data.extra("online CRR_exp_beta1|R|0|Env-A")  # its Stage 1 is MPO's
    measured = []
    real = report.measure_random_returns
    monkeypatch.setattr(report, "measure_random_returns", lambda preset: measured.append(1) or real(preset))
    text = write_report(output, plots=False)
    assert "## Forgetting and transfer in the field's terms" in text, text
    assert len(measured) == 1
    record = json.loads((output / "random_returns.json").read_text())
    assert record["env_names"] == ["Env-A", "Env-B"] and record["episodes"] == report.RANDOM_EPISODES
    assert record["returns"] == real(data.preset)  # seeded: the same measurement every time
    write_report(output, plots=False)
    assert len(measured) == 1  # read back, not measured again


def test_an_online_final_is_the_mean_of_its_last_three_evaluations_by_hand(study):
    """MPO's final score in each environment: the mean of its last three evaluations there, read from ``eval.csv``
    with the csv module (the reading every committed study's tables and claims use)."""
    import csv

    output, _ = study
    finals = load_study(output).finals
    for seed in (0, 1):
        with open(output / f"seed_{seed}" / "collect" / "eval.csv", newline="") as handle:
            rows = list(csv.DictReader(handle))
        for env in {row["env"] for row in rows}:
            returns = [float(row["mean_reward"]) for row in rows if row["env"] == env]
            assert len(returns) > 3  # more evaluations than the three read, so the count matters
            got = finals[(finals["seed"] == seed) & (finals["method"] == "MPO") & (finals["env"] == env)]["score"]
            assert got.item() == pytest.approx(sum(returns[-3:]) / 3, rel=1e-12)
