import json
import os
import pickle
import signal
import subprocess
import sys
import time
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import SAC, TD3
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.env_util import make_vec_env
from testkit import ACT, OBS, all_rows, fill

import sb3_lifelong
from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError, LifelongBufferView, merge_buffers
from sb3_lifelong.buffers.rowstore import RowStore

PACKAGE_DIR = os.path.dirname(sb3_lifelong.__file__)  # where a light child process imports the row store from


# ---------------------------------------------------------------------------------------------- SB3 semantics
@pytest.mark.parametrize("n_steps", [1, 4])
def test_same_samples_as_sb3(n_steps):
    n_envs, steps = 3, 300
    ours = LifelongReplayBuffer(1000, OBS, ACT, device="cpu", n_envs=n_envs, n_steps=n_steps, gamma=0.9)
    if n_steps == 1:
        ref = ReplayBuffer(1000, OBS, ACT, device="cpu", n_envs=n_envs)
    else:
        ref = NStepReplayBuffer(1000, OBS, ACT, device="cpu", n_envs=n_envs, n_steps=n_steps, gamma=0.9)
    fill(ours, steps, n_envs, seed=1)
    fill(ref, steps, n_envs, seed=1)
    assert ours.size() == steps * n_envs and ours.pos == steps * n_envs and not ours.full
    batch_inds = np.arange(steps)
    np.random.seed(3)
    env_inds = np.random.randint(0, n_envs, size=steps)
    np.random.seed(3)
    expected = ref._get_samples(batch_inds)
    got = ours._get_samples(batch_inds * n_envs + env_inds)
    for name in ("observations", "actions", "next_observations", "dones", "rewards", "discounts"):
        a, b = getattr(expected, name), getattr(got, name)
        if a is None:
            assert b is None
            continue
        assert b.shape == a.shape and b.dtype == a.dtype, name
        th.testing.assert_close(b, a, msg=name)


@pytest.mark.parametrize("algo", [SAC, TD3])
def test_drop_in_sb3(algo, tmp_path):
    model = algo(
        "MlpPolicy",
        "Pendulum-v1",
        learning_starts=50,
        batch_size=32,
        policy_kwargs=dict(net_arch=[16]),
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=str(tmp_path / "buf"), n_steps=3, gamma=0.98, chunk_size=64),
        device="cpu",
        seed=0,
    )
    model.learn(150)
    buffer = model.replay_buffer
    assert isinstance(buffer, LifelongReplayBuffer) and buffer.size() == 150
    # save / load through SB3 (a directory buffer pickles as a reference: tiny file, reopened on load)
    model.save_replay_buffer(tmp_path / "rb.pkl")
    assert os.path.getsize(tmp_path / "rb.pkl") < 20_000
    model.save(tmp_path / "model")
    buffer.close()
    # a different number of envs with the loaded buffer: SB3's own buffer breaks here
    model = algo.load(tmp_path / "model", env=make_vec_env("Pendulum-v1", n_envs=2, seed=1), device="cpu")
    model.load_replay_buffer(tmp_path / "rb.pkl")
    assert model.replay_buffer is not buffer and model.replay_buffer.size() == 150
    model.learn(60, reset_num_timesteps=False)
    assert model.replay_buffer.size() == 150 + 60
    model.replay_buffer.close()
    reopened = LifelongReplayBuffer.open(tmp_path / "buf", read_only=True)
    assert reopened.size() == 210


def test_drop_in_mpo():
    from sb3_lifelong import MPO

    model = MPO("MlpPolicy", "Pendulum-v1", learning_starts=50, batch_size=32, replay_buffer_class=LifelongReplayBuffer,
                replay_buffer_kwargs=dict(n_steps=2, gamma=0.99), device="cpu", seed=0)  # fmt: skip
    model.learn(120)
    assert model.replay_buffer.size() == 120 and model.replay_buffer.n_steps == 2
    assert model._n_updates > 0  # it trained on the buffer's samples: two-step, discounted by 0.99^2 (Pendulum never ends)
    batch = model.replay_buffer._get_samples(np.arange(100))  # rows with a successor stored (the newest has none yet)
    assert batch.discounts is not None and th.allclose(batch.discounts, th.full_like(batch.discounts, 0.99**2))


