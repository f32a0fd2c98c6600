"""Fault safety of the on-disk buffer: disk full during a flush or a manifest write, then a retry; a lost manifest."""

import contextlib
import errno
import os
import pickle
import shutil
import stat
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest

import sb3_lifelong
from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError, CommitNotDurableError
from sb3_lifelong.buffers.manifest import FIELD_NAMES
from sb3_lifelong.buffers.rowstore import RowStore

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)
PACKAGE_DIR = os.path.dirname(sb3_lifelong.__file__)  # where a light child process imports the row store from
needs_proc = pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc/self/fd (Linux)")


def transition(k, n_envs=1):
    """Row k (and the next n_envs - 1 rows) of a deterministic sequence, as add() arguments."""
    index = np.arange(k, k + n_envs)
    obs = np.stack([index, -index, index * 0.25], axis=1).astype(np.float32)
    actions = np.stack([np.sin(index), np.cos(index)], axis=1).astype(np.float32)
    infos = [{"TimeLimit.truncated": bool(i % 11 == 10)} for i in index]
    return obs, obs + 0.5, actions, (index * 0.001).astype(np.float32), index % 5 == 4, infos


def rewards(start, stop):
    return (np.arange(start, stop) * 0.001).astype(np.float32)


def add_rows(buffer, start, stop, n_envs=1):
    for k in range(start, stop, n_envs):
        buffer.add(*transition(k, n_envs))
    return stop


def check_rows(buffer, count):
    """The buffer holds exactly rows 0..count-1 of the sequence (read_range and sample)."""
    assert buffer.size() == count
    obs, next_obs, actions, rewards, _, _ = transition(0, count)
    got = {name: np.array(buffer.store.read_range(name, 0, count)) for name in FIELD_NAMES}
    np.testing.assert_array_equal(got["observations"], obs)
    np.testing.assert_array_equal(got["next_observations"], next_obs)
    np.testing.assert_array_equal(got["actions"], actions)
    np.testing.assert_array_equal(got["rewards"], rewards)
    samples = buffer.sample(256)
    if buffer.n_steps > 1:
        assert samples.observations.shape == (256, 3)
        return
    rows = samples.rewards.numpy().reshape(-1) / np.float32(0.001)
    index = np.rint(rows).astype(np.int64)
    assert index.min() >= 0 and index.max() < count
    np.testing.assert_array_equal(samples.observations.numpy(), obs[index])
    np.testing.assert_array_equal(samples.actions.numpy(), actions[index])


@contextlib.contextmanager
def disk_full(monkeypatch, directory, budget=0, names=None):
    """
    ``os.write`` to files under ``directory`` (only those whose base name is in ``names``, if given) writes
    ``budget`` more bytes in all, then fails with ENOSPC, as a filling disk does (a short write, then an error).
    """
    real_write = os.write
    root = os.path.realpath(directory) + os.sep
    state = {"left": budget, "failures": 0}

    def write(fd, data):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            target = ""
        if not target.startswith(root) or (names is not None and os.path.basename(target) not in names):
            return real_write(fd, data)
        if state["left"] <= 0:
            state["failures"] += 1
            raise OSError(errno.ENOSPC, "No space left on device (injected)")
        written = real_write(fd, memoryview(data)[: state["left"]])
        state["left"] -= written
        return written

    monkeypatch.setattr(os, "write", write)
    try:
        yield state
    finally:
        monkeypatch.setattr(os, "write", real_write)


def make_buffer(path, layout, chunk_size=50, **kwargs):
    capacity = None if layout == "single" else 10_000
    return LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=path, chunk_size=chunk_size, capacity=capacity, **kwargs)


