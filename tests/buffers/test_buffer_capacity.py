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
from stable_baselines3 import SAC

import sb3_lifelong
from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError, LifelongBufferView, files, merge_buffers
from sb3_lifelong.buffers.manifest import FIELD_NAMES
from sb3_lifelong.buffers.rowstore import RowStore

OBS = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
ACT = gym.spaces.Box(-1, 1, (1,), np.float32)
PACKAGE_DIR = os.path.dirname(sb3_lifelong.__file__)  # where a light child process imports the row store from


def add_rows(buffer, start, count, n_envs=1, stage=None):
    """``count`` add() calls of ``n_envs`` rows; the row written k-th overall has observation [k, ...] and reward k."""
    row = start
    for _ in range(count):
        index = np.arange(row, row + n_envs)
        obs = np.stack([index, np.full(n_envs, -1.0)], axis=1).astype(np.float32)
        infos = [{"stage": stage} if stage is not None else {} for _ in range(n_envs)]
        actions = np.sin(index).reshape(n_envs, 1)
        buffer.add(obs, obs + 0.5, actions, index.astype(np.float32), index % 7 == 6, infos)
        row += n_envs
    return row


def all_rows(buffer):
    return {name: np.array(buffer.store.read_range(name, 0, buffer.size())) for name in FIELD_NAMES}


def assert_last_rows(buffer, reference, count):
    """``buffer`` holds exactly the last ``count`` rows of the uncapped ``reference``."""
    assert buffer.size() == count
    got, expected = all_rows(buffer), all_rows(reference)
    for name in FIELD_NAMES:
        np.testing.assert_array_equal(got[name], expected[name][reference.size() - count :], err_msg=name)


def chunk_files(path):
    return sorted(name for name in os.listdir(path) if name.startswith("chunk."))


def fill_both(capped, reference):
    """The same rows into both buffers: two sources, a change of n_envs."""
    row = add_rows(capped, 0, 23, stage=0)
    add_rows(reference, 0, 23, stage=0)
    row = add_rows(capped, row, 20, n_envs=3, stage=1)
    add_rows(reference, 23, 20, n_envs=3, stage=1)
    return row


# ---------------------------------------------------------------------------------------------- in memory
def test_capacity_in_memory():
    capped = LifelongReplayBuffer(1_000_000, OBS, ACT, capacity=30, n_steps=3, gamma=0.5)
    reference = LifelongReplayBuffer(0, OBS, ACT, n_steps=3, gamma=0.5)
    assert capped.capacity == 30 and capped.buffer_size == 30 and not capped.full
    assert reference.capacity is None and reference.buffer_size == 0
    add_rows(capped, 0, 20)
    add_rows(reference, 0, 20)
    assert capped.size() == 20 and not capped.full
    total = 20 + add_rows(capped, 20, 20, n_envs=3, stage=1) - 20
    add_rows(reference, 20, 20, n_envs=3, stage=1)
    assert total == 80 and capped.full and capped.pos == 30
    assert_last_rows(capped, reference, 30)
    assert capped.source_counts() == {1: 30}
    # the retained rows sample exactly like the same rows of the uncapped buffer (n-step returns included)
    inds = np.arange(30)
    got, expected = capped._get_samples(inds), reference._get_samples(inds + 50)
    for field in ("observations", "actions", "next_observations", "rewards", "dones", "discounts"):
        th.testing.assert_close(getattr(got, field), getattr(expected, field), msg=field)
    # many single adds: the arrays are compacted, contents stay right
    for _ in range(7):
        total = add_rows(capped, total, 37)
        add_rows(reference, total - 37, 37)
        assert_last_rows(capped, reference, 30)
    assert len(capped.store._tail["rewards"]) <= 2 * 30
    clone = pickle.loads(pickle.dumps(capped))
    assert len(clone.store._tail["rewards"]) == 30  # evicted rows are not pickled
    assert_last_rows(clone, reference, 30)
    add_rows(clone, total, 5)
    assert clone.size() == 30 and all_rows(clone)["rewards"][-1] == total + 4
    capped.reset()
    assert capped.size() == 0 and capped.source_counts() == {}
    add_rows(capped, 0, 3)
    assert capped.size() == 3 and all_rows(capped)["rewards"].tolist() == [0, 1, 2]


