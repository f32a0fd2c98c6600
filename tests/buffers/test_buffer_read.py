"""read_mode="pread" (positioned reads) against read_mode="mmap" (memory maps): bit-identical reads everywhere."""

import os
import pickle
import subprocess
import sys
import time
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces

import sb3_lifelong
from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError, LifelongBufferView, merge_buffers, readers
from sb3_lifelong.buffers.manifest import chunk_file_name
from sb3_lifelong.buffers.rowstore import RowStore

OBS = gym.spaces.Box(-np.inf, np.inf, (5,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)
DICT_OBS = spaces.Dict(
    {
        "pos": spaces.Box(-1, 1, (3,), np.float32),
        "image": spaces.Box(0, 255, (2, 4, 4), np.uint8),
        "mode": spaces.Discrete(4),
    }
)
LAYOUTS = {"single": None, "chunked": 150}  # capacity of each layout
PACKAGE_DIR = os.path.dirname(sb3_lifelong.__file__)  # where a light child process imports the row store from
linux_only = pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc/self (Linux)")


def random_obs(space, rng, n_envs):
    if isinstance(space, spaces.Dict):
        return {
            "pos": rng.uniform(-1, 1, (n_envs, 3)).astype(np.float32),
            "image": rng.integers(0, 256, (n_envs, 2, 4, 4)).astype(np.uint8),
            "mode": rng.integers(0, 4, n_envs),
        }
    return rng.standard_normal((n_envs, *space.shape)).astype(np.float32)


def fill(buffers, steps, n_envs, seed, stage=None):
    """The same ``steps`` add() calls of ``n_envs`` envs into every buffer (episode ends, timeouts, a stage)."""
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        space = buffers[0].observation_space
        obs, next_obs = random_obs(space, rng, n_envs), random_obs(space, rng, n_envs)
        actions = rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32)
        rewards = rng.normal(size=n_envs).astype(np.float32)
        done = rng.random(n_envs) < 0.1
        infos = [{"TimeLimit.truncated": bool(d and rng.random() < 0.5)} for d in done]
        if stage is not None:
            for info in infos:
                info["stage"] = stage
        for buffer in buffers:
            buffer.add(obs, next_obs, actions, rewards, done, infos)


def make_pair(tmp_path, layout, observation_space=OBS, chunk_size=40, **kwargs):
    """Two writers on two directories, one per read mode, meant to be given the same rows."""
    return [
        LifelongReplayBuffer(
            0,
            observation_space,
            ACT,
            device="cpu",
            path=tmp_path / mode,
            chunk_size=chunk_size,
            capacity=LAYOUTS[layout],
            read_mode=mode,
            **kwargs,
        )
        for mode in ("mmap", "pread")
    ]


def assert_same_tensors(x, y, what):
    if isinstance(x, dict):
        assert set(x) == set(y), what
        for key in x:
            assert_same_tensors(x[key], y[key], f"{what}.{key}")
    elif x is None:
        assert y is None, what
    else:
        assert x.dtype == y.dtype and x.shape == y.shape, what
        assert th.equal(x, y), what


def assert_same_samples(a, b, seeds=range(5), batch_size=64):
    """``sample`` with the same numpy seed gives bit-identical batches from both buffers."""
    for seed in seeds:
        np.random.seed(seed)
        x, sources_x = a.sample(batch_size, return_sources=True)
        np.random.seed(seed)
        y, sources_y = b.sample(batch_size, return_sources=True)
        assert type(x) is type(y)
        for name in x._fields:
            assert_same_tensors(getattr(x, name), getattr(y, name), name)
        assert th.equal(sources_x, sources_y)


