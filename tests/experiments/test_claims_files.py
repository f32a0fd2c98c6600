"""A study's claims are data of its folder: read from its claims.py by path, beside its seeds or given to the report."""

import shutil

import pandas as pd
import pytest
from testkit import PAPER_CLAIMS

from sb3_lifelong.experiments import load_claims, write_report
from sb3_lifelong.experiments.__main__ import main


def test_claims_files_are_read_or_refused_clearly(tmp_path):
    claims = load_claims(PAPER_CLAIMS)
    assert [claim.name for claim in claims][:2] == ["C1 forgetting", "C2a conservative online CRR remembers"]
    with pytest.raises(FileNotFoundError, match=r"no file .*claims\.py: a study.s CLAIMS are defined"):
        load_claims(tmp_path / "claims.py")
    (tmp_path / "empty.py").write_text("X = 1\n")
    with pytest.raises(ValueError, match="must define CLAIMS"):
        load_claims(tmp_path / "empty.py")


def test_the_report_reads_the_claims_beside_the_seeds_or_given(study, tmp_path, capsys):
    source, _ = study
    output = tmp_path / "study"
    shutil.copytree(source, output, ignore=shutil.ignore_patterns("buffer*"))
    write_report(output, plots=False)
    assert "No claims were given" in (output / "report.md").read_text()
    assert main(["report", str(output), "--no-plots", "--claims", str(PAPER_CLAIMS)]) == 0
    given = pd.read_csv(output / "claims.csv")
    assert list(given["claim"]) == [claim.name for claim in load_claims(PAPER_CLAIMS)]
    shutil.copy(PAPER_CLAIMS, output / "claims.py")  # a study folder: its claims beside its seeds
    write_report(output, plots=False)
    beside = pd.read_csv(output / "claims.csv")
    pd.testing.assert_frame_equal(beside, given)


def test_study_presets_files_are_read_or_refused_clearly(tmp_path):
    from testkit import ROOT

    from sb3_lifelong.experiments import PRESETS
    from sb3_lifelong.experiments.presets import load_presets

    assert sorted(PRESETS) == ["cpu", "demo", "paper", "tiny"]  # the package keeps the presets users run
    three = load_presets(ROOT / "benchmarks" / "studies" / "paper_cpu_three_c51" / "presets.py")
    assert three["cpu_three_c51"].student_critic == "categorical" and len(three["cpu_three_c51"].stages) == 3
    with pytest.raises(FileNotFoundError, match=r"no file .*presets\.py: a study's PRESETS are defined"):
        load_presets(tmp_path / "presets.py")
    (tmp_path / "bad.py").write_text("PRESETS = {'x': 1}\n")
    with pytest.raises(ValueError, match="must define PRESETS"):
        load_presets(tmp_path / "bad.py")
    main_exit = pytest.raises(SystemExit)
    with main_exit:
        main(["list", "--preset", "cpu_three"])  # a study's preset needs its file
    assert (
        main(["list", "--presets", str(ROOT / "benchmarks/studies/paper_cpu_three/presets.py"), "--preset", "cpu_three"]) == 0
    )


def test_claims_that_are_not_a_list_of_claims_are_refused(tmp_path):
    # a tuple of claims, and a list holding something else: each refused on its own (mutation survivors: an `and`
    # for the `or` of the check let both through)
    (tmp_path / "tuple.py").write_text(f"import runpy\nCLAIMS = tuple(runpy.run_path({str(PAPER_CLAIMS)!r})['CLAIMS'])\n")
    (tmp_path / "mixed.py").write_text("CLAIMS = ['C1 forgetting']\n")
    for name in ("tuple.py", "mixed.py"):
        with pytest.raises(ValueError, match="must define CLAIMS"):
            load_claims(tmp_path / name)


def test_ratios_keep_positive_denominators_below_one():
    from sb3_lifelong.experiments.claims import ratio, undefined_ratios

    numerator, denominator = {0: 0.3, 1: 2.0, 2: 1.0}, {0: 0.5, 1: 0.0, 2: -1.0}
    assert ratio(numerator, denominator) == {0: 0.3 / 0.5}
    assert undefined_ratios(numerator, denominator) == {1: 0.0, 2: -1.0}


def test_mean_over_environments_is_the_mean_on_the_seeds_scored_in_each():
    import pathlib

    import pandas as pd

    from sb3_lifelong.experiments.claims import mean_over, mean_over_envs
    from sb3_lifelong.experiments.scores import Study

    finals = pd.DataFrame(
        [dict(seed=0, method="X", kind="student", env="Env-A", score=100.0),
         dict(seed=0, method="X", kind="student", env="Env-B", score=50.0),
         dict(seed=1, method="X", kind="student", env="Env-A", score=80.0)]  # seed 1 has no Env-B score
    )  # fmt: skip
    study = Study(pathlib.Path("synthetic"), {"env_names": ["Env-A", "Env-B"]}, [0, 1], finals, pd.DataFrame())
    assert mean_over_envs(study, "X") == {0: 75.0}
    assert mean_over(study, "X", ["Env-A"]) == {0: 100.0, 1: 80.0}
