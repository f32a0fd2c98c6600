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
from stable_baselines3.common.callbacks import BaseCallback
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
    record = {"path": str(tmp_path / "buffer"), "transitions": 152, "buffer_id": buffer_id, "timesteps": 152}
    assert data["_buffer_checkpoint"] == record
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


CRASH_IN_A_STEP = textwrap.dedent("""
    import os, signal, sys
    import torch as th
    th.set_num_threads(1)
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList, CheckpointCallback
    from sb3_lifelong import MPO, LifelongReplayBuffer
    buffer, checkpoints, point, at = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])

    def die():
        os.kill(os.getpid(), signal.SIGKILL)

    class Die(BaseCallback):  # after the checkpoint callback: the step's transition is not stored yet
        def _on_step(self):
            if point == "callback" and self.num_timesteps == at:
                die()
            return True

    model = MPO("MlpPolicy", "Pendulum-v1", seed=4, replay_buffer_class=LifelongReplayBuffer,
                replay_buffer_kwargs=dict(path=buffer, chunk_size=30), **{kwargs})
    if point == "update":  # on the class: an attribute of the model would be saved with it
        train = MPO.train
        def die_in_train(self, *args, **kwargs):
            train(self, *args, **kwargs)
            if self.num_timesteps >= at:
                die()
        MPO.train = die_in_train
    model.learn(400, callback=CallbackList([CheckpointCallback(100, checkpoints), Die()]))
    """)


@pytest.mark.parametrize(
    "point, at, kept_after",
    [
        ("callback", 200, 0),  # in the step that SB3's CheckpointCallback saved: its transition was never stored
        ("callback", 201, 0),  # the next step: that transition stored, not committed
        ("callback", 250, 30),  # a chunk committed after the checkpoint
        ("update", 204, 0),  # in the first update after the checkpoint
    ],
)
def test_the_checkpoint_rule_after_sigkill_at_each_point_of_a_step(tmp_path, point, at, kept_after):
    """SB3's CheckpointCallback saves every 100 steps (from a callback: the step in flight is counted, its transition
    not yet stored), the run is killed; load of the last checkpoint + learn(reset_num_timesteps=False) resumes at the
    timestep its buffer reaches: one transition per timestep, none lost or stored twice."""
    script = CRASH_IN_A_STEP.replace("{kwargs}", repr(KWARGS))
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    args = [str(tmp_path / "buffer"), str(tmp_path / "checkpoints"), point, str(at)]
    child = subprocess.run([sys.executable, "-c", script, *args], env=env, capture_output=True, text=True, timeout=600)
    assert child.returncode == -signal.SIGKILL, child.stderr
    held = committed(tmp_path / "buffer")
    assert held == 199 + kept_after  # the save at 200 committed the 199 stored transitions; a chunk after it

    uninterrupted = pendulum_model(tmp_path / "uninterrupted", chunk_size=30)
    uninterrupted.learn(held)
    expected = {name: np.array(uninterrupted.replay_buffer.store.read_range(name, 0, held)) for name in FIELDS}
    uninterrupted.replay_buffer.close()

    resumed = MPO.load(tmp_path / "checkpoints" / "rl_model_200_steps.zip", env=gym.make("Pendulum-v1"))
    assert resumed.num_timesteps == 200
    if kept_after:
        with pytest.warns(
            UserWarning,
            match=f"holds {kept_after} transitions committed after this checkpoint .* resumes at " f"timestep {held}, not 200",
        ):
            resumed.learn(100, reset_num_timesteps=False)
    else:
        with warnings_as_errors():
            resumed.learn(100, reset_num_timesteps=False)
    resumed.replay_buffer.close()
    assert resumed.num_timesteps == held + 100
    assert committed(tmp_path / "buffer") == resumed.num_timesteps  # one transition per timestep
    for name in FIELDS:  # the stopped run's transitions, each once, then the resumed run's
        np.testing.assert_array_equal(np.array(resumed.replay_buffer.store.read_range(name, 0, held)), expected[name], name)


def test_a_checkpoint_records_the_timestep_its_transitions_reach(tmp_path):
    model = pendulum_model(tmp_path / "buffer")

    class SaveInTheStep(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps == 120:
                self.model.save(tmp_path / "in_step.zip")
            return True

    model.learn(150, callback=SaveInTheStep())
    model.save(tmp_path / "between.zip")
    model.replay_buffer.close()
    in_step = json.loads(zipfile.ZipFile(tmp_path / "in_step.zip").read("data"))
    between = json.loads(zipfile.ZipFile(tmp_path / "between.zip").read("data"))
    assert (in_step["num_timesteps"], in_step["_buffer_checkpoint"]["transitions"]) == (120, 119)
    assert in_step["_buffer_checkpoint"]["timesteps"] == 119  # the step in flight was counted, not stored
    assert between["_buffer_checkpoint"]["timesteps"] == between["_buffer_checkpoint"]["transitions"] == model.num_timesteps


def test_the_checkpoint_rule_holds_with_the_buffer_named_again_at_load(tmp_path):
    model = pendulum_model(tmp_path / "buffer", chunk_size=50)
    model.learn(100)
    model.save(tmp_path / "model.zip")
    model.learn(80, reset_num_timesteps=False)  # 50 more committed (a chunk), 30 pending
    model.replay_buffer.store.abandon()  # the process stops: what was pending is lost
    assert committed(tmp_path / "buffer") == 150
    kwargs = dict(path=str(tmp_path / "buffer"), mode="append", chunk_size=50)
    resumed = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"), replay_buffer_kwargs=kwargs)
    with pytest.warns(UserWarning, match="holds 50 transitions committed after this checkpoint"):
        resumed.learn(50, reset_num_timesteps=False)
    resumed.replay_buffer.close()
    assert resumed.num_timesteps == committed(tmp_path / "buffer") == 150 + 52  # 50, rounded up to rollouts of 4
    again = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"), replay_buffer_kwargs=kwargs)
    again.learn(20)  # reset_num_timesteps=True: the timesteps count from 0 again, as in SB3
    again.replay_buffer.close()
    assert again.num_timesteps == 20
