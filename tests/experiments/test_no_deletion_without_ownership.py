"""Markers never decide deletions: a run deletes only what an unfinished attempt of its own wrote, and refuses the rest."""

import json
import os
import pathlib
import shutil

import pytest
from testkit import ACT, OBS, fill, small_preset

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.experiments import run_seed
from sb3_lifelong.experiments.collection import (
    COLLECTED_BUFFERS,
    REWIND_MARKER,
    REWIND_STAGING,
    _rewind_to_pause,
    remove_unfinished_collection,
)
from sb3_lifelong.experiments.jobs import (
    OWNED_MARKER,
    NotOwnedError,
    claim_directory,
    finish_job,
    remove_unfinished,
    start_job,
)
from sb3_lifelong.experiments.protocol import adopt_collection, distill_student, online

SMALL = small_preset()


def snapshot(root: pathlib.Path) -> dict[str, bytes]:
    """:return: every file under ``root`` (links as their target), by relative path, with its bytes"""
    files = {}
    for path in sorted(root.rglob("*")):
        key = str(path.relative_to(root))
        if path.is_symlink():
            files[key] = b"-> " + os.readlink(path).encode()
        elif path.is_file():
            files[key] = path.read_bytes()
    return files


@pytest.fixture
def study(small_collection, tmp_path) -> pathlib.Path:
    """A copy of the ``small_collection`` study, to change."""
    shutil.copytree(small_collection, tmp_path / "study", symlinks=True)
    return tmp_path / "study"


@pytest.mark.parametrize("also_lost", [(), ("collect/final.zip",)])
def test_a_finished_collection_whose_done_json_was_lost_is_refused_not_deleted(study, also_lost):
    """Before: run re-collected, deleting the finished buffer and everything in collect/ without a word."""
    run_dir = study / "seed_0"
    (run_dir / "collect" / "done.json").unlink()
    for name in also_lost:  # without the final checkpoint, the manifest of the complete buffer is the evidence
        (run_dir / name).unlink()
    before = snapshot(study)
    with pytest.raises(NotOwnedError) as caught:
        run_seed(SMALL, 0, study, jobs=["collect"], log=lambda m: None)
    message = str(caught.value)
    assert "no " + str(run_dir / "collect" / "done.json") in message and "Nothing was deleted" in message
    assert "manifest holds 120 transitions" in message and ("final.zip" in message) == (not also_lost)
    assert "restore it" in message and "move" in message
    assert snapshot(study) == before  # every file byte-identical


def test_files_no_unfinished_attempt_wrote_are_refused(study):
    """A partial collection without the marker of the attempt that wrote it (by hand, an older version): refused."""
    run_dir = study / "seed_0"
    (run_dir / "collect" / "done.json").unlink()
    (run_dir / "collect" / "final.zip").unlink()
    shutil.rmtree(run_dir / "buffer")
    with LifelongReplayBuffer(0, OBS, ACT, path=run_dir / "buffer") as buffer:  # a partial buffer, not ours
        fill(buffer, 10, 1, stage=0)
    before = snapshot(study)
    with pytest.raises(NotOwnedError, match=rf"{run_dir / 'collect'} holds files .*Nothing was deleted"):
        run_seed(SMALL, 0, study, jobs=["collect"], log=lambda m: None)
    shutil.rmtree(run_dir / "collect")  # the collect directory moved away, the buffer is still there
    with pytest.raises(NotOwnedError, match=rf"{run_dir / 'buffer'} exists but no unfinished collection .* wrote it"):
        run_seed(SMALL, 0, study, jobs=["collect"], log=lambda m: None)
    assert snapshot(run_dir / "buffer") == {k[len("seed_0/buffer/") :]: v for k, v in before.items() if "/buffer/" in k}


def test_an_unfinished_attempt_of_its_own_is_removed_and_said(tmp_path):
    run_dir = tmp_path / "seed_0"
    claim_directory(run_dir / "collect", "collect", beside=COLLECTED_BUFFERS)
    (run_dir / "collect" / "eval.csv").write_text("timesteps,env,mean_reward,std_reward,n_episodes\n")
    with LifelongReplayBuffer(0, OBS, ACT, path=run_dir / "buffer") as buffer:  # killed before its first pause
        fill(buffer, 10, 1, stage=0)
    (run_dir / "buffer_stage1").symlink_to(tmp_path)  # a link: unlinked, what it points to untouched
    (run_dir / "keep.txt").write_text("not the attempt's")
    messages: list = []
    remove_unfinished_collection(SMALL, run_dir, messages.append)
    assert sorted(path.name for path in run_dir.iterdir()) == ["keep.txt"]
    assert any("removed the unfinished attempt" in m and str(run_dir / "buffer") in m for m in messages)


