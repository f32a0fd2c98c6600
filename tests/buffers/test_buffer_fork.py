"""
A writer that forks: the child's copy of a directory writer reads, never writes, commits or releases the directory,
and its exit (normal, with garbage collection and interpreter shutdown) commits nothing of the parent's.
"""

import atexit
import gc
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest

import sb3_lifelong
from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers.rowstore import ForkedWriterError, RowStore

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)
LAYOUTS = {"single": None, "chunked": 100_000}
needs_fork = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork (POSIX)")
PACKAGE_DIR = os.path.dirname(sb3_lifelong.__file__)  # where a light child process imports the row store from


def add_rows(buffer: LifelongReplayBuffer, start: int, stop: int) -> None:
    for k in range(start, stop):
        obs = np.array([[k, -k, 0.5 * k]], dtype=np.float32)
        buffer.add(obs, obs + 1, np.array([[0.1, -0.1]], np.float32), np.array([k * 0.01], np.float32), np.zeros(1), [{}])


def committed(path) -> int:
    with open(os.path.join(path, "manifest.json")) as file:
        return json.load(file)["num_transitions"]


def in_child(body, buffer: LifelongReplayBuffer) -> int:
    """
    Run ``body()`` in a child made by ``os.fork()``, then what a normal exit runs (the finalizer of ``buffer``'s store,
    garbage collection, ``atexit`` handlers) before leaving with ``os._exit`` (a child of pytest must not return into
    pytest; a real normal exit is tested by ``test_a_child_that_exits_normally_commits_nothing``).

    :return: the child's exit status (99: ``body`` raised something else)
    """
    pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        signal.alarm(60)  # a child that hangs is killed: the test fails instead of hanging
        code = 99
        try:
            code = body()
            buffer.store.__del__()
            gc.collect()
            atexit._run_exitfuncs()
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


@needs_fork
@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_forked_child_can_read_but_never_writes(tmp_path, layout):
    """Before: the child's add() and flush() returned normally (the parent's next commit overwrote those rows), and
    the child's normal exit committed the parent's pending rows."""
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=50, capacity=LAYOUTS[layout], device="cpu")
    add_rows(buffer, 0, 70)  # one committed chunk, 20 pending rows
    assert committed(path) == 50

    def child() -> int:
        refused = 0
        assert buffer.size() == 70 and buffer.sample(8).observations.shape == (8, 3)  # reading works
        np.testing.assert_array_equal(buffer.store.read_range("observations", 0, 70)[:, 0], np.arange(70))
        for call in (lambda: add_rows(buffer, 70, 71), buffer.flush, buffer.checkpoint, buffer.close):
            try:
                call()
            except ForkedWriterError as error:
                refused += "fork" in str(error) and str(path) in str(error)
        return 10 + refused  # 14: the four calls refused with a message naming the directory

    assert in_child(child, buffer) == 14
    assert committed(path) == 50  # the child's exit (its __del__ and shutdown included) committed nothing
    add_rows(buffer, 70, 100)  # the parent goes on: rows 0..99, every one its own
    buffer.close()
    reopened = LifelongReplayBuffer.open(path, read_only=True, verify="all")
    assert reopened.size() == 100
    np.testing.assert_array_equal(reopened.store.read_range("observations", 0, 100)[:, 0], np.arange(100))


EXITING_CHILD = r"""
import os, sys, types
import numpy as np
# the row store's modules import only numpy, the standard library and one another: load them without the package's
# __init__ (which imports torch and SB3), so that this process starts in a fraction of a second
for name, folder in (("sb3_lifelong", sys.argv[1]), ("sb3_lifelong.buffers", sys.argv[1] + "/buffers")):
    sys.modules[name] = types.ModuleType(name)
    sys.modules[name].__path__ = [folder]
from sb3_lifelong.buffers import rowstore
fields = {"observations": ("<f4", (3,)), "next_observations": ("<f4", (3,)), "actions": ("<f4", (2,)),
          "rewards": ("<f4", ()), "flags": ("|u1", ()), "sources": ("<u2", ()), "streams": ("<u4", ()),
          "widths": ("<u2", ())}
def rows(a, b):
    idx = np.arange(a, b)
    obs = np.stack([idx, -idx, idx * 0.5], 1).astype(np.float32)
    return {"observations": obs, "next_observations": obs + 1, "actions": np.zeros((b - a, 2), np.float32),
            "rewards": (idx * 0.01).astype(np.float32), "flags": np.zeros(b - a, np.uint8),
            "sources": np.zeros(b - a, np.uint16), "streams": np.zeros(b - a, np.uint32), "widths": np.ones(b - a, np.uint16)}
STORE = rowstore.RowStore(fields, path=sys.argv[2], chunk_size=50)
STORE.append(rows(0, 30))  # pending
if os.fork() == 0:
    if sys.argv[3] == "write":
        try:
            STORE.append(rows(1000, 1010))
        except rowstore.ForkedWriterError:
            print("refused", flush=True)
    sys.exit(0)  # a normal exit, STORE still referenced: the interpreter's shutdown finalizes it
_, status = os.wait()
print("child", os.waitstatus_to_exitcode(status), flush=True)
with open(os.path.join(sys.argv[2], "manifest.json")) as file:
    print("committed by the child's exit", __import__("json").load(file)["num_transitions"], flush=True)
STORE.append(rows(30, 40))
STORE.close()
"""


