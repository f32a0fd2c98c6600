import sys

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers.manifest import FIELD_NAMES

minari = pytest.importorskip("minari")
pytest.importorskip("h5py")  # minari's default (hdf5) storage

# minari warns about every piece of metadata left out (author, code_permalink, ...)
pytestmark = pytest.mark.filterwarnings("ignore::UserWarning:minari")

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)  # float64 like gymnasium's MuJoCo envs: kept as it is
ACT = gym.spaces.Box(-2.0, 2.0, (2,), np.float32)


@pytest.fixture(autouse=True)
def minari_root(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))


def play(buffer, steps, n_envs, seed=0, stage=None):
    """SB3-like collection: observations chain within an episode, random episode ends and time-limit truncations."""
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n_envs, 3))
    for t in range(steps):
        next_obs = rng.normal(size=(n_envs, 3))
        done = rng.random(n_envs) < 0.08
        truncated = done & (rng.random(n_envs) < 0.5)
        infos = [{"TimeLimit.truncated": bool(truncated[i])} for i in range(n_envs)]
        for info in infos:
            if stage is not None:
                info.update(stage=stage(t), dynamics_params={"mass": 1.0 + stage(t)})
        actions = rng.uniform(-1, 1, size=(n_envs, 2)).astype(np.float32)  # normalised, as SB3 stores them
        buffer.add(obs, next_obs, actions, rng.normal(size=n_envs), done, infos)
        obs = np.where(done[:, None], rng.normal(size=(n_envs, 3)), next_obs)


def rows(buffer):
    return {name: np.array(buffer.store.read_range(name, 0, buffer.size())) for name in FIELD_NAMES}