def assert_same_ranges(a, b):
    """``read_range`` of every field over ranges crossing chunk boundaries and the unflushed tail."""
    size = a.size()
    assert b.size() == size
    bounds = sorted({0, 1, size // 3, size // 2, size - 7, size - 1, size} & set(range(size + 1)))
    for name in a.store.fields:
        for start in bounds:
            for stop in bounds:
                x, y = a.store.read_range(name, start, stop), b.store.read_range(name, start, stop)
                assert x.dtype == y.dtype and x.shape == y.shape, (name, start, stop)
                assert x.tobytes() == y.tobytes(), (name, start, stop)


def assert_same_gather(a, b, rng):
    size = a.size()
    indices = np.concatenate([rng.integers(0, size, 300), [0, size - 1, 0, 5, 5, 6]]).astype(np.int64)
    names = tuple(a.store.fields)
    x, y = a.store.gather(names, indices), b.store.gather(names, indices)
    for name in names:
        assert x[name].dtype == y[name].dtype and x[name].tobytes() == y[name].tobytes(), name
    empty = b.store.gather(names, np.zeros(0, dtype=np.int64))
    assert all(empty[name].shape == (0, *b.store.fields[name][1]) for name in names)


def fd_count():
    return len(os.listdir("/proc/self/fd"))


def open_files(path):
    """The files under ``path`` this process has file descriptors of."""
    names = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            names.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:  # closed meanwhile (the descriptor of the listing itself)
            pass
    return [name for name in names if name.startswith(str(path))]


def mapped_files(path):
    with open("/proc/self/maps") as file:
        return [line for line in file if str(path) in line]


# ---------------------------------------------------------------------------------------------------------------- API
@pytest.mark.parametrize("read_mode", ["mmap", "pread"])
def test_max_resident_bytes_maps_onto_pread(tmp_path, read_mode):
    """The remap limit of earlier releases is replaced by read_mode="pread", the one way to bound the RSS."""
    with pytest.warns(FutureWarning, match=r"max_resident_bytes=1048576 is replaced by read_mode='pread'"):
        writer = LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "b", read_mode=read_mode, max_resident_bytes=1 << 20)
    assert writer.store.read_mode == "pread"
    fill([writer], 30, 2, seed=0)
    writer.store.flush()
    assert mapped_files(tmp_path / "b") == []  # nothing of the directory is mapped
    assert len(writer.sample(8).rewards) == 8
    # a store pickled by an earlier release records max_resident_bytes (None by default): it reopens as it was read
    for limit, expected in ((None, "mmap"), (1 << 20, "pread")):
        state = {"path": str(tmp_path / "b"), "read_only": True, "chunk_size": 10_000, "read_mode": "mmap"}
        copy = RowStore.__new__(RowStore)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            copy.__setstate__(dict(state, max_resident_bytes=limit))
        assert copy.read_mode == expected and len(copy) == 60
        assert [w.category for w in caught] == ([] if limit is None else [FutureWarning])
        copy.close()
    writer.close()


def test_a_model_saved_with_max_resident_bytes_still_loads(tmp_path):
    """A zip of an earlier release whose replay_buffer_kwargs name max_resident_bytes loads, reads and resumes."""
    from sb3_lifelong import MPO

    kwargs = dict(path=str(tmp_path / "life"), chunk_size=5, max_resident_bytes=256 << 20)
    with pytest.warns(FutureWarning, match="max_resident_bytes"):
        model = MPO(
            "MlpPolicy", "Pendulum-v1", num_samples=2, replay_buffer_class=LifelongReplayBuffer,
            replay_buffer_kwargs=kwargs, policy_kwargs=dict(net_arch=[8]), learning_starts=10, batch_size=8, seed=0,
        )  # fmt: skip
        model.learn(12)
    model.save(tmp_path / "mpo.zip")
    model.replay_buffer.close()
    del model
    for safe in (True, False):
        with pytest.warns(FutureWarning, match="max_resident_bytes"):
            loaded = MPO.load(tmp_path / "mpo.zip", safe=safe, env=gym.make("Pendulum-v1"))
        buffer = loaded.replay_buffer
        assert isinstance(buffer, LifelongReplayBuffer) and buffer.store.path == kwargs["path"]
        assert buffer.store.read_only and buffer.store.read_mode == "pread" and buffer.size() == 12
        assert len(buffer.sample(4).rewards) == 4
    with pytest.warns(FutureWarning, match="max_resident_bytes"):
        loaded.learn(4, reset_num_timesteps=False)  # reattached for writing, read as before
    assert loaded.replay_buffer.size() == 16 and loaded.replay_buffer.store.read_mode == "pread"
    loaded.replay_buffer.close()


def test_bad_read_mode(tmp_path):
    for bad in ("mmap2", "PREAD", None, 1):
        with pytest.raises(ValueError, match="read_mode must be one of"):
            LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "bad", read_mode=bad)
        with pytest.raises(ValueError, match="read_mode must be one of"):
            RowStore({"rewards": ("<f4", ())}, read_mode=bad)
    assert not os.path.exists(tmp_path / "bad")  # refused before creating anything
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "ok")
    fill([buffer], 3, 1, seed=0)
    buffer.close()
    with pytest.raises(ValueError, match="read_mode must be one of"):
        LifelongReplayBuffer.open(tmp_path / "ok", read_only=True, read_mode="mmmap")
    assert LifelongReplayBuffer.open(tmp_path / "ok", read_only=True).read_mode == "mmap"  # the default
    assert LifelongReplayBuffer.open(tmp_path / "ok", read_only=True, read_mode="pread").read_mode == "pread"
    memory = LifelongReplayBuffer(0, OBS, ACT, read_mode="pread")  # no effect in memory
    fill([memory], 5, 2, seed=0)
    memory.sample(4)


