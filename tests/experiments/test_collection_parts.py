"""A collection or a student in parts: paused, continued, rewound, and equal to an uninterrupted run."""

import dataclasses
import json
import os
import pathlib

import numpy as np
import pandas as pd
import pytest
import torch as th

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import merge_buffers
from sb3_lifelong.experiments import PRESETS, STUDENTS, run_seed
from sb3_lifelong.experiments.__main__ import main
from sb3_lifelong.experiments.collection import REWIND_STAGING


def test_a_collection_runs_in_parts(tmp_path, capsys):
    """``until`` pauses the collection with a checkpoint; the same call continues it, through the switch, to the end."""
    messages: list = []
    preset = PRESETS["tiny"]  # 200 steps of Env-A, 400 of Env-B
    run_dir = tmp_path / "seed_0"
    main(["run", "--preset", "tiny", "--seed", "0", "--output", str(tmp_path), "--jobs", "collect", "--until", "150"])
    out = capsys.readouterr().out
    assert "paused at step 150" in out and "The collection is paused" in out and "report" not in out.split("paused")[-1]
    assert (run_dir / "collect" / "paused.zip").exists() and not (run_dir / "collect" / "stage1.zip").exists()
    assert not (run_dir / "collect" / "done.json").exists()
    assert json.loads((run_dir / "collect" / "paused.json").read_text()) == dict(timesteps=150, transitions=150)
    with open(run_dir / "collect" / "eval.csv", "a") as handle:  # a part killed after logging past the pause
        handle.write("300,Env-A,1.0,0.0,1\n")
    assert run_seed(preset, 0, tmp_path, jobs=["collect"], log=messages.append, until=450) == []  # through the switch
    with LifelongReplayBuffer.open(run_dir / "buffer_stage1", read_only=True) as stage1:
        assert stage1.size() == 200
    assert run_seed(preset, 0, tmp_path, jobs=["collect"], log=messages.append) == ["collect"]
    assert not (run_dir / "collect" / "paused.zip").exists() and (run_dir / "collect" / "final.zip").exists()
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        counts = buffer.source_counts()  # the robot changes at the first episode start from step 200 on
        assert buffer.size() == 600 and sorted(counts) == [0, 1] and 200 <= counts[0] < 600
    steps = pd.read_csv(run_dir / "collect" / "eval.csv").groupby("env")["timesteps"].apply(list)
    assert all(list(s) == list(range(100, 601, 100)) for s in steps)  # every evaluation once, none repeated
    train = pd.read_csv(run_dir / "collect" / "train.csv")  # one header, its rows in order across the parts
    assert list(train["timesteps"]) == sorted(set(train["timesteps"])) and train["timesteps"].max() == 600
    assert train["timesteps"].min() <= 200  # the parts before the last pause are kept


def test_a_collection_in_parts_evaluates_and_trains_as_an_uninterrupted_one(tmp_path):
    """Each part of a paused collection runs in a new process with new evaluation environments: the evaluations still
    play the same seeded episodes as an uninterrupted collection's (``same_episodes``), so its ``eval.csv`` and
    ``q_sources.csv`` are the uninterrupted one's to the last digit. (Seeded once per process instead, the first
    evaluation after each pause would play the episodes of a run's first evaluation, and the logs would part there.)
    The pauses fall on episode ends (HalfCheetah's episodes have a fixed length): a resumed model starts a new episode,
    so a pause inside one changes the data from there on."""
    preset = dataclasses.replace(PRESETS["tiny"], env_id="HalfCheetah-v5", max_episode_steps=50)
    run_seed(preset, 0, tmp_path / "whole", jobs=["collect"], log=lambda m: None)
    for until in (150, 350, None):  # two pauses, one on each side of the switch at 200
        run_seed(preset, 0, tmp_path / "parts", jobs=["collect"], log=lambda m: None, until=until)
    for log in ("eval.csv", "q_sources.csv"):
        whole = pd.read_csv(tmp_path / "whole" / "seed_0" / "collect" / log)
        parts = pd.read_csv(tmp_path / "parts" / "seed_0" / "collect" / log)
        assert len(whole) >= 6, log
        pd.testing.assert_frame_equal(parts, whole, check_exact=True)


