"""One way in for data: from_offline_data, distill and the buffer's imports share one opener, validator and normaliser."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces

from sb3_lifelong import CRR, MPO, LifelongReplayBuffer
from sb3_lifelong.buffers.manifest import MAX_SOURCE_ID
from sb3_lifelong.core import datasets
from sb3_lifelong.core.datasets import OfflineDataError, normalize_actions
from sb3_lifelong.distill import distill

SMALL = dict(policy_kwargs=dict(net_arch=[16, 16]), batch_size=16, seed=0)


def two_stage_buffer(path) -> LifelongReplayBuffer:
    """An MPO run on Pendulum whose second half is tagged as another source (as a DynamicsSchedule stage would be)."""
    model = MPO(
        "MlpPolicy",
        "Pendulum-v1",
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=str(path)),
        learning_starts=1_000,  # collection only: no update needed here
        seed=0,
        **{k: v for k, v in SMALL.items() if k != "seed"},
    )
    model.learn(200)
    model.replay_buffer.set_source(1, name="Env-B", metadata={"g": 5.0})  # the next transitions' source
    model.learn(100, reset_num_timesteps=False)
    model.replay_buffer.flush()
    return model.replay_buffer


def test_from_offline_data_opens_a_buffer_directory(tmp_path):
    buffer = two_stage_buffer(tmp_path / "buffer")
    counts = buffer.source_counts()
    assert counts == {0: 200, 1: 100}
    model = CRR.from_offline_data(str(tmp_path / "buffer"), **SMALL)
    data = model.replay_buffer
    assert isinstance(data, LifelongReplayBuffer) and data.store.read_only  # opened read-only: collection may go on
    assert data.source_counts() == counts and data.sources[1]["name"] == "Env-B"
    assert model.action_space.high[0] == pytest.approx(2.0)
    model.learn_offline(20, log_interval=0)
    assert model.num_timesteps == 20
    student = distill(tmp_path / "buffer", total_updates=10, **SMALL)  # a PathLike too
    assert student.replay_buffer.source_counts() == counts


def test_a_mistyped_path_names_the_path(tmp_path):
    two_stage_buffer(tmp_path / "buffer")
    mistyped = str(tmp_path / "bufer")
    with pytest.raises(FileNotFoundError, match=f"no offline data at '{mistyped}': no such file or directory"):
        CRR.from_offline_data(mistyped)
    with pytest.raises(FileNotFoundError, match="bufer"):
        distill(mistyped, total_updates=10)
    (tmp_path / "empty").mkdir()
    with pytest.raises(OfflineDataError, match=r"empty'? is a directory, but not a LifelongReplayBuffer"):
        CRR.from_offline_data(tmp_path / "empty")


class TestMinari:
    @pytest.fixture(autouse=True)
    def minari_root(self, tmp_path, monkeypatch):
        pytest.importorskip("minari")
        pytest.importorskip("h5py")
        monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))

    @pytest.mark.filterwarnings("ignore::UserWarning:minari")
    def test_a_dataset_id_keeps_each_steps_source(self, tmp_path):
        buffer = two_stage_buffer(tmp_path / "buffer")
        buffer.to_minari("lifelong/pendulum-v0", env="Pendulum-v1")
        model = CRR.from_offline_data("lifelong/pendulum-v0", **SMALL)
        data = model.replay_buffer
        assert data.source_counts() == {0: 200, 1: 100}  # not every row as source 0
        assert data.sources[1]["name"] == "Env-B" and data.sources[1]["metadata"]["g"] == 5.0
        np.testing.assert_allclose(data.to_d4rl()["actions"], buffer.to_d4rl()["actions"], atol=1e-6)
        model.learn_offline(10, log_interval=0)

    @pytest.mark.filterwarnings("ignore::UserWarning:minari")
    def test_exports_carry_the_env_spec_of_imported_data(self, tmp_path):
        import minari

        buffer = two_stage_buffer(tmp_path / "buffer")
        buffer.to_minari("lifelong/with-env-v0", env="Pendulum-v1")
        imported = LifelongReplayBuffer.from_minari("lifelong/with-env-v0")
        imported.to_minari("lifelong/again-v0")  # no env given: the one recorded at import
        env = minari.load_dataset("lifelong/again-v0").recover_environment()
        assert env.spec.id == "Pendulum-v1" and env.observation_space.shape == (3,)
        without = LifelongReplayBuffer.from_d4rl(buffer.to_d4rl(), buffer.observation_space, buffer.action_space)
        assert minari.load_dataset(without.to_minari("lifelong/bare-v0").id).spec.env_spec is None  # nothing to carry

    def test_an_absent_dataset_id_says_how_to_get_it(self):
        with pytest.raises(FileNotFoundError, match=r"no local Minari dataset.*download_dataset\('nowhere/none-v0'\)"):
            CRR.from_offline_data("nowhere/none-v0")


def test_one_normaliser_for_every_import():
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(41, 3)).astype(np.float32)
    data = {
        "observations": obs[:-1],
        "next_observations": obs[1:],
        "actions": rng.uniform(-2.0, 2.0, size=(40, 1)),  # float64, environment units
        "rewards": rng.normal(size=40),
        "terminals": np.zeros(40, dtype=bool),
    }
    space = spaces.Box(-2.0, 2.0, (1,), np.float32)
    expected = normalize_actions(data["actions"], space)
    assert expected.dtype == np.float32
    np.testing.assert_array_equal(expected, (data["actions"] / 2.0).astype(np.float32))  # in float64, then float32
    buffer = LifelongReplayBuffer.from_d4rl(data, action_space=space)
    model = CRR.from_offline_data(data, action_space=space, **SMALL)
    for stored in (buffer, model.replay_buffer):
        np.testing.assert_array_equal(stored.to_d4rl(by_episode=False, normalized_actions=True)["actions"], expected)
    data["actions"][5] = 2.5  # outside the bounds: clipped with a warning, by the buffer's import too
    with pytest.warns(UserWarning, match="1 of 40 actions lie outside"):
        clipped = LifelongReplayBuffer.from_d4rl(data, action_space=space)
    assert clipped.to_d4rl(by_episode=False, normalized_actions=True)["actions"][5, 0] == 1.0
    unbounded = LifelongReplayBuffer.from_d4rl(data)  # no bounds: nothing to normalise with, values kept
    np.testing.assert_array_equal(unbounded.to_d4rl(by_episode=False)["actions"], data["actions"].astype(np.float32))
    discrete = normalize_actions(np.array([[0], [2]]), spaces.Discrete(3))
    assert discrete.dtype.kind == "i" and discrete.tolist() == [[0], [2]]


def test_one_validator_for_every_import(tmp_path):
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(21, 3))
    data = {
        "observations": obs[:-1],
        "next_observations": obs[1:],
        "actions": rng.uniform(-1, 1, size=(20, 1)).astype(np.float32),
        "rewards": rng.normal(size=20),
        "terminals": np.full(20, 0.5),  # not 0/1
    }
    for make in (lambda: LifelongReplayBuffer.from_d4rl(data), lambda: CRR.from_offline_data(data)):
        with pytest.raises(OfflineDataError, match="'terminals' must hold only 0/1"):
            make()
    data["terminals"] = np.zeros(20, dtype=bool)
    del data["rewards"]
    with pytest.raises(OfflineDataError, match=r"from_d4rl is missing the key\(s\) \['rewards'\]"):
        LifelongReplayBuffer.from_d4rl(data)
    data["rewards"] = np.zeros(20)
    kept = LifelongReplayBuffer.from_d4rl(data)  # the buffer keeps float64 observations (no cast at import)
    assert kept.observation_space.dtype == np.float64
    np.testing.assert_array_equal(kept.to_d4rl(by_episode=False)["observations"], data["observations"])
    assert datasets.MAX_SOURCE_ID == MAX_SOURCE_ID


def test_distill_follows_a_logger_given_with_set_logger(tmp_path, capsys):
    from stable_baselines3.common.logger import configure

    model = MPO(
        "MlpPolicy",
        "Pendulum-v1",
        replay_buffer_class=LifelongReplayBuffer,
        learning_starts=50,
        num_samples=8,
        verbose=1,
        **SMALL,
    )
    model.set_logger(configure(str(tmp_path / "run"), ["stdout", "csv"]))  # no tensorboard_log
    model.learn(100)
    envs = {"Env-A": gym.make("Pendulum-v1")}
    student = model.distill(CRR, total_updates=40, eval_env=envs, eval_freq=20, n_eval_episodes=1, log_interval=20)
    assert student.logger.get_dir() == str(tmp_path / "run" / "distill")
    progress = (tmp_path / "run" / "distill" / "progress.csv").read_text()
    assert "eval/Env-A/mean_reward" in progress and "train/critic_loss" in progress
    out = capsys.readouterr().out
    assert (
        f"Distilling 100 transitions (source_0: 100) into CRR: 40 gradient updates, logging to {tmp_path / 'run' / 'distill'}"
        in out
    )
    assert "Eval at 40: mean reward Env-A" in out