def test_in_memory_pickle_and_sources():
    buffer = LifelongReplayBuffer(10, OBS, ACT, device="cpu")
    fill(buffer, 30, 1)
    fill(buffer, 20, 1, stage=2)
    buffer.set_source(5, name="field test", metadata={"terrain": "gravel"})
    fill(buffer, 10, 1)
    assert buffer.source_counts() == {0: 30, 2: 20, 5: 10}
    # a stage's source is named as stage_envs names the stage's evaluation copy (stage 2: Env-C)
    assert buffer.sources[2] == {"name": "Env-C", "metadata": {"mass": 3.0}}
    assert buffer.sources[5]["metadata"] == {"terrain": "gravel"}
    assert buffer.source_counts(by_name=True) == {"source_0": 30, "Env-C": 20, "field test": 10}
    buffer.name_source(5, "Env-C")
    with pytest.raises(ValueError, match="sources 2 and 5 are both named 'Env-C'"):
        buffer.source_counts(by_name=True)
    assert buffer.buffer_size == 60  # never a limit: nothing was overwritten
    clone = pickle.loads(pickle.dumps(buffer))
    for name, values in all_rows(buffer).items():
        np.testing.assert_array_equal(all_rows(clone)[name], values)
    fill(clone, 5, 2)
    assert clone.size() == 70
    _, sources = buffer.sample(64, return_sources=True)
    assert sources.shape == (64,) and set(sources.tolist()) <= {0, 2, 5}
    assert not hasattr(buffer, "last_sampled_sources")  # the sources come from sample(return_sources=True) only
    with pytest.raises(NotImplementedError, match="action spaces"):
        LifelongReplayBuffer(10, OBS, gym.spaces.Dict({"a": ACT}))
    with pytest.raises(ValueError):
        buffer.set_source(70000)


def test_store_owns_streams_sources_and_spaces():
    buffer = LifelongReplayBuffer(10, OBS, ACT, device="cpu")
    fill(buffer, 12, 2, stage=1)
    store = buffer.store
    # the buffer layer reads these; only the store's own methods change them
    with pytest.raises(AttributeError):
        store.next_stream_id = 0
    with pytest.raises(TypeError):
        store.fields["rewards"] = ("<f8", ())
    with pytest.raises(TypeError):
        store.spaces["action"] = {}
    assert store.next_stream_id == 2 and store.reserve_streams(3) == 2 and store.next_stream_id == 5
    store.set_source(4, "four", {"k": 1.0})
    copy = store.source(4)
    assert copy == {"name": "four", "metadata": {"k": 1.0}}
    copy["metadata"]["k"] = 2.0  # copies: the table is unchanged
    assert store.source_table()[4] == {"name": "four", "metadata": {"k": 1.0}} and store.source(9) is None
    with pytest.raises(ValueError):
        store.set_source(70000, "too large", {})
    store.describe_spaces({"observation": {}, "action": {}})  # a store that has a description keeps it
    assert store.spaces["action"]["type"] == "Box"
    # an in-memory store pickles its rows (and its layout, "memory"), and keeps its tables
    clone = pickle.loads(pickle.dumps(store))
    assert (dict(clone.fields), clone.next_stream_id, clone.source_table()) == (dict(store.fields), 5, store.source_table())
    assert clone.layout == store.layout == "memory" and clone.path is None and len(clone) == len(store)
    for name in store.fields:
        np.testing.assert_array_equal(clone.read_range(name, 0, len(store)), store.read_range(name, 0, len(store)))