def test_capacity_errors(tmp_path):
    for bad in (0, -5, 2.5, True, "10"):
        with pytest.raises(ValueError, match="capacity must be a positive int"):
            LifelongReplayBuffer(0, OBS, ACT, capacity=bad)
    # a directory created without a capacity keeps every row in one file per field: it cannot start evicting
    plain = LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "plain", chunk_size=8)
    add_rows(plain, 0, 20)
    plain.close()
    with pytest.raises(ValueError, match=r"cannot evict.*merge_buffers"):
        LifelongReplayBuffer.open(tmp_path / "plain", capacity=10)
    # ... but it can be copied into a capped one
    source = LifelongReplayBuffer.open(tmp_path / "plain", read_only=True)
    copy = merge_buffers([source], path=tmp_path / "copy", capacity=10, chunk_size=4)
    assert copy.size() == 10 and all_rows(copy)["rewards"].tolist() == list(range(10, 20))
    copy.close()
    with pytest.raises(ValueError, match="read-only"):
        LifelongReplayBuffer.open(tmp_path / "copy", read_only=True, capacity=5)


# ---------------------------------------------------------------------------------------------- on disk
def test_capacity_on_disk_reopen_and_files(tmp_path):
    path = tmp_path / "capped"
    capped = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=10, capacity=25, n_steps=3)
    reference = LifelongReplayBuffer(0, OBS, ACT, n_steps=3)
    total = fill_both(capped, reference)
    assert total == 83
    assert_last_rows(capped, reference, 25)
    assert capped.source_counts() == {1: 25}
    # chunks of 10 rows: 80 rows flushed, rows 58.. retained -> chunks 50, 60, 70 on disk; 3 rows unflushed
    assert chunk_files(path) == [f"chunk.{start:012d}.bin" for start in (50, 60, 70)]
    manifest = json.loads((path / "manifest.json").read_text())
    assert manifest["version"] == 2 and manifest["layout"] == "chunked" and manifest["capacity"] == 25
    assert manifest["num_transitions"] == 80 and manifest["first_row"] == 55
    assert [c["start"] for c in manifest["chunks"]] == [50, 60, 70]
    assert os.path.getsize(path / "chunk.000000000050.bin") == 10 * (2 * 8 + 4 + 4 + 1 + 2 + 4 + 2)
    capped.close()
    reopened = LifelongReplayBuffer.open(path, n_steps=3, verify="all", chunk_size=10)
    assert reopened.capacity == 25 and reopened.recovered == 25
    assert_last_rows(reopened, reference, 25)
    samples = reopened._get_samples(np.arange(25))
    expected = reference._get_samples(np.arange(58, 83))
    for field in ("observations", "rewards", "discounts", "dones"):
        th.testing.assert_close(getattr(samples, field), getattr(expected, field), msg=field)
    total = add_rows(reopened, total, 12, stage=2)
    add_rows(reference, 83, 12, stage=2)
    assert_last_rows(reopened, reference, 25)
    reopened.close()
    # a smaller capacity evicts at once when asked to (and deletes the chunks no longer needed)
    smaller = LifelongReplayBuffer.open(path, capacity=8, evict=True)
    assert_last_rows(smaller, reference, 8)
    assert chunk_files(path) == ["chunk.000000000083.bin", "chunk.000000000093.bin"]  # 80-82 | 83-92 | 93-94
    assert json.loads((path / "manifest.json").read_text())["first_row"] == 87
    smaller.close()
    again = LifelongReplayBuffer.open(path, read_only=True)
    assert again.capacity == 8 and again.source_counts() == {2: 8}
    # SB3 trains with a capped directory buffer
    model = SAC(
        "MlpPolicy",
        "Pendulum-v1",
        learning_starts=40,
        batch_size=16,
        policy_kwargs=dict(net_arch=[16]),
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=str(tmp_path / "sac"), capacity=50, chunk_size=20),
        device="cpu",
        seed=0,
    )
    model.learn(130)
    assert model.replay_buffer.size() == 50 and model.replay_buffer.full
    model.replay_buffer.close()
    assert chunk_files(tmp_path / "sac") == [f"chunk.{start:012d}.bin" for start in (80, 100, 120)]  # rows 80-129