# ---------------------------------------------------------------------------------------------- disk full in a flush
@needs_proc
@pytest.mark.parametrize("layout", ["single", "chunked"])
@pytest.mark.parametrize("budget", [0, 7, 130, 1500])
def test_disk_full_during_flush_then_retry(tmp_path, monkeypatch, layout, budget):
    path = tmp_path / "b"
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)  # two chunks committed, 20 rows pending
    with disk_full(monkeypatch, path, budget=budget) as fault:
        with pytest.raises(OSError) as error:
            buffer.flush()
        assert error.value.errno == errno.ENOSPC and fault["failures"] == 1
        check_rows(buffer, 120)  # committed rows intact, the pending ones still served from memory
        assert buffer.store.num_committed == 100 and buffer.store.num_tail == 20
        with pytest.raises(OSError):  # still full: a retry fails the same way and changes nothing
            buffer.flush()
        check_rows(buffer, 120)
    buffer.flush()  # space freed: the retry writes the same bytes to the same place
    assert buffer.store.num_committed == 120
    check_rows(buffer, 120)
    add_rows(buffer, 120, 170)
    check_rows(buffer, 170)
    buffer.close()
    reopened = LifelongReplayBuffer.open(path, device="cpu", verify="all")
    check_rows(reopened, 170)
    if layout == "single":
        for name in FIELD_NAMES:  # no stray bytes after the committed rows
            assert os.path.getsize(path / f"{name}.bin") == 170 * reopened.store.row_bytes[name]


@needs_proc
@pytest.mark.parametrize("layout", ["single", "chunked"])
@pytest.mark.parametrize("n_envs", [1, 3])
def test_disk_full_in_add_then_retry(tmp_path, monkeypatch, layout, n_envs):
    path = tmp_path / "b"
    buffer = make_buffer(path, layout, chunk_size=31)
    row = add_rows(buffer, 0, 30, n_envs)  # the next add() fills the tail (after its first row) and flushes
    counts = buffer.source_counts()
    with disk_full(monkeypatch, path, budget=200):
        for _ in range(2):
            with pytest.raises(OSError):
                buffer.add(*transition(row, n_envs))
            assert buffer.size() == row and buffer.source_counts() == counts  # the failed add() stored nothing
            check_rows(buffer, row)
    row = add_rows(buffer, row, row + 30 * n_envs, n_envs)  # the same add() again, then more
    check_rows(buffer, row)
    assert buffer.source_counts() == {0: row}
    buffer.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), row)


RLIMIT_CHILD = r"""
import resource, signal, sys, types
import numpy as np
# the row store's modules import only numpy, the standard library and one another: load them without the package's
# __init__ (which imports torch and SB3), so that this process starts in a fraction of a second
for name, folder in (("sb3_lifelong", sys.argv[1]), ("sb3_lifelong.buffers", sys.argv[1] + "/buffers")):
    sys.modules[name] = types.ModuleType(name)
    sys.modules[name].__path__ = [folder]
from sb3_lifelong.buffers import rowstore
path, capacity = sys.argv[2], None if sys.argv[3] == "none" else int(sys.argv[3])
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past RLIMIT_FSIZE then fails with EFBIG
fields = {"observations": ("<f4", (4,)), "next_observations": ("<f4", (4,)), "actions": ("<f4", (2,)),
          "rewards": ("<f4", ()), "flags": ("|u1", ()), "sources": ("<u2", ()), "streams": ("<u4", ()),
          "widths": ("<u2", ())}
def rows(a, b):
    idx = np.arange(a, b)
    return {"observations": (idx[:, None] * 4 + np.arange(4)).astype(np.float32),
            "next_observations": (idx[:, None] * 4 + np.arange(4) + 0.5).astype(np.float32),
            "actions": np.stack([np.sin(idx), np.cos(idx)], 1).astype(np.float32),
            "rewards": (idx * 0.001).astype(np.float32), "flags": (idx % 3).astype(np.uint8),
            "sources": (idx // 1000).astype(np.uint16), "streams": (idx // 77).astype(np.uint32),
            "widths": np.ones(b - a, np.uint16)}
store = rowstore.RowStore(fields, path=path, chunk_size=1000, capacity=capacity)
store.append(rows(0, 30))
store.flush()
store.append(rows(30, 60))
soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
resource.setrlimit(resource.RLIMIT_FSIZE, (30 * 16 + 100, hard))  # room for 100 more bytes per file
try:
    store.flush()
    print("flushed", flush=True)
except OSError as error:
    print("error", error.errno, flush=True)
resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
store.flush()
expected = rows(0, 60)
live = all(np.array_equal(store.read_range(name, 0, 60), expected[name]) for name in fields)
print("live", live, store.num_committed, flush=True)
store.close()
"""


