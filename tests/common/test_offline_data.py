"""The offline data path: sources, space inference, validation, conversion."""

import sys
import types

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_lifelong import BC, CRR, LifelongReplayBuffer
from sb3_lifelong.buffers.loading import as_lifelong_data, resolve_data
from sb3_lifelong.core.datasets import (
    OfflineDataError,
    OfflineSamples,
    load_d4rl,
    minari_to_d4rl,
    replay_buffer_to_d4rl,
    validate_d4rl,
)
from sb3_lifelong.evaluation.callbacks import make_eval_envs

SMALL = dict(policy_kwargs=dict(net_arch=[16, 16]), batch_size=16, seed=0)


def make_data(n: int = 60, obs_dim: int = 3, action_dim: int = 1, action_scale: float = 2.0, episode: int = 20) -> dict:
    """Chained trajectories of ``episode`` steps, actions in [-action_scale, action_scale]."""
    rng = np.random.default_rng(0)
    obs = np.zeros((n, obs_dim), dtype=np.float32)
    next_obs = np.zeros((n, obs_dim), dtype=np.float32)
    state = rng.normal(size=obs_dim).astype(np.float32)
    timeouts = np.zeros(n, dtype=bool)
    for i in range(n):
        obs[i] = state
        state = (state + rng.normal(size=obs_dim) * 0.1).astype(np.float32)
        next_obs[i] = state
        if (i + 1) % episode == 0:
            timeouts[i] = True
            state = rng.normal(size=obs_dim).astype(np.float32)
    return {
        "observations": obs,
        "actions": rng.uniform(-action_scale, action_scale, size=(n, action_dim)).astype(np.float32),
        "rewards": rng.normal(size=n).astype(np.float32),
        "next_observations": next_obs,
        "terminals": np.zeros(n, dtype=bool),
        "timeouts": timeouts,
    }


# ---------------------------------------------------------------------------------------------------------------------
# Sources
# ---------------------------------------------------------------------------------------------------------------------


def test_dict_source_scales_actions_and_trains():
    data = make_data()
    pendulum = gym.make("Pendulum-v1")  # action bounds +-2
    model = CRR.from_offline_data(data, env=pendulum, **SMALL)
    buffer = model.replay_buffer
    assert isinstance(buffer, LifelongReplayBuffer) and buffer.size() == 60 and buffer.path is None
    stored = buffer.to_d4rl(by_episode=False, normalized_actions=True)
    np.testing.assert_allclose(stored["actions"][:, 0], data["actions"][:, 0] / 2.0, atol=1e-6)
    np.testing.assert_array_equal(stored["observations"], data["observations"])
    # timeouts are stored as done + timeout: no effect on bootstrapping
    samples = buffer.sample(200)
    assert float(samples.dones.sum()) == 0.0
    model.learn_offline(20, log_interval=0)
    assert model.num_timesteps == 20 and model._n_updates == 20


def test_npz_source(tmp_path):
    data = make_data()
    path = tmp_path / "data.npz"
    np.savez(path, **data)
    model = BC.from_offline_data(str(path), action_space=spaces.Box(-2, 2, (1,)), **SMALL)
    assert model.replay_buffer.size() == 60
    stored = model.replay_buffer.to_d4rl(by_episode=False, normalized_actions=True)
    np.testing.assert_allclose(stored["actions"][:, 0], data["actions"][:, 0] / 2.0, atol=1e-6)
    model.learn_offline(10, log_interval=0)
    with pytest.raises(FileNotFoundError):
        CRR.from_offline_data(str(tmp_path / "missing.npz"))


