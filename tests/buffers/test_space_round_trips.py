"""
Safety v4 (issue 65), spaces: every space the constructor accepts reopens equal (bounds, dtype, ``nvec``, ``start``,
``n``) and exports and re-imports exactly (d4rl and Minari); every other space is refused at construction, with the
list of the supported ones.
"""

import json
import os

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError
from sb3_lifelong.buffers.schema import MAX_LISTED_ELEMENTS, MAX_SPACES_JSON_CHARS, SUPPORTED_SPACES

spaces = gym.spaces
BIG = MAX_LISTED_ELEMENTS + 100  # elements of a Box whose bounds are not written as a list
RAMP = np.linspace(-3.0, 3.0, BIG)

OBSERVATION_SPACES = {
    "box-f32-finite": spaces.Box(np.array([-1.5, 0.1, -2.0], np.float32), np.array([1.0, 0.3, 7.25], np.float32)),
    "box-f32-infinite": spaces.Box(np.array([-np.inf, 0.0], np.float32), np.array([1.0, np.inf], np.float32)),
    "box-f64": spaces.Box(np.array([-0.1, -np.inf]), np.array([0.7, 1e300]), dtype=np.float64),
    "box-big-uniform": spaces.Box(0, 255, (BIG,), np.uint8),
    "box-big-ramp": spaces.Box(RAMP.astype(np.float32), (RAMP + 1.0).astype(np.float32)),
    "box-big-ramp-inf": spaces.Box(np.where(RAMP > 0, -np.inf, RAMP), np.inf, (BIG,), np.float64),
    "box-int64": spaces.Box(np.array([-(2**62) - 1, 0]), np.array([2**62 + 1, 10]), dtype=np.int64),
    "box-int64-unbounded": spaces.Box(-np.inf, 5, (2,), np.int64),
    "box-int-big-ramp": spaces.Box(np.arange(BIG) - 5, np.arange(BIG) * 2, dtype=np.int32),
    "box-bool": spaces.Box(0, 1, (3,), bool),
    "discrete": spaces.Discrete(7, start=-2),
    "multidiscrete": spaces.MultiDiscrete([3, 5, 2], start=[0, -1, 4]),
    "multidiscrete-int32": spaces.MultiDiscrete(np.array([4, 9], np.int32), dtype=np.int32),
    "multibinary": spaces.MultiBinary(4),
    "multibinary-2d": spaces.MultiBinary((2, 3)),
}
ACTION_SPACES = {
    "box-f32": spaces.Box(np.array([-2.0, 0.0], np.float32), np.array([2.0, 10.0], np.float32)),
    "box-f64": spaces.Box(-1.0, 3.0, (2,), np.float64),
    "box-2d": spaces.Box(-1, 1, (2, 3), np.float32),
    "box-unbounded": spaces.Box(-np.inf, np.inf, (2,), np.float32),
    "box-int64": spaces.Box(0, 10, (2,), np.int64),
    "discrete": spaces.Discrete(5, start=1),
    "multidiscrete": spaces.MultiDiscrete([3, 5, 2]),
    "multibinary": spaces.MultiBinary(3),
}
DICT_SPACE = spaces.Dict(
    {
        "image": spaces.Box(0, 255, (BIG,), np.uint8),
        "pos": spaces.Box(-np.inf, 2.5, (2,), np.float32),
        "mode": spaces.Discrete(3),
        "switches": spaces.MultiBinary(2),
        "gears": spaces.MultiDiscrete([2, 4]),
    }
)
FLOAT_OBS = spaces.Box(-np.inf, np.inf, (2,), np.float32)
FLOAT_ACT = spaces.Box(-1, 1, (2,), np.float32)