@pytest.mark.skipif(not hasattr(os, "getuid") or sys.platform != "linux", reason="RLIMIT_FSIZE test (Linux)")
@pytest.mark.parametrize("capacity", ["none", "100000"])
def test_file_size_limit_during_flush_then_retry(tmp_path, capacity):
    """A real short write (RLIMIT_FSIZE, EFBIG) in the middle of a flush, then a retry, in a subprocess."""
    path = tmp_path / "b"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    out = subprocess.run(
        [sys.executable, "-c", RLIMIT_CHILD, PACKAGE_DIR, str(path), capacity],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        check=True,
    ).stdout.split("\n")
    assert out[0] == f"error {errno.EFBIG}"
    assert out[1] == "live True 60"
    store = RowStore(path=str(path), verify="all")
    assert store.num_committed == 60
    idx = np.arange(60)
    expected = (idx[:, None] * 4 + np.arange(4)).astype(np.float32)
    np.testing.assert_array_equal(store.read_range("observations", 0, 60), expected)
    np.testing.assert_array_equal(store.read_range("rewards", 0, 60), (idx * 0.001).astype(np.float32))


# ---------------------------------------------------------------------------------------------- disk full in the manifest
@needs_proc
@pytest.mark.parametrize("layout", ["single", "chunked"])
@pytest.mark.parametrize("fault", ["write", "short write", "fsync", "replace"])
def test_manifest_write_fails_then_retry(tmp_path, monkeypatch, layout, fault):
    path = tmp_path / "b"
    buffer = make_buffer(path, layout, n_steps=3)
    add_rows(buffer, 0, 120)
    before = (path / "manifest.json").read_bytes()
    with contextlib.ExitStack() as stack:
        if fault in ("write", "short write"):
            budget = 0 if fault == "write" else 40
            stack.enter_context(disk_full(monkeypatch, path, budget=budget, names={"manifest.json.tmp"}))
        else:
            name = "fsync" if fault == "fsync" else "replace"
            real = getattr(os, name)

            def failing(*args):
                raise OSError(errno.EIO if name == "fsync" else errno.ENOSPC, f"{name} failed (injected)")

            def selective(*args):  # only the manifest's temporary file fails
                if name == "replace" or os.readlink(f"/proc/self/fd/{args[0]}").endswith("manifest.json.tmp"):
                    return failing(*args)
                return real(*args)

            stack.enter_context(monkeypatch.context()).setattr(os, name, selective)
        with pytest.raises(OSError):
            buffer.flush()
        # nothing committed in memory either: the 20 rows are still pending and served; the manifest is unchanged
        assert buffer.store.num_committed == 100 and buffer.store.num_tail == 20
        assert (path / "manifest.json").read_bytes() == before
        check_rows(buffer, 120)
        for _ in range(20):
            buffer.sample(64)
    assert not (path / "manifest.json.tmp").exists()
    buffer.flush()  # the retry writes the chunk and the manifest again, and maps the new rows
    assert buffer.store.num_committed == 120
    check_rows(buffer, 120)
    reader = LifelongReplayBuffer.open(path, read_only=True, device="cpu", verify="all")
    check_rows(reader, 120)
    add_rows(buffer, 120, 160)
    buffer.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), 160)


@needs_proc
def test_manifest_write_fails_while_evicting(tmp_path, monkeypatch):
    """With a capacity, a failed commit deletes no chunk file: the retained rows stay readable, and the retry evicts."""
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=path, chunk_size=20, capacity=50)
    add_rows(buffer, 0, 100)  # rows 50..99 retained (chunks from row 40 on listed)
    files = sorted(os.listdir(path))
    add_rows(buffer, 100, 119)
    with disk_full(monkeypatch, path, names={"manifest.json.tmp"}):
        with pytest.raises(OSError):
            add_rows(buffer, 119, 120)  # fills the chunk: flush, evict rows up to 69 (chunk 40 dropped)
        assert sorted(os.listdir(path)) == files  # the new chunk file was not kept, no evicted file deleted
        assert buffer.size() == 50 and buffer.store.num_committed == 100
        np.testing.assert_array_equal(buffer.store.read_range("rewards", 0, 50), rewards(69, 119))
    add_rows(buffer, 119, 120)
    assert buffer.store.committed_first == 70 and buffer.store.num_committed == 120
    assert "chunk.000000000040.bin" not in os.listdir(path) and "chunk.000000000060.bin" in os.listdir(path)
    np.testing.assert_array_equal(buffer.store.read_range("rewards", 0, 50), rewards(70, 120))
    buffer.close()
    reopened = LifelongReplayBuffer.open(path, device="cpu", verify="all")
    np.testing.assert_array_equal(reopened.store.read_range("rewards", 0, 50), rewards(70, 120))