def _filled_sb3_buffer(n_envs: int = 2, size: int = 30, steps: int = 40) -> ReplayBuffer:
    obs_space = spaces.Box(-np.inf, np.inf, (3,), np.float32)
    act_space = spaces.Box(-1, 1, (2,), np.float32)
    buffer = ReplayBuffer(size, obs_space, act_space, device="cpu", n_envs=n_envs)
    rng = np.random.default_rng(1)
    obs = rng.normal(size=(n_envs, 3)).astype(np.float32)
    for t in range(steps):
        next_obs = obs + 1.0
        done = np.array([t % 7 == 6] * n_envs)
        buffer.add(obs, next_obs, rng.uniform(-1, 1, (n_envs, 2)), rng.normal(size=n_envs), done, [{}] * n_envs)
        obs = np.where(done[:, None], rng.normal(size=(n_envs, 3)), next_obs).astype(np.float32)
    return buffer


def test_replay_buffer_source_is_used_as_is():
    buffer = _filled_sb3_buffer()
    model = CRR.from_offline_data(buffer, **SMALL)
    assert model.replay_buffer is buffer
    assert model.observation_space.shape == (3,) and model.action_space.shape == (2,)
    model.learn_offline(10, log_interval=0)
    with pytest.raises(ValueError, match="normalised"):
        CRR.from_offline_data(buffer, normalized_actions=False, **SMALL)


def test_a_buffer_on_another_device_samples_onto_the_model_device():
    """A buffer built or opened for another device (here "meta", standing for a GPU) samples where the model's networks
    are from the model's first use on: its construction, set_offline_data and every training run."""
    import torch as th

    buffer = _filled_sb3_buffer()
    buffer.device = th.device("meta")
    model = CRR.from_offline_data(buffer, device="cpu", **SMALL)
    assert model.replay_buffer is buffer and buffer.device == model.device == th.device("cpu")
    for adopt in (lambda: model.set_offline_data(buffer), lambda: None):  # the second: learn_offline alone adopts it
        buffer.device = th.device("meta")
        adopt()
        model.learn_offline(3, log_interval=0)
        assert buffer.device == th.device("cpu") and model.replay_buffer.sample(4).observations.device.type == "cpu"
    online = CRR("MlpPolicy", "Pendulum-v1", learning_starts=10, device="cpu", **SMALL)
    online.learn(20)
    online.replay_buffer.device = th.device("meta")  # e.g. shared with a model on another device
    online.learn(10, reset_num_timesteps=False)
    assert online.replay_buffer.device == th.device("cpu")


def test_replay_buffer_to_d4rl_time_order_and_sarsa():
    buffer = _filled_sb3_buffer(n_envs=2, size=60, steps=40)  # 30 rows per env: wrapped around
    data = replay_buffer_to_d4rl(buffer)
    assert len(data["observations"]) == 60
    first_env = data["observations"][:30]
    # rows of one env are in time order: each next_observation is obs + 1 and starts the following row
    continues = ~data["terminals"][:29]
    np.testing.assert_array_equal(first_env[1:][continues], data["next_observations"][:29][continues])
    # the lifelong copy of an SB3 buffer knows the next action of every row whose trajectory goes on
    copy = as_lifelong_data(buffer)
    assert isinstance(copy, LifelongReplayBuffer) and copy.size() == 60
    samples, _ = copy._get_samples_and_sources(np.arange(60), None, next_actions=True)
    known = samples.next_action_mask.numpy()[:, 0].astype(bool)
    assert known[:29].sum() == continues.sum() and not known[29]
    np.testing.assert_allclose(samples.next_actions.numpy()[:29][known[:29]], data["actions"][1:30][known[:29]], atol=1e-6)
    # SARSA on an SB3 buffer: the buffer is converted to a lifelong one, which knows next actions
    model = CRR.from_offline_data(buffer, critic_target="sarsa", **SMALL)
    model.learn_offline(5, log_interval=0)
    assert isinstance(model.replay_buffer, LifelongReplayBuffer)


