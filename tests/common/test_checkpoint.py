"""A checkpoint is a checkpoint: ``save`` commits a LifelongReplayBuffer directory, and ``load`` tells a lagging one."""

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import zipfile

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from testkit import flat_params

from sb3_lifelong import BC, CRR, MPO, LifelongReplayBuffer

KWARGS = dict(policy_kwargs=dict(net_arch=[16]), batch_size=32, learning_starts=100, train_freq=4, num_samples=8)
FIELDS = ("observations", "next_observations", "actions", "rewards", "flags", "sources")


def pendulum_model(path, chunk_size: int = 1000) -> MPO:
    return MPO(
        "MlpPolicy",
        "Pendulum-v1",
        seed=4,
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=path, chunk_size=chunk_size),
        **KWARGS,
    )


def committed(path) -> int:
    return json.loads((path / "manifest.json").read_text())["num_transitions"]


def test_save_commits_the_buffer_and_records_it(tmp_path):
    model = pendulum_model(tmp_path / "buffer")
    model.learn(152)
    assert committed(tmp_path / "buffer") == 0  # fewer than chunk_size transitions: all still in memory
    model.save(tmp_path / "model.zip")
    assert committed(tmp_path / "buffer") == model.num_timesteps == 152  # the checkpoint committed them
    data = json.loads(zipfile.ZipFile(tmp_path / "model.zip").read("data"))
    buffer_id = model.replay_buffer.buffer_id
    assert isinstance(buffer_id, str) and len(buffer_id) == 32  # the buffer's identity, checked when it is reattached
    assert data["_buffer_checkpoint"] == {"path": str(tmp_path / "buffer"), "transitions": 152, "buffer_id": buffer_id}
    model.replay_buffer.close()


def test_a_checkpoint_whose_buffer_cannot_be_committed_is_not_written(tmp_path, monkeypatch):
    model = pendulum_model(tmp_path / "buffer")
    model.learn(120)

    def disk_full() -> None:
        raise OSError(errno.ENOSPC, "No space left on device (injected)")

    monkeypatch.setattr(model.replay_buffer.store, "flush", disk_full)
    with pytest.raises(OSError, match="No space left"):
        model.save(tmp_path / "model.zip")
    assert not (tmp_path / "model.zip").exists()
    monkeypatch.undo()
    model.replay_buffer.close()


CRASH_AFTER_SAVE = textwrap.dedent("""
    import os, signal, sys
    import torch as th
    th.set_num_threads(1)
    from sb3_lifelong import MPO, LifelongReplayBuffer
    model = MPO("MlpPolicy", "Pendulum-v1", seed=4, replay_buffer_class=LifelongReplayBuffer,
                replay_buffer_kwargs=dict(path=sys.argv[1], chunk_size=1000), **{kwargs})
    model.learn(200)
    model.save(sys.argv[2])
    os.kill(os.getpid(), signal.SIGKILL)  # the process dies right after the checkpoint, the buffer never closed
    """)


def test_crash_right_after_a_save_resumes_bit_identical(tmp_path):
    """save() after 200 steps, then SIGKILL: the buffer holds every transition of the checkpoint (fewer than a chunk,
    so only the save committed them), and load + learn(reset_num_timesteps=False) continues exactly like the
    uninterrupted run."""
    script = CRASH_AFTER_SAVE.replace("{kwargs}", repr(KWARGS))
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    child = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path / "resumed"), str(tmp_path / "model.zip")],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert child.returncode == -signal.SIGKILL, child.stderr
    assert committed(tmp_path / "resumed") == 200

    uninterrupted = pendulum_model(tmp_path / "uninterrupted")
    uninterrupted.learn(200)
    uninterrupted.learn(200, reset_num_timesteps=False)

    with warnings_as_errors():  # the buffer does not lag the checkpoint: no warning
        resumed = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))  # no buffer argument: as in SB3
    assert resumed.replay_buffer.size() == resumed.num_timesteps == 200
    resumed.learn(200, reset_num_timesteps=False)  # reattaches the directory the model was saved with
    assert resumed.replay_buffer.path == str(tmp_path / "resumed")
    for name in FIELDS:
        expected = np.array(uninterrupted.replay_buffer.store.read_range(name, 0, 400))
        np.testing.assert_array_equal(np.array(resumed.replay_buffer.store.read_range(name, 0, 400)), expected, name)
    th.testing.assert_close(flat_params(resumed), flat_params(uninterrupted), rtol=0, atol=0)
    uninterrupted.replay_buffer.close()
    resumed.replay_buffer.close()