# -------------------------------------------------------------------------------------------------- bit-identical reads
@pytest.mark.parametrize("layout", list(LAYOUTS))
@pytest.mark.parametrize("observation_space", [OBS, DICT_OBS], ids=["box", "dict"])
def test_same_reads_as_mmap(tmp_path, layout, observation_space):
    writers = make_pair(tmp_path, layout, observation_space)
    fill(writers, 70, 1, seed=1, stage=0)
    fill(writers, 45, 3, seed=2, stage=1)  # n_envs change: streams every 3 rows
    fill(writers, 13, 2, seed=3)  # leaves unflushed rows in the tails
    mmap_writer, pread_writer = writers
    assert mmap_writer.store.num_tail > 0 and pread_writer.read_mode == "pread"
    assert mmap_writer.size() == pread_writer.size() == (150 if layout == "chunked" else 231)
    rng = np.random.default_rng(0)
    assert_same_samples(mmap_writer, pread_writer)  # committed rows and the writer's tail
    assert_same_ranges(mmap_writer, pread_writer)
    assert_same_gather(mmap_writer, pread_writer, rng)
    for writer in writers:  # n-step returns and per-source weights / reward scales
        writer.n_steps, writer.gamma = 3, 0.9
        writer.set_sampling_weights({0: 3.0})
        writer.set_reward_scale({1: -2.0})
    assert_same_samples(mmap_writer, pread_writer)
    for writer in writers:
        writer.close()
    readers = [LifelongReplayBuffer.open(tmp_path / m, read_only=True, n_steps=2, read_mode=m) for m in ("mmap", "pread")]
    assert readers[1].store.num_tail == 0 and readers[1].size() == mmap_writer.size()
    assert_same_samples(*readers)
    assert_same_ranges(*readers)
    assert_same_gather(*readers, rng)
    # the other read mode on the same directory
    assert_same_samples(readers[0], LifelongReplayBuffer.open(tmp_path / "mmap", read_only=True, n_steps=2, read_mode="pread"))


@pytest.mark.parametrize("merge_gap", [0, 16384, 1 << 40])
def test_merge_gap_and_short_reads(tmp_path, monkeypatch, merge_gap):
    """Rows read one call each, runs of nearby rows, or everything in one call; reads that return fewer bytes."""
    monkeypatch.setattr(readers, "PREAD_MERGE_GAP", merge_gap)
    writers = make_pair(tmp_path, "chunked", chunk_size=30)
    fill(writers, 200, 1, seed=4)
    assert_same_gather(*writers, np.random.default_rng(1))
    assert_same_samples(*writers)
    real_pread, real_preadv = os.pread, os.preadv

    def short_pread(fd, size, offset):
        return real_pread(fd, min(size, 7), offset)

    def short_preadv(fd, buffers, offset):
        return real_preadv(fd, [memoryview(buffers[0])[:7]], offset)

    monkeypatch.setattr(os, "pread", short_pread)
    monkeypatch.setattr(os, "preadv", short_preadv)
    assert_same_gather(*writers, np.random.default_rng(2))
    assert_same_ranges(*writers)