def test_lifelong_buffer_source():
    buffer = LifelongReplayBuffer.from_d4rl(
        make_data(action_scale=1.0),
        observation_space=spaces.Box(-np.inf, np.inf, (3,)),
        action_space=spaces.Box(-1, 1, (1,)),
    )
    model = CRR.from_offline_data(buffer, **SMALL)
    assert model.replay_buffer is buffer
    model.learn_offline(10, log_interval=0)
    sarsa = CRR.from_offline_data(buffer, critic_target="sarsa", **SMALL)
    sarsa.learn_offline(5, log_interval=0)
    assert sarsa.replay_buffer is buffer  # SARSA reads the lifetime buffer itself: no copy
    batch = buffer.sample(64, next_actions=True)
    assert isinstance(batch, OfflineSamples) and batch.next_action_mask.any()


@pytest.mark.parametrize("n_steps", [1, 3])
def test_next_actions_follow_each_env_stream(n_steps):
    """Two envs written interleaved, episodes of different lengths: the next action is the same env's next one."""
    obs_space, act_space = spaces.Box(-np.inf, np.inf, (2,)), spaces.Box(-1, 1, (1,))
    buffer = LifelongReplayBuffer(200, obs_space, act_space, n_envs=2, n_steps=n_steps, gamma=0.9, device="cpu")
    lengths = (4, 3)  # env 0 ends an episode every 4 steps (a terminal), env 1 every 3 (a timeout)
    actions = np.zeros((30, 2), dtype=np.float32)
    for t in range(30):
        actions[t] = [0.001 * t, -0.001 * t]  # a row's action says which env and step it is
        dones = np.array([(t + 1) % lengths[0] == 0, (t + 1) % lengths[1] == 0])
        infos = [{}, {"TimeLimit.truncated": bool(dones[1])}]
        obs = np.array([[t, 0.0], [t, 1.0]], dtype=np.float32)
        buffer.add(obs, obs + 1, actions[t].reshape(2, 1), np.ones(2), dones, infos)
    rows = np.arange(buffer.size())
    samples, _ = buffer._get_samples_and_sources(rows, None, next_actions=True)
    mask = samples.next_action_mask.numpy()[:, 0]
    got = samples.next_actions.numpy()[:, 0]
    for row in rows:
        t, env = divmod(int(row), 2)
        last = t  # the step whose next observation the sample bootstraps from
        for _ in range(n_steps - 1):
            if (last + 1) % lengths[env] == 0 or last + 1 >= 30:
                break
            last += 1
        ends = (last + 1) % lengths[env] == 0
        expected_known = not ends and last + 1 < 30
        assert mask[row] == float(expected_known), (row, n_steps)
        if expected_known:
            assert got[row] == pytest.approx(actions[last + 1, env])


class _FakeMinariDataset:
    """Duck-typed Minari dataset: two episodes of 4 and 3 steps."""

    observation_space = spaces.Box(-5, 5, (2,), np.float32)
    action_space = spaces.Box(-3, 3, (1,), np.float32)

    def iterate_episodes(self):
        for steps, terminated in ((4, True), (3, False)):
            yield types.SimpleNamespace(
                observations=np.arange((steps + 1) * 2, dtype=np.float32).reshape(steps + 1, 2),
                actions=np.full((steps, 1), 1.5, dtype=np.float32),
                rewards=np.ones(steps),
                terminations=np.array([False] * (steps - 1) + [terminated]),
                truncations=np.array([False] * (steps - 1) + [not terminated]),
            )


def test_minari_source():
    data, obs_space, act_space = minari_to_d4rl(_FakeMinariDataset())
    assert len(data["observations"]) == 7 and act_space.shape == (1,) and obs_space.shape == (2,)
    np.testing.assert_array_equal(data["next_observations"][0], data["observations"][1])
    assert data["terminals"].tolist() == [False, False, False, True, False, False, False]
    assert data["timeouts"].tolist() == [False] * 6 + [True]
    model = CRR.from_offline_data(_FakeMinariDataset(), **SMALL)
    assert model.action_space == _FakeMinariDataset.action_space  # the dataset's spaces are used
    np.testing.assert_allclose(model.replay_buffer.to_d4rl(normalized_actions=True)["actions"][:7, 0], 0.5)  # 1.5 in [-3, 3]
    model.learn_offline(5, log_interval=0)