def test_minari_round_trip(tmp_path):
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "life", chunk_size=64)
    play(buffer, 150, 2, stage=lambda t: t // 100)
    buffer.set_source(7, name="field", metadata={"terrain": "gravel"})
    play(buffer, 30, 1, seed=1)  # a third stream (other n_envs), from the write head: its last episode is unfinished
    dataset = buffer.to_minari("lifelong/test-v0", author="tests")
    assert dataset.total_steps == buffer.size() == 330
    expected = buffer.to_d4rl()  # episodes in stream order, actions in environment units
    # the dataset itself: one chain of observations per episode, actions in environment units
    episodes = list(minari.load_dataset("lifelong/test-v0").iterate_episodes())
    observations = np.concatenate([e.observations[:-1] for e in episodes])
    np.testing.assert_array_equal(observations, expected["observations"])
    assert observations.dtype == np.float64
    np.testing.assert_array_equal(np.concatenate([e.observations[1:] for e in episodes]), expected["next_observations"])
    np.testing.assert_array_equal(np.concatenate([e.actions for e in episodes]), expected["actions"])
    assert np.abs(expected["actions"]).max() > 1.0  # really environment units (bounds +-2)
    for episode in episodes:
        ends = episode.terminations | episode.truncations
        assert ends[-1] and not ends[:-1].any()
    # back into a buffer (on disk): identical rows, stored actions normalised again, sources restored
    back = LifelongReplayBuffer.from_minari("lifelong/test-v0", path=tmp_path / "back", n_steps=3)
    got = back.to_d4rl()
    for key in ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts", "sources"):
        np.testing.assert_array_equal(got[key], expected[key], err_msg=key)
        assert got[key].dtype == expected[key].dtype, key
    original = rows(buffer)
    order = np.argsort(original["streams"], kind="stable")
    np.testing.assert_array_equal(rows(back)["actions"], original["actions"][order])
    assert back.source_counts() == buffer.source_counts() == {0: 200, 1: 100, 7: 30}
    assert back.sources[7] == {"name": "field", "metadata": {"terrain": "gravel", "minari_dataset_id": "lifelong/test-v0"}}
    assert back.sources[1]["metadata"]["mass"] == 2.0
    back.close()
    reopened = LifelongReplayBuffer.open(tmp_path / "back", read_only=True, n_steps=3)
    assert reopened.size() == 330
    reopened.sample(16)
    with pytest.raises(ValueError, match="already exists"):
        buffer.to_minari("lifelong/test-v0")


def test_minari_episode_split_unfinished_and_cuts():
    buffer = LifelongReplayBuffer(0, OBS, ACT)
    obs = np.arange(12, dtype=np.float64).reshape(4, 1, 3)
    zero = np.zeros((1, 2))
    buffer.add(obs[0], obs[1], zero, np.ones(1), np.array([False]), [{}])
    buffer.add(obs[1], obs[2], zero, np.ones(1), np.array([True]), [{}])  # terminal: episode 0 (2 steps)
    buffer.add(obs[0], obs[1], zero, np.ones(1), np.array([False]), [{}])
    buffer.add(obs[3], obs[2], zero, np.ones(1), np.array([False]), [{}])  # does not continue obs[1]: cut
    buffer.add(obs[2], obs[3], zero, np.ones(1), np.array([False]), [{}])  # unfinished (write head)
    dataset = buffer.to_minari("split/all-v0")
    episodes = list(dataset.iterate_episodes())
    assert [len(e) for e in episodes] == [2, 1, 2]
    assert [e.terminations.tolist() for e in episodes] == [[False, True], [False], [False, False]]
    assert [e.truncations.tolist() for e in episodes] == [[False, False], [True], [False, True]]
    np.testing.assert_array_equal(episodes[2].observations, obs[[3, 2, 3], 0])
    finished = buffer.to_minari("split/finished-v0", unfinished="drop")
    assert [len(e) for e in finished.iterate_episodes()] == [2, 1]
    with pytest.raises(ValueError, match="unfinished"):
        buffer.to_minari("split/bad-v0", unfinished="keep")
    with pytest.raises(ValueError, match="empty"):
        LifelongReplayBuffer(0, OBS, ACT).to_minari("split/empty-v0")


def test_minari_single_source_discrete_actions_normalized():
    buffer = LifelongReplayBuffer(0, OBS, gym.spaces.Discrete(3), n_steps=2)
    rng = np.random.default_rng(2)
    for t in range(40):
        action = rng.integers(0, 3, (1, 1))
        buffer.add(rng.normal(size=(1, 3)), rng.normal(size=(1, 3)), action, np.ones(1), [t % 10 == 9], [{}])
    dataset = buffer.to_minari("discrete/test-v0")
    assert dataset.action_space == gym.spaces.Discrete(3) and next(dataset.iterate_episodes()).actions.shape == (1,)
    back = LifelongReplayBuffer.from_minari(dataset, source=3, source_metadata={"robot": "op3"})
    assert back.source_counts() == {3: 40}
    assert back.sources[3]["name"] == "minari:discrete/test-v0"
    assert back.sources[3]["metadata"] == {
        "minari_dataset_id": "discrete/test-v0",
        "minari_total_episodes": 40,  # random observations never chain: one step per episode
        "minari_total_steps": 40,
        "robot": "op3",
    }
    np.testing.assert_array_equal(rows(back)["actions"], rows(buffer)["actions"])
    # normalised export: the stored [-1, 1] actions and a Box(-1, 1) space
    box = LifelongReplayBuffer(0, OBS, ACT)
    play(box, 30, 1)
    normalized = box.to_minari("box/normalized-v0", normalized_actions=True)
    assert normalized.action_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    again = LifelongReplayBuffer.from_minari("box/normalized-v0", normalized_actions=True)
    np.testing.assert_array_equal(rows(again)["actions"], rows(box)["actions"])


def test_minari_missing_package(monkeypatch):
    buffer = LifelongReplayBuffer(0, OBS, ACT)
    play(buffer, 5, 1)
    monkeypatch.setitem(sys.modules, "minari", None)  # `import minari` raises ImportError
    with pytest.raises(ImportError, match="pip install minari"):
        buffer.to_minari("any/dataset-v0")
    with pytest.raises(ImportError, match="pip install minari"):
        LifelongReplayBuffer.from_minari("any/dataset-v0")


def test_minari_export_is_quiet_and_records_what_it_is_given():
    """Minari's reminders of optional fields left out are not shown; what the caller gives is recorded."""
    import warnings

    buffer = LifelongReplayBuffer(0, OBS, ACT)
    play(buffer, 40, 1, stage=lambda t: t // 20)
    buffer.set_source(0, name="Env-A")
    buffer.set_source(1, name="Env-B")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dataset = buffer.to_minari("lifelong/quiet-v0")
        assert "sources: Env-A, Env-B" in dataset.storage.metadata["description"]
        given = buffer.to_minari("lifelong/given-v0", author="tests", code_permalink="https://example.org/code")
    assert given.storage.metadata["author"] == {"tests"} or given.storage.metadata["author"] == "tests"
    assert given.storage.metadata["code_permalink"] == "https://example.org/code"