# ----------------------------------------------------------------------------------------------- followers, views, merge
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_followers_read_the_same_while_writer_appends(tmp_path, layout):
    writer = LifelongReplayBuffer(0, DICT_OBS, ACT, device="cpu", path=tmp_path / "b", chunk_size=25, capacity=LAYOUTS[layout])
    fill([writer], 30, 1, seed=5)
    followers = [LifelongReplayBuffer.open(tmp_path / "b", read_only=True, read_mode=m, n_steps=3) for m in ("mmap", "pread")]
    for step in range(12):  # the writer flushes (and, with a capacity, evicts and deletes chunk files) in between
        fill([writer], 17, 1 + step % 3, seed=10 + step, stage=step % 2)
        sizes = [follower.refresh() for follower in followers]
        assert sizes[0] == sizes[1] == writer.store.num_committed - writer.store.committed_first
        assert_same_samples(*followers, seeds=[step], batch_size=32)
        assert_same_ranges(*followers)
        assert followers[0].source_counts() == followers[1].source_counts()
    if layout == "chunked":
        assert len(os.listdir(tmp_path / "b")) < 12  # chunk files were deleted
        if os.path.isdir("/proc/self/fd"):  # the pread follower keeps the files of the retained chunks open, no other
            store = followers[1].store
            opened = {os.readlink(f"/proc/self/fd/{fd}") for fd in store._reader.fds.values()}
            assert opened == {os.path.join(store.path, chunk_file_name(c["start"])) for c in store.chunks}
            assert not [fd for fd in open_files(tmp_path / "b") if fd.endswith("(deleted)")]
    writer.close()


