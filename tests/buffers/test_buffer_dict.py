import json
import os

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.type_aliases import DictReplayBufferSamples

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError, LifelongBufferView, merge_buffers

OBS = spaces.Dict(
    {
        "pos": spaces.Box(-1, 1, (3,), np.float32),
        "image": spaces.Box(0, 255, (2, 4, 4), np.uint8),
        "mode": spaces.Discrete(4),
    }
)
ACT = spaces.Box(-1, 1, (2,), np.float32)


def random_obs(rng, n_envs):
    return {
        "pos": rng.uniform(-1, 1, (n_envs, 3)).astype(np.float32),
        "image": rng.integers(0, 256, (n_envs, 2, 4, 4)).astype(np.uint8),
        "mode": rng.integers(0, 4, n_envs),
    }


def fill(buffer, steps, n_envs, seed=0, stage=None):
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        done = rng.random(n_envs) < 0.15
        trunc = done & (rng.random(n_envs) < 0.5)
        infos = [{"TimeLimit.truncated": bool(trunc[i])} for i in range(n_envs)]
        if stage is not None:
            for info in infos:
                info.update(stage=stage)
        buffer.add(
            random_obs(rng, n_envs),
            random_obs(rng, n_envs),
            rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32),
            rng.normal(size=n_envs).astype(np.float32),
            done,
            infos,
        )


def all_rows(buffer):
    return {name: np.array(buffer.store.read_range(name, 0, buffer.size())) for name in buffer.store.fields}


