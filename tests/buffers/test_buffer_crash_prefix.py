"""
The buffer's rows after a crash at any write are a prefix of what was added (``hypothesis``).

A forked child adds a deterministic sequence of transitions to an on-disk buffer, flushing now and then, and dies
(``os._exit``, no cleanup, as a killed process does) just before its k-th file-system call that changes the directory
(a write, after writing part of its bytes; an fsync, truncate, rename or delete). The parent then opens the directory
as a new process would and checks that

- its rows are exactly the first ``n`` rows of the sequence, ``n`` at most what was added,
- ``n`` is at least what the child had seen committed (the rows added before its last ``flush()`` returned),
- the buffer takes new rows after the recovered ones, and they read back in order.

The calls are counted in a run without a crash first (the same deterministic scenario), so every k hits a real call.
"""

import mmap
import os
import struct
import tempfile
import warnings

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers.manifest import FIELD_NAMES

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)
#: the calls through which the buffer changes its directory (``os.write`` writes part of its bytes before dying)
CALLS = ("write", "fsync", "ftruncate", "truncate", "replace", "rename", "remove", "unlink")
CRASHED = 17  # the child's exit code when it died at its k-th call

needs_fork = pytest.mark.skipif(not hasattr(os, "fork"), reason="the crash is a forked child's death (needs os.fork)")


def transition(k: int, n_envs: int):
    """Rows k .. k + n_envs - 1 of a deterministic sequence, as add() arguments."""
    index = np.arange(k, k + n_envs)
    obs = np.stack([index, -index, index * 0.25], axis=1).astype(np.float32)
    actions = np.stack([np.sin(index), np.cos(index)], axis=1).astype(np.float32)
    infos = [{"TimeLimit.truncated": False} for _ in index]
    return obs, obs + 0.5, actions, (index * 0.001).astype(np.float32), index % 7 == 6, infos


def expected(count: int) -> dict:
    obs, next_obs, actions, rewards, _, _ = transition(0, count)
    return dict(observations=obs, next_observations=next_obs, actions=actions, rewards=rewards)


def new_buffer(path: str, layout: str, chunk_size: int, n_envs: int) -> LifelongReplayBuffer:
    capacity = None if layout == "single" else 100_000  # chunked, never evicting: the rows stay a prefix
    return LifelongReplayBuffer(0, OBS, ACT, device="cpu", n_envs=n_envs, path=path, chunk_size=chunk_size, capacity=capacity)


def scenario(path: str, layout: str, chunk_size: int, n_envs: int, adds: int, flush_every: int, seen) -> None:
    """Create the buffer, add ``adds`` steps of ``n_envs`` rows, flush every ``flush_every`` steps, close."""
    buffer = new_buffer(path, layout, chunk_size, n_envs)
    for step in range(adds):
        buffer.add(*transition(step * n_envs, n_envs))
        if (step + 1) % flush_every == 0:
            buffer.flush()
            seen((step + 1) * n_envs)
    buffer.close()
    seen(adds * n_envs)


class Counter:
    """Counts (and, from the k-th on, ends the process at) the calls of :data:`CALLS` on files under a directory."""

    def __init__(self, root: str, crash_at: int = 0):
        self.root = os.path.realpath(root) + os.sep
        self.crash_at = crash_at
        self.calls = 0
        self.real = {name: getattr(os, name) for name in CALLS if hasattr(os, name)}

    def _mine(self, name: str, args: tuple) -> bool:
        target = args[0]
        if isinstance(target, int):  # a descriptor: where does it point?
            try:
                target = os.readlink(f"/proc/self/fd/{target}")
            except OSError:
                return True  # cannot tell: count it (a call too many only moves the crash point)
        return os.path.realpath(os.fsdecode(target)).startswith(self.root) or name in ("replace", "rename")

    def wrap(self, name: str):
        real = self.real[name]

        def call(*args, **kwargs):
            if self._mine(name, args):
                self.calls += 1
                if self.calls == self.crash_at:
                    if name == "write" and len(args[1]) > 1:
                        real(args[0], bytes(args[1])[: len(args[1]) // 2])  # a torn write
                    os._exit(CRASHED)
            return real(*args, **kwargs)

        return call

    def __enter__(self):
        for name in self.real:
            setattr(os, name, self.wrap(name))
        return self

    def __exit__(self, *exc):
        for name, real in self.real.items():
            setattr(os, name, real)


def count_calls(layout: str, chunk_size: int, n_envs: int, adds: int, flush_every: int) -> int:
    with tempfile.TemporaryDirectory() as directory:
        with Counter(directory) as counter:
            scenario(os.path.join(directory, "b"), layout, chunk_size, n_envs, adds, flush_every, lambda rows: None)
        return counter.calls


def crash_child(path: str, root: str, crash_at: int, shared: mmap.mmap, **scenario_kwargs) -> int:
    """:return: the child's exit code (:data:`CRASHED` when it died at its ``crash_at``-th call)"""
    pid = os.fork()
    if pid == 0:  # the child: never returns
        code = 1
        try:

            def seen(rows: int) -> None:
                shared[:8] = struct.pack("<q", rows)  # memory, not a file: not a counted call

            with Counter(root, crash_at):
                scenario(path, seen=seen, **scenario_kwargs)
            code = 0
        except BaseException:  # an assertion in the child: reported by its exit code
            code = 1
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


@needs_fork
@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc/self/fd (Linux) to tell a descriptor's file")
@settings(max_examples=60, deadline=None)
@given(
    layout=st.sampled_from(["single", "chunked"]),
    chunk_size=st.integers(3, 40),
    n_envs=st.integers(1, 3),
    adds=st.integers(1, 60),
    flush_every=st.integers(1, 25),
    where=st.floats(0.0, 1.0, exclude_max=True),
)
def test_rows_after_a_crash_at_any_call_are_a_prefix_of_what_was_added(layout, chunk_size, n_envs, adds, flush_every, where):
    kwargs = dict(layout=layout, chunk_size=chunk_size, n_envs=n_envs, adds=adds, flush_every=flush_every)
    total = count_calls(**kwargs)
    assert total > 0
    crash_at = 1 + int(where * total)
    with tempfile.TemporaryDirectory() as root:
        path = os.path.join(root, "b")
        shared = mmap.mmap(-1, 8)
        shared[:8] = struct.pack("<q", 0)
        code = crash_child(path, root, crash_at, shared, **kwargs)
        assert code == CRASHED, f"the child ended with {code}, not at its call {crash_at} of {total}"
        committed_seen = struct.unpack("<q", shared[:8])[0]
        added = adds * n_envs
        if not os.path.exists(os.path.join(path, "manifest.json")):
            assert committed_seen == 0  # nothing was committed: no manifest is right
            return
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a recovery may warn about what it removed
            buffer = LifelongReplayBuffer.open(path, device="cpu", n_envs=n_envs, verify="all")
        rows = buffer.size()
        assert committed_seen <= rows <= added
        want = expected(added + 2 * n_envs)
        for name in FIELD_NAMES:
            if name in want:
                np.testing.assert_array_equal(buffer.read_range(name, 0, rows), want[name][:rows], err_msg=name)
        # the recovered buffer takes new rows right after the kept ones (they must be a whole step of n_envs rows)
        if rows % n_envs == 0:
            buffer.add(*transition(rows, n_envs))
            buffer.flush()
            assert buffer.size() == rows + n_envs
            for name in ("observations", "rewards"):
                np.testing.assert_array_equal(buffer.read_range(name, 0, rows + n_envs), want[name][: rows + n_envs])
        buffer.close()
