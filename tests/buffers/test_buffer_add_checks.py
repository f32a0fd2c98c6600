"""LifelongReplayBuffer refuses data it would store wrongly: non-finite values, shapes that do not fit the spaces."""

import re
import types

import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers.manifest import FIELD_NAMES

OBS = spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = spaces.Box(-1, 1, (2,), np.float32)


def args(n_envs, seed=0):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n_envs, 3)).astype(np.float32)
    return {
        "obs": obs,
        "next_obs": obs + 1,
        "action": rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32),
        "reward": rng.normal(size=n_envs).astype(np.float32),
        "done": np.zeros(n_envs, dtype=bool),
        "infos": [{} for _ in range(n_envs)],
    }


def stored(buffer):
    return {name: np.array(buffer.store.read_range(name, 0, buffer.size())) for name in buffer.store.fields}


def assert_unchanged(buffer, before):
    after = stored(buffer)
    assert after.keys() == before.keys()
    for name in before:
        np.testing.assert_array_equal(after[name], before[name], err_msg=name)


@pytest.fixture(params=["memory", "directory"])
def buffer(request, tmp_path):
    path = None if request.param == "memory" else tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=path, chunk_size=7)
    for seed in range(5):  # one chunk committed, a few rows pending
        buffer.add(**args(2, seed))
    return buffer


# ---------------------------------------------------------------------------------------------- non-finite values
@pytest.mark.parametrize("field", ["obs", "next_obs", "action", "reward"])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("n_envs", [1, 3])
def test_add_refuses_non_finite(buffer, field, value, n_envs):
    before, counts = stored(buffer), buffer.source_counts()
    bad = args(n_envs, seed=9)
    bad[field] = bad[field].copy()
    bad[field][n_envs - 1] = value  # the last env
    name = {"obs": "observations", "next_obs": "next_observations", "action": "actions", "reward": "rewards"}[field]
    with pytest.raises(ValueError, match=rf"{name}\b.*env {n_envs - 1}\b.*not finite"):
        buffer.add(**bad)
    assert buffer.size() == 10 and buffer.source_counts() == counts
    assert_unchanged(buffer, before)
    buffer.add(**args(3, seed=10))  # the buffer keeps working
    assert buffer.size() == 13
    np.testing.assert_array_equal(stored(buffer)["rewards"][10:], args(3, seed=10)["reward"])


@pytest.mark.parametrize("first, second", [("obs", "next_obs"), ("next_obs", "obs")])
def test_add_refuses_non_finite_facing_zeros(buffer, first, second):
    """One element non-finite, the same element of the other observation 0 (a check by products must still see it)."""
    bad = args(2)
    bad[first], bad[second] = np.ones((2, 3), np.float32), np.zeros((2, 3), np.float32)
    for value in (np.inf, -np.inf, np.nan):
        bad[first][1, 2] = value
        with pytest.raises(ValueError, match=r"observations\b.*env 1\b.*not finite"):
            buffer.add(**bad)
    assert buffer.size() == 10


def test_add_accepts_large_finite_values(buffer):
    """Values whose squares overflow float32 are finite: stored."""
    big = args(2)
    big["obs"] = np.full((2, 3), 3e38, np.float32)
    big["next_obs"] = -big["obs"]
    big["action"] = np.full((2, 2), -3e38, np.float32)
    big["reward"] = np.full(2, 3e38, np.float32)
    buffer.add(**big)
    np.testing.assert_array_equal(stored(buffer)["observations"][-2:], big["obs"])


@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")
def test_add_refuses_values_that_overflow_the_stored_dtype(buffer):
    bad = args(1)
    bad["action"] = np.array([[1e39, 0.0]])  # finite in float64, inf once stored as float32
    with pytest.raises(ValueError, match=r"actions\b.*env 0\b.*not finite"):
        buffer.add(**bad)
    assert buffer.size() == 10


def test_add_refuses_non_finite_dict_observations():
    space = spaces.Dict({"pos": spaces.Box(-1, 1, (3,), np.float32), "image": spaces.Box(0, 255, (2, 2), np.uint8)})
    buffer = LifelongReplayBuffer(0, space, ACT, device="cpu")
    obs = {"pos": np.zeros((2, 3), np.float32), "image": np.zeros((2, 2, 2), np.uint8)}
    good = dict(args(2), obs=obs, next_obs=obs)
    buffer.add(**good)
    bad_pos = np.zeros((2, 3), np.float32)
    bad_pos[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"next_observations\['pos'\].*env 1\b.*not finite"):
        buffer.add(**dict(good, next_obs={"pos": bad_pos, "image": obs["image"]}))
    image = np.ones((2, 2, 2))
    image[1, 0, 1] = np.nan
    with pytest.raises(ValueError, match=r"observations\['image'\].*env 1\b.*not finite"):  # float given for uint8
        buffer.add(**dict(good, obs={"pos": obs["pos"], "image": image}))
    assert buffer.size() == 2