def assert_same_space(got, expected):
    """Equal, and exactly so: gymnasium's == compares Box bounds with a tolerance and ignores what is unbounded."""
    assert got == expected and expected == got, (got, expected)
    assert type(got) is type(expected)
    if isinstance(expected, spaces.Dict):
        assert list(got.spaces) == list(expected.spaces)
        for key in expected.spaces:
            assert_same_space(got[key], expected[key])
        return
    assert got.dtype == expected.dtype and got.shape == expected.shape
    if isinstance(expected, spaces.Box):
        for name in ("low", "high", "bounded_below", "bounded_above"):
            np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), err_msg=name)
            assert getattr(got, name).dtype == getattr(expected, name).dtype, name
    elif isinstance(expected, spaces.MultiDiscrete):
        np.testing.assert_array_equal(got.nvec, expected.nvec)
        np.testing.assert_array_equal(got.start, expected.start)
        assert got.nvec.dtype == expected.nvec.dtype
    elif isinstance(expected, spaces.MultiBinary):
        assert got.n == expected.n
    elif isinstance(expected, spaces.Discrete):
        assert (got.n, got.start) == (expected.n, expected.start)


def samples(space, count, seed):
    space.seed(seed)
    if isinstance(space, spaces.Box) and np.dtype(space.dtype).kind == "f":
        # gymnasium samples an unbounded Box from a normal distribution; keep the values within float32 and exact
        return np.stack([np.clip(space.sample(), -1e30, 1e30).astype(space.dtype) for _ in range(count)])
    return np.stack([np.asarray(space.sample()) for _ in range(count)])


def fill(buffer, observation_space, action_space, count=6):
    obs = samples(observation_space, count + 1, 0)
    actions = samples(action_space, count, 1)
    if isinstance(action_space, spaces.Box) and np.dtype(action_space.dtype).kind == "f":
        actions = np.clip(actions, -1, 1)  # SB3 stores a float Box's actions normalised
    for i in range(count):
        buffer.add(
            obs[i : i + 1], obs[i + 1 : i + 2], actions[i : i + 1], np.array([float(i)]), np.array([i == count - 1]), [{}]
        )
    return obs, actions


def written_and_reopened(tmp_path, observation_space, action_space):
    path = tmp_path / "buffer"
    with LifelongReplayBuffer(0, observation_space, action_space, path=path, chunk_size=4, device="cpu") as buffer:
        fill(buffer, observation_space, action_space)
        stored = {name: buffer.read_range(name, 0, buffer.size()).copy() for name in ("observations", "actions")}
    reopened = LifelongReplayBuffer.open(path, read_only=True, device="cpu")
    return reopened, stored


@pytest.mark.parametrize("name", sorted(OBSERVATION_SPACES))
def test_observation_space_reopens_equal_and_exports_exactly(tmp_path, name):
    space = OBSERVATION_SPACES[name]
    reopened, stored = written_and_reopened(tmp_path, space, FLOAT_ACT)
    assert_same_space(reopened.observation_space, space)
    assert_same_space(reopened.action_space, FLOAT_ACT)
    np.testing.assert_array_equal(reopened.read_range("observations", 0, reopened.size()), stored["observations"])
    data = reopened.to_d4rl(by_episode=False)
    assert data["observations"].dtype == np.dtype(space.dtype)
    np.testing.assert_array_equal(data["observations"].reshape(stored["observations"].shape), stored["observations"])
    copy = LifelongReplayBuffer.from_d4rl(data, observation_space=space, action_space=FLOAT_ACT, device="cpu")
    assert_same_space(copy.observation_space, space)
    for field in ("observations", "next_observations", "actions", "rewards", "flags"):
        np.testing.assert_array_equal(copy.read_range(field, 0, copy.size()), reopened.read_range(field, 0, reopened.size()))