# ---------------------------------------------------------------------------------------------- persistence
def test_round_trip_reopen_append(tmp_path):
    path = tmp_path / "life"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=50, n_steps=3)
    fill(buffer, 120, 1, stage=0)
    before = all_rows(buffer)
    buffer.close()
    # the format is plain JSON + raw files
    manifest = json.loads((path / "manifest.json").read_text())
    assert manifest["num_transitions"] == 120 and manifest["sources"]["0"]["name"] == "Env-A"
    assert os.path.getsize(path / "observations.bin") == 120 * 3 * 4
    reopened = LifelongReplayBuffer.open(path, n_steps=3)
    assert reopened.recovered == 120 and reopened.observation_space.shape == (3,)
    for name, values in all_rows(reopened).items():
        np.testing.assert_array_equal(values, before[name])
    fill(reopened, 40, 2, seed=7, stage=1)
    reopened.close()
    again = LifelongReplayBuffer.open(path, read_only=True, verify="all", n_steps=3)
    assert again.size() == 200 and again.source_counts() == {0: 120, 1: 80}
    rows = all_rows(again)
    # streams restart after a reopen and after a change of n_envs: n-step never chains across them
    assert len(set(rows["streams"][:120])) == 1 and set(rows["streams"][120:]).isdisjoint(rows["streams"][:120])
    samples = again._get_samples(np.array([119]))
    assert samples.discounts.item() == pytest.approx(0.99)
    with pytest.raises(RuntimeError, match="read-only"):
        fill(again, 1, 1)


def test_n_envs_change_and_stream_ends():
    buffer = LifelongReplayBuffer(0, OBS, ACT, n_steps=5, gamma=0.5, device="cpu")
    for width in (1, 1, 2, 2, 3, 1):
        obs = np.ones((width, 3))
        buffer.add(obs, obs, np.zeros((width, 2)), np.ones(width), np.zeros(width), [{}] * width)
    # rows: 0,1 (w1) | 2,3 ; 4,5 (w2) | 6,7,8 (w3) | 9 (w1)
    samples = buffer._get_samples(np.arange(10))
    expected_steps = np.array([2, 1, 2, 2, 1, 1, 1, 1, 1, 1])
    np.testing.assert_allclose(samples.discounts.numpy().ravel(), 0.5**expected_steps)
    np.testing.assert_allclose(samples.rewards.numpy().ravel(), (1 - 0.5**expected_steps) / 0.5)


def test_read_only_reader_follows_writer(tmp_path):
    writer = LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "b", chunk_size=10)
    fill(writer, 25, 1)
    reader = LifelongReplayBuffer.open(tmp_path / "b", read_only=True)
    assert reader.size() == 20  # only flushed chunks are visible to other readers
    with pytest.raises(RuntimeError, match="another buffer"):
        LifelongReplayBuffer.open(tmp_path / "b")
    fill(writer, 30, 1, seed=3)
    assert reader.refresh() == 50
    np.testing.assert_array_equal(all_rows(reader)["observations"], all_rows(writer)["observations"][:50])
    reader.sample(8)


CHILD = r"""
import sys, types
import numpy as np
# the row store's modules import only numpy, the standard library and one another: load them without the package's
# __init__ (which imports torch and SB3), so that this process starts in a fraction of a second
for name, folder in (("sb3_lifelong", sys.argv[1]), ("sb3_lifelong.buffers", sys.argv[1] + "/buffers")):
    sys.modules[name] = types.ModuleType(name)
    sys.modules[name].__path__ = [folder]
from sb3_lifelong.buffers import rowstore
path, chunk, seed = sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
fields = {"observations": ("<f4", (4,)), "next_observations": ("<f4", (4,)), "actions": ("<f4", (2,)),
          "rewards": ("<f4", ()), "flags": ("|u1", ()), "sources": ("<u2", ()), "streams": ("<u4", ()),
          "widths": ("<u2", ())}
store = rowstore.RowStore(fields, path=path, chunk_size=chunk)
rng = np.random.default_rng(seed)
print("open", store.num_committed, flush=True)
while True:
    start = len(store)
    n = int(rng.integers(1, 3 * chunk))
    idx = np.arange(start, start + n)
    store.append({
        "observations": (idx[:, None] * 4 + np.arange(4)).astype(np.float32),
        "next_observations": (idx[:, None] * 4 + np.arange(4) + 0.5).astype(np.float32),
        "actions": np.stack([np.sin(idx), np.cos(idx)], 1).astype(np.float32),
        "rewards": (idx * 0.001).astype(np.float32), "flags": (idx % 3).astype(np.uint8),
        "sources": (idx // 1000).astype(np.uint16), "streams": (idx // 77).astype(np.uint32),
        "widths": np.ones(n, np.uint16)})
    print("committed", store.num_committed, flush=True)
"""