# ---------------------------------------------------------------------------------------------- lost manifest
def snapshot(path):
    return {name: (path / name).read_bytes() for name in sorted(os.listdir(path)) if name != "writer.lock"}


@pytest.mark.parametrize("layout", ["single", "chunked"])
def test_lost_manifest_is_not_overwritten(tmp_path, layout):
    path = tmp_path / "b"
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)
    buffer.close()
    os.remove(path / "manifest.json")
    files = snapshot(path)
    data_file = "observations.bin" if layout == "single" else "chunk.000000000000.bin"
    attempts = [
        lambda: make_buffer(path, layout),  # the same constructor call that created it
        lambda: make_buffer(path, "chunked" if layout == "single" else "single"),
        lambda: LifelongReplayBuffer.open(path),
        lambda: LifelongReplayBuffer.open(path, read_only=True),
        lambda: RowStore({name: ("<f4", ()) for name in FIELD_NAMES}, path=str(path)),
    ]
    for attempt in attempts:
        with pytest.raises(BufferFormatError) as error:
            attempt()
        message = str(error.value)
        assert str(path) in message and "manifest.json" in message and data_file in message
        assert "move" in message.lower()
        assert snapshot(path) == files  # nothing truncated, deleted or created
    # the way out the message gives: move the files away
    moved = tmp_path / "lost"
    os.rename(path, moved)
    make_buffer(path, layout).close()
    assert snapshot(moved) == files


def test_empty_files_of_an_interrupted_creation_are_reused(tmp_path):
    """A writer killed while creating a directory leaves empty field files and no manifest: nothing to lose."""
    path = tmp_path / "b"
    path.mkdir()
    for name in FIELD_NAMES:
        (path / f"{name}.bin").write_bytes(b"")
    buffer = make_buffer(path, "single")
    add_rows(buffer, 0, 60)
    buffer.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), 60)


# ---------------------------------------------------------------------------------------------- file errors
def test_missing_field_file_is_called_a_field_file(tmp_path):
    path = tmp_path / "b"
    buffer = make_buffer(path, "single")
    add_rows(buffer, 0, 60)
    buffer.close()
    os.remove(path / "flags.bin")
    with pytest.raises(BufferFormatError, match=r"field file flags\.bin is missing") as error:
        LifelongReplayBuffer.open(path, read_only=True)
    assert "chunk" not in str(error.value)


def test_from_d4rl_names_the_file_it_cannot_read(tmp_path):
    single = tmp_path / "single.npz"
    with open(single, "wb") as file:  # np.save into a file named .npz: one array, no names
        np.save(file, np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"single\.npz.*single array.*np\.savez"):
        LifelongReplayBuffer.from_d4rl(single)
    objects = tmp_path / "objects.npz"
    np.savez(objects, observations=np.array([object()], dtype=object), rewards=np.zeros(1))
    with pytest.raises(ValueError, match=r"objects\.npz.*'observations'.*pickle"):
        LifelongReplayBuffer.from_d4rl(objects)
    pickled = tmp_path / "pickled.npz"
    pickled.write_bytes(pickle.dumps({"observations": np.zeros((2, 3))}))
    with pytest.raises(ValueError, match=r"pickled\.npz.*pickle"):
        LifelongReplayBuffer.from_d4rl(pickled)
    with pytest.raises(FileNotFoundError):
        LifelongReplayBuffer.from_d4rl(tmp_path / "missing.npz")