def test_a_job_directory_is_deleted_only_when_an_unfinished_attempt_of_its_own_wrote_it(tmp_path):
    job = tmp_path / "online_CRR_indicator"
    job.mkdir()
    (job / "eval.csv").write_text("results\n")
    with pytest.raises(NotOwnedError, match=r"holds files \(eval.csv\) but no record .*Nothing was deleted"):
        remove_unfinished(job, job.name, log=lambda m: None)
    claim_directory(tmp_path / "other", "other")
    with pytest.raises(FileExistsError, match="not empty"):
        claim_directory(job, job.name)
    (job / OWNED_MARKER).write_text(json.dumps(dict(job=job.name, beside=[])))
    (job / "done.json").write_text("{}")
    with pytest.raises(NotOwnedError, match="holds a finished online_CRR_indicator job"):
        remove_unfinished(job, job.name, log=lambda m: None)
    assert (job / "eval.csv").read_text() == "results\n"
    (job / "done.json").unlink()
    (job / OWNED_MARKER).write_text(json.dumps(dict(job=job.name, beside=["../elsewhere"])))
    with pytest.raises(NotOwnedError, match="not beside it"):
        remove_unfinished(job, job.name, log=lambda m: None)
    (job / OWNED_MARKER).write_text(json.dumps(dict(job=job.name, beside=[])))
    remove_unfinished(job, job.name, log=lambda m: None)
    assert not job.exists() and (tmp_path / "other").is_dir()


def test_the_jobs_refuse_a_directory_they_did_not_write(study):
    """online and distill_student start anew in their directory: only after an unfinished attempt of their own."""
    run_dir = study / "seed_0"
    for job in ("online_CRR_indicator", "distill_BC"):
        (run_dir / job).mkdir()
        (run_dir / job / "eval.csv").write_text("timesteps,env,mean_reward\n100,Env-A,5.0\n")
    before = snapshot(study)
    with pytest.raises(NotOwnedError, match="online_CRR_indicator holds files"):
        online("CRR_indicator", SMALL, 0, run_dir, log=lambda m: None)
    with pytest.raises(NotOwnedError, match="distill_BC holds files"):
        distill_student("BC", SMALL, 0, run_dir, log=lambda m: None)
    assert snapshot(study) == before


def test_reusing_a_collection_never_deletes_a_finished_own_one(small_collection, study):
    """--collection-from replaced the seed's own collection when its done.json was missing, finished or not."""
    run_dir = study / "seed_0"
    (run_dir / "collect" / "done.json").unlink()
    before = snapshot(study)
    with pytest.raises(NotOwnedError, match="a finished collection is there"):
        adopt_collection(SMALL, 0, small_collection, study, log=lambda m: None)
    assert snapshot(study) == before


def test_a_rewind_deletes_only_its_own_partial_copy(tmp_path):
    with LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "buffer", chunk_size=16) as buffer:
        fill(buffer, 40, 1, stage=0)
    (tmp_path / REWIND_STAGING).mkdir()
    (tmp_path / REWIND_STAGING / "notes.txt").write_text("mine")
    with pytest.raises(NotOwnedError, match=rf"{REWIND_STAGING} exists, but no rewind .* nothing was deleted"):
        _rewind_to_pause(tmp_path, 25, 40, log=lambda m: None)
    assert (tmp_path / REWIND_STAGING / "notes.txt").read_text() == "mine"
    (tmp_path / REWIND_MARKER).write_text("{}")  # a partial copy of a rewind that stopped while copying
    _rewind_to_pause(tmp_path, 25, 40, log=lambda m: None)
    assert not (tmp_path / REWIND_MARKER).exists()
    with LifelongReplayBuffer.open(tmp_path / "buffer", read_only=True) as head:
        assert head.size() == 25


def test_a_job_started_then_finished_is_never_deleted_by_a_later_attempt(tmp_path):
    """start_job claims a new directory (an unfinished attempt's goes first); finish_job writes done.json, then the marker."""
    directory = tmp_path / "distill_BC"
    start_job(directory, "distill_BC", log=lambda m: None)
    (directory / "eval.csv").write_text("timesteps\n1\n")
    start_job(directory, "distill_BC", log=lambda m: None)  # an unfinished attempt of its own: deleted, claimed again
    assert sorted(path.name for path in directory.iterdir()) == [OWNED_MARKER]
    (directory / "eval.csv").write_text("timesteps\n1\n")
    finish_job(directory, dict(job="distill_BC", seconds=1.0))
    assert json.loads((directory / "done.json").read_text()) == dict(job="distill_BC", seconds=1.0)
    assert not (directory / OWNED_MARKER).exists()
    before = snapshot(tmp_path)
    with pytest.raises(NotOwnedError, match="holds a finished distill_BC job"):
        start_job(directory, "distill_BC", log=lambda m: None)
    (directory / "done.json").unlink()  # a finished job whose done.json was lost: no marker either, refused too
    with pytest.raises(NotOwnedError, match="no record that an unfinished attempt"):
        start_job(directory, "distill_BC", log=lambda m: None)
    assert snapshot(tmp_path) == {key: value for key, value in before.items() if key != "distill_BC/done.json"}
