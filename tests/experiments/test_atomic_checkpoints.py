"""The experiments' checkpoints are saved atomically: a pause that fails to save leaves the previous pause whole."""

import errno
import gc
import json

import pytest
import torch as th
from testkit import small_preset

from sb3_lifelong import MPO
from sb3_lifelong.core.atomic import AtomicWriteError
from sb3_lifelong.experiments import run_seed


def test_a_pause_that_cannot_be_saved_leaves_the_previous_one(tmp_path, monkeypatch):
    preset = small_preset()  # the switch at 60
    collect = tmp_path / "seed_0" / "collect"
    assert run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None, until=20) == []
    before = {name: (collect / name).read_bytes() for name in ("paused.zip", "paused.json")}
    real_save = th.save

    def disk_full(obj, file, *args, **kwargs):  # the zip half written when the disk fills up
        real_save(obj, file, *args, **kwargs)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(th, "save", disk_full)
    with pytest.raises(
        AtomicWriteError, match=rf"could not write {collect / 'paused.zip'} \(No space left on device\)"
    ) as caught:
        run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None, until=40)
    monkeypatch.undo()
    del caught  # (its traceback holds the failed part's model, whose buffer holds the directory's writer lock)
    gc.collect()
    assert {name: (collect / name).read_bytes() for name in before} == before
    assert not [path.name for path in collect.iterdir() if path.name.endswith(".tmp")]
    assert MPO.load(collect / "paused.zip", device="cpu", custom_objects={"replay_buffer_kwargs": {}}).num_timesteps == 20
    # the next part continues from that pause (its buffer cut back to it, the later transitions kept aside)
    assert run_seed(preset, 0, tmp_path, jobs=["collect"], log=lambda m: None, until=40) == []
    assert json.loads((collect / "paused.json").read_text()) == dict(timesteps=40, transitions=40)
    assert (tmp_path / "seed_0" / "buffer.after_pause_20").is_dir()
