"""A save that fails (disk full, file-size limit) leaves the previous checkpoint as it was: loadable, byte for byte."""

import errno
import os
import signal
import sys

import pytest
import torch as th

from sb3_lifelong import MPO
from sb3_lifelong.core.atomic import AtomicWriteError

KWARGS = dict(policy_kwargs=dict(net_arch=[16]), batch_size=32, learning_starts=10, num_samples=8, seed=1)


@pytest.fixture
def saved(tmp_path):
    model = MPO("MlpPolicy", "Pendulum-v1", **KWARGS)
    model.save(tmp_path / "model")  # .zip added, as SB3 does
    path = tmp_path / "model.zip"
    assert os.listdir(tmp_path) == ["model.zip"]
    return model, path, path.read_bytes()


def check_untouched(path, before):
    assert path.read_bytes() == before
    assert os.listdir(path.parent) == [path.name]  # no temporary file left
    MPO.load(path, device="cpu")  # still a checkpoint


def test_a_disk_full_in_the_middle_of_a_save_keeps_the_old_zip(saved, monkeypatch):
    model, path, before = saved
    real_save = th.save

    def disk_full(obj, file, *args, **kwargs):  # the zip is half written when the disk fills up
        real_save(obj, file, *args, **kwargs)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(th, "save", disk_full)
    with pytest.raises(AtomicWriteError) as caught:
        model.save(path)
    monkeypatch.undo()
    assert caught.value.errno == errno.ENOSPC and str(path) in str(caught.value)
    check_untouched(path, before)
    with pytest.raises(AtomicWriteError, match=r"model\.zip"):  # without the suffix too
        with monkeypatch.context() as patch:
            patch.setattr(th, "save", disk_full)
            model.save(path.with_suffix(""))
    check_untouched(path, before)


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX resource limits")
def test_a_file_size_limit_keeps_the_old_zip(saved):
    import resource

    model, path, before = saved
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
    resource.setrlimit(resource.RLIMIT_FSIZE, (len(before) // 2, hard))
    try:
        with pytest.raises(AtomicWriteError) as caught:
            model.save(path)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
    assert caught.value.errno == errno.EFBIG and str(path) in str(caught.value)
    check_untouched(path, before)


def test_the_replay_buffer_pickle_is_saved_atomically(tmp_path, monkeypatch):
    model = MPO("MlpPolicy", "Pendulum-v1", **KWARGS)
    model.learn(20)
    model.save_replay_buffer(tmp_path / "buffer")
    path = tmp_path / "buffer.pkl"
    before = path.read_bytes()

    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("stable_baselines3.common.save_util.pickle.dump", disk_full)
    with pytest.raises(AtomicWriteError, match=r"buffer\.pkl"):
        model.save_replay_buffer(path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["buffer.pkl"]


def test_a_directory_in_the_way_is_refused(tmp_path):
    model = MPO("MlpPolicy", "Pendulum-v1", **KWARGS)
    (tmp_path / "model.zip").mkdir()
    with pytest.raises(IsADirectoryError, match=r"model\.zip"):
        model.save(tmp_path / "model.zip")
    model.save(tmp_path / "new" / "deeper" / "model.zip")  # missing directories are created, as SB3 does
    MPO.load(tmp_path / "new" / "deeper" / "model.zip", device="cpu")
