"""
Loading runs code, unless asked not to: SB3's load (and load_replay_buffer) unpickle a tampered file's payload, as
the docs warn; ``load(..., safe=True)`` unpickles only what a model of this package saves and refuses the rest.
"""

import base64
import json
import pickle
import zipfile

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_lifelong import BC, CRR, MPO, LifelongReplayBuffer

SMALL = dict(policy_kwargs=dict(net_arch=[8]), learning_starts=10, batch_size=8, seed=0)


class Payload:
    """What an attacker pickles: unpickling it runs ``code``."""

    def __init__(self, code: str):
        self.code = code

    def __reduce__(self):
        return exec, (self.code,)


class CallsAClass:
    """A pickle that calls a class safe=True allows only as a reference (here: a buffer that deletes a directory)."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        space = gym.spaces.Box(-1, 1, (2,))
        # positional up to mode="overwrite": LifelongReplayBuffer(0, ..., path=self.path, ..., mode="overwrite")
        args = (0, space, space, "cpu", 1, False, True, 1, 0.99, self.path, False, 10, "last", 0, None, None, "mmap")
        return LifelongReplayBuffer, (*args, "overwrite")


def tamper(source, target, key: str, payload: object) -> None:
    """Copy a saved model, replacing the pickle of ``data[key]``."""
    with zipfile.ZipFile(source) as archive:
        files = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(files["data"])
    data[key][":serialized:"] = base64.b64encode(pickle.dumps(payload)).decode()
    files["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(target, "w") as archive:
        for name, content in files.items():
            archive.writestr(name, content)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    root = tmp_path_factory.mktemp("saved")
    model = MPO("MlpPolicy", "Pendulum-v1", num_samples=2, **SMALL)
    model.learn(12)
    model.save(root / "mpo.zip")
    return root


def test_loading_a_tampered_zip_runs_its_payload_unless_safe(saved, tmp_path):
    marker = tmp_path / "pwned"
    tamper(saved / "mpo.zip", tmp_path / "tampered.zip", "observation_space", Payload(f"open({str(marker)!r}, 'w')"))
    with pytest.raises(pickle.UnpicklingError, match=r"data\['observation_space'\]: the pickle asks for builtins\.exec"):
        MPO.load(tmp_path / "tampered.zip", safe=True)
    assert not marker.exists()  # refused before anything ran
    with pytest.raises(Exception):  # noqa: B017 (whatever SB3 makes of the payload's result)
        MPO.load(tmp_path / "tampered.zip")  # the default, as SB3: the payload runs
    assert marker.exists()


def test_safe_load_refuses_calling_a_class_it_may_only_refer_to(saved, tmp_path):
    victim = tmp_path / "victim"
    with LifelongReplayBuffer(0, gym.spaces.Box(-1, 1, (2,)), gym.spaces.Box(-1, 1, (2,)), path=victim) as buffer:
        buffer.add(np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 2)), np.zeros(1), np.zeros(1), [{}])
    tamper(saved / "mpo.zip", tmp_path / "tampered.zip", "replay_buffer_kwargs", {"x": CallsAClass(str(victim))})
    with pytest.raises(pickle.UnpicklingError, match=r"calls sb3_lifelong\.buffers\.lifelong\.LifelongReplayBuffer: refused"):
        MPO.load(tmp_path / "tampered.zip", safe=True)
    with LifelongReplayBuffer.open(victim, read_only=True) as kept:
        assert kept.size() == 1


def test_a_tampered_replay_buffer_pickle_runs_its_payload(saved, tmp_path):
    """load_replay_buffer is SB3's pickle load: the caveat holds (directory buffers: reopen them by path instead)."""
    marker = tmp_path / "pwned"
    with open(tmp_path / "buffer.pkl", "wb") as file:
        pickle.dump(Payload(f"open({str(marker)!r}, 'w')"), file)
    model = MPO.load(saved / "mpo.zip", safe=True)
    with pytest.raises(Exception):  # noqa: B017
        model.load_replay_buffer(tmp_path / "buffer.pkl")
    assert marker.exists()


class DictObs(gym.ObservationWrapper):
    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.observation_space = gym.spaces.Dict({"state": env.observation_space, "scale": gym.spaces.Box(0, 1, (1,))})

    def observation(self, observation):
        return {"state": observation, "scale": np.ones(1, dtype=np.float32)}


