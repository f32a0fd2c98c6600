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
    with pytest.raises(FileNotFoundError, match="no claims file"):
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