@pytest.mark.parametrize("path", [None, "dir"])
def test_capacity_sampling_never_returns_evicted(tmp_path, path):
    np.random.seed(0)
    capacity = 17
    buffer = LifelongReplayBuffer(
        0, OBS, ACT, capacity=capacity, chunk_size=6, path=None if path is None else tmp_path / path, n_steps=2
    )
    total = 0
    for step in range(40):
        total = add_rows(buffer, total, 1, n_envs=1 + step % 3, stage=step % 2)
        low = total - capacity
        samples = buffer.sample(256)
        assert samples.observations[:, 0].min().item() >= max(low, 0)
        assert samples.observations[:, 0].max().item() < total
        # weights and source counts only see retained rows
        if 1 in buffer.source_counts():
            buffer.set_sampling_weights({0: 0.0})
            _, only = buffer.sample(64, return_sources=True)
            assert set(only.tolist()) == {1}
        kept = all_rows(buffer)
        assert buffer.source_counts() == {int(s): int(c) for s, c in zip(*np.unique(kept["sources"], return_counts=True))}
        buffer.set_sampling_weights(None)
    view = LifelongBufferView([buffer, buffer])
    assert view.size() == 2 * capacity
    assert view.sample(500).observations[:, 0].min().item() >= total - capacity


def test_capacity_reader_follows_evicting_writer(tmp_path):
    writer = LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "b", chunk_size=5, capacity=12)
    total = add_rows(writer, 0, 13)
    reader = LifelongReplayBuffer.open(tmp_path / "b", read_only=True)
    assert reader.size() == 10 and all_rows(reader)["rewards"].tolist() == list(range(10))
    total = add_rows(writer, total, 30, stage=1)  # the chunks the reader mapped are deleted
    assert "chunk.000000000000.bin" not in chunk_files(tmp_path / "b")
    assert reader.refresh() == 12
    assert all_rows(reader)["rewards"].tolist() == list(range(28, 40))
    assert reader.source_counts() == {1: 12}
    assert reader.sample(100).observations[:, 0].min().item() >= 28


def test_capacity_crash_between_commit_and_delete(tmp_path, monkeypatch):
    path = tmp_path / "b"
    deleted = []
    monkeypatch.setattr(files, "delete_file", deleted.append)  # the "crash": files are never deleted
    writer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=10, capacity=15)
    add_rows(writer, 0, 60)
    # the manifest no longer lists the evicted chunks, their files are still there
    listed = [f"chunk.{c['start']:012d}.bin" for c in json.loads((path / "manifest.json").read_text())["chunks"]]
    assert listed == ["chunk.000000000040.bin", "chunk.000000000050.bin"]
    assert len(chunk_files(path)) == 6 and len(deleted) == 4
    writer.store._release_lock()  # the writer dies without closing (no further flush, lock released)
    writer.store._closed = True
    monkeypatch.undo()
    reader = LifelongReplayBuffer.open(path, read_only=True, verify="all")
    assert reader.size() == 15 and all_rows(reader)["rewards"].tolist() == list(range(45, 60))
    assert len(chunk_files(path)) == 6  # readers never delete
    with pytest.warns(UserWarning, match="4 unreferenced chunk files removed"):
        recovered = LifelongReplayBuffer.open(path)
    assert chunk_files(path) == listed
    assert recovered.recovered == 15 and all_rows(recovered)["rewards"].tolist() == list(range(45, 60))
    add_rows(recovered, 60, 12)
    assert all_rows(recovered)["rewards"].tolist() == list(range(57, 72))


