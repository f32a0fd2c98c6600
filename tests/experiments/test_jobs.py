"""A seed's jobs are typed: parsed once from their names, printed back to the same names; a student names a known
algorithm."""

import pytest

from sb3_lifelong.experiments.presets import STUDENTS, Job, Student, job_names


def test_every_job_name_parses_and_prints_back():
    names = job_names(student_repeats=3)
    for name in names:
        assert str(Job.parse(name)) == name
    assert Job.parse("collect") == Job("collect")
    assert Job.parse("distill_CRR_exp_beta1__r2") == Job("distill", "CRR_exp_beta1", 2)
    assert Job.parse("distill_CRR_exp_beta1__r2").student_job == "CRR_exp_beta1__r2"
    assert Job.parse("online_CRR_indicator") == Job("online", "CRR_indicator")
    kinds = [Job.parse(n).kind for n in names]
    assert kinds[0] == "collect" and kinds.count("distill") == 3 * len(STUDENTS) and kinds.count("online") == 2


@pytest.mark.parametrize("name", ["", "distill_", "online_", "collect_more", "train_CRR", "Collect"])
def test_a_name_that_is_no_job_is_refused(name):
    with pytest.raises(ValueError, match="not a job name"):
        Job.parse(name)


def test_a_job_is_consistent():
    with pytest.raises(ValueError, match="not a job"):
        Job("collect", "CRR")
    with pytest.raises(ValueError, match="not a job"):
        Job("distill")
    with pytest.raises(ValueError, match="only a distillation job has repeats"):
        Job("online", "CRR_indicator", 1)


def test_a_student_names_a_known_algorithm():
    with pytest.raises(ValueError, match="one of \\('CRR', 'BC'\\), got 'SAC'"):
        Student("SAC")
    assert {student.algorithm for student in STUDENTS.values()} == {"CRR", "BC"}


def test_a_job_lock_holds_against_another_process_and_is_freed_after(tmp_path):
    import subprocess
    import sys

    from sb3_lifelong.experiments.jobs import job_lock

    probe = (
        "import pathlib\nfrom sb3_lifelong.experiments.jobs import job_lock\n"
        f"with job_lock(pathlib.Path({str(tmp_path)!r}), 'collect') as held: print(held)"
    )
    with job_lock(tmp_path, "collect") as ours:
        assert ours
        other = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
        assert other.stdout.strip() == "False", other.stderr
        with job_lock(tmp_path, "distill_BC") as another_job:  # one lock per job
            assert another_job
    other = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert other.stdout.strip() == "True", other.stderr


def test_a_paused_students_logs_are_cut_back_with_the_collections_rule(tmp_path):
    """``cut_logs_back`` keeps the rows up to the pause; a row cut short (a stop while writing it) is past the pause, as
    for a collection's logs; the whole log is kept beside it, and a log with nothing to cut is left as it is."""
    from sb3_lifelong.experiments.jobs import cut_logs_back

    train = tmp_path / "train.csv"
    train.write_text("timesteps,loss\n10,0.5\n20,0.4\n30,0.3\n40\n")
    other = tmp_path / "eval.csv"
    other.write_text("timesteps,mean_reward\n10,1.0\n20,2.0\n")
    notes = tmp_path / "notes.csv"
    notes.write_text("name,value\na,1\n")
    lines: list[str] = []
    cut_logs_back(tmp_path, 20, lines.append)
    assert train.read_text().splitlines() == ["timesteps,loss", "10,0.5", "20,0.4"]
    assert (tmp_path / "train.after_pause_20.csv").read_text() == "timesteps,loss\n10,0.5\n20,0.4\n30,0.3\n40\n"
    assert other.read_text() == "timesteps,mean_reward\n10,1.0\n20,2.0\n" and notes.read_text() == "name,value\na,1\n"
    assert lines == ["  train.csv: 2 rows past the pause at 20 updates (all kept in train.after_pause_20.csv)"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval.csv", "notes.csv", "train.after_pause_20.csv", "train.csv"]