def test_a_part_that_stopped_without_pausing_continues_from_the_pause(tmp_path):
    """A part continued from a pause, committed transitions and was killed: the next call cuts the buffer back to the
    pause (the later transitions kept beside it), continues from there and ends as an uninterrupted collection."""
    preset = PRESETS["tiny"]
    run_dir = tmp_path / "seed_0"
    run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None, until=150)
    pause = {name: (run_dir / "collect" / name).read_bytes() for name in ("paused.zip", "paused.json")}
    # the killed part: it committed up to step 250, past the switch at 200 (here: paused there), and left the pause at
    # 150 as it was
    run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None, until=250)
    assert (run_dir / "buffer_stage1").exists() and (run_dir / "collect" / "stage1.zip").exists()
    for name, content in pause.items():
        (run_dir / "collect" / name).write_bytes(content)
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        assert buffer.size() == 250
        later = buffer.store.read_range("observations", 0, 250).copy()
    messages: list = []
    assert run_seed(preset, 0, tmp_path, jobs=["collect"], log=messages.append, until=300) == []
    assert any("250 transitions, 100 past the pause" in m for m in messages)
    aside = run_dir / "buffer.after_pause_150"
    with LifelongReplayBuffer.open(aside, read_only=True) as kept, LifelongReplayBuffer.open(
        run_dir / "buffer", read_only=True
    ) as buffer:
        np.testing.assert_array_equal(kept.store.read_range("observations", 0, 250), later)  # nothing lost
        assert buffer.size() == 300 and buffer.sources == kept.sources  # 150 kept, then 150 collected again
        np.testing.assert_array_equal(buffer.store.read_range("observations", 0, 150), later[:150])
    assert not (run_dir / REWIND_STAGING).exists()
    # the Stage-1 agent and buffer are the resumed collection's, the stopped part's kept beside them
    assert (run_dir / "buffer_stage1.after_pause_150").is_dir() and (
        run_dir / "collect" / "stage1.after_pause_150.zip"
    ).exists()
    with LifelongReplayBuffer.open(run_dir / "buffer_stage1", read_only=True) as stage1, LifelongReplayBuffer.open(
        run_dir / "buffer", read_only=True
    ) as buffer:
        assert stage1.size() == 200
        np.testing.assert_array_equal(
            stage1.store.read_range("observations", 0, 200), buffer.store.read_range("observations", 0, 200)
        )
    assert run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None) == ["collect"]
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        assert buffer.size() == 600
    steps = pd.read_csv(run_dir / "collect" / "eval.csv").groupby("env")["timesteps"].apply(list)
    assert all(list(s) == list(range(100, 601, 100)) for s in steps)  # every evaluation once, none repeated


def test_rewinds_that_stopped_half_way_or_repeat_keep_everything(tmp_path):
    """A rewind stopped between its renames is finished; a part killed again from the same pause is cut back again;
    each time the Stage-1 agent and buffer of a part that passed the switch are set aside under a free name."""
    preset = PRESETS["tiny"]  # the switch at 200
    run_dir, collect = tmp_path / "seed_0", tmp_path / "seed_0" / "collect"
    run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None, until=150)
    pause = {name: (collect / name).read_bytes() for name in ("paused.zip", "paused.json")}

    def killed_part(until: int) -> None:  # a part from the pause that committed up to `until` and stopped unrecorded
        run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None, until=until)
        for name, content in pause.items():
            (collect / name).write_bytes(content)

    killed_part(250)
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as whole:  # the rewind, stopped between renames
        merge_buffers([whole], path=run_dir / REWIND_STAGING, stops=[150]).close()
    os.replace(run_dir / "buffer", run_dir / "buffer.after_pause_150")
    killed_part(260)  # finishes the rewind, sets the Stage-1 files aside, then goes on to 260 and is "killed" again
    assert (run_dir / "buffer_stage1.after_pause_150").is_dir() and (collect / "stage1.after_pause_150.zip").exists()
    assert run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None, until=300) == []
    for kept, size in (("buffer.after_pause_150", 250), ("buffer.after_pause_150.1", 260)):
        with LifelongReplayBuffer.open(run_dir / kept, read_only=True) as buffer:
            assert buffer.size() == size
    assert (run_dir / "buffer_stage1.after_pause_150.1").is_dir() and (collect / "stage1.after_pause_150.1.zip").exists()
    with LifelongReplayBuffer.open(run_dir / "buffer_stage1", read_only=True) as stage1, LifelongReplayBuffer.open(
        run_dir / "buffer", read_only=True
    ) as buffer:
        assert stage1.size() == 200 and buffer.size() == 300
        np.testing.assert_array_equal(
            stage1.store.read_range("observations", 0, 200), buffer.store.read_range("observations", 0, 200)
        )


def test_rewind_copies_the_head_and_keeps_the_whole_buffer(tmp_path):
    from testkit import ACT, OBS, all_rows, fill

    from sb3_lifelong.experiments.collection import _rewind_to_pause

    with LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "buffer", chunk_size=16) as buffer:
        fill(buffer, 40, 1, stage=0)
        whole = all_rows(buffer)
    _rewind_to_pause(tmp_path, 25, 40, log=lambda m: None)
    with LifelongReplayBuffer.open(tmp_path / "buffer", read_only=True) as head:
        assert head.size() == 25
        for name, values in all_rows(head).items():
            np.testing.assert_array_equal(values, whole[name][:25])
    with LifelongReplayBuffer.open(tmp_path / "buffer.after_pause_25", read_only=True) as kept:
        assert kept.size() == 40
    with LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "evicting" / "buffer", capacity=30) as buffer:
        fill(buffer, 40, 1, stage=0)
    with pytest.raises(RuntimeError, match=r"it evicts.*Nothing was deleted"):
        _rewind_to_pause(tmp_path / "evicting", 20, 30, log=lambda m: None)
    with LifelongReplayBuffer.open(tmp_path / "evicting" / "buffer", read_only=True) as buffer:
        assert buffer.size() == 30