def test_minari_id_needs_minari(monkeypatch):
    monkeypatch.setitem(sys.modules, "minari", None)  # `import minari` raises ImportError, installed or not
    with pytest.raises(ImportError, match="minari"):
        CRR.from_offline_data("D4RL/door/human-v2")


# ---------------------------------------------------------------------------------------------------------------------
# Spaces
# ---------------------------------------------------------------------------------------------------------------------


def test_space_inference():
    unit = CRR.from_offline_data(make_data(action_scale=1.0, obs_dim=5, action_dim=2), **SMALL)
    assert unit.observation_space == spaces.Box(-np.inf, np.inf, (5,), np.float32)
    assert unit.action_space == spaces.Box(-1, 1, (2,), np.float32)
    with pytest.warns(UserWarning, match="inferred from the range"):
        wide = CRR.from_offline_data(make_data(action_scale=2.0), **SMALL)
    assert np.all(wide.action_space.high <= 2.0) and np.all(wide.action_space.high > 1.0)
    normalised = CRR.from_offline_data(make_data(action_scale=1.0), normalized_actions=True, **SMALL)
    assert normalised.action_space == spaces.Box(-1, 1, (1,), np.float32)
    # the env's spaces win, and a mismatch is an error
    with pytest.raises(OfflineDataError, match="observation"):
        CRR.from_offline_data(make_data(obs_dim=4), env="Pendulum-v1", **SMALL)
    with pytest.raises(OfflineDataError, match="action"):
        CRR.from_offline_data(make_data(action_dim=2), env="Pendulum-v1", **SMALL)


def test_out_of_bound_actions_are_clipped_with_a_warning():
    with pytest.warns(UserWarning, match="outside the action space"):
        model = BC.from_offline_data(make_data(action_scale=3.0), action_space=spaces.Box(-1, 1, (1,)), **SMALL)
    assert np.abs(model.replay_buffer.to_d4rl(normalized_actions=True)["actions"]).max() <= 1.0


def test_bad_spaces():
    with pytest.raises(OfflineDataError, match="Box"):
        CRR.from_offline_data(make_data(), action_space=spaces.Discrete(3))
    with pytest.raises(OfflineDataError, match="finite bounds"):
        CRR.from_offline_data(make_data(), action_space=spaces.Box(-np.inf, np.inf, (1,)))
    with pytest.raises(TypeError, match="ReplayBuffer"):
        CRR.from_offline_data(42)


# ---------------------------------------------------------------------------------------------------------------------
# Bad data gives clear errors
# ---------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "corrupt, match",
    [
        (lambda d: d.pop("terminals"), r"missing the key\(s\) \['terminals'\]"),
        (lambda d: d.pop("next_observations"), "next_observations"),
        (lambda d: d.update(rewards=d["rewards"][:-1]), "same length"),
        (lambda d: d.update(timeouts=d["timeouts"][:10]), "same length"),
        (lambda d: d["observations"].__setitem__((5, 1), np.nan), "'observations' holds NaN.*row 5"),
        (lambda d: d["rewards"].__setitem__(7, np.inf), "'rewards' holds NaN or infinite"),
        (lambda d: d["actions"].__setitem__((3, 0), np.nan), "'actions' holds NaN"),
        (lambda d: d.update(actions=d["actions"].astype(str)), "'actions' must have a floating-point dtype"),
        (lambda d: d.update(actions=np.ones((60, 1), dtype=np.int64)), "'actions' must have a floating-point dtype"),
        (lambda d: d.update(observations=np.full((60, 3), "x")), "'observations' must have a numeric"),
        (lambda d: d.update(terminals=np.full(60, 0.5)), "'terminals' must hold only 0/1"),
        (lambda d: d.update(terminals=np.array(["no"] * 60)), "'terminals' must be boolean"),
        (lambda d: d.update(next_observations=d["next_observations"][:, :2]), "same shape"),
        (lambda d: d.update(rewards=np.ones((60, 2))), r"rewards must be \[N\]"),
        (lambda d: d.update(rewards=np.float32(1.0)), "scalar"),
    ],
)
def test_bad_data_errors(corrupt, match):
    data = make_data()
    corrupt(data)
    with pytest.raises(OfflineDataError, match=match):
        CRR.from_offline_data(data, action_space=spaces.Box(-2, 2, (1,)))