def d4rl_data(rows=20):
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(rows + 1, 3)).astype(np.float32)
    return {
        "observations": obs[:-1],
        "next_observations": obs[1:],
        "actions": rng.uniform(-1, 1, (rows, 2)).astype(np.float32),
        "rewards": rng.normal(size=rows).astype(np.float32),
        "terminals": np.zeros(rows, dtype=bool),
    }


@pytest.mark.parametrize("key", ["observations", "next_observations", "actions", "rewards"])
def test_from_d4rl_refuses_non_finite(tmp_path, key):
    data = d4rl_data()
    data[key] = data[key].copy()
    data[key][7] = np.nan
    data[key][12] = np.inf
    with pytest.raises(ValueError, match=rf"{key}\b.*row 7\b.*not finite"):
        LifelongReplayBuffer.from_d4rl(data, path=tmp_path / "b")
    assert not (tmp_path / "b").exists()  # refused before anything was created
    np.savez(tmp_path / "data.npz", **data)
    with pytest.raises(ValueError, match=rf"data.npz.*{key}\b.*row 7\b.*not finite"):
        LifelongReplayBuffer.from_d4rl(tmp_path / "data.npz")
    data[key][[7, 12]] = 0.0
    assert LifelongReplayBuffer.from_d4rl(data).size() == 20


class FakeMinari:
    """A duck-typed Minari dataset (``iterate_episodes``, spaces): two episodes."""

    def __init__(self, bad_key=None):
        rng = np.random.default_rng(1)
        self.observation_space, self.action_space, self.id = OBS, ACT, "fake/test-v0"
        self.episodes = []
        for steps in (5, 6):
            episode = types.SimpleNamespace(
                id=len(self.episodes),
                observations=rng.normal(size=(steps + 1, 3)).astype(np.float32),
                actions=rng.uniform(-1, 1, (steps, 2)).astype(np.float32),
                rewards=rng.normal(size=steps),
                terminations=np.arange(steps) == steps - 1,
                truncations=np.zeros(steps, dtype=bool),
                infos={},
            )
            self.episodes.append(episode)
        if bad_key is not None:  # transition 7 overall (episode 1, step 2)
            getattr(self.episodes[1], bad_key)[2] = np.nan

    def iterate_episodes(self):
        return iter(self.episodes)


@pytest.mark.parametrize(
    "key, field, row", [("observations", "observations", 7), ("actions", "actions", 7), ("rewards", "rewards", 7)]
)
def test_from_minari_refuses_non_finite(tmp_path, key, field, row):
    assert LifelongReplayBuffer.from_minari(FakeMinari()).size() == 11
    with pytest.raises(ValueError, match=rf"{field}\b.*row {row}\b.*not finite"):
        LifelongReplayBuffer.from_minari(FakeMinari(key), path=tmp_path / "b")
    assert not (tmp_path / "b").exists()


# ---------------------------------------------------------------------------------------------- shapes
@pytest.mark.parametrize(
    "change, field, expected",
    [
        (dict(obs=np.zeros((3, 2), np.float32)), "observations", r"\(2, 3\)"),  # transposed: no longer scrambled
        (dict(next_obs=np.zeros((2, 4), np.float32)), "next_observations", r"\(2, 3\)"),
        (dict(obs=np.zeros((4, 3), np.float32)), "observations", r"\(2, 3\)"),
        (dict(action=np.zeros((2, 3), np.float32)), "actions", r"\(2, 2\)"),  # wrong element count
        (dict(action=np.zeros(4, np.float32)), "actions", r"\(2, 2\)"),  # flat: SB3 would reshape it
        (dict(done=np.zeros(3, bool)), "dones", r"\(2,\)"),
        (dict(reward=np.zeros((2, 1), np.float32)), "rewards", r"\(n_envs,\)"),
        (dict(infos=[]), "infos", "2 envs"),
        (dict(infos=[{}, {}, {}]), "infos", "2 envs"),
    ],
)
def test_add_checks_shapes(buffer, change, field, expected):
    before = stored(buffer)
    with pytest.raises(ValueError, match=rf"{field}\b.*{expected}") as error:
        buffer.add(**dict(args(2), **change))
    got = next(iter(change.values()))
    assert str(getattr(got, "shape", len(got))) in str(error.value)
    assert buffer.size() == 10
    assert_unchanged(buffer, before)