def expected_rows(n):
    idx = np.arange(n)
    return {
        "observations": (idx[:, None] * 4 + np.arange(4)).astype(np.float32),
        "next_observations": (idx[:, None] * 4 + np.arange(4) + 0.5).astype(np.float32),
        "actions": np.stack([np.sin(idx), np.cos(idx)], 1).astype(np.float32),
        "rewards": (idx * 0.001).astype(np.float32),
        "flags": (idx % 3).astype(np.uint8),
        "sources": (idx // 1000).astype(np.uint16),
        "streams": (idx // 77).astype(np.uint32),
        "widths": np.ones(n, np.uint16),
    }


def test_crash_sigkill_loses_only_unflushed_tail(tmp_path):
    rng = np.random.default_rng(0)
    path = str(tmp_path / "crash")
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    total_before = 0
    for trial in range(30):
        chunk = int(rng.integers(5, 200))
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD, PACKAGE_DIR, path, str(chunk), str(trial)],
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        # most trials let the writer open the directory first (python starts slowly on a loaded machine); every
        # fourth one may kill it while it starts or creates the directory
        first_line = "" if trial % 4 == 0 else child.stdout.readline()
        time.sleep(float(rng.uniform(0.15, 0.6)))
        child.send_signal(signal.SIGKILL)
        out, _ = child.communicate()
        out = first_line + out
        assert child.returncode == -signal.SIGKILL
        lines = out.split("\n")[:-1]  # complete lines only: the kill can tear the last print
        committed = [int(line.split()[1]) for line in lines if line.startswith("committed")]
        opened = [int(line.split()[1]) for line in lines if line.startswith("open")]
        if opened:
            assert opened[0] == total_before  # reopening continues exactly where the last commit stopped
        least = committed[-1] if committed else total_before
        if not os.path.exists(os.path.join(path, "manifest.json")):  # killed while creating the directory
            assert not committed
            continue
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            store = RowStore(path=path, verify="all")
        if store.discarded_bytes:  # reopening says how many transitions were recovered
            assert any(f"recovered {store.num_committed} transitions" in str(w.message) for w in caught)
        assert store.num_committed >= least and store.recovered == store.num_committed
        for name, values in expected_rows(store.num_committed).items():
            np.testing.assert_array_equal(store.read_range(name, 0, store.num_committed), values, err_msg=name)
            assert os.path.getsize(os.path.join(path, name + ".bin")) == values.nbytes  # tail cut off
        total_before = store.num_committed
        store.close()
    assert total_before > 0


def test_crash_of_sb3_writer_reports_recovery(tmp_path):
    script = (
        "import sys, numpy as np, gymnasium as gym\n"
        "from sb3_lifelong import LifelongReplayBuffer\n"
        "box = gym.spaces.Box(-1, 1, (3,))\n"
        "b = LifelongReplayBuffer(0, box, gym.spaces.Box(-1, 1, (2,)), path=sys.argv[1], chunk_size=100)\n"
        "for t in range(250):\n"
        "    b.add(np.full((1, 3), t), np.full((1, 3), t + 1), np.zeros((1, 2)), np.ones(1), np.zeros(1), [{}])\n"
        "print('ready', flush=True)\n"
        "import time; time.sleep(60)\n"
    )
    child = subprocess.Popen([sys.executable, "-c", script, str(tmp_path / "b")], stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "ready"
    child.send_signal(signal.SIGKILL)
    child.communicate()
    buffer = LifelongReplayBuffer.open(tmp_path / "b", verify="all")
    assert buffer.recovered == 200  # the 50 unflushed transitions are lost, the 2 flushed chunks are intact
    np.testing.assert_array_equal(all_rows(buffer)["observations"][:, 0], np.arange(200))


# ---------------------------------------------------------------------------------------------- hostile input
def _write_buffer(path):
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=10)
    fill(buffer, 30, 1)
    buffer.close()
    return json.loads((path / "manifest.json").read_text())


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda m: m.update(format="pickle"), "format"),
        (lambda m: m.update(version=99), "version"),
        (lambda m: m.update(num_transitions=10**12), "chunks hold"),
        (lambda m: m.update(num_transitions=-1), "non-negative"),
        (lambda m: m["fields"]["observations"].update(dtype="|O"), "dtype"),
        (lambda m: m["fields"]["observations"].update(dtype="<f4; import os"), "dtype"),
        (lambda m: m["fields"]["observations"].update(shape=[-3]), "shape"),
        (lambda m: m["fields"]["rewards"].update(dtype="<f8"), "rewards"),
        (lambda m: m["fields"].update(evil={"dtype": "<f4", "shape": []}), "fields"),
        (lambda m: m["chunks"][1].update(start=3), "start"),
        (lambda m: m["chunks"][0].update(rows="10"), "rows"),
        (lambda m: m["sources"].update({"../x": {"name": "a", "metadata": {}}}), "source id"),
        (lambda m: m.update(__reduce__="os.system('touch /tmp/pwned')"), "keys"),
        (lambda m: m.update(next_stream_id=1.5), "next_stream_id"),
    ],
)
def test_hostile_manifest(tmp_path, mutate, message):
    path = tmp_path / "b"
    manifest = _write_buffer(path)
    mutate(manifest)
    (path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BufferFormatError, match=message):
        LifelongReplayBuffer.open(path, read_only=True)