@needs_fork
@pytest.mark.parametrize("child", ["write", "exit"])
def test_a_child_that_exits_normally_commits_nothing(tmp_path, child):
    """Before: the child's exit (interpreter shutdown: the store's __del__ flushed) committed the parent's pending rows,
    and its own."""
    path = tmp_path / "b"
    out = subprocess.run(
        [sys.executable, "-c", EXITING_CHILD, PACKAGE_DIR, str(path), child],
        capture_output=True,
        text=True,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    expected = (["refused"] if child == "write" else []) + ["child 0", "committed by the child's exit 0"]
    assert out.stdout.split("\n")[:-1] == expected, out.stderr
    store = RowStore(path=str(path), read_only=True, verify="all")
    assert store.num_committed == 40  # the parent's rows, every one
    np.testing.assert_array_equal(store.read_range("observations", 0, 40)[:, 0], np.arange(40))


@needs_fork
def test_the_lock_stays_the_parents_and_leaves_with_it(tmp_path):
    """A writer's lock is released only by the process that took it, and a child does not keep it once the parent
    closed the buffer (before: the child's inherited descriptor kept the directory locked as long as it lived)."""
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=50)
    add_rows(buffer, 0, 10)
    ready_r, ready_w = os.pipe()
    done_r, done_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        signal.alarm(60)  # a child that hangs (e.g. the parent failed before releasing it) is killed
        code = 1
        try:
            try:
                buffer.close()  # refused: must not release the parent's lock
            except ForkedWriterError:
                pass
            try:
                LifelongReplayBuffer.open(path)
            except RuntimeError as error:
                code = 0 if "open for writing" in str(error) else 2  # still the parent's
            os.write(ready_w, b"x")
            os.read(done_r, 1)  # the parent closes and reopens meanwhile
        finally:
            os._exit(code)
    try:
        os.read(ready_r, 1)
        with pytest.raises(RuntimeError, match="open for writing"):
            LifelongReplayBuffer.open(path)  # the child's refused close() did not release it
        buffer.close()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            again = LifelongReplayBuffer.open(path)  # the child, still alive, does not hold the lock
        add_rows(again, 10, 20)
        again.close()
    finally:
        os.write(done_w, b"x")  # the child leaves, whatever happened here
        _, status = os.waitpid(pid, 0)
        for fd in (ready_r, ready_w, done_r, done_w):
            os.close(fd)
    assert os.waitstatus_to_exitcode(status) == 0
    assert committed(path) == 20


def _worker_adds(buffer: LifelongReplayBuffer, queue) -> None:
    try:
        add_rows(buffer, 100, 101)
        queue.put("added")
    except ForkedWriterError:
        queue.put("refused")


@needs_fork
def test_a_multiprocessing_fork_worker_is_refused(tmp_path):
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=50)
    add_rows(buffer, 0, 10)
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    worker = context.Process(target=_worker_adds, args=(buffer, queue))
    worker.start()
    assert queue.get(timeout=30) == "refused"
    worker.join(30)
    assert worker.exitcode == 0
    assert buffer.size() == 10
    buffer.close()
    assert committed(path) == 10


def test_in_memory_buffers_and_readers_are_not_owned(tmp_path):
    """Only a directory writer is tied to its process: an in-memory buffer is the child's own copy."""
    buffer = LifelongReplayBuffer(0, OBS, ACT)
    assert not buffer.store.forked() and buffer.store._owner_pid is None
    writer = LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "b")
    assert writer.store._owner_pid == os.getpid() and not writer.store.forked()
    writer.store._owner_pid = -1  # what a fork's copy sees
    with pytest.raises(ForkedWriterError, match="add"):
        add_rows(writer, 0, 1)
    assert writer.size() == 0
    writer.store._owner_pid = os.getpid()
    writer.close()