@pytest.mark.parametrize("name", sorted(ACTION_SPACES))
def test_action_space_reopens_equal_and_exports_exactly(tmp_path, name):
    space = ACTION_SPACES[name]
    reopened, stored = written_and_reopened(tmp_path, FLOAT_OBS, space)
    assert_same_space(reopened.action_space, space)
    actions = reopened.read_range("actions", 0, reopened.size())
    np.testing.assert_array_equal(actions, stored["actions"].reshape(actions.shape))
    exported = reopened.to_d4rl(by_episode=False)["actions"]
    if isinstance(space, spaces.Box) and np.dtype(space.dtype).kind == "f" and space.is_bounded() and name != "box-2d":
        assert not np.array_equal(exported, actions)  # in the env's units: rescaled from [-1, 1]
    else:  # unbounded, [-1, 1], integer Box, Discrete, MultiDiscrete, MultiBinary: the values stored
        np.testing.assert_array_equal(exported, actions)
        assert exported.dtype == actions.dtype
    copy = LifelongReplayBuffer.from_d4rl(reopened.to_d4rl(by_episode=False), FLOAT_OBS, space, device="cpu")
    assert_same_space(copy.action_space, space)
    again = copy.read_range("actions", 0, copy.size())
    if isinstance(space, spaces.Box) and np.dtype(space.dtype).kind == "f":
        np.testing.assert_allclose(again, actions, atol=1e-6)  # rescaled there and back, in float64
    else:
        np.testing.assert_array_equal(again, actions)


def test_integer_box_actions_export_unscaled(tmp_path):
    """The issue's case: [1, 2] stored in Box(0, 10, int64) exported as [10, 15] (rescaled as if normalised)."""
    space = spaces.Box(0, 10, (2,), np.int64)
    with LifelongReplayBuffer(0, FLOAT_OBS, space, path=tmp_path / "b", device="cpu") as buffer:
        buffer.add(np.zeros((1, 2)), np.ones((1, 2)), np.array([[1, 2]]), np.array([0.0]), np.array([True]), [{}])
    reopened = LifelongReplayBuffer.open(tmp_path / "b", read_only=True)
    for normalized in (False, True):
        exported = reopened.to_d4rl(normalized_actions=normalized)["actions"]
        np.testing.assert_array_equal(exported, [[1, 2]])
        assert exported.dtype == np.int64
    # an import stores integer actions as they are, exactly, or refuses them
    data = reopened.to_d4rl()
    assert LifelongReplayBuffer.from_d4rl(data, FLOAT_OBS, space).read_range("actions", 0, 1).tolist() == [[1, 2]]
    with pytest.raises(ValueError, match="fractional"):
        LifelongReplayBuffer.from_d4rl({**data, "actions": np.array([[0.5, 2.0]])}, FLOAT_OBS, space)


def test_multidiscrete_and_multibinary_export_their_values(tmp_path):
    """The issue's case: a MultiDiscrete reopened as a Box at int64's minimum exported every action as -9.2e18."""
    obs_space, act_space = spaces.MultiDiscrete([3, 4]), spaces.MultiDiscrete([2, 6])
    with LifelongReplayBuffer(0, obs_space, act_space, path=tmp_path / "b", device="cpu") as buffer:
        buffer.add(np.array([[2, 3]]), np.array([[1, 0]]), np.array([[1, 5]]), np.array([0.0]), np.array([True]), [{}])
    data = LifelongReplayBuffer.open(tmp_path / "b", read_only=True).to_d4rl()
    assert data["actions"].tolist() == [[1, 5]] and data["observations"].tolist() == [[2, 3]]


def test_dict_observation_space_reopens_equal(tmp_path):
    path = tmp_path / "dict"
    with LifelongReplayBuffer(0, DICT_SPACE, ACTION_SPACES["multibinary"], path=path, device="cpu") as buffer:
        for i in range(3):
            obs = {key: samples(sub, 1, i) for key, sub in DICT_SPACE.spaces.items()}
            buffer.add(obs, obs, np.array([[1, 0, 1]]), np.array([0.0]), np.array([False]), [{}])
    reopened = LifelongReplayBuffer.open(path, read_only=True)
    assert_same_space(reopened.observation_space, DICT_SPACE)
    assert_same_space(reopened.action_space, ACTION_SPACES["multibinary"])


def test_large_bounds_are_not_written_as_lists(tmp_path):
    """Bounds of more than MAX_LISTED_ELEMENTS elements: one value when uniform, compressed otherwise."""
    space = OBSERVATION_SPACES["box-big-ramp"]
    LifelongReplayBuffer(
        0, spaces.Dict({"u": OBSERVATION_SPACES["box-big-uniform"], "r": space}), FLOAT_ACT, path=tmp_path
    ).close()
    with open(os.path.join(tmp_path, "manifest.json")) as file:
        described = json.load(file)["spaces"]["observation"]["spaces"]
    assert described["u"]["low"] == {"fill": 0} and described["u"]["high"] == {"fill": 255}
    assert set(described["r"]["low"]) == {"zlib"}