def offline_buffer() -> LifelongReplayBuffer:
    buffer = LifelongReplayBuffer(100, gym.spaces.Box(-1, 1, (3,), np.float32), gym.spaces.Box(-1, 1, (2,), np.float32))
    rng = np.random.default_rng(0)
    for _ in range(40):
        obs = rng.uniform(-1, 1, (1, 3)).astype(np.float32)
        buffer.add(obs, obs, rng.uniform(-1, 1, (1, 2)), np.ones(1), np.zeros(1), [{}])
    return buffer


def trained(kind: str, tmp_path):
    if kind == "MPO Box, directory buffer, activation class":
        kwargs = dict(SMALL, policy_kwargs=dict(net_arch=[8], activation_fn=th.nn.ELU))
        model = MPO(
            "MlpPolicy",
            "Pendulum-v1",
            num_samples=2,
            replay_buffer_class=LifelongReplayBuffer,
            replay_buffer_kwargs=dict(path=tmp_path / "buffer", chunk_size=8),  # a pathlib path, pickled
            **kwargs,
        )
        model.learn(12)
    elif kind == "MPO Dict":
        model = MPO("MultiInputPolicy", DictObs(gym.make("Pendulum-v1")), num_samples=2, **SMALL)
        model.learn(12)
    else:
        algorithm = CRR if kind == "CRR" else BC
        model = algorithm.from_offline_data(offline_buffer(), policy_kwargs=dict(net_arch=[8]), batch_size=8, seed=0)
        model.learn_offline(3)
    model.save(tmp_path / "model.zip")
    if hasattr(model.replay_buffer, "close"):
        model.replay_buffer.close()
    return type(model)


@pytest.mark.parametrize("kind", ["MPO Box, directory buffer, activation class", "MPO Dict", "CRR", "BC"])
def test_safe_load_loads_what_this_package_saves(tmp_path, kind):
    algorithm = trained(kind, tmp_path)
    safe = algorithm.load(tmp_path / "model.zip", safe=True)
    usual = algorithm.load(tmp_path / "model.zip", replay_buffer_kwargs={})
    for a, b in zip(safe.policy.parameters(), usual.policy.parameters()):
        th.testing.assert_close(a, b, rtol=0, atol=0)
    assert safe.observation_space == usual.observation_space and safe.action_space == usual.action_space
    assert safe.action_space.np_random.bit_generator.state == usual.action_space.np_random.bit_generator.state
    assert safe.policy_kwargs == usual.policy_kwargs and safe.replay_buffer_class is usual.replay_buffer_class
    assert safe.lr_schedule(0.5) == usual.lr_schedule(0.5)
    obs = safe.observation_space.sample()
    np.testing.assert_array_equal(safe.predict(obs, deterministic=True)[0], usual.predict(obs, deterministic=True)[0])
    if kind.startswith("MPO Box"):
        assert safe.replay_buffer.size() == 12 and safe.policy_kwargs["activation_fn"] is th.nn.ELU
        safe.replay_buffer.close()


def test_a_schedule_saved_as_a_function_is_code(tmp_path):
    model = MPO("MlpPolicy", "Pendulum-v1", num_samples=2, learning_rate=lambda progress: 1e-3 * progress, **SMALL)
    model.learn(12)
    model.save(tmp_path / "model.zip")
    with pytest.raises(pickle.UnpicklingError, match=r"data\['learning_rate'\]: the pickle asks for cloudpickle"):
        MPO.load(tmp_path / "model.zip", safe=True)
    given = MPO.load(tmp_path / "model.zip", safe=True, custom_objects={"learning_rate": 1e-3, "lr_schedule": lambda _: 1e-3})
    assert given.lr_schedule(0.3) == 1e-3


# ---------------------------------------------------------------------------------------- loading never writes
PENDULUM_OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
PENDULUM_ACT = gym.spaces.Box(-2, 2, (1,), np.float32)