class warnings_as_errors:
    def __enter__(self):
        import warnings

        self._catcher = warnings.catch_warnings()
        self._catcher.__enter__()
        warnings.simplefilter("error")

    def __exit__(self, *args):
        self._catcher.__exit__(*args)


def test_load_warns_when_the_buffer_on_disk_lags_the_checkpoint(tmp_path):
    model = pendulum_model(tmp_path / "buffer", chunk_size=50)
    model.learn(120)
    model.replay_buffer.flush()
    shutil.copytree(tmp_path / "buffer", tmp_path / "old_copy")  # a copy made before the save: 120 transitions
    model.learn(80, reset_num_timesteps=False)
    model.save(tmp_path / "model.zip")
    model.replay_buffer.close()
    os.remove(tmp_path / "old_copy" / "writer.lock")
    with pytest.warns(UserWarning, match=r"holds 120 transitions, but .*model.zip was saved when its buffer \(then at "):
        lagging = MPO.load(
            tmp_path / "model.zip", replay_buffer_kwargs=dict(path=tmp_path / "old_copy", chunk_size=50, mode="append")
        )
    lagging.replay_buffer.close()
    # load_replay_buffer (a pickled reference to the directory) checks too
    model = MPO.load(tmp_path / "model.zip")
    stale = LifelongReplayBuffer.open(tmp_path / "old_copy", read_only=True)
    import pickle

    with open(tmp_path / "buffer.pkl", "wb") as file:
        pickle.dump(stale, file)
    with pytest.warns(UserWarning, match=r"lags the model by 80 transitions"):
        model.load_replay_buffer(tmp_path / "buffer.pkl")


@pytest.mark.parametrize("other", [CRR, BC])
def test_loading_another_algorithms_zip_names_both_classes(tmp_path, other):
    model = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8]), learning_starts=10, batch_size=8, seed=0)
    model.learn(12)
    model.save(tmp_path / "mpo.zip")
    with pytest.raises(ValueError, match=rf"mpo was saved by MPO \(its policy is .*MPOPolicy\), not by {other.__name__}"):
        other.load(tmp_path / "mpo")
    assert MPO.load(tmp_path / "mpo").num_timesteps == 12


def test_loading_a_model_created_with_overwrite_keeps_its_buffer(tmp_path):
    """The saved replay_buffer_kwargs never write at load: mode="overwrite" must not delete the very buffer the model
    was saved with (it is opened read-only, then learn() continues it; replay_buffer_kwargs given to load are used as
    they are)."""
    model = MPO(
        "MlpPolicy",
        "Pendulum-v1",
        seed=0,
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=str(tmp_path / "buffer"), chunk_size=1000, mode="overwrite"),
        **KWARGS,
    )
    model.learn(120)
    model.save(tmp_path / "model.zip")
    model.replay_buffer.close()
    loaded = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))
    assert loaded.replay_buffer.size() == 120 and committed(tmp_path / "buffer") == 120
    loaded.learn(8, reset_num_timesteps=False)  # the buffer it was saved with, continued (not deleted, not refused)
    assert loaded.replay_buffer.size() == 128 and loaded.replay_buffer.path == str(tmp_path / "buffer")
    loaded.replay_buffer.close()
    assert committed(tmp_path / "buffer") == 128
    with pytest.warns(UserWarning, match="lags the model by 120 transitions"):  # asked for explicitly, and told
        fresh = MPO.load(tmp_path / "model.zip", replay_buffer_kwargs=dict(path=str(tmp_path / "buffer"), mode="overwrite"))
    assert fresh.replay_buffer.size() == 0
    fresh.replay_buffer.close()