def assert_same_samples(a, b):
    assert type(a) is type(b)
    for name in ("observations", "next_observations"):
        x, y = getattr(a, name), getattr(b, name)
        assert set(x) == set(y)
        for key in x:
            th.testing.assert_close(x[key], y[key], msg=f"{name}.{key}")
    for name in ("actions", "dones", "rewards", "discounts"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None:
            assert y is None
        else:
            th.testing.assert_close(x, y, msg=name)


class DictPointEnv(gym.Env):
    """A point that moves towards a goal: Dict observations of its position and of the goal."""

    observation_space = spaces.Dict({"goal": spaces.Box(-1, 1, (2,), np.float32), "pos": spaces.Box(-1, 1, (2,), np.float32)})
    action_space = spaces.Box(-1, 1, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.np_random.uniform(-1, 1, 2).astype(np.float32)
        self.goal = self.np_random.uniform(-1, 1, 2).astype(np.float32)
        self.steps = 0
        return self._obs(), {}

    def _obs(self):
        return {"goal": self.goal.copy(), "pos": self.pos.copy()}

    def step(self, action):
        self.pos = np.clip(self.pos + 0.2 * np.asarray(action, dtype=np.float32), -1, 1)
        self.steps += 1
        distance = float(np.linalg.norm(self.pos - self.goal))
        return self._obs(), -distance, distance < 0.1, self.steps >= 20, {}


# ---------------------------------------------------------------------------------------------- tests
def test_dict_same_samples_as_sb3():
    n_envs, steps = 2, 100
    ours = LifelongReplayBuffer(1000, OBS, ACT, device="cpu", n_envs=n_envs)
    ref = DictReplayBuffer(1000, OBS, ACT, device="cpu", n_envs=n_envs)
    fill(ours, steps, n_envs, seed=1)
    fill(ref, steps, n_envs, seed=1)
    batch_inds = np.arange(steps)
    np.random.seed(3)  # SB3 draws the env indices itself
    env_inds = np.random.randint(0, n_envs, size=steps)
    np.random.seed(3)
    expected = ref._get_samples(batch_inds)
    got = ours._get_samples(batch_inds * n_envs + env_inds)
    assert isinstance(got, DictReplayBufferSamples)
    for name in ("observations", "next_observations"):
        for key in OBS.spaces:
            a, b = getattr(expected, name)[key], getattr(got, name)[key]
            assert b.shape == a.shape and b.dtype == a.dtype, (name, key)
            th.testing.assert_close(b, a, msg=f"{name}.{key}")
    for name in ("actions", "dones", "rewards"):
        th.testing.assert_close(getattr(got, name), getattr(expected, name), msg=name)


def test_dict_on_disk_reopen_nstep_and_sources(tmp_path):
    path = tmp_path / "dict"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=32, n_steps=3, gamma=0.9)
    fill(buffer, 60, 2, stage=0)
    fill(buffer, 40, 1, seed=2, stage=1)
    before = all_rows(buffer)
    buffer.close()
    # one file per field and key, listed in a version 2 manifest
    manifest = json.loads((path / "manifest.json").read_text())
    assert manifest["version"] == 2 and manifest["num_transitions"] == 160
    assert manifest["fields"]["observations.image"] == {"dtype": "|u1", "shape": [2, 4, 4]}
    assert os.path.getsize(path / "next_observations.pos.bin") == 160 * 3 * 4
    assert not (path / "observations.bin").exists()
    reopened = LifelongReplayBuffer.open(path, n_steps=3, gamma=0.9)
    assert reopened.observation_space == OBS and reopened.obs_shape == {"image": (2, 4, 4), "mode": (1,), "pos": (3,)}
    for name, values in all_rows(reopened).items():
        np.testing.assert_array_equal(values, before[name], err_msg=name)
    assert reopened.source_counts() == {0: 120, 1: 40}
    # n-step returns and bootstrap observations: the same as those of a Box buffer holding the same rows
    twin = LifelongReplayBuffer(0, OBS["pos"], ACT, n_steps=3, gamma=0.9)
    rows = {name: values for name, values in before.items() if "." not in name}
    rows.update(observations=before["observations.pos"], next_observations=before["next_observations.pos"])
    twin.append_rows(rows)
    inds = np.arange(160)
    got, expected = reopened._get_samples(inds), twin._get_samples(inds)
    assert got.discounts is not None and (got.discounts < 0.9).any()
    for field in ("actions", "rewards", "dones", "discounts"):
        th.testing.assert_close(getattr(got, field), getattr(expected, field), msg=field)
    th.testing.assert_close(got.next_observations["pos"], expected.next_observations)
    # per-source weights and reward scales
    reopened.set_sampling_weights({0: 0.0})
    _, sources = reopened.sample(200, return_sources=True)
    assert set(sources.tolist()) == {1}
    reopened.set_reward_scale({1: 2.0})
    scaled = reopened._get_samples(np.arange(120, 160)).rewards
    reopened.set_reward_scale(None)
    th.testing.assert_close(scaled, 2 * reopened._get_samples(np.arange(120, 160)).rewards)
    # appending after a reopen
    fill(reopened, 10, 1, seed=5)
    reopened.close()
    assert LifelongReplayBuffer.open(path, read_only=True, verify="all").size() == 170


def test_dict_view_merge_and_sac(tmp_path):
    a = LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "a", chunk_size=16)
    b = LifelongReplayBuffer(0, OBS, ACT, n_steps=2)
    fill(a, 30, 1, stage=0)
    fill(b, 20, 2, seed=5, stage=1)
    view = LifelongBufferView([a, b], n_steps=2)
    samples = view.sample(40)
    assert isinstance(samples, DictReplayBufferSamples) and samples.observations["image"].shape == (40, 2, 4, 4)
    merged = merge_buffers([a, b], path=tmp_path / "m", n_steps=2)
    ra, rb, rm = all_rows(a), all_rows(b), all_rows(merged)
    for name in ("observations.image", "next_observations.mode", "actions", "sources"):
        np.testing.assert_array_equal(rm[name], np.concatenate([ra[name], rb[name]]))
    inds = np.arange(70)
    assert_same_samples(view._get_samples(inds), merged._get_samples(inds))
    box = LifelongReplayBuffer(0, OBS["pos"], ACT)
    with pytest.raises(ValueError, match="different observation"):
        LifelongBufferView([a, box])
    # SB3 would pick its DictReplayBuffer itself: the lifelong buffer trains a MultiInputPolicy as well
    model = SAC(
        "MultiInputPolicy",
        gym.wrappers.TimeLimit(DictPointEnv(), 20),
        learning_starts=40,
        batch_size=16,
        policy_kwargs=dict(net_arch=[16]),
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=str(tmp_path / "sac"), n_steps=2, gamma=0.98, chunk_size=50),
        device="cpu",
        seed=0,
    )
    model.learn(120)
    buffer = model.replay_buffer
    assert isinstance(buffer, LifelongReplayBuffer) and buffer.size() == 120
    rows = all_rows(buffer)
    assert set(rows) >= {"observations.goal", "observations.pos", "next_observations.goal"}
    ends = (rows["flags"] & 1) != 0
    # within an episode, next_observations[t] == observations[t + 1] (the goal is fixed during an episode)
    np.testing.assert_array_equal(rows["next_observations.pos"][:-1][~ends[:-1]], rows["observations.pos"][1:][~ends[:-1]])
    assert (rows["observations.goal"][1:][~ends[:-1]] == rows["observations.goal"][:-1][~ends[:-1]]).all()
    buffer.close()


