"""The report validates its inputs: a malformed row of a result file is named (file and line), never used silently."""

import shutil

import pandas as pd
import pytest

from sb3_lifelong.experiments import load_study, write_report
from sb3_lifelong.experiments.__main__ import main
from sb3_lifelong.experiments.scores import MalformedResultsError, MalformedRowWarning, read_log

HEADER = "timesteps,env,mean_reward,std_reward,n_episodes\r\n"


@pytest.fixture
def study(small_collection, tmp_path):
    shutil.copytree(small_collection, tmp_path / "study")
    return tmp_path / "study"


def test_a_log_cut_in_the_middle_of_its_last_row_is_refused_by_the_report(study, capsys):
    evals = study / "seed_0" / "collect" / "eval.csv"
    rows = evals.read_bytes().split(b"\r\n")[:-1]
    assert rows[-1].startswith(b"120,Env-B,") and len(rows) == 5
    whole_b = pd.read_csv(evals).query("env == 'Env-B'")["mean_reward"]
    evals.write_bytes(b"\r\n".join(rows[:-1]) + b"\r\n" + rows[-1][: len(b"120,Env-B,1")])  # a write cut short
    with pytest.raises(MalformedResultsError, match=rf"{evals}:5: the file ends in the middle of this row"):
        write_report(study, plots=False)
    assert not (study / "report.md").exists() and not (study / "scores.csv").exists()  # nothing written from it
    with pytest.raises(SystemExit) as exited:
        main(["report", str(study), "--no-plots"])
    assert exited.value.code == 1
    err = capsys.readouterr().err
    assert f"{evals}:5:" in err and "--drop-malformed" in err
    # left out on request: named in a warning and in the report, and not in the scores
    with pytest.warns(MalformedRowWarning, match=rf"{evals}:5: the file ends in the middle"):
        text = write_report(study, plots=False, malformed="drop")
    assert "## Rows left out" in text and "`seed_0/collect/eval.csv`, line 5" in text
    scores = pd.read_csv(study / "scores.csv").query("method == 'MPO' and env == 'Env-B'")
    assert scores["score"].tolist() == pytest.approx([whole_b.iloc[0]])  # the Env-B evaluation at 60 only, not the cut "1"


def test_every_kind_of_malformed_row_is_named(tmp_path):
    path = tmp_path / "eval.csv"
    path.write_text(
        HEADER
        + "100,Env-A,5.0,0.0,1\r\n"
        + "200,Env-A,6.0\r\n"  # too few fields
        + "300,Env-A,7.0,0.0,1300,Env-B,1.0,0.0,1\r\n"  # two rows run together (a cut row, then the next write)
        + "400,Env-A,abc,0.0,1\r\n"  # not a number
        + "500,,8.0,0.0,1\r\n"  # no environment
        + "600,Env-A,,0.0,1\r\n"  # no return
        + "700,Env-A,9.0,,\r\n"  # optional numbers may be empty
    )
    problems: list = []
    frame = read_log(path, problems)
    assert [(row.line, row.problem) for row in problems] == [
        (3, "3 fields where the header has 5 (a row cut short, or two run together)"),
        (4, "9 fields where the header has 5 (a row cut short, or two run together)"),
        (5, "mean_reward is 'abc', not a number"),
        (6, "no env"),
        (7, "no mean_reward"),
    ]
    assert list(frame["timesteps"]) == [100, 700] and frame["mean_reward"].dtype == float
    assert frame["std_reward"].isna().tolist() == [False, True]
    with pytest.raises(MalformedResultsError, match=rf"(?s)5 malformed row\(s\).*{path}:3: 3 fields"):
        read_log(path)


def test_a_log_without_a_required_column_or_header_is_unusable(tmp_path):
    path = tmp_path / "eval.csv"
    path.write_text("timesteps,env,std_reward\r\n100,Env-A,0.0\r\n")
    with pytest.raises(MalformedResultsError, match=rf"{path}:1: no column 'mean_reward' \(its columns: timesteps, env"):
        read_log(path)
    path.write_text("")
    with pytest.raises(MalformedResultsError, match="an empty file"):
        read_log(path)
    path.write_text("timesteps,env,mean_re")
    problems: list = []
    assert len(read_log(path, problems)) == 0 and "no column" in problems[0].problem
    q = tmp_path / "q_sources.csv"
    q.write_text("timesteps,source,name,q_mean,n,q_probe,mc_return,overestimation,n_mc\r\n60,0,Env-A,0.5,10,,,,\r\n")
    assert read_log(q)["q_probe"].isna().all()  # the Monte-Carlo columns are empty until a source has an episode


def test_a_malformed_student_log_is_named_too(study):
    """Every log the report reads is checked: here the collector's q_sources.csv and train.csv."""
    collect = study / "seed_0" / "collect"
    with open(collect / "q_sources.csv", "a", newline="") as handle:
        handle.write("180,1,Env-B,0.4\r\n")
    with open(collect / "train.csv", "a", newline="") as handle:
        handle.write("180," + ",".join(["x"] * (len((collect / "train.csv").read_text().splitlines()[0].split(",")) - 1)))
    with pytest.raises(MalformedResultsError) as caught:
        load_study(study)
    named = {(row.path.name, row.line) for row in caught.value.rows}
    assert ("q_sources.csv", 5) in named  # (train.csv is read for the students' weights only)