def test_corrupted_files(tmp_path):
    path = tmp_path / "b"
    _write_buffer(path)
    good = (path / "manifest.json").read_bytes()
    for payload in (b"", b"\x80\x04\x95 pickle", b"{" * 100000, b'{"format": NaN}', good[: len(good) // 2]):
        (path / "manifest.json").write_bytes(payload)
        with pytest.raises(BufferFormatError, match=r"JSON|manifest"):
            LifelongReplayBuffer.open(path, read_only=True)
    (path / "manifest.json").write_bytes(good)
    # flipped bit in a committed chunk: caught by the checksum
    data = bytearray((path / "rewards.bin").read_bytes())
    data[5] ^= 1
    (path / "rewards.bin").write_bytes(bytes(data))
    with pytest.raises(BufferFormatError, match="checksum"):
        LifelongReplayBuffer.open(path, read_only=True, verify="all")
    # truncated field file
    (path / "rewards.bin").write_bytes(bytes(data[:40]))
    with pytest.raises(BufferFormatError, match="truncated"):
        LifelongReplayBuffer.open(path, read_only=True, verify="none")
    os.remove(path / "flags.bin")
    with pytest.raises(BufferFormatError, match="missing"):
        LifelongReplayBuffer.open(path, read_only=True)
    with pytest.raises(FileNotFoundError):
        LifelongReplayBuffer.open(tmp_path / "nothing")
    # npz with object arrays is refused (no pickle)
    np.savez(tmp_path / "evil.npz", observations=np.array([object()], dtype=object))
    with pytest.raises(ValueError, match="pickle"):
        LifelongReplayBuffer.from_d4rl(tmp_path / "evil.npz")


# ---------------------------------------------------------------------------------------------- sampling options
def test_reward_range_reads_every_block():
    buffer = LifelongReplayBuffer(0, OBS, ACT)
    with pytest.raises(ValueError, match="empty buffer"):
        buffer.reward_range()
    fill(buffer, 250, 1, stage=0)
    rewards = all_rows(buffer)["rewards"]
    expected = (float(rewards.min()), float(rewards.max()))
    assert buffer.reward_range() == expected == buffer.reward_range(block=7)  # blocks that do not divide the size
    buffer.set_reward_scale({0: 10.0})
    assert buffer.reward_range() == expected  # as stored, whatever is applied at sampling time


def test_sampling_weights_and_reward_scale():
    np.random.seed(0)
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu")
    fill(buffer, 1000, 1, stage=0)
    fill(buffer, 200, 1, stage=1)
    fill(buffer, 300, 1, stage=2)
    fill(buffer, 100, 1, stage=1)  # a second, non-contiguous run of stage 1
    batch = 20_000
    _, sources = buffer.sample(batch, return_sources=True)
    counts = np.bincount(sources.numpy(), minlength=3) / batch
    np.testing.assert_allclose(counts, [1000 / 1600, 300 / 1600, 300 / 1600], atol=4 * np.sqrt(0.25 / batch))
    buffer.set_sampling_weights({1: 5.0, 2: 0.0})
    _, sources = buffer.sample(batch, return_sources=True)
    ratio = np.bincount(sources.numpy(), minlength=3) / batch
    expected = np.array([1000, 5 * 300, 0]) / 2500
    np.testing.assert_allclose(ratio, expected, atol=4 * np.sqrt(0.25 / batch))
    # sampled rows really belong to the source they report
    rows = all_rows(buffer)
    inds = buffer._sample_indices(5000)
    assert set(rows["sources"][inds].tolist()) == {0, 1}
    buffer.set_sampling_weights(None)
    buffer.set_reward_scale({2: 10.0})
    inds = np.arange(buffer.size())
    samples = buffer._get_samples(inds)
    expected_rewards = rows["rewards"] * np.where(rows["sources"] == 2, 10.0, 1.0)
    np.testing.assert_allclose(samples.rewards.numpy().ravel(), expected_rewards, rtol=1e-6)
    with pytest.raises(ValueError):
        buffer.set_sampling_weights({0: -1.0})


# ---------------------------------------------------------------------------------------------- merge / interop
def test_view_and_merge(tmp_path):
    a = LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "a", chunk_size=16)
    b = LifelongReplayBuffer(0, OBS, ACT)
    fill(a, 40, 1, stage=0)
    fill(b, 30, 2, seed=5, stage=1)
    view = LifelongBufferView([a, b], n_steps=3, gamma=0.9)
    assert view.size() == 100 and set(view.sources) == {0, 1}
    assert view.source_counts() == {0: 40, 1: 60}
    samples, _ = view.sample(50, return_sources=True)
    assert samples.observations.shape == (50, 3)
    merged = merge_buffers([a, b], path=tmp_path / "m", n_steps=3, gamma=0.9)
    ra, rb, rm = all_rows(a), all_rows(b), all_rows(merged)
    for name in ("observations", "actions", "rewards", "flags", "sources"):
        np.testing.assert_array_equal(rm[name], np.concatenate([ra[name], rb[name]]))
    # n-step targets of the view and of the merged copy agree (no chaining across buffers)
    inds = np.arange(100)
    for field in ("rewards", "discounts", "next_observations", "dones"):
        th.testing.assert_close(getattr(view._get_samples(inds), field), getattr(merged._get_samples(inds), field))
    # copies of a common ancestor: keep the shared head once
    partial = merge_buffers([a, b], starts=[0, 20])
    rp = all_rows(partial)
    np.testing.assert_array_equal(rp["observations"], np.concatenate([ra["observations"], rb["observations"][20:]]))
    with pytest.raises(ValueError, match="starts"):
        merge_buffers([a, b], starts=[0, 61])
    head = merge_buffers([a, b], path=tmp_path / "head", starts=[0, 20], stops=[25, 20])  # a's first 25 rows alone
    rh = all_rows(head)
    for name in ("observations", "actions", "rewards", "flags", "sources"):
        np.testing.assert_array_equal(rh[name], ra[name][:25])
    assert head.size() == 25 and set(head.sources) == {0, 1}  # the sources' names and metadata are all kept
    with pytest.raises(ValueError, match="stops"):
        merge_buffers([a, b], starts=[0, 20], stops=[40, 10])
    head.close()
    with pytest.raises(FileExistsError, match=r"held 25 transitions.*mix"):  # never merged into a buffer holding data
        merge_buffers([a], path=tmp_path / "head")
    with LifelongReplayBuffer.open(tmp_path / "head", read_only=True) as kept:
        assert kept.size() == 25
    fill(b, 5, 1, seed=9)
    assert view.size() == 105  # a view follows its buffers
    with pytest.raises(RuntimeError):
        view.add()


def test_d4rl_round_trip(tmp_path):
    buffer = LifelongReplayBuffer(0, OBS, ACT, n_steps=3)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(1, 3)).astype(np.float32)
    for t in range(100):  # a real trajectory: next_obs of one step is obs of the next
        nxt = rng.normal(size=(1, 3)).astype(np.float32)
        done = np.array([t % 30 == 29])
        info = {"TimeLimit.truncated": t == 59, "stage": t // 50}
        buffer.add(obs, nxt, rng.uniform(-1, 1, (1, 2)), rng.normal(size=1), done, [info])
        obs = rng.normal(size=(1, 3)).astype(np.float32) if done[0] else nxt
    data = buffer.to_d4rl()
    assert set(data) >= {"observations", "actions", "rewards", "next_observations", "terminals", "timeouts"}
    assert data["terminals"].sum() == 2 and data["timeouts"][59] and data["timeouts"][-1]
    buffer.save_npz(tmp_path / "d.npz")
    back = LifelongReplayBuffer.from_d4rl(tmp_path / "d.npz", n_steps=3)
    assert back.source_counts() == {0: 50, 1: 50}
    inds = np.arange(99)  # the last row ends a stream in both (write head vs exported timeout)
    for field in ("observations", "rewards", "discounts", "next_observations", "dones"):
        th.testing.assert_close(getattr(back._get_samples(inds), field), getattr(buffer._get_samples(inds), field))


def test_d4rl_actions_in_environment_units():
    action_space = gym.spaces.Box(-2.0, 2.0, shape=(2,), dtype=np.float32)
    buffer = LifelongReplayBuffer(0, OBS, action_space, device="cpu")
    rng = np.random.default_rng(1)
    stored = rng.uniform(-1, 1, size=(20, 2)).astype(np.float32)  # SB3 stores normalised actions
    for t in range(20):
        buffer.add(rng.normal(size=(1, 3)), rng.normal(size=(1, 3)), stored[t : t + 1], np.zeros(1), np.array([t == 19]), [{}])
    data = buffer.to_d4rl(by_episode=False)
    np.testing.assert_allclose(data["actions"], 2.0 * stored, rtol=1e-6)  # environment units
    np.testing.assert_array_equal(buffer.to_d4rl(by_episode=False, normalized_actions=True)["actions"], stored)
    back = LifelongReplayBuffer.from_d4rl(data, observation_space=OBS, action_space=action_space, device="cpu")
    np.testing.assert_allclose(back._get_samples(np.arange(20)).actions.numpy(), stored, rtol=1e-6, atol=1e-7)


def test_a_rerun_never_mixes_into_an_earlier_buffer(tmp_path):
    from sb3_lifelong import MPO

    path = tmp_path / "runs" / "buffer"
    small = dict(policy_kwargs=dict(net_arch=[8]), learning_starts=10, batch_size=8, num_samples=2, seed=0)
    first = MPO(
        "MlpPolicy", "Pendulum-v1", replay_buffer_class=LifelongReplayBuffer, replay_buffer_kwargs=dict(path=path), **small
    )
    first.learn(30)
    first.replay_buffer.close()  # the run ends (its process would release the writer lock)
    again = MPO(
        "MlpPolicy", "Pendulum-v1", replay_buffer_class=LifelongReplayBuffer, replay_buffer_kwargs=dict(path=path), **small
    )
    assert again.replay_buffer.size() == 30  # opening it is fine (reading, SB3's load)
    with pytest.raises(FileExistsError, match=r"mode='append'.*mode='overwrite'"):
        again.learn(5)
    with LifelongReplayBuffer.open(path, read_only=True) as kept:
        assert kept.size() == 30  # nothing was added by the refused run
    again.replay_buffer.close()
    appended = MPO(
        "MlpPolicy",
        "Pendulum-v1",
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=path, mode="append"),
        **small,
    )
    appended.learn(20)
    assert appended.replay_buffer.size() == 50
    appended.replay_buffer.close()
    fresh = MPO(
        "MlpPolicy",
        "Pendulum-v1",
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=path, mode="overwrite"),
        **small,
    )
    assert fresh.replay_buffer.size() == 0
    fresh.learn(15)
    assert fresh.replay_buffer.size() == 15
    with pytest.raises(ValueError, match="mode must be one of"):
        box = gym.spaces.Box(-1, 1, (2,))
        LifelongReplayBuffer(10, box, box, path=tmp_path / "other", mode="merge")