@pytest.mark.parametrize("name", sorted(OBSERVATION_SPACES))
def test_minari_round_trip(tmp_path, monkeypatch, name):
    pytest.importorskip("minari")
    space = OBSERVATION_SPACES[name]
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    reopened, _ = written_and_reopened(tmp_path, space, ACTION_SPACES["box-int64"])
    dataset = reopened.to_minari(f"test/{name}-v0")
    copy = LifelongReplayBuffer.from_minari(dataset)
    assert_same_space(copy.observation_space, space)
    assert_same_space(copy.action_space, ACTION_SPACES["box-int64"])
    for field in ("observations", "next_observations", "actions", "rewards"):
        np.testing.assert_array_equal(copy.read_range(field, 0, copy.size()), reopened.read_range(field, 0, reopened.size()))


REFUSED = {  # id: (observation space, action space, what the message names)
    "Tuple": (spaces.Tuple([FLOAT_OBS]), FLOAT_ACT, "observation space Tuple"),
    "Text": (spaces.Text(5), FLOAT_ACT, "observation space Text"),
    "Sequence": (spaces.Sequence(FLOAT_OBS), FLOAT_ACT, "observation space Sequence"),
    "nested Dict": (spaces.Dict({"a": spaces.Dict({"b": FLOAT_OBS})}), FLOAT_ACT, "key 'a': nested Dict"),
    "Dict action": (FLOAT_OBS, spaces.Dict({"a": FLOAT_ACT}), "action space Dict"),
    "Tuple action": (FLOAT_OBS, spaces.Tuple([FLOAT_ACT]), "action space Tuple"),
    "2-D nvec": (spaces.MultiDiscrete([[2, 3], [4, 5]]), FLOAT_ACT, r"MultiDiscrete of nvec shape \(2, 2\)"),
    "2-D MultiBinary action": (FLOAT_OBS, spaces.MultiBinary((2, 2)), "MultiBinary action space of several dimensions"),
    "empty Box": (spaces.Box(np.inf, np.inf, (2,), np.float32), FLOAT_ACT, r"a low of \+inf"),
}


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_unsupported_space_refused_at_construction(tmp_path, name):
    observation_space, action_space, named = REFUSED[name]
    path = tmp_path / "refused"
    with pytest.raises(NotImplementedError, match=named) as error:
        LifelongReplayBuffer(0, observation_space, action_space, path=path)
    assert SUPPORTED_SPACES in str(error.value)
    assert not path.exists()  # before anything is written


def test_incompressible_large_bounds_refused_at_construction(tmp_path):
    rng = np.random.default_rng(0)
    size = MAX_SPACES_JSON_CHARS // 4  # float64 bounds of random bits: about 2 x 8 x 4 / 3 characters each
    low = rng.standard_normal(size)
    with pytest.raises(ValueError, match="MAX_SPACES_JSON_CHARS"):
        LifelongReplayBuffer(0, spaces.Box(low, low + 1, dtype=np.float64), FLOAT_ACT, path=tmp_path / "big")
    assert not (tmp_path / "big").exists()


def test_a_description_that_does_not_match_its_fields_is_refused(tmp_path):
    LifelongReplayBuffer(0, spaces.MultiDiscrete([3, 4]), FLOAT_ACT, path=tmp_path).close()
    manifest = os.path.join(tmp_path, "manifest.json")
    with open(manifest) as file:
        data = json.load(file)
    data["spaces"]["observation"]["nvec"] = [3, 4, 5]
    with open(manifest, "w") as file:
        json.dump(data, file)
    with pytest.raises(BufferFormatError, match="'spaces' do not describe"):
        LifelongReplayBuffer.open(tmp_path, read_only=True)
