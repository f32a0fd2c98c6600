"""
Resuming like SB3: ``load(zip, env=env)`` + ``learn(..., reset_num_timesteps=False)`` continues the buffer directory the
model was saved with, with no extra argument, once it is checked to be that buffer (its id) holding the transitions
the checkpoint committed. Loading itself writes nothing; a buffer that is not the model's is never written to.
"""

import json
import os
import shutil
import warnings
import zipfile

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import MPO, LifelongReplayBuffer

KWARGS = dict(policy_kwargs=dict(net_arch=[8]), batch_size=8, learning_starts=10, num_samples=2)


def make_model(path, seed: int = 0) -> MPO:
    return MPO(
        "MlpPolicy",
        "Pendulum-v1",
        seed=seed,
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=path, chunk_size=16),
        **KWARGS,
    )


def saved_model(tmp_path, steps: int = 60) -> MPO:
    """A model trained ``steps`` steps into ``tmp_path/buffer``, saved as ``tmp_path/model.zip``, its buffer closed."""
    model = make_model(tmp_path / "buffer")
    model.learn(steps)
    model.save(tmp_path / "model.zip")
    model.replay_buffer.close()
    return model


def snapshot(directory) -> dict[str, bytes]:
    """Every file under ``directory``, by relative name."""
    found = {}
    for root, _, names in os.walk(directory):
        for name in names:
            full = os.path.join(root, name)
            with open(full, "rb") as file:
                found[os.path.relpath(full, directory)] = file.read()
    return found


def record(zip_path) -> dict:
    with zipfile.ZipFile(zip_path) as archive:
        return json.loads(archive.read("data"))["_buffer_checkpoint"]


def rewrite_record(zip_path, change) -> None:
    """Edit the buffer record a saved model holds (plain JSON in its ``data``)."""
    with zipfile.ZipFile(zip_path) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(entries["data"])
    change(data["_buffer_checkpoint"])
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(zip_path, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)


def rewards(path) -> np.ndarray:
    with LifelongReplayBuffer.open(path, read_only=True) as buffer:
        return np.array(buffer.read_range("rewards", 0, buffer.size()))


def test_load_then_learn_resumes_appending_to_the_saved_buffer(tmp_path):
    """Before: the first step raised FileExistsError ("held 60 transitions"), unless mode="append" was passed."""
    saved_model(tmp_path)
    before = snapshot(tmp_path / "buffer")
    first = rewards(tmp_path / "buffer")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the buffer is the model's and holds what it committed: nothing to warn about
        loaded = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))
    assert snapshot(tmp_path / "buffer") == before  # loading wrote nothing
    assert loaded.replay_buffer.store.read_only and loaded.replay_buffer.size() == 60
    loaded.learn(40, reset_num_timesteps=False)
    assert loaded.num_timesteps == loaded.replay_buffer.size() == 100 and not loaded.replay_buffer.store.read_only
    loaded.save(tmp_path / "again.zip")
    loaded.replay_buffer.close()
    assert record(tmp_path / "again.zip") == dict(record(tmp_path / "model.zip"), transitions=100, timesteps=100)
    resumed = rewards(tmp_path / "buffer")
    assert len(resumed) == 100 and np.array_equal(resumed[:60], first)  # continued after the rows it held
    twice = MPO.load(tmp_path / "again.zip", env=gym.make("Pendulum-v1"))
    twice.learn(20, reset_num_timesteps=False)
    assert twice.replay_buffer.size() == twice.num_timesteps == 120
    twice.replay_buffer.close()


def test_a_new_model_on_a_buffer_that_holds_rows_says_how_to_continue(tmp_path):
    saved_model(tmp_path)
    again = make_model(tmp_path / "buffer")
    with pytest.raises(FileExistsError, match=r"held 60 transitions.*load its saved model.*mode='append'"):
        again.learn(5)
    again.replay_buffer.close()
    assert len(rewards(tmp_path / "buffer")) == 60


def test_a_buffer_created_again_at_the_path_is_not_the_models(tmp_path):
    saved_model(tmp_path)
    shutil.rmtree(tmp_path / "buffer")
    other = make_model(tmp_path / "buffer", seed=1)  # another run, same spaces, at the same path
    other.learn(30)
    other.replay_buffer.close()
    before = snapshot(tmp_path / "buffer")
    with pytest.warns(UserWarning, match=r"not attached: .*holds another buffer .*Nothing was written there"):
        loaded = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))
    assert loaded.replay_buffer.path is None and loaded.replay_buffer.size() == 0
    with pytest.raises(ValueError, match=r"cannot resume .*holds another buffer.*'mode': 'append'"):
        loaded.learn(10, reset_num_timesteps=False)
    assert snapshot(tmp_path / "buffer") == before


