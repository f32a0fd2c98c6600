"""The experiments CLI refuses counts below 1 and unknown jobs before it writes anything (issue 65: a refused command
must leave the output as it was, so the corrected command is not taken for a study of other settings)."""

import pytest

from sb3_lifelong.experiments.__main__ import main


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--stage-steps", "100", "-5"], "--stage-steps must be at least 1, got -5"),
        (["--student-repeats", "0"], "--student-repeats must be at least 1, got 0"),
        (["--distill-steps", "0"], "--distill-steps must be at least 1, got 0"),
        (["--until", "-3"], "--until must be at least 1, got -3"),
        (["--threads", "0"], "--threads must be at least 1, got 0"),
        (["--jobs", "collect", "distill_nothing"], "unknown job 'distill_nothing' for preset tiny"),
    ],
)
def test_run_refuses_before_writing(tmp_path, capsys, extra, message):
    output = tmp_path / "study"
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "--preset", "tiny", "--seed", "0", "--output", str(output), *extra])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert not output.exists()


def test_study_refuses_workers_and_repeats_below_one(tmp_path, capsys):
    for extra, message in (
        (["--workers", "0"], "--workers must be at least 1, got 0"),
        (["--student-repeats", "-1"], "--student-repeats must be at least 1, got -1"),
    ):
        with pytest.raises(SystemExit):
            main(["study", "--preset", "tiny", "--seeds", "0", "--output", str(tmp_path / "s"), *extra])
        assert message in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_the_jobs_of_repeated_students_are_known():
    """With two student repeats each student's second repeat is a job of its own: the check accepts it."""
    import argparse
    import dataclasses

    from sb3_lifelong.experiments.__main__ import _check_counts
    from sb3_lifelong.experiments.presets import PRESETS

    tiny = PRESETS["tiny"]
    repeated = [job for job in dataclasses.replace(tiny, student_repeats=2).jobs() if job not in tiny.jobs()]
    assert repeated
    parser = argparse.ArgumentParser()
    args = argparse.Namespace(settings=tiny, preset="tiny", student_repeats=2, jobs=["collect", *repeated])
    _check_counts(parser, args)  # no SystemExit
    with pytest.raises(SystemExit):
        _check_counts(parser, argparse.Namespace(settings=tiny, preset="tiny", student_repeats=None, jobs=repeated))