CHILD = r"""
import sys, types
import numpy as np
# the row store's modules import only numpy, the standard library and one another: load them without the package's
# __init__ (which imports torch and SB3), so that this process starts in a fraction of a second
for name, folder in (("sb3_lifelong", sys.argv[1]), ("sb3_lifelong.buffers", sys.argv[1] + "/buffers")):
    sys.modules[name] = types.ModuleType(name)
    sys.modules[name].__path__ = [folder]
from sb3_lifelong.buffers import rowstore
path, chunk, seed, capacity = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
fields = {"observations": ("<f4", (2,)), "next_observations": ("<f4", (2,)), "actions": ("<f4", (1,)),
          "rewards": ("<f4", ()), "flags": ("|u1", ()), "sources": ("<u2", ()), "streams": ("<u4", ()),
          "widths": ("<u2", ())}
store = rowstore.RowStore(fields, path=path, chunk_size=chunk, capacity=capacity)
rng = np.random.default_rng(seed)
print("open", store.num_committed, len(store), flush=True)
while True:
    start = store.end
    n = int(rng.integers(1, 3 * chunk))
    idx = np.arange(start, start + n)
    store.append({
        "observations": np.stack([idx, -idx], 1).astype(np.float32),
        "next_observations": np.stack([idx, idx], 1).astype(np.float32),
        "actions": np.sin(idx).reshape(n, 1).astype(np.float32), "rewards": (idx * 0.5).astype(np.float32),
        "flags": (idx % 3).astype(np.uint8), "sources": (idx // 1000).astype(np.uint16),
        "streams": (idx // 77).astype(np.uint32), "widths": np.ones(n, np.uint16)})
    print("committed", store.num_committed, flush=True)
"""


def test_capacity_crash_sigkill(tmp_path):
    rng = np.random.default_rng(1)
    path = str(tmp_path / "crash")
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    capacity, committed_before = 150, 0
    for trial in range(8):
        chunk = int(rng.integers(5, 60))
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD, PACKAGE_DIR, path, str(chunk), str(trial), str(capacity)],
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        # most trials let the writer open the directory first (python starts slowly on a loaded machine); every
        # fourth one may kill it while it starts or creates the directory
        first_line = "" if trial % 4 == 0 else child.stdout.readline()
        time.sleep(float(rng.uniform(0.2, 0.5)))
        child.send_signal(signal.SIGKILL)
        out, _ = child.communicate()
        out = first_line + out
        # complete lines only: the kill can tear the last print
        committed = [int(line.split()[1]) for line in out.split("\n")[:-1] if line.startswith("committed")]
        if not os.path.exists(os.path.join(path, "manifest.json")):
            assert not committed
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            store = RowStore(path=path, verify="all")
        end = store.num_committed
        assert end >= max(committed[-1] if committed else 0, committed_before)
        assert len(store) == min(capacity, end) and store.first == end - len(store)
        idx = np.arange(store.first, end)
        np.testing.assert_array_equal(store.read_range("rewards", 0, len(store)), (idx * 0.5).astype(np.float32))
        np.testing.assert_array_equal(store.read_range("observations", 0, len(store))[:, 0], idx)
        # only the chunks holding retained rows are left
        starts = [c["start"] for c in store.chunks]
        assert chunk_files(path) == [f"chunk.{s:012d}.bin" for s in starts]
        assert not starts or starts[0] <= store.first < starts[0] + store.chunks[0]["rows"]
        committed_before = end
        store.close()
    assert committed_before > capacity


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda m: m.update(capacity=0), "capacity"),
        (lambda m: m.update(capacity=None), "capacity"),
        (lambda m: m.update(layout="../evil"), "layout"),
        (lambda m: m.update(first_row=m["chunks"][0]["start"] + m["chunks"][0]["rows"]), "first chunk"),
        (lambda m: m.update(first_row=-1), "first_row"),
        (lambda m: m.update(capacity=3), "exceed the capacity"),
        (lambda m: m["chunks"][1].update(start=7), "start"),
        (lambda m: m.pop("first_row"), "keys"),
    ],
)
def test_capacity_hostile_manifest(tmp_path, mutate, message):
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=4, capacity=10)
    add_rows(buffer, 0, 21)
    buffer.close()
    manifest = json.loads((path / "manifest.json").read_text())
    mutate(manifest)
    (path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BufferFormatError, match=message):
        LifelongReplayBuffer.open(path, read_only=True)