def test_an_older_copy_of_the_buffer_is_read_but_not_continued(tmp_path):
    model = make_model(tmp_path / "buffer")
    model.learn(40)
    model.replay_buffer.flush()
    shutil.copytree(tmp_path / "buffer", tmp_path / "copy")  # the same buffer (same id), 40 transitions
    model.learn(24, reset_num_timesteps=False)
    model.save(tmp_path / "model.zip")
    model.replay_buffer.close()
    shutil.rmtree(tmp_path / "buffer")
    os.rename(tmp_path / "copy", tmp_path / "buffer")
    before = snapshot(tmp_path / "buffer")
    with pytest.warns(UserWarning, match="lags the model by 24 transitions"):
        loaded = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))
    assert loaded.replay_buffer.size() == 40  # readable (e.g. to distil it)
    with pytest.raises(ValueError, match="holds 40 transitions, fewer than the 64 committed when the model was saved"):
        loaded.learn(10, reset_num_timesteps=False)
    assert snapshot(tmp_path / "buffer") == before


def test_without_ids_only_the_transitions_are_checked(tmp_path):
    """A buffer made before buffers had an id, and a zip saved before records had one, still resume."""
    saved_model(tmp_path)
    manifest = json.loads((tmp_path / "buffer" / "manifest.json").read_text())
    del manifest["buffer_id"]
    (tmp_path / "buffer" / "manifest.json").write_text(json.dumps(manifest))
    rewrite_record(tmp_path / "model.zip", lambda entry: entry.pop("buffer_id"))
    loaded = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))
    loaded.learn(20, reset_num_timesteps=False)
    assert loaded.replay_buffer.size() == 80 and loaded.replay_buffer.buffer_id is None
    loaded.replay_buffer.close()


def test_a_buffer_without_an_id_is_not_the_buffer_of_a_zip_that_records_one(tmp_path):
    saved_model(tmp_path)
    manifest = json.loads((tmp_path / "buffer" / "manifest.json").read_text())
    del manifest["buffer_id"]
    (tmp_path / "buffer" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.warns(UserWarning, match=r"holds another buffer \(id none recorded\)"):
        loaded = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))
    with pytest.raises(ValueError, match="holds another buffer"):
        loaded.learn(10)


def test_a_loaded_model_saved_again_keeps_its_record(tmp_path):
    model = make_model(tmp_path / "buffer")
    model.learn(40)
    model.save(tmp_path / "model.zip")  # the writer stays open
    loaded = MPO.load(tmp_path / "model.zip")
    model.learn(16, reset_num_timesteps=False)  # the writer goes on meanwhile
    loaded.save(tmp_path / "again.zip")
    assert record(tmp_path / "again.zip") == record(tmp_path / "model.zip")  # as loaded: 40, the same id
    model.replay_buffer.close()


def test_the_saved_model_still_open_in_this_process_hands_its_buffer_over(tmp_path):
    model = make_model(tmp_path / "buffer")
    model.learn(40)
    model.save(tmp_path / "model.zip")
    model.learn(10, reset_num_timesteps=False)  # 10 more, pending in the old writer
    loaded = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))
    with pytest.warns(UserWarning, match="open for writing by another buffer of this process"):
        loaded.learn(10, reset_num_timesteps=False)
    assert loaded.replay_buffer.size() == 60  # the old writer's rows were committed first, none lost
    with pytest.raises(RuntimeError, match="buffer is closed"):
        model.learn(5, reset_num_timesteps=False)
    loaded.replay_buffer.close()


def test_a_writer_in_another_process_is_refused(tmp_path):
    fcntl = pytest.importorskip("fcntl")
    saved_model(tmp_path)
    before = snapshot(tmp_path / "buffer")
    loaded = MPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))
    with open(tmp_path / "buffer" / "writer.lock", "a+") as lock:  # what another process's writer holds
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(RuntimeError, match="open for writing by another buffer"):
            loaded.learn(10, reset_num_timesteps=False)
    assert snapshot(tmp_path / "buffer") == before
    loaded.learn(10, reset_num_timesteps=False)  # once it is gone
    assert loaded.replay_buffer.size() == 70
    loaded.replay_buffer.close()


def test_replay_buffer_kwargs_given_to_load_are_used_as_they_are(tmp_path):
    saved_model(tmp_path)
    with pytest.warns(UserWarning, match="lags the model by 60"):  # a buffer of the caller's choice: as before
        fresh = MPO.load(
            tmp_path / "model.zip",
            env=gym.make("Pendulum-v1"),
            replay_buffer_kwargs=dict(path=tmp_path / "new", chunk_size=16),
        )
    fresh.learn(10, reset_num_timesteps=False)
    assert fresh.replay_buffer.path == str(tmp_path / "new") and fresh.replay_buffer.size() == 10
    fresh.replay_buffer.close()
    assert len(rewards(tmp_path / "buffer")) == 60