def test_follower_of_a_writer_process(tmp_path):
    """A pread follower reading while another process appends and evicts: every row read is the committed one."""
    child = subprocess.Popen(
        [sys.executable, "-c", WRITER_CHILD, PACKAGE_DIR, str(tmp_path / "b")], stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout is not None
        assert child.stdout.readline().startswith("open")
        readers = [RowStore(path=str(tmp_path / "b"), read_only=True, read_mode=mode) for mode in ("pread", "mmap")]
        rng = np.random.default_rng(0)
        checks, deadline = 0, time.monotonic() + 60.0
        while time.monotonic() < deadline and (checks < 100 or readers[0].first == 0):
            for reader in readers:
                reader.refresh()
                first, end = reader.first, reader.end
                if end == first:
                    continue
                expected = expected_rows(end)
                for name in ("observations", "rewards", "flags", "streams"):
                    np.testing.assert_array_equal(reader.read_range(name, 0, end - first), expected[name][first:end])
                indices = rng.integers(0, end - first, 200)
                got = reader.gather(("observations", "actions", "sources"), indices)
                for name, values in got.items():
                    np.testing.assert_array_equal(values, expected[name][first + indices], err_msg=name)
                checks += 1
        assert readers[0].first > 0 and checks >= 100  # the writer evicted while we read
    finally:
        child.kill()
        child.wait()


WRITER_CHILD = r"""
import sys, time, types
import numpy as np
# the row store's modules import only numpy, the standard library and one another: load them without the package's
# __init__ (which imports torch and SB3), so that this process starts in a fraction of a second
for name, folder in (("sb3_lifelong", sys.argv[1]), ("sb3_lifelong.buffers", sys.argv[1] + "/buffers")):
    sys.modules[name] = types.ModuleType(name)
    sys.modules[name].__path__ = [folder]
from sb3_lifelong.buffers import rowstore
fields = {"observations": ("<f4", (6,)), "next_observations": ("<f4", (6,)), "actions": ("<f4", (2,)),
          "rewards": ("<f4", ()), "flags": ("|u1", ()), "sources": ("<u2", ()), "streams": ("<u4", ()),
          "widths": ("<u2", ())}
store = rowstore.RowStore(fields, path=sys.argv[2], chunk_size=50, capacity=1000)
print("open", flush=True)
while store.end < 5_000_000:  # 20 flushes per capacity: readers refresh long before their newest chunk goes
    time.sleep(0.002)
    idx = np.arange(store.end, store.end + 37)
    store.append({
        "observations": (idx[:, None] * 6 + np.arange(6)).astype(np.float32),
        "next_observations": (idx[:, None] * 6 + np.arange(6) + 0.5).astype(np.float32),
        "actions": np.stack([np.sin(idx), np.cos(idx)], 1).astype(np.float32),
        "rewards": (idx * 0.25).astype(np.float32), "flags": (idx % 3).astype(np.uint8),
        "sources": (idx % 1000).astype(np.uint16), "streams": (idx // 77).astype(np.uint32),
        "widths": np.ones(len(idx), np.uint16)})
"""


def expected_rows(n):
    idx = np.arange(n)
    return {
        "observations": (idx[:, None] * 6 + np.arange(6)).astype(np.float32),
        "actions": np.stack([np.sin(idx), np.cos(idx)], 1).astype(np.float32),
        "rewards": (idx * 0.25).astype(np.float32),
        "flags": (idx % 3).astype(np.uint8),
        "sources": (idx % 1000).astype(np.uint16),
        "streams": (idx // 77).astype(np.uint32),
    }


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_views_and_merges(tmp_path, layout):
    pairs = [make_pair(tmp_path / name, layout, DICT_OBS, chunk_size=20) for name in ("a", "b")]
    for k, pair in enumerate(pairs):
        fill(pair, 90, 1 + k, seed=20 + k, stage=k)
    mmap_view = LifelongBufferView([pairs[0][0], pairs[1][0]], n_steps=3)
    pread_view = LifelongBufferView([pairs[0][1], pairs[1][1]], n_steps=3)
    assert_same_samples(mmap_view, pread_view)
    mmap_merged = merge_buffers([pair[0] for pair in pairs], path=tmp_path / "merged_mmap")
    pread_merged = merge_buffers([pair[1] for pair in pairs], path=tmp_path / "merged_pread", read_mode="pread")
    assert pread_merged.read_mode == "pread"
    assert_same_samples(mmap_merged, pread_merged)
    assert_same_ranges(mmap_merged, pread_merged)


def test_pickle_keeps_read_mode(tmp_path):
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=tmp_path / "b", chunk_size=10, read_mode="pread")
    fill([buffer], 25, 1, seed=6)
    again = pickle.loads(pickle.dumps(buffer))  # a directory buffer pickles as a reference: hands the directory over
    assert again.read_mode == "pread" and again.size() == 25
    reference = LifelongReplayBuffer.open(tmp_path / "b", read_only=True, device="cpu")
    assert_same_samples(reference, again)
    again.close()


# ------------------------------------------------------------------------------------------------ files and memory maps
@linux_only
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_file_descriptors_closed_on_close(tmp_path, layout):
    writer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=tmp_path / "b", chunk_size=40, capacity=LAYOUTS[layout])
    fill([writer], 130, 1, seed=7)
    rewards = np.array(writer.store.read_range("rewards", 0, 10))
    writer.close()
    del writer  # its memory maps
    before = fd_count()
    assert not mapped_files(tmp_path / "b")
    reader = LifelongReplayBuffer.open(tmp_path / "b", read_only=True, read_mode="pread")
    files = len(reader.store.fields) if layout == "single" else len(reader.store.chunks)
    assert fd_count() == before + files
    reader.sample(32)
    assert not mapped_files(tmp_path / "b")  # no page of the buffer's files is mapped into this process
    reader.close()
    assert fd_count() == before
    reader.sample(8)  # the data stays readable: the files are opened again...
    np.testing.assert_array_equal(reader.store.read_range("rewards", 0, 10), rewards)
    assert fd_count() == before + files
    reader.close()  # ... and closed by the next close()
    assert fd_count() == before
    reader.refresh()  # a closed reader does not open them to refresh
    assert fd_count() == before
    mapped = LifelongReplayBuffer.open(tmp_path / "b", read_only=True)
    mapped.sample(32)
    assert mapped_files(tmp_path / "b")  # while read_mode="mmap" maps them
    del mapped
    writer = LifelongReplayBuffer.open(tmp_path / "b", read_mode="pread", chunk_size=40)  # a pread writer
    fill([writer], 60, 1, seed=8)
    writer.sample(16)
    writer.close()
    assert fd_count() == before
    del writer, reader  # garbage collection closes them too
    reader = LifelongReplayBuffer.open(tmp_path / "b", read_only=True, read_mode="pread")
    del reader
    assert fd_count() == before


def test_file_truncated_while_open(tmp_path):
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=tmp_path / "b", chunk_size=10)
    fill([buffer], 40, 1, seed=9)
    buffer.close()
    reader = LifelongReplayBuffer.open(tmp_path / "b", read_only=True, read_mode="pread")
    with open(tmp_path / "b" / "observations.bin", "r+b") as file:
        file.truncate(100)
    with pytest.raises(BufferFormatError, match="truncated or replaced"):
        reader.store.read_range("observations", 0, 40)
    with pytest.raises(BufferFormatError, match="truncated or replaced"):
        reader.store.gather(("observations",), np.array([39]))
    reader.close()