@pytest.mark.parametrize("layout", ["single", "chunked"])
def test_default_verify_checks_only_the_last_chunk(tmp_path, layout):
    """Documented behaviour: verify="last" (default) serves a flipped byte of an earlier chunk; "all" refuses it."""
    assert "earlier chunk" in " ".join(LifelongReplayBuffer.__doc__.split()) and "NOT detected" in LifelongReplayBuffer.__doc__
    path = tmp_path / "b"
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 100)  # two chunks of 50 rows
    buffer.close()
    data_file = path / ("rewards.bin" if layout == "single" else "chunk.000000000000.bin")
    data = bytearray(data_file.read_bytes())
    block = 0 if layout == "single" else 50 * (12 + 12 + 8)  # the rewards of the first chunk
    data[block + 4 * 3] ^= 0x40  # a byte of the reward of row 3
    data_file.write_bytes(bytes(data))
    reopened = LifelongReplayBuffer.open(path, device="cpu")  # default verify="last": not detected
    assert reopened.store.read_range("rewards", 3, 4)[0] != rewards(3, 4)[0]
    reopened.close()
    with pytest.raises(BufferFormatError, match="checksum"):
        LifelongReplayBuffer.open(path, device="cpu", verify="all")


# ---------------------------------------------------------------------------------------------- directory fsync fails
@contextlib.contextmanager
def directory_fsync_fails(monkeypatch, after_rename=True):
    """
    ``os.fsync`` of a directory fails with EIO: only the first one after the manifest's rename (``after_rename``), or
    the first one before it (layout "chunked": the sync of the new chunk file's directory entry).
    """
    real_fsync, real_replace = os.fsync, os.replace
    state = {"armed": not after_rename, "failures": 0}

    def replace(source, target, *args, **kwargs):
        result = real_replace(source, target, *args, **kwargs)
        if after_rename and os.path.basename(os.fspath(target)) == "manifest.json":
            state["armed"] = True
        return result

    def fsync(fd):
        if state["armed"] and stat.S_ISDIR(os.fstat(fd).st_mode):
            state["armed"] = False
            state["failures"] += 1
            raise OSError(errno.EIO, "Input/output error (injected)")
        return real_fsync(fd)

    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(os, "fsync", fsync)
    try:
        yield state
    finally:
        monkeypatch.setattr(os, "fsync", real_fsync)
        monkeypatch.setattr(os, "replace", real_replace)


@pytest.mark.parametrize("layout", ["single", "chunked"])
def test_directory_fsync_fails_after_the_manifest_rename(tmp_path, monkeypatch, layout):
    """
    The new manifest is in place but may not be durable: flush() raises CommitNotDurableError (it does not claim a
    durable commit), the rows are committed and served, no file the previous manifest needs is touched (so a power
    loss that brings the previous manifest back leaves a consistent buffer), and flush() again syncs it.
    """
    path = tmp_path / "b"
    buffer = make_buffer(path, layout, n_steps=3)
    add_rows(buffer, 0, 120)
    previous = (path / "manifest.json").read_bytes()
    previous_files = snapshot(path)
    with directory_fsync_fails(monkeypatch) as fault:
        with pytest.raises(CommitNotDurableError) as error:
            buffer.flush()
    assert fault["failures"] == 1 and isinstance(error.value, OSError) and error.value.errno == errno.EIO
    message = " ".join(str(error.value).split())
    assert "120 transitions are committed" in message and "power loss" in message and "flush()" in message
    assert buffer.store.num_committed == 120 and buffer.store.num_tail == 0
    check_rows(buffer, 120)
    check_rows(LifelongReplayBuffer.open(path, read_only=True, device="cpu", verify="all"), 120)
    for name, data in previous_files.items():  # committed bytes untouched: the previous manifest still fits them
        assert (path / name).read_bytes()[: len(data)] == data or name == "manifest.json"

    # a power loss may bring the previous manifest back: a copy of the directory with it is a consistent buffer
    lost = tmp_path / "after_power_loss"
    shutil.copytree(path, lost)
    (lost / "manifest.json").write_bytes(previous)
    (lost / "writer.lock").unlink()
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        check_rows(LifelongReplayBuffer.open(lost, device="cpu", verify="all"), 100)

    buffer.flush()  # syncs the manifest again
    add_rows(buffer, 120, 160)
    buffer.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), 160)