def test_capacity_corrupted_chunk_files(tmp_path):
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=4, capacity=10)
    add_rows(buffer, 0, 20)
    buffer.close()
    last = path / chunk_files(path)[-1]
    data = bytearray(last.read_bytes())
    data[-1] ^= 1
    last.write_bytes(bytes(data))
    with pytest.raises(BufferFormatError, match="checksum mismatch in field 'widths'"):
        LifelongReplayBuffer.open(path, read_only=True)
    last.write_bytes(bytes(data[:-3]))
    with pytest.raises(BufferFormatError, match="truncated"):
        LifelongReplayBuffer.open(path, read_only=True, verify="none")
    os.remove(last)
    with pytest.raises(BufferFormatError, match="missing"):
        LifelongReplayBuffer.open(path, read_only=True)


def test_a_new_capacity_is_checked_against_the_rows_retained_not_ever_added(tmp_path):
    # 83 rows through a capacity of 25: 58 evicted, 25 retained (first_row 58). A larger capacity keeps them all
    evicted = tmp_path / "evicted"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=evicted, chunk_size=10, capacity=25)
    add_rows(buffer, 0, 83)
    buffer.close()
    manifest = json.loads((evicted / "manifest.json").read_text())
    assert manifest["num_transitions"] - manifest["first_row"] == 25 and manifest["first_row"] > 0
    grown = LifelongReplayBuffer.open(evicted, capacity=40)
    assert grown.capacity == 40 and grown.size() == 25 and float(grown.store.read_range("rewards", 24, 25)[0]) == 82.0
    grown.close()
    # 20 rows under a capacity of 25: a capacity of exactly 20 evicts nothing, so it needs no evict=True; 19 does
    partial = tmp_path / "partial"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=partial, chunk_size=10, capacity=25)
    add_rows(buffer, 0, 20)
    buffer.close()
    exact = LifelongReplayBuffer.open(partial, capacity=20)
    assert exact.capacity == 20 and exact.size() == 20
    exact.close()
    with pytest.raises(ValueError, match="would evict the oldest 1 of them at once"):
        LifelongReplayBuffer.open(partial, capacity=19)
    assert LifelongReplayBuffer.open(partial, read_only=True).size() == 20  # nothing was changed


def test_a_store_that_fails_to_open_writes_nothing_when_collected(tmp_path, monkeypatch):
    """The commit of reopening with a smaller capacity is interrupted: the constructor raises, and the half-built
    store writes no manifest, now or when it is garbage-collected (it released the lock: another writer may be in)."""
    import gc

    from sb3_lifelong.buffers.rowstore import RowStore

    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=4, capacity=20)
    add_rows(buffer, 0, 20)
    buffer.close()
    manifest = (path / "manifest.json").read_bytes()

    def interrupted(self, chunks, num_committed):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(RowStore, "_commit", interrupted)
        with pytest.raises(KeyboardInterrupt):
            LifelongReplayBuffer.open(path, capacity=8, evict=True)
        gc.collect()
    assert (path / "manifest.json").read_bytes() == manifest
    with LifelongReplayBuffer.open(path, read_only=True) as reopened:
        assert reopened.size() == 20