def test_add_transposed_actions_refused_for_three_envs(buffer):
    with pytest.raises(ValueError, match=r"actions.*shape \(2, 3\), expected \(3, 2\)"):
        buffer.add(**dict(args(3), action=np.zeros((2, 3), np.float32)))


def test_add_dict_observation_shapes():
    space = spaces.Dict({"pos": spaces.Box(-1, 1, (3,), np.float32), "mode": spaces.Discrete(4)})
    buffer = LifelongReplayBuffer(0, space, ACT, device="cpu")
    obs = {"pos": np.zeros((2, 3), np.float32), "mode": np.array([1, 2])}
    buffer.add(**dict(args(2), obs=obs, next_obs=obs))
    with pytest.raises(ValueError, match=r"observations\['pos'\].*shape \(3, 2\), expected \(2, 3\)"):
        buffer.add(**dict(args(2), obs=dict(obs, pos=np.zeros((3, 2), np.float32)), next_obs=obs))
    with pytest.raises(ValueError, match=r"next_observations\['mode'\]"):
        buffer.add(**dict(args(2), obs=obs, next_obs=dict(obs, mode=np.array([1, 2, 3]))))
    with pytest.raises(ValueError, match="keys"):
        buffer.add(**dict(args(2), obs={"pos": obs["pos"]}, next_obs=obs))
    assert buffer.size() == 2


OBS_2D = spaces.Box(-1, 1, (2, 2), np.float32)


@pytest.mark.parametrize(
    "observation_space, action_space, n_envs, shapes",
    [
        (OBS, ACT, 1, dict(obs=(3,), next_obs=(1, 3), action=(2,), reward=(), done=())),  # one env, unbatched
        (OBS, ACT, 1, dict(obs=(1, 3), next_obs=(1, 1, 3), action=(1, 2), reward=(1,), done=(1,))),
        (OBS, ACT, 3, dict(obs=(3,), next_obs=(1, 3), action=(3, 2), reward=(3,), done=(1, 3))),  # broadcast obs
        (spaces.Discrete(5), spaces.Discrete(4), 3, dict(obs=(3,), next_obs=(3, 1), action=(3,), reward=(3,), done=(3,))),
        (spaces.Discrete(5), spaces.Discrete(4), 3, dict(obs=(3, 1), next_obs=(3,), action=(3, 1), reward=(3,), done=(3,))),
        (OBS_2D, spaces.Box(-1, 1, (2, 2), np.float32), 2, dict(obs=(2, 2, 2), next_obs=(2, 2), action=(2, 2, 2))),
        (OBS_2D, spaces.Box(-1, 1, (2, 2), np.float32), 2, dict(obs=(2, 2, 2), next_obs=(2, 2, 2), action=(2, 4))),
    ],
)
def test_add_accepts_what_sb3_accepts(observation_space, action_space, n_envs, shapes):
    """The shapes SB3's ReplayBuffer.add accepts for n_envs envs are accepted, and stored as SB3 stores them."""
    rng = np.random.default_rng(0)
    shapes = {"reward": (n_envs,), "done": (n_envs,), **shapes}

    def value(name, shape):
        if name in ("obs", "next_obs") and isinstance(observation_space, spaces.Discrete):
            return rng.integers(0, 5, shape)
        if name == "action" and isinstance(action_space, spaces.Discrete):
            return rng.integers(0, 4, shape)
        if name == "done":
            return rng.random(shape) < 0.5
        return rng.uniform(-1, 1, shape).astype(np.float32)

    call = {name: value(name, shape) for name, shape in shapes.items()}
    call["infos"] = [{} for _ in range(n_envs)]
    ours = LifelongReplayBuffer(0, observation_space, action_space, device="cpu", n_envs=n_envs)
    sb3 = ReplayBuffer(10, observation_space, action_space, device="cpu", n_envs=n_envs)
    ours.add(**call)
    sb3.add(**{k: np.array(v) if k != "infos" else v for k, v in call.items()})
    rows = stored(ours)
    assert ours.size() == n_envs
    np.testing.assert_array_equal(rows["observations"], sb3.observations[0])
    np.testing.assert_array_equal(rows["next_observations"], sb3.next_observations[0])
    np.testing.assert_array_equal(rows["actions"], sb3.actions[0])
    np.testing.assert_array_equal(rows["rewards"], sb3.rewards[0])
    np.testing.assert_array_equal(rows["flags"] & 1, sb3.dones[0])
    assert set(rows) == set(FIELD_NAMES)