@pytest.fixture(scope="module")
def memory_buffer_zip(tmp_path_factory):
    """A model whose replay buffer is a LifelongReplayBuffer in memory: its zip names no directory."""
    root = tmp_path_factory.mktemp("memory")
    model = MPO("MlpPolicy", "Pendulum-v1", num_samples=2, replay_buffer_class=LifelongReplayBuffer, **SMALL)
    model.learn(12)
    model.save(root / "mpo.zip")
    return root / "mpo.zip"


def craft(source, target, replay_buffer_kwargs: dict) -> None:
    """What anyone can do to a zip: its replay_buffer_kwargs are plain JSON."""
    with zipfile.ZipFile(source) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(entries["data"])
    data["replay_buffer_kwargs"] = replay_buffer_kwargs
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(target, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)


def files_of(directory) -> dict:
    import os

    found = {}
    for root, _, names in os.walk(directory):
        for name in names:
            with open(os.path.join(root, name), "rb") as file:
                found[os.path.relpath(os.path.join(root, name), directory)] = file.read()
    return found


def victim_buffer(path, rows: int) -> None:
    """Someone's lifetime buffer (capacity 500), ``rows`` transitions."""
    with LifelongReplayBuffer(0, PENDULUM_OBS, PENDULUM_ACT, path=path, capacity=500, chunk_size=50) as buffer:
        for k in range(rows):
            obs = np.full((1, 3), k, np.float32)
            buffer.add(obs, obs, np.zeros((1, 1), np.float32), np.array([k], np.float32), np.array([False]), [{}])


@pytest.mark.parametrize("safe", [True, False])
def test_a_crafted_zip_cannot_evict_another_buffer(memory_buffer_zip, tmp_path, safe):
    """Before: loading the zip only to evaluate its policy evicted 499 of the victim's 500 transitions."""
    victim_buffer(tmp_path / "victim", 500)
    before = files_of(tmp_path / "victim")
    crafted = dict(path=str(tmp_path / "victim"), capacity=1, evict=True, mode="overwrite", chunk_size=1)
    craft(memory_buffer_zip, tmp_path / "crafted.zip", crafted)
    model = MPO.load(tmp_path / "crafted.zip", safe=safe)
    model.predict(np.zeros(3, np.float32), deterministic=True)  # evaluated
    del model
    assert files_of(tmp_path / "victim") == before  # byte-identical: nothing evicted, cut, locked or rewritten
    with LifelongReplayBuffer.open(tmp_path / "victim", read_only=True) as kept:
        assert kept.size() == 500 and kept.capacity == 500


def test_learning_after_loading_a_crafted_zip_never_applies_its_capacity(memory_buffer_zip, tmp_path):
    """learn() continues the directory (it appends), never with the zip's capacity, evict or mode."""
    victim_buffer(tmp_path / "victim", 100)
    first = files_of(tmp_path / "victim")["chunk.000000000000.bin"]
    craft(memory_buffer_zip, tmp_path / "crafted.zip", dict(path=str(tmp_path / "victim"), capacity=1, evict=True))
    model = MPO.load(tmp_path / "crafted.zip", env=gym.make("Pendulum-v1"), safe=True)
    model.learn(20, reset_num_timesteps=False)
    assert model.replay_buffer.size() == 120 and model.replay_buffer.capacity == 500
    model.replay_buffer.close()
    assert files_of(tmp_path / "victim")["chunk.000000000000.bin"] == first  # its first rows, untouched


@pytest.mark.parametrize("relative", [False, True])
def test_a_bare_path_in_a_zip_creates_nothing(memory_buffer_zip, tmp_path, monkeypatch, relative):
    """Before: loading created a buffer directory where the zip said."""
    monkeypatch.chdir(tmp_path)
    where = "elsewhere/buffer" if relative else str(tmp_path / "elsewhere" / "buffer")
    craft(memory_buffer_zip, tmp_path / "crafted.zip", dict(path=where))
    with pytest.warns(UserWarning, match=r"not attached: there is no buffer at .*elsewhere/buffer.*Nothing was written"):
        model = MPO.load(tmp_path / "crafted.zip", env=gym.make("Pendulum-v1"), safe=True)
    assert model.replay_buffer.path is None and not (tmp_path / "elsewhere").exists()
    with pytest.raises(FileNotFoundError, match=r"cannot resume .*there is no buffer at .*replay_buffer_kwargs"):
        model.learn(5)
    assert not (tmp_path / "elsewhere").exists()