def test_directory_fsync_fails_while_evicting(tmp_path, monkeypatch):
    """With a capacity, the chunk files a not-durable commit drops are kept until a later manifest is synced."""
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=path, chunk_size=20, capacity=50)
    add_rows(buffer, 0, 119)  # rows 69..118 retained, chunks from row 40 on listed; 19 rows pending
    previous = (path / "manifest.json").read_bytes()
    with directory_fsync_fails(monkeypatch):
        with pytest.raises(CommitNotDurableError):
            add_rows(buffer, 119, 120)  # fills the chunk: commits rows 100..119 and drops chunk 40
    assert buffer.size() == 50 and buffer.source_counts() == {0: 50}  # the add's row is stored
    assert buffer.store.committed_first == 70 and buffer.store.num_committed == 120
    np.testing.assert_array_equal(buffer.store.read_range("rewards", 0, 50), rewards(70, 120))
    assert "chunk.000000000040.bin" in os.listdir(path)  # kept: the previous manifest lists it
    lost = tmp_path / "after_power_loss"
    shutil.copytree(path, lost)
    (lost / "manifest.json").write_bytes(previous)
    (lost / "writer.lock").unlink()
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        reopened = LifelongReplayBuffer.open(lost, device="cpu", verify="all")
    np.testing.assert_array_equal(reopened.store.read_range("rewards", 0, 50), rewards(50, 100))
    buffer.flush()  # the manifest is synced: the dropped chunk file goes
    assert "chunk.000000000040.bin" not in os.listdir(path)
    buffer.close()
    np.testing.assert_array_equal(
        LifelongReplayBuffer.open(path, device="cpu", verify="all").store.read_range("rewards", 0, 50), rewards(70, 120)
    )


def test_directory_fsync_fails_before_the_manifest(tmp_path, monkeypatch):
    """Layout "chunked": the new chunk file's entry is synced before a manifest names it; if that fails, nothing is
    committed (an ordinary failed flush)."""
    path = tmp_path / "b"
    buffer = make_buffer(path, "chunked")
    add_rows(buffer, 0, 120)
    files = snapshot(path)
    with directory_fsync_fails(monkeypatch, after_rename=False) as fault:
        with pytest.raises(OSError) as error:
            buffer.flush()
    assert fault["failures"] == 1 and not isinstance(error.value, CommitNotDurableError)
    assert snapshot(path) == files and buffer.store.num_committed == 100 and buffer.store.num_tail == 20
    check_rows(buffer, 120)
    buffer.flush()
    buffer.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), 120)


# ------------------------------------------------------------------------------- failures after the manifest's rename
@contextlib.contextmanager
def interrupted_after_the_rename(monkeypatch):
    """The first rename of a manifest happens, then raises KeyboardInterrupt (Ctrl-C before the directory's fsync)."""
    real_replace = os.replace
    state = {"interrupts": 0}

    def replace(source, target, *args, **kwargs):
        real_replace(source, target, *args, **kwargs)
        if os.path.basename(os.fspath(target)) == "manifest.json" and not state["interrupts"]:
            state["interrupts"] += 1
            raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", replace)
    try:
        yield state
    finally:
        monkeypatch.setattr(os, "replace", real_replace)


@pytest.mark.parametrize("layout", ["single", "chunked"])
def test_interrupt_after_the_manifest_rename_keeps_the_commit(tmp_path, monkeypatch, layout):
    """
    Ctrl-C after the new manifest's rename (in the directory's fsync): the rows are committed, so none of their bytes
    may be given back as if the commit had failed; the object counts them and goes on.
    """
    path = tmp_path / "b"
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)
    with interrupted_after_the_rename(monkeypatch) as fault:
        with pytest.raises(KeyboardInterrupt):
            buffer.flush()
    assert fault["interrupts"] == 1
    assert buffer.store.num_committed == 120 and buffer.store.num_tail == 0
    check_rows(buffer, 120)
    check_rows(LifelongReplayBuffer.open(path, read_only=True, device="cpu", verify="all"), 120)
    add_rows(buffer, 120, 160)
    buffer.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), 160)