@pytest.mark.parametrize("key", ["a/b", "../x", "", "a.b", "-x", "caf\u00e9", "x" * 65, 3])
def test_dict_key_names_must_be_safe_file_names(key):
    with pytest.raises(BufferFormatError, match="cannot name a field file"):
        LifelongReplayBuffer(0, spaces.Dict({key: spaces.Box(-1, 1, (2,))}), ACT)


def test_dict_errors(tmp_path):
    with pytest.raises(BufferFormatError, match="differ only by case"):
        LifelongReplayBuffer(0, spaces.Dict({"A": spaces.Box(-1, 1, (1,)), "a": spaces.Box(-1, 1, (1,))}), ACT)
    with pytest.raises(NotImplementedError, match="nested"):
        LifelongReplayBuffer(0, spaces.Dict({"a": spaces.Dict({"b": spaces.Box(-1, 1, (1,))})}), ACT)
    buffer = LifelongReplayBuffer(0, OBS, ACT)
    fill(buffer, 5, 1)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="expected a dict with the keys"):
        obs = random_obs(rng, 1)
        del obs["mode"]
        buffer.add(obs, random_obs(rng, 1), np.zeros((1, 2)), np.zeros(1), np.zeros(1), [{}])
    with pytest.raises(ValueError, match="expected a dict"):
        buffer.add(np.zeros((1, 3)), random_obs(rng, 1), np.zeros((1, 2)), np.zeros(1), np.zeros(1), [{}])
    for export in (buffer.to_d4rl, lambda: buffer.save_npz(tmp_path / "x.npz"), lambda: buffer.to_minari("dict/x-v0")):
        with pytest.raises(NotImplementedError, match="Dict observations is not supported"):
            export()
    with pytest.raises(NotImplementedError, match="Dict observation spaces are not supported"):
        LifelongReplayBuffer.from_d4rl(LifelongReplayBuffer(0, OBS["pos"], ACT).to_d4rl(), observation_space=OBS)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda m: m["fields"].update({"observations.../x": m["fields"]["observations.pos"]}), "cannot name a field file"),
        (lambda m: m["fields"].pop("next_observations.pos"), "fields"),
        (lambda m: m["fields"]["next_observations.pos"].update(shape=[4]), "next_observations.pos"),
        (lambda m: [m.pop(key) for key in ("layout", "capacity", "first_row")] and m.update(version=1), "version 2"),
    ],
)
def test_dict_hostile_manifest(tmp_path, mutate, message):
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=10)
    fill(buffer, 20, 1)
    buffer.close()
    manifest = json.loads((path / "manifest.json").read_text())
    mutate(manifest)
    (path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BufferFormatError, match=message):
        LifelongReplayBuffer.open(path, read_only=True)