def test_a_paused_collection_whose_buffer_lost_rows_is_not_deleted(tmp_path):
    """A buffer holding fewer transitions than its pause committed: resuming refuses, naming what to remove; data kept."""
    preset = PRESETS["tiny"]
    run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None, until=150)
    record = tmp_path / "seed_0" / "collect" / "paused.json"
    record.write_text(json.dumps(dict(timesteps=180, transitions=180)))  # the buffer now holds fewer than recorded
    with pytest.raises(RuntimeError, match=r"fewer than the 180 the pause committed.*Nothing was deleted"):
        run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None)
    with LifelongReplayBuffer.open(tmp_path / "seed_0" / "buffer", read_only=True) as buffer:
        assert buffer.size() == 150


def test_a_stopped_student_continues_from_its_last_pause_exactly(study, tmp_path, monkeypatch):
    """A student pauses at each evaluation; stopped after a pause, it continues from there as if never stopped."""

    from sb3_lifelong.experiments import jobs
    from sb3_lifelong.experiments.protocol import distill_on_study

    output, _ = study
    preset = dataclasses.replace(PRESETS["tiny"], distill_steps=150, distill_eval_freq=50)
    student = {"ind": STUDENTS["CRR_indicator"]}
    distill_on_study(output, 0, tmp_path / "whole", student, preset, log=lambda _: None)

    recorded = jobs.write_json_atomic
    calls = []

    def stop_at_the_second_pause(path: str, data: dict) -> None:
        if pathlib.Path(path).name == "paused.json":  # the pause records (not the directory's marker)
            calls.append(1)
            if len(calls) == 2:  # its checkpoint is written, its record is not: the first pause's record still holds
                raise KeyboardInterrupt
        recorded(path, data)

    monkeypatch.setattr(jobs, "write_json_atomic", stop_at_the_second_pause)
    with pytest.raises(KeyboardInterrupt):
        distill_on_study(output, 0, tmp_path / "parts", student, preset, log=lambda _: None)
    monkeypatch.setattr(jobs, "write_json_atomic", recorded)
    directory = tmp_path / "parts" / "seed_0" / "distill_ind"
    assert json.loads((directory / "paused.json").read_text())["updates"] == 50
    assert sorted(p.name for p in directory.glob("paused_*.zip")) == ["paused_100.zip", "paused_50.zip"]
    assert "100" in (directory / "eval.csv").read_text().split("\n", 2)[-1]  # the evaluation at 100 was written

    messages: list[str] = []
    th.manual_seed(123), np.random.seed(123)  # the pause's generators are restored, whatever they are now
    assert distill_on_study(output, 0, tmp_path / "parts", student, preset, log=messages.append) == ["ind"]
    assert any("continuing the student from its checkpoint at 50 of 150 updates" in m for m in messages)
    assert any("distill_ind: checkpoint at 100 of 150 updates" in m for m in messages)
    whole = tmp_path / "whole" / "seed_0" / "distill_ind"
    for name in ("eval.csv", "train.csv", "q_sources.csv"):
        assert (directory / name).read_text() == (whole / name).read_text(), name
    kept = pd.read_csv(directory / "eval.after_pause_50.csv")  # the stopped part's log, whole
    assert sorted(set(kept["timesteps"])) == [50, 100]
    from sb3_lifelong import CRR

    params = [CRR.load(d / "student.zip").policy.state_dict() for d in (whole, directory)]
    for key, value in params[0].items():
        assert th.equal(value, params[1][key]), key
    assert not list(directory.glob("paused_*.zip")) and (directory / "done.json").exists()
    finished = json.loads((directory / "paused.json").read_text())  # a stop before done.json: nothing left to train
    assert finished["updates"] == 150 and finished["model"] == "student.zip" and finished["compiled"] is False
    done = json.loads((directory / "done.json").read_text())
    assert done["seconds"] > 0

    (directory / "done.json").unlink()  # stopped after the student was saved, before done.json: nothing is trained again
    assert distill_on_study(output, 0, tmp_path / "parts", student, preset, log=lambda _: None) == ["ind"]
    again = CRR.load(directory / "student.zip").policy.state_dict()
    assert all(th.equal(value, again[key]) for key, value in params[1].items())
    assert json.loads((directory / "done.json").read_text())["seconds"] >= done["seconds"]
    assert (directory / "eval.csv").read_text() == (whole / "eval.csv").read_text()

    # a pause of other settings is refused, and nothing is touched
    other = dataclasses.replace(preset, distill_steps=200)
    (directory / "done.json").unlink()
    (directory / "paused.json").write_text(json.dumps(dict(updates=50, model="student.zip", settings={"other": 1})))
    with pytest.raises(ValueError, match="student checkpoint at 50 updates with other settings"):
        distill_on_study(output, 0, tmp_path / "parts", student, other, log=lambda _: None)
    assert (directory / "student.zip").exists()