@pytest.mark.parametrize("layout", ["single", "chunked"])
def test_interrupt_after_the_manifest_rename_in_add_keeps_every_row(tmp_path, monkeypatch, layout):
    """The same in an add() of three envs whose rows complete a chunk: the committed rows and the call's rows after
    them (pending) are all stored."""
    path = tmp_path / "b"
    buffer = make_buffer(path, layout, n_envs=3)
    add_rows(buffer, 0, 48, n_envs=3)  # 48 pending; the next add completes the chunk of 50 and leaves 1 pending
    with interrupted_after_the_rename(monkeypatch):
        with pytest.raises(KeyboardInterrupt):
            buffer.add(*transition(48, 3))
    assert buffer.store.num_committed == 50 and buffer.store.num_tail == 1
    check_rows(buffer, 51)
    buffer.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), 51)


@pytest.mark.parametrize("read_mode", ["mmap", "pread"])
@pytest.mark.parametrize("layout", ["single", "chunked"])
def test_reader_that_cannot_follow_a_commit_does_not_undo_it(tmp_path, monkeypatch, layout, read_mode):
    """
    Mapping (or opening) the new rows fails after the commit (ENOMEM, EMFILE): add() does not report the call as not
    stored, no row of it is lost, and reads map again once they can (raising while they cannot).
    """
    path = tmp_path / "b"
    buffer = make_buffer(path, layout, n_envs=3, read_mode=read_mode)
    add_rows(buffer, 0, 48, n_envs=3)
    reader = type(buffer.store._reader)
    real_sync = reader.sync
    state = {"failing": True}

    def sync(self, *args, **kwargs):
        if state["failing"]:
            raise OSError(errno.ENOMEM, "Cannot allocate memory (injected)")
        return real_sync(self, *args, **kwargs)

    monkeypatch.setattr(reader, "sync", sync)
    buffer.add(*transition(48, 3))  # commits rows 0-49, row 50 pending: no error
    assert buffer.store.num_committed == 50 and buffer.store.num_tail == 1
    with pytest.raises(OSError, match="injected"):
        buffer.store.read_range("rewards", 0, 51)
    state["failing"] = False
    check_rows(buffer, 51)
    buffer.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), 51)


@pytest.mark.parametrize("layout", ["single", "chunked"])
def test_writer_takes_the_lock_before_reading_the_manifest(tmp_path, monkeypatch, layout):
    """
    A second writer opens the directory while the first one commits and closes: it reads the manifest only once it
    holds the lock, so it sees the first writer's last rows instead of cutting them off as unflushed bytes.
    """
    path = tmp_path / "b"
    first = make_buffer(path, layout)
    add_rows(first, 0, 120)  # 100 committed, 20 pending
    real_take_lock = RowStore._take_lock
    state = {"raced": False}

    def take_lock(self, *args, **kwargs):
        if not state["raced"]:  # the first writer commits and closes just before the second one locks
            state["raced"] = True
            add_rows(first, 120, 130)
            first.close()
        return real_take_lock(self, *args, **kwargs)

    monkeypatch.setattr(RowStore, "_take_lock", take_lock)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "discarded bytes of unflushed rows"
        second = LifelongReplayBuffer.open(path, device="cpu")
    assert state["raced"]
    check_rows(second, 130)
    add_rows(second, 130, 160)
    second.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), 160)