def test_add_still_accepts_lists_and_python_scalars():
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu")
    buffer.add([[0.0, 1.0, 2.0]], [[1.0, 2.0, 3.0]], [[0.5, -0.5]], [1.5], [True], [{"TimeLimit.truncated": True}])
    buffer.add([0.0, 1.0, 2.0], [1.0, 2.0, 3.0], [0.5, -0.5], 2.5, False, [{}])
    rows = stored(buffer)
    np.testing.assert_array_equal(rows["rewards"], [1.5, 2.5])
    np.testing.assert_array_equal(rows["flags"], [3, 0])


# ---------------------------------------------------------------------------------------------- only real numbers
NOT_REAL = {
    "complex": lambda a: a.astype(np.complex64) + 1j,
    "datetime64": lambda a: np.full(a.shape, "2024-05-01", dtype="datetime64[D]"),
    "timedelta64": lambda a: np.ones(a.shape, dtype="timedelta64[s]"),
    "str": lambda a: a.astype(str),
    "bytes": lambda a: a.astype(str).astype(np.bytes_),
    "object": lambda a: a.astype(object),
}


@pytest.mark.parametrize("field", ["obs", "next_obs", "action", "reward", "done"])
@pytest.mark.parametrize("kind", NOT_REAL)
def test_add_refuses_what_is_not_a_real_number(buffer, field, kind):
    """Before: complex values lost their imaginary part (a warning), datetimes were stored as integers and numeric
    strings were parsed (a done of "False" was True)."""
    before, width = stored(buffer), buffer._width
    bad = args(3, seed=4)
    bad[field] = NOT_REAL[kind](np.asarray(bad[field]))
    name = {"obs": "observations", "next_obs": "next_observations", "action": "actions", "reward": "rewards"}.get(
        field, "dones"
    )
    with pytest.raises(
        ValueError, match=rf"add\(\): {name} have dtype {re.escape(str(bad[field].dtype))} .*only real numbers"
    ):
        buffer.add(**bad)
    assert_unchanged(buffer, before)
    assert buffer._width == width


def test_add_refuses_a_dict_observation_that_is_not_a_real_number():
    space = spaces.Dict({"pos": spaces.Box(-1, 1, (2,), np.float32), "image": spaces.Box(0, 255, (4,), np.uint8)})
    buffer = LifelongReplayBuffer(0, space, ACT, device="cpu")
    obs = {"pos": np.zeros((1, 2), np.float32), "image": np.zeros((1, 4), np.uint8)}
    good = dict(action=np.zeros((1, 2), np.float32), reward=np.zeros(1), done=np.zeros(1), infos=[{}])
    buffer.add(obs, obs, **good)
    with pytest.raises(ValueError, match=r"next_observations\['image'\] have dtype <U3"):
        buffer.add(obs, {**obs, "image": np.full((1, 4), "255")}, **good)
    assert buffer.size() == 1


@pytest.mark.parametrize("where", ["memory", "directory"])
def test_add_of_more_envs_than_the_widths_hold_is_refused(tmp_path, where):
    """Before: an OverflowError from the uint16 env count, after the call had changed the buffer's streams (the next
    add of as many envs then stored a wrong stride for every row)."""
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=None if where == "memory" else tmp_path / "b")
    buffer.add(**args(1))
    streams = buffer.store.next_stream_id
    n_envs = 1 << 16
    huge = {**args(1), "infos": [{}] * n_envs}
    huge = {k: (np.repeat(v, n_envs, axis=0) if k != "infos" else v) for k, v in huge.items()}
    for _ in range(2):
        with pytest.raises(ValueError, match=r"65,536 envs in one call, at most 65,535"):
            buffer.add(**huge)
    assert buffer.size() == 1 and buffer.store.next_stream_id == streams
    buffer.add(**args(1))  # the buffer goes on
    np.testing.assert_array_equal(buffer.read_range("widths", 0, 2), [1, 1])