def test_empty_and_non_mapping():
    empty = {key: value[:0] for key, value in make_data().items()}
    with pytest.raises(OfflineDataError, match="empty"):
        validate_d4rl(empty)
    with pytest.raises(OfflineDataError, match="mapping"):
        validate_d4rl([1, 2, 3])  # type: ignore[arg-type]
    with pytest.raises(OfflineDataError, match="empty"):
        resolve_data(ReplayBuffer(10, spaces.Box(-1, 1, (2,)), spaces.Box(-1, 1, (1,)), device="cpu"))


def test_npz_with_pickled_objects_is_refused(tmp_path):
    data = make_data()
    data["observations"] = np.array([np.zeros(3)] * 59 + [np.zeros(2)], dtype=object)
    path = tmp_path / "objects.npz"
    np.savez(path, **data)
    with pytest.raises(OfflineDataError, match="without pickle"):
        load_d4rl(str(path))


def test_learn_offline_without_data():
    model = CRR("MlpPolicy", "Pendulum-v1", **SMALL)
    with pytest.raises(ValueError, match="No offline data"):
        model.learn_offline(10)


def test_eval_env_names():
    envs = make_eval_envs({"a": "Pendulum-v1", "b": gym.make("Pendulum-v1")})
    assert list(envs) == ["a", "b"]
    envs = make_eval_envs(["Pendulum-v1", gym.make("Pendulum-v1")])
    assert list(envs) == ["Pendulum-v1", "Pendulum-v1_1"]


def test_learn_offline_keeps_the_env_it_has_and_lends_callbacks_a_stand_in_otherwise():
    """A model built with an env keeps it through ``learn_offline``; one without gets a stand-in for the callbacks
    (which cannot be stepped) and has no env again afterwards."""
    from stable_baselines3.common.callbacks import BaseCallback

    from sb3_lifelong.common.offline import NoEnvironment

    class Seen(BaseCallback):
        def _on_step(self) -> bool:
            self.seen = self.training_env.envs[0].unwrapped
            return True

    pendulum = gym.make("Pendulum-v1")
    with_env = CRR.from_offline_data(make_data(), env=pendulum, **SMALL)
    before, seen = with_env.get_env(), Seen()
    with_env.learn_offline(2, log_interval=0, callback=seen)
    assert with_env.get_env() is before and seen.seen is pendulum.unwrapped
    alone, seen = CRR.from_offline_data(make_data(), observation_space=pendulum.observation_space, **SMALL), Seen()
    alone.learn_offline(2, log_interval=0, callback=seen)
    assert isinstance(seen.seen, NoEnvironment) and alone.get_env() is None


@pytest.mark.parametrize("updates, dumps", [(7, [5, 7]), (10, [5, 10])])
def test_learn_offline_dumps_every_log_interval_and_once_at_the_end(tmp_path, updates, dumps):
    """The logs are written every ``log_interval`` updates and after the last update, never twice for one update."""
    import csv as csv_module

    from stable_baselines3.common.logger import configure

    model = CRR.from_offline_data(make_data(), env=gym.make("Pendulum-v1"), **SMALL)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn_offline(updates, log_interval=5)
    with open(tmp_path / "progress.csv", newline="") as handle:
        rows = list(csv_module.DictReader(handle))
    assert [int(row["time/updates"]) for row in rows] == dumps
    assert all(0 <= int(row["time/time_elapsed"]) < 600 for row in rows)  # seconds since this call began