# ---------------------------------------------------------------------------------------------- a large append fails
@needs_proc
@pytest.mark.parametrize("layout", ["single", "chunked"])
@pytest.mark.parametrize("budget", [0, 2500, 6000])
def test_large_add_that_fails_midway_stores_nothing(tmp_path, monkeypatch, layout, budget):
    """
    One add() of 130 envs (2 chunks and more, after 20 pending rows) whose writing fails after a first chunk (or
    before): none of its rows is stored, in the object or on disk; the pending rows stay; the error says so.
    """
    path = tmp_path / "b"
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)  # 100 committed, 20 pending
    manifest, counts = (path / "manifest.json").read_bytes(), buffer.source_counts()
    files = {name: data for name, data in snapshot(path).items() if name != "manifest.json"}
    data_files = {f"{name}.bin" for name in FIELD_NAMES} | {f"chunk.{start:012d}.bin" for start in (100, 150, 200)}
    with disk_full(monkeypatch, path, budget=budget, names=data_files) as fault:  # the manifest can be written
        with pytest.raises(OSError) as error:
            buffer.add(*transition(120, 130))
    assert fault["failures"] == 1 and error.value.errno == errno.ENOSPC
    assert buffer.size() == 120 and buffer.source_counts() == counts
    assert buffer.store.num_committed == 100 and buffer.store.num_tail == 20
    check_rows(buffer, 120)
    assert (path / "manifest.json").read_bytes() == manifest
    after = {name: data for name, data in snapshot(path).items() if name != "manifest.json"}
    assert after == files  # the bytes written were removed: no stray chunk file, field files cut back
    message = " ".join(str(error.value).split())
    assert str(path) in message and "none of the 130 transitions of this call was stored" in message
    assert "20 transitions pending before it stay" in message
    buffer.add(*transition(120, 130))  # the same add() again, once space is free
    check_rows(buffer, 250)
    assert buffer.store.num_committed == 250 and buffer.store.num_tail == 0
    buffer.close()
    check_rows(LifelongReplayBuffer.open(path, device="cpu", verify="all"), 250)


@needs_proc
def test_large_import_that_fails_midway_creates_no_rows(tmp_path, monkeypatch):
    """from_d4rl of more rows than a chunk into a directory: a failure midway commits none of them."""
    data = dict(zip(("observations", "next_observations", "actions", "rewards"), transition(0, 300)[:4]))
    data["terminals"] = np.zeros(300, bool)
    np.savez(tmp_path / "data.npz", **data)
    path = tmp_path / "b"
    with disk_full(monkeypatch, path, budget=5000, names={"chunk.000000000000.bin", "chunk.000000000064.bin"}):
        with pytest.raises(OSError, match="none of the 300 transitions"):
            LifelongReplayBuffer.from_d4rl(tmp_path / "data.npz", path=path, chunk_size=64, capacity=1000)
    store = RowStore(path=str(path))
    assert store.num_committed == 0 and not [name for name in os.listdir(path) if name.startswith("chunk.")]


@needs_proc
def test_learning_goes_on_after_a_failed_add_without_a_wrong_transition(tmp_path, monkeypatch):
    """MPO's add() fails (disk full) during learn(); learn(reset_num_timesteps=False) after space is freed starts a new
    episode instead of storing the observation before the failed step with the outcome of the next one."""
    from sb3_lifelong import MPO

    class Line(gym.Env):
        observation_space = gym.spaces.Box(-10.0, 10.0, (2,), np.float32)
        action_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.x, self.t = 3.0, 0
            return np.array([self.x, self.t], np.float32), {}

        def step(self, action):
            self.x, self.t = float(np.clip(self.x + 0.5 * float(action[0]), -10, 10)), self.t + 1
            return np.array([self.x, self.t], np.float32), -abs(self.x), False, self.t >= 50, {}

    path = tmp_path / "b"
    model = MPO(
        "MlpPolicy",
        Line(),
        seed=0,
        learning_starts=1000,
        replay_buffer_class=LifelongReplayBuffer,
        n_steps=3,
        replay_buffer_kwargs=dict(path=path, chunk_size=30),
    )
    model.learn(20)
    with disk_full(monkeypatch, path):
        with pytest.raises(OSError, match="none of the 1 transitions"):
            model.learn(20, reset_num_timesteps=False)  # the 30th transition completes a chunk: its flush fails
    model.learn(20, reset_num_timesteps=False)
    buffer = model.replay_buffer
    obs, next_obs = buffer.store.read_range("observations", 0, 49), buffer.store.read_range("next_observations", 0, 49)
    actions = buffer.store.read_range("actions", 0, 49)
    np.testing.assert_allclose(next_obs[:, 0], np.clip(obs[:, 0] + 0.5 * 2.0 * actions[:, 0], -10, 10), rtol=1e-6)
    np.testing.assert_array_equal(next_obs[:, 1], obs[:, 1] + 1)  # one step each: no step skipped
    assert obs[29, 1] == 0 and obs[29, 0] == 3.0  # the env was reset after the failure
    streams = buffer.store.read_range("streams", 0, 49)
    assert streams[29] != streams[28]  # n-step returns do not chain into the new episode
