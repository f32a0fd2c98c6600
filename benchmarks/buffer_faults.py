"""
Fault injection into LifelongReplayBuffer directories, both layouts ("single": one file per field, no capacity;
"chunked": one file per chunk, with a capacity). Prints a table and writes it to
``benchmarks/results/faults/buffer_faults.md``:
faults injected, transitions committed, transitions recovered bit-identical, lost, wrong rows served (the goal is 0
lost and 0 wrong).

Cases, for each layout:

- ``SIGKILL``: a child process appends transitions (batches of 1 to 3 chunks, chunks of 5 to 199 rows) and is killed
  with SIGKILL at a random moment (every fourth one possibly while it starts or creates the directory); the next
  child continues the same directory. After each kill the directory is reopened as a writer with ``verify="all"``.
- ``disk full: data`` / ``disk full: large add``: ENOSPC injected into ``os.write`` of the field or chunk files after
  a random number of bytes (a short write, then the error), during a ``flush()`` of 20 pending rows, or during one
  ``add()`` of 130 envs that completes three chunks; then space is "freed" and the same call is repeated.
- ``disk full: manifest``: the same for the manifest's temporary file; ``manifest fsync/rename``: EIO from its
  fsync, ENOSPC from its rename.
- ``directory fsync``: the fsync of the directory after the manifest's rename fails (EIO): ``CommitNotDurableError``;
  a copy of the directory with the previous manifest (what a power loss may leave) is opened too.
- ``Ctrl-C after the rename``, ``reader fails after a commit``, ``second writer, first closes``: see ``NOTES``.
- ``file size limit``: a real short write past ``RLIMIT_FSIZE`` (EFBIG) in a child, then a retry.
- ``lost manifest``: ``manifest.json`` deleted; creating or opening a buffer there (5 ways) must refuse and change no
  file; the manifest is then put back.
- ``live overwrite``: a second process opens the directory of a live writer with ``mode="overwrite"``: refused, nothing
  deleted, the live writer goes on.
- ``foreign directory``: ``mode="overwrite"`` on directories that hold a ``manifest.json`` of something else (a web
  app's, invalid JSON, an unknown format version) beside other files: refused, no file changed or created.
- ``crash after save``: a child trains MPO with a directory buffer, saves the model (a checkpoint) and is killed with
  SIGKILL right after; every transition of the checkpoint must be in the directory.
- ``planted symlinks``: links to a file outside the directory planted at ``manifest.json.tmp``, at the next chunk file
  (layout "chunked") or instead of a field file (layout "single"), and at ``writer.lock``: nothing may be written
  through them.
- ``forked writer``, ``add of non-real dtypes``, ``damaged chunk: salvage``, ``hostile manifest``: a writer's forked
  child writing and exiting; complex, datetime, string and object observations; a bit flip in one chunk, then
  ``check_directory`` and ``salvage``; hostile manifests (a huge row, deep nesting, a huge number). See ``NOTES``.

*Foreign bytes written or deleted* counts the bytes of files that are not the buffer's (outside its directory, or
in a directory that is not a buffer) that were written, changed, deleted or created.

Counting: *transitions committed* are those whose commit the writer was told of (``flush()`` / ``add()`` /
``append()`` returned, or the child printed it) and that the buffer must still hold (a capacity keeps only the most
recent ones), summed over the faults; *recovered bit-identical* are those of them that the reopened directory returns
byte for byte; *wrong rows served* counts every row returned by a read (``read_range`` over every retained row and
``sample`` on the live object during and after the fault, and on the reopened directory) that differs from what was
written.

Usage (Linux: ``/proc/self/fd`` and ``RLIMIT_FSIZE``; one thread)::

    OMP_NUM_THREADS=1 python benchmarks/buffer_faults.py
    OMP_NUM_THREADS=1 python benchmarks/buffer_faults.py --kills 8 --out /tmp/faults.md   # quicker
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import datetime
import errno
import functools
import gc
import json
import os
import platform
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Callable, Optional

import gymnasium as gym
import numpy as np

import sb3_lifelong
from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError, CommitNotDurableError
from sb3_lifelong.buffers.manifest import FIELD_NAMES
from sb3_lifelong.buffers.rowstore import RowStore

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)
PACKAGE_DIR = os.path.dirname(sb3_lifelong.__file__)  # where a light child process imports the row store from
LAYOUTS = ("single", "chunked")
CHUNK = 50
CHECKED = ("observations", "next_observations", "actions", "rewards", "flags", "sources")
NOTES = """
Cases, for each layout ("single": one file per field, no capacity; "chunked": one file per chunk, capacity 3,000 in the
SIGKILL loop, 100,000 elsewhere):

- *SIGKILL*: a child appends batches of 1 to 3 chunks (chunks of 5 to 199 rows) and is killed at a random moment
  (every fourth kill possibly while it starts or creates the directory); the next child continues the directory;
  after each kill it is reopened as a writer with `verify="all"` and every retained row is compared.
- *disk full: data*: ENOSPC from `os.write` on the field or chunk files after 0 to 800 bytes (a short write, then the
  error) during a `flush()` of 20 pending rows (100 committed); then the same `flush()` again.
- *disk full: large add*: the same during one `add()` of 130 envs that completes three chunks of 50 (after 20
  pending rows), failing after 0 to 6,700 of its 6,750 bytes; then the same `add()` again.
- *disk full: manifest*: ENOSPC on the manifest's temporary file after 0 to 600 bytes; *manifest fsync/rename*: EIO
  from its fsync, ENOSPC from its rename; then `flush()` again.
- *directory fsync*: the fsync of the directory after the manifest's rename fails with EIO (`CommitNotDurableError`);
  a copy of the directory with the previous manifest put back (what a power loss may leave) is opened too; then
  `flush()` again.
- *Ctrl-C after the rename*: `KeyboardInterrupt` right after the manifest's rename (before the directory's fsync),
  in a `flush()` of 20 pending rows and in an `add()` of 130 envs; the commit happened, so every row of the call
  must be stored (committed, or pending after the commit) and none of their bytes given back.
- *reader fails after a commit*: mapping (`read_mode="mmap"`) or opening (`"pread"`) the new rows fails with ENOMEM
  after an `add()` of 133 envs committed 250 rows (3 left pending): the add returns (its rows are stored), the next
  read raises (the report), and every row is there once the reader can follow.
- *second writer, first closes*: a second writer opens the directory while the first one commits its last rows
  and closes (injected just before the second one takes the lock); it must see those rows, not cut them off.
  These three cases came with their fixes (2026-11-24); the store before them lost 130, 6 and 60 of their
  transitions per layout (392 in all) and served 496 wrong rows.
- *file size limit*: a real short write past `RLIMIT_FSIZE` (EFBIG) in a child during a flush, then a retry.
- *lost manifest*: `manifest.json` deleted; creating or opening a buffer there in 5 ways must raise
  `BufferFormatError` and change no file; then the manifest is put back and the directory opened.
- *live overwrite*: a writer holds 100 committed and 20 pending transitions; a second process opens the directory with
  `mode="overwrite"` (it must be refused with the second writer's `RuntimeError`, nothing deleted); the writer adds
  20 more and closes.
- *foreign directory*: `mode="overwrite"` on a directory holding a `manifest.json` that is not a buffer's (a web app's
  manifest, invalid JSON, a buffer manifest of an unknown version) beside an `index.html`, a file named
  `observations.bin` and a subdirectory: it must raise `BufferFormatError` and change, delete or create no file.
- *crash after save*: a child collects 150, 230 or 310 Pendulum steps with MPO into a directory buffer (chunks of
  1,000, 64 or 100 transitions), saves the model and kills itself with SIGKILL; the transitions of the checkpoint
  (the model's timesteps, also recorded in the zip) must be in the directory, bit-identical to what the child held.
- *planted symlinks*: a link to a 16 KiB file outside the directory is planted at `manifest.json.tmp` (then a flush),
  at the next chunk file (layout "chunked", then a flush) or instead of `rewards.bin` (layout "single": the flush
  must fail, then the file is put back and the flush repeated), and at `writer.lock` of a closed buffer (opening it
  as a writer must fail; readers still open it). A fault counts as not reported when a write went through a link.
  These four cases came with their fixes (issue 32). The store before them (commit 3291fb1, run with `--kills 2`)
  lost 956 of their transitions (the live writer's 140 per layout, written into re-created files; 198 per layout
  of the checkpoints, still in memory at the kill; the 140 of the symlinked directory per layout, unreadable after),
  served 342 wrong rows, wrote or deleted 88,739 bytes of other files, and left 12 of these faults unreported (the
  overwrites it accepted, the writes it made through links).

- *forked writer*, *add of non-real dtypes*, *damaged chunk: salvage*, *hostile manifest* (issue 50): a writer with
  100 committed and 20 pending transitions forks; its child calls `add()`, `flush()` and `close()` (each must raise)
  and then runs what a normal exit runs (the store's finalizer, garbage collection, `atexit`): 4 faults, not reported
  when a call returned or the manifest changed; the parent then adds 20 more and closes. `add()` of complex,
  `datetime64`, numeric-string and object observations (each must raise a `ValueError`, nothing stored). A bit
  flipped in the second of three chunks of 50: `verify="all"` must refuse the directory, `check_directory` must name
  that chunk, and `salvage` must copy the other two chunks bit-identical (*transitions committed* counts those 100:
  the flipped chunk's rows were destroyed by the disk, not lost by the buffer; the default `verify="last"` serves
  the flipped row, as documented). A `manifest.json` with a row of 2**24 float64 elements, JSON nested 100,000
  levels or a number of 5,000 digits, opened read-only and as a writer: each must raise `BufferFormatError` naming
  the file and write nothing (a `MemoryError` or `RecursionError`, what the store did before, counts as not
  reported). These four cases came with their fixes (issue 50). The store before them (commit e0bb76f, these cases
  only) left 26 of their 30 faults unreported: the forked child's `add()`, `flush()` and `close()` returned (its row
  was committed, then overwritten by the parent's next commit) and its exit committed the parent's pending rows; the
  four `add()`s stored their rows (19 rows per layout, 78 wrong rows served in all); 5 of the 6 hostile manifests per
  layout raised something else than `BufferFormatError` (`RecursionError`, `ValueError`); and it had no salvage.

What the columns count:

- *faults injected*: the failures the buffer met (a SIGKILL, a failed write, fsync or rename, a lost manifest);
- *faults not reported*: those after which the call returned as if nothing had happened (goal 0; a SIGKILL cannot be
  reported);
- *transitions committed*: those whose commit the writer was told of (the call returned, or the child printed it)
  and that the buffer must still hold (with a capacity, the most recent ones), summed over the faults;
- *recovered bit-identical*: those of them that the directory, reopened with `verify="all"`, returns byte for byte;
  *lost* is the difference;
- *wrong rows served*: every row returned by a read (every retained row by `read_range`, and sampled rows, on the
  live buffer during and after the fault and on the reopened directory) that differs from what was written.
- *foreign bytes written or deleted*: bytes of files that are not the buffer's (outside its directory, or in a
  directory that is not a buffer) written, changed, deleted or created.

The `directory fsync` rows also count the previous commit (100 transitions) read back from a copy of the directory
with the previous manifest put back, which is what a power loss may leave after that fault. The pending (unflushed)
transitions that a SIGKILL loses were never committed and are not counted.
"""


@dataclass
class Tally:
    """One row of the table."""

    case: str
    layout: str
    faults: int = 0
    committed: int = 0
    recovered: int = 0
    wrong: int = 0
    runs: int = 0
    unreported: int = 0  # faults after which the call returned without an error
    foreign: int = 0  # bytes of files that are not the buffer's written, changed, deleted or created

    @property
    def lost(self) -> int:
        return self.committed - self.recovered


# ---------------------------------------------------------------------------------------------------------------- rows
def transition(k: int, n_envs: int = 1) -> tuple[Any, ...]:
    """Transitions k .. k + n_envs - 1 of a deterministic sequence, as add() arguments (one per env)."""
    index = np.arange(k, k + n_envs)
    obs = np.stack([index, -index, index * 0.25], axis=1).astype(np.float32)
    actions = np.stack([np.sin(index), np.cos(index)], axis=1).astype(np.float32)
    infos = [{"TimeLimit.truncated": bool(i % 11 == 10)} for i in index]
    return obs, obs + 0.5, actions, (index * 0.001).astype(np.float32), index % 5 == 4, infos


def expected(start: int, stop: int) -> dict[str, np.ndarray]:
    """What transitions start .. stop - 1 of :func:`transition` are stored as."""
    obs, next_obs, actions, rewards, dones, _ = transition(start, stop - start)
    index = np.arange(start, stop)
    flags = dones.astype(np.uint8) | (2 * (index % 11 == 10)).astype(np.uint8)
    return {
        "observations": obs,
        "next_observations": next_obs,
        "actions": actions,
        "rewards": rewards,
        "flags": flags,
        "sources": np.zeros(stop - start, np.uint16),
    }


def add_rows(buffer: LifelongReplayBuffer, start: int, stop: int) -> int:
    for k in range(start, stop):
        buffer.add(*transition(k))
    return stop


def matching_rows(store: RowStore, start: int, stop: int) -> int:
    """How many of the global rows start .. stop - 1 the store returns as written (read_range of every field)."""
    if stop <= start:
        return 0
    want = expected(start, stop)
    same = np.ones(stop - start, dtype=bool)
    for name in CHECKED:
        got = np.asarray(store.read_range(name, start - store.first, stop - store.first))
        same &= (got == want[name]).reshape(stop - start, -1).all(axis=1)
    return int(same.sum())


def served_wrong(buffer: LifelongReplayBuffer, count: int, batches: int = 4) -> int:
    """Rows a live buffer serves wrongly: every row by read_range (it must hold exactly rows 0 .. count - 1), and
    sampled rows (identified by their reward) compared with what was written."""
    store = buffer.store
    wrong = abs(len(store) - count) + (len(store) - matching_rows(store, store.first, store.end))
    for _ in range(batches):
        samples: Any = buffer.sample(64)
        index = np.rint(samples.rewards.numpy().reshape(-1) / np.float32(0.001)).astype(np.int64)
        valid = (index >= store.first) & (index < count)
        want = expected(0, count)
        index = np.where(valid, index, 0)
        same = valid & (samples.observations.numpy() == want["observations"][index]).all(axis=1)
        same &= (samples.actions.numpy() == want["actions"][index]).all(axis=1)
        wrong += int((~same).sum())
    return wrong


def reopen_and_check(path: str, committed: int, tally: Tally, first: int = 0) -> None:
    """Reopen the directory (writer, verify="all"): count the committed rows recovered and the wrong rows served."""
    tally.committed += committed - first
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "recovered N transitions; discarded B bytes ..."
            buffer = LifelongReplayBuffer.open(path, device="cpu", verify="all")
    except (BufferFormatError, OSError, RuntimeError) as error:  # the directory cannot be opened: every row is lost
        print(f"  {tally.case} {tally.layout}: reopening failed: {type(error).__name__}: {error}", file=sys.stderr)
        return
    store = buffer.store
    tally.recovered += matching_rows(store, max(first, store.first), min(committed, store.end))
    tally.wrong += served_wrong(buffer, store.end)
    buffer.close()


def make_buffer(
    path: str, layout: str, chunk_size: int = CHUNK, capacity: int = 100_000, **kwargs: Any
) -> LifelongReplayBuffer:
    return LifelongReplayBuffer(
        0,
        OBS,
        ACT,
        device="cpu",
        path=path,
        chunk_size=chunk_size,
        capacity=None if layout == "single" else capacity,
        **kwargs,
    )


# ------------------------------------------------------------------------------------------------------ fault helpers
@contextlib.contextmanager
def disk_full(directory: str, budget: int, names: Optional[set[str]] = None) -> Iterator[dict[str, int]]:
    """``os.write`` to files of ``directory`` (base names in ``names``, if given) writes ``budget`` more bytes in all,
    then fails with ENOSPC, as a filling disk does."""
    real_write = os.write
    root = os.path.realpath(directory) + os.sep
    state = {"left": budget, "failures": 0}

    def write(fd: int, data: Any) -> int:
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

    os.write = write
    try:
        yield state
    finally:
        os.write = real_write


@contextlib.contextmanager
def failing(name: str, error: int, when: Callable[..., bool]) -> Iterator[dict[str, int]]:
    """``os.<name>`` raises OSError(error) whenever ``when(*args)`` is true."""
    real = getattr(os, name)
    state = {"failures": 0}

    def patched(*args: Any, **kwargs: Any) -> Any:
        if when(*args):
            state["failures"] += 1
            raise OSError(error, f"{name} failed (injected)")
        return real(*args, **kwargs)

    setattr(os, name, patched)
    try:
        yield state
    finally:
        setattr(os, name, real)


@contextlib.contextmanager
def directory_fsync_fails() -> Iterator[dict[str, int]]:
    """The first fsync of a directory after the manifest's rename fails with EIO."""
    real_fsync, real_replace = os.fsync, os.replace
    state = {"armed": 0, "failures": 0}

    def replace(source: Any, target: Any, *args: Any, **kwargs: Any) -> None:
        real_replace(source, target, *args, **kwargs)
        if os.path.basename(os.fspath(target)) == "manifest.json":
            state["armed"] = 1

    def fsync(fd: int) -> None:
        if state["armed"] and stat.S_ISDIR(os.fstat(fd).st_mode):
            state["armed"] = 0
            state["failures"] += 1
            raise OSError(errno.EIO, "Input/output error (injected)")
        real_fsync(fd)

    os.replace, os.fsync = replace, fsync  # type: ignore[assignment]
    try:
        yield state
    finally:
        os.replace, os.fsync = real_replace, real_fsync  # type: ignore[assignment]


def data_files() -> set[str]:
    return {f"{name}.bin" for name in FIELD_NAMES} | {f"chunk.{start:012d}.bin" for start in range(0, 1000, CHUNK)}


# --------------------------------------------------------------------------------------------------- in-process cases
def write_fault(root: str, layout: str, tally: Tally, inject: Callable[[str], Any], operation: str) -> None:
    """
    100 rows committed and 20 pending; a fault during ``flush()`` (operation "flush") or during one ``add()`` of 130
    envs (operation "add"); reads during the fault; the same call again without the fault; reopen and compare.
    """
    path = os.path.join(root, f"{tally.case}-{layout}-{tally.runs}".replace(" ", "_").replace(":", ""))
    tally.runs += 1
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)
    count = 120 if operation == "flush" else 250
    try:
        failed = False
        with inject(path) as fault:
            try:
                if operation == "flush":
                    buffer.flush()
                else:
                    buffer.add(*transition(120, 130))
            except OSError:
                failed = True
        tally.faults += fault["failures"]
        tally.unreported += int(fault["failures"] > 0 and not failed)
        tally.wrong += served_wrong(buffer, 120 if failed else count)
        if failed:  # space freed: the same call again
            if operation == "flush":
                buffer.flush()
            else:
                buffer.add(*transition(120, 130))
        tally.wrong += served_wrong(buffer, count)
        buffer.close()
    except Exception as error:  # a failure to recover shows as lost rows
        print(f"  {tally.case} {layout}: {type(error).__name__}: {error}", file=sys.stderr)
    reopen_and_check(path, count, tally)


def directory_fsync_case(root: str, layout: str, tally: Tally) -> None:
    path = os.path.join(root, f"dirsync-{layout}")
    tally.runs += 1
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)
    previous = open(os.path.join(path, "manifest.json"), "rb").read()
    with directory_fsync_fails() as fault:
        try:
            buffer.flush()
            tally.unreported += 1  # a commit claimed that a power loss may undo
        except CommitNotDurableError:
            pass
    tally.faults += fault["failures"]
    tally.wrong += served_wrong(buffer, 120)  # committed, not durable: served
    lost = path + "-power-loss"
    shutil.copytree(path, lost)
    with open(os.path.join(lost, "manifest.json"), "wb") as file:
        file.write(previous)
    os.remove(os.path.join(lost, "writer.lock"))
    reopen_and_check(lost, 100, tally)  # the previous commit, acknowledged before the fault
    buffer.flush()  # synced now
    buffer.close()
    reopen_and_check(path, 120, tally)


@contextlib.contextmanager
def interrupted_after_the_rename() -> Iterator[dict[str, int]]:
    """The next rename of a manifest happens, then raises KeyboardInterrupt (Ctrl-C before the directory's fsync)."""
    real_replace = os.replace
    state = {"failures": 0}

    def replace(source: Any, target: Any, *args: Any, **kwargs: Any) -> None:
        real_replace(source, target, *args, **kwargs)
        if os.path.basename(os.fspath(target)) == "manifest.json" and not state["failures"]:
            state["failures"] += 1
            raise KeyboardInterrupt

    os.replace = replace  # type: ignore[assignment]
    try:
        yield state
    finally:
        os.replace = real_replace  # type: ignore[assignment]


def interrupt_case(root: str, layout: str, tally: Tally, operation: str) -> None:
    """Ctrl-C after the manifest's rename, in a ``flush()`` of 20 pending rows or an ``add()`` of 130 envs."""
    path = os.path.join(root, f"interrupt-{layout}-{operation}")
    tally.runs += 1
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)
    count = 120 if operation == "flush" else 250
    reported = False
    with interrupted_after_the_rename() as fault:
        try:
            if operation == "flush":
                buffer.flush()
            else:
                buffer.add(*transition(120, 130))
        except KeyboardInterrupt:
            reported = True
    tally.faults += fault["failures"]
    tally.unreported += int(not reported)
    tally.wrong += served_wrong(buffer, count)  # the commit happened: every row of the call is stored
    buffer.close()
    reopen_and_check(path, count, tally)


def reader_fails_case(root: str, layout: str, tally: Tally, read_mode: str) -> None:
    """
    The reader cannot follow a commit (ENOMEM from mapping, or opening, the new rows) in an ``add()`` of 133 envs:
    the add is committed and returns; the next read raises; once the reader can follow, every row is served.
    """
    path = os.path.join(root, f"reader-{layout}-{read_mode}")
    tally.runs += 1
    buffer = LifelongReplayBuffer(
        0, OBS, ACT, device="cpu", path=path, chunk_size=CHUNK, read_mode=read_mode,
        capacity=None if layout == "single" else 100_000,
    )  # fmt: skip
    add_rows(buffer, 0, 120)
    reader = type(buffer.store._reader)
    real_sync = reader.sync
    state = {"failing": 1}

    def sync(self: Any, *args: Any, **kwargs: Any) -> None:
        if state["failing"]:
            raise OSError(errno.ENOMEM, "Cannot allocate memory (injected)")
        real_sync(self, *args, **kwargs)

    reader.sync = sync  # type: ignore[method-assign]
    tally.faults += 1
    try:
        buffer.add(*transition(120, 133))  # commits 250 rows and leaves 3 pending
        try:
            buffer.store.read_range("rewards", 0, 253)
            tally.unreported += 1  # served rows the reader does not map
        except OSError:
            pass
    except OSError as error:  # an add that calls committed rows "not stored" shows as lost rows below
        print(f"  {tally.case} {layout}: {type(error).__name__}: {error}", file=sys.stderr)
    finally:
        reader.sync = real_sync  # type: ignore[method-assign]
    buffer.close()
    reopen_and_check(path, 253, tally)


def writer_race_case(root: str, layout: str, tally: Tally) -> None:
    """A second writer opens the directory while the first one commits its last rows and closes."""
    path = os.path.join(root, f"race-{layout}")
    tally.runs += 1
    first = make_buffer(path, layout)
    add_rows(first, 0, 120)
    real_take_lock = RowStore._take_lock

    def take_lock(self: RowStore, create: bool = False) -> bool:
        RowStore._take_lock = real_take_lock  # type: ignore[method-assign]
        add_rows(first, 120, 130)  # the first writer's last rows, committed by its close()
        first.close()
        tally.faults += 1
        return real_take_lock(self, create)

    RowStore._take_lock = take_lock  # type: ignore[method-assign]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            second = LifelongReplayBuffer.open(path, device="cpu")
    finally:
        RowStore._take_lock = real_take_lock  # type: ignore[method-assign]
    tally.wrong += served_wrong(second, 130)
    add_rows(second, 130, 160)
    second.close()
    reopen_and_check(path, 160, tally)


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
print("committed", store.num_committed, flush=True)
store.close()
"""


def store_rows(start: int, stop: int) -> dict[str, np.ndarray]:
    """The rows the child processes write (row i is a function of i)."""
    idx = np.arange(start, stop)
    return {
        "observations": (idx[:, None] * 4 + np.arange(4)).astype(np.float32),
        "next_observations": (idx[:, None] * 4 + np.arange(4) + 0.5).astype(np.float32),
        "actions": np.stack([np.sin(idx), np.cos(idx)], 1).astype(np.float32),
        "rewards": (idx * 0.001).astype(np.float32),
        "flags": (idx % 3).astype(np.uint8),
        "sources": (idx // 1000).astype(np.uint16),
        "streams": (idx // 77).astype(np.uint32),
        "widths": np.ones(stop - start, np.uint16),
    }


def store_matching(store: RowStore, start: int, stop: int) -> int:
    if stop <= start:
        return 0
    want = store_rows(start, stop)
    same = np.ones(stop - start, dtype=bool)
    for name, values in want.items():
        got = np.asarray(store.read_range(name, start - store.first, stop - store.first))
        same &= (got == values).reshape(stop - start, -1).all(axis=1)
    return int(same.sum())


def reopen_store(path: str, acknowledged: int, tally: Tally) -> RowStore:
    """Reopen a child's directory as a writer (verify="all"): count the acknowledged rows the capacity keeps."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        store = RowStore(path=path, verify="all")
    low = store.first if store.capacity is not None else 0
    tally.committed += max(acknowledged - low, 0)
    tally.recovered += store_matching(store, low, min(acknowledged, store.num_committed))
    tally.wrong += len(store) - store_matching(store, store.first, store.end)
    return store


def file_size_limit_case(root: str, layout: str, tally: Tally, env: dict[str, str]) -> None:
    path = os.path.join(root, f"rlimit-{layout}")
    tally.runs += 1
    out = subprocess.run(
        [sys.executable, "-c", RLIMIT_CHILD, PACKAGE_DIR, path, "none" if layout == "single" else "100000"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    ).stdout.split("\n")
    tally.faults += 1
    tally.unreported += int("flushed" in out)
    acknowledged = max([int(line.split()[1]) for line in out if line.startswith("committed")], default=0)
    reopen_store(path, acknowledged, tally).close()


def lost_manifest_case(root: str, layout: str, tally: Tally) -> None:
    path = os.path.join(root, f"lost-{layout}")
    tally.runs += 1
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)
    buffer.close()
    manifest = os.path.join(path, "manifest.json")
    saved = open(manifest, "rb").read()
    os.remove(manifest)
    tally.faults += 1

    def snapshot() -> dict[str, bytes]:
        return {
            name: open(os.path.join(path, name), "rb").read() for name in sorted(os.listdir(path)) if name != "writer.lock"
        }

    files = snapshot()
    attempts: list[Callable[[], Any]] = [
        lambda: make_buffer(path, layout),
        lambda: make_buffer(path, "chunked" if layout == "single" else "single"),
        lambda: LifelongReplayBuffer.open(path),
        lambda: LifelongReplayBuffer.open(path, read_only=True),
        lambda: RowStore({name: ("<f4", ()) for name in FIELD_NAMES}, path=path),
    ]
    for attempt in attempts:
        try:
            made = attempt()
        except BufferFormatError:
            pass
        else:  # it opened something: whatever it serves is not the data
            tally.unreported += 1
            tally.wrong += 120
            made.close()
    if snapshot() != files:
        print(f"  lost manifest {layout}: files changed", file=sys.stderr)
    with open(manifest, "wb") as file:  # the way back: the manifest is found again (e.g. restored from a copy)
        file.write(saved)
    reopen_and_check(path, 120, tally)


# ------------------------------------------------------------------------------------ ownership and checkpoint cases
def files_of(directory: str) -> dict[str, bytes]:
    """Every entry under ``directory`` by relative name: a file's bytes, a link's target, a directory's marker."""
    found: dict[str, bytes] = {}
    for parent, folders, names in os.walk(directory):
        for name in folders + names:
            full = os.path.join(parent, name)
            key = os.path.relpath(full, directory)
            if os.path.islink(full):
                found[key] = b"-> " + os.readlink(full).encode()
            elif os.path.isdir(full):
                found[key] = b"<dir>"
            else:
                with open(full, "rb") as file:
                    found[key] = file.read()
    return found


def bytes_changed(before: bytes, after: Optional[bytes]) -> int:
    """Bytes of a file written, changed or deleted (``after`` None: deleted; ``before`` empty: created)."""
    if after is None:
        return max(len(before), 1)
    if after == before:
        return 0
    common = min(len(before), len(after))
    differing = int(np.count_nonzero(np.frombuffer(before[:common], np.uint8) != np.frombuffer(after[:common], np.uint8)))
    return max(differing + abs(len(after) - len(before)), 1)  # a created empty file counts as one


def foreign_changed(before: dict[str, bytes], after: dict[str, bytes]) -> int:
    """Bytes written, changed, deleted or created among entries that are not the buffer's."""
    total = sum(bytes_changed(content, after.get(name)) for name, content in before.items())
    return total + sum(bytes_changed(b"", content) for name, content in after.items() if name not in before)


OVERWRITE_CHILD = r"""
import sys
import gymnasium as gym
import numpy as np
from sb3_lifelong import LifelongReplayBuffer
path, layout = sys.argv[1], sys.argv[2]
obs = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
act = gym.spaces.Box(-1, 1, (2,), np.float32)
try:
    LifelongReplayBuffer(0, obs, act, device="cpu", path=path, chunk_size=50,
                         capacity=None if layout == "single" else 100_000, mode="overwrite")
    print("accepted", flush=True)
except Exception as error:
    print("refused", type(error).__name__, error, flush=True)
"""


def live_overwrite_case(root: str, layout: str, tally: Tally, env: dict[str, str]) -> None:
    """A second process opens the directory of a live writer with mode="overwrite"; the writer goes on and closes."""
    path = os.path.join(root, f"live-overwrite-{layout}")
    tally.runs += 1
    live = make_buffer(path, layout)
    add_rows(live, 0, 120)  # 100 committed, 20 pending
    out = subprocess.run(
        [sys.executable, "-c", OVERWRITE_CHILD, path, layout], capture_output=True, text=True, env=env, timeout=300
    ).stdout
    tally.faults += 1
    tally.unreported += int("refused RuntimeError" not in out)
    try:
        tally.wrong += served_wrong(live, 120)
        add_rows(live, 120, 140)
        live.close()
    except Exception as error:  # e.g. files deleted under it: shows as lost rows
        print(f"  live overwrite {layout}: {type(error).__name__}: {error}", file=sys.stderr)
    reopen_and_check(path, 140, tally)


FOREIGN_MANIFESTS = (
    '{"name": "My App", "short_name": "app", "start_url": "/index.html", "display": "standalone"}',
    "not JSON at all",
    '{"format": "sb3-lifelong-buffer", "version": 99, "fields": {}}',
)


def foreign_directory_case(root: str, layout: str, tally: Tally) -> None:
    """mode="overwrite" on directories that hold a manifest.json of something else, beside other files."""
    for k, manifest in enumerate(FOREIGN_MANIFESTS):
        project = os.path.join(root, f"foreign-{layout}-{k}")
        os.makedirs(os.path.join(project, "static"))
        for name, content in {
            "manifest.json": manifest.encode(),
            "index.html": b"<html><body>" + b"x" * 1000 + b"</body></html>",
            "observations.bin": bytes(range(256)) * 4,  # named like a buffer's field file
            os.path.join("static", "thesis.tex"): b"\\chapter{Results}\n" * 50,
        }.items():
            with open(os.path.join(project, name), "wb") as file:
                file.write(content)
        before = files_of(project)
        tally.runs += 1
        tally.faults += 1
        try:
            make_buffer(project, layout, mode="overwrite").close()
            tally.unreported += 1
        except BufferFormatError:
            pass
        except Exception as error:  # refused, but not as a format error
            print(f"  foreign directory {layout}: {type(error).__name__}: {error}", file=sys.stderr)
        tally.foreign += foreign_changed(before, files_of(project))


SAVE_CHILD = r"""
import os, signal, sys
import numpy as np
import torch as th
th.set_num_threads(1)
from sb3_lifelong import MPO, LifelongReplayBuffer
path, zip_path, npz_path = sys.argv[1], sys.argv[2], sys.argv[3]
steps, chunk = int(sys.argv[4]), int(sys.argv[5])
capacity = None if sys.argv[6] == "none" else int(sys.argv[6])
model = MPO("MlpPolicy", "Pendulum-v1", seed=steps, learning_starts=10**6, policy_kwargs=dict(net_arch=[8]),
            replay_buffer_class=LifelongReplayBuffer,
            replay_buffer_kwargs=dict(path=path, chunk_size=chunk, capacity=capacity))
model.learn(steps)
store = model.replay_buffer.store
names = ("observations", "next_observations", "actions", "rewards", "flags", "sources")
np.savez(npz_path, **{name: np.asarray(store.read_range(name, 0, len(store))) for name in names})
model.save(zip_path)
print("saved", model.num_timesteps, flush=True)
os.kill(os.getpid(), signal.SIGKILL)  # right after the checkpoint: the buffer is never closed
"""


def crash_after_save_case(root: str, layout: str, tally: Tally, env: dict[str, str]) -> None:
    """A child saves an MPO model whose buffer is a directory, then is killed: the checkpoint's rows must be there."""
    for steps, chunk in ((150, 1000), (230, 64), (310, 100)):
        path = os.path.join(root, f"save-{layout}-{steps}")
        tally.runs += 1
        out = subprocess.run(
            [
                sys.executable, "-c", SAVE_CHILD, path, path + ".zip", path + ".npz", str(steps), str(chunk),
                "none" if layout == "single" else "100000",
            ],
            capture_output=True, text=True, env=env, timeout=600,
        ).stdout  # fmt: skip
        tally.faults += 1
        saved = [int(line.split()[1]) for line in out.split("\n") if line.startswith("saved")]
        if not saved:
            print(f"  crash after save {layout}: the child did not save: {out}", file=sys.stderr)
            continue
        with np.load(path + ".npz") as held:
            want = {name: held[name] for name in CHECKED}
        tally.committed += saved[0]
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                buffer = LifelongReplayBuffer.open(path, device="cpu", verify="all", read_only=True)
        except (BufferFormatError, OSError) as error:
            print(f"  crash after save {layout}: reopening failed: {type(error).__name__}: {error}", file=sys.stderr)
            continue
        count = min(buffer.size(), len(want["rewards"]))
        same = np.ones(count, dtype=bool)
        for name in CHECKED if count else ():
            got = np.asarray(buffer.store.read_range(name, 0, count))
            same &= (got == want[name][:count]).reshape(count, -1).all(axis=1)
        tally.recovered += int(same.sum())
        tally.wrong += int((~same).sum())
        buffer.close()


def planted_link(root: str, layout: str, name: str) -> tuple[str, bytes]:
    """A 16 KiB file outside the buffer directory, for a link planted in it to point to."""
    outside = os.path.join(root, f"someone-elses-{layout}-{name}")
    content = np.random.default_rng(len(name)).integers(0, 256, 16384, dtype=np.uint8).tobytes()
    with open(outside, "wb") as file:
        file.write(content)
    return outside, content


def planted_symlinks_case(root: str, layout: str, tally: Tally) -> None:
    """Links to a file outside the directory planted where the writer writes: nothing may be written through them."""
    path = os.path.join(root, f"symlinks-{layout}")
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)  # 100 committed, 20 pending

    def outside_changed(outside: str, content: bytes) -> int:
        with open(outside, "rb") as file:
            return bytes_changed(content, file.read())

    # the temporary manifest: the writer creates it anew, never through the link
    tally.runs += 1
    tally.faults += 1
    outside, content = planted_link(root, layout, "tmp")
    os.symlink(outside, os.path.join(path, "manifest.json.tmp"))
    try:
        buffer.flush()
    except OSError as error:
        print(f"  planted symlinks {layout}: {type(error).__name__}: {error}", file=sys.stderr)
    changed = outside_changed(outside, content)
    tally.foreign += changed
    tally.unreported += int(changed > 0)
    tally.wrong += served_wrong(buffer, 120)
    add_rows(buffer, 120, 140)  # pending again

    # the next data file: a new chunk file (created anew), or a field file replaced by a link (writing must fail)
    tally.runs += 1
    tally.faults += 1
    outside, content = planted_link(root, layout, "data")
    if layout == "chunked":
        os.symlink(outside, os.path.join(path, f"chunk.{buffer.store.num_committed:012d}.bin"))
        try:
            buffer.flush()
        except OSError as error:
            print(f"  planted symlinks {layout}: {type(error).__name__}: {error}", file=sys.stderr)
        tally.unreported += int(outside_changed(outside, content) > 0)
    else:
        field = os.path.join(path, "rewards.bin")
        os.rename(field, field + ".aside")
        os.symlink(outside, field)
        try:
            buffer.flush()
            tally.unreported += 1
        except OSError:
            pass
        os.remove(field)  # the real file put back, the flush repeated
        os.rename(field + ".aside", field)
        buffer.flush()
    tally.foreign += outside_changed(outside, content)
    tally.wrong += served_wrong(buffer, 140)
    buffer.close()

    # the writer lock of a closed buffer: opening it as a writer must fail (readers take no lock)
    tally.runs += 1
    tally.faults += 1
    outside, content = planted_link(root, layout, "lock")
    lock = os.path.join(path, "writer.lock")
    os.remove(lock)
    os.symlink(outside, lock)
    try:
        LifelongReplayBuffer.open(path, device="cpu").close()
        tally.unreported += 1
    except (BufferFormatError, OSError, RuntimeError):
        pass
    tally.foreign += outside_changed(outside, content)
    os.remove(lock)
    reopen_and_check(path, 140, tally)


# ------------------------------------------------------------------------------------------ safety cases (issue 50)
def forked_writer_case(root: str, layout: str, tally: Tally) -> None:
    """A writer forks: in the child, add(), flush() and close() must raise and its exit (its finalizers, atexit) must
    commit nothing; the parent then goes on. A fault is not reported when a call of the child returned normally or
    when the child's exit changed the manifest."""
    path = os.path.join(root, f"fork-{layout}")
    tally.runs += 1
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)  # 100 committed, 20 pending
    manifest = os.path.join(path, "manifest.json")
    before = open(manifest, "rb").read()
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: report how many of its calls returned normally, then exit as a normal exit would
        returned = 0
        try:
            for call in (lambda: buffer.add(*transition(10_000)), buffer.flush, buffer.close):
                try:
                    call()
                    returned += 1
                except RuntimeError:
                    pass
            buffer.store.__del__()
            gc.collect()
            atexit._run_exitfuncs()
        finally:
            os.write(write_end, bytes([returned]))
            os._exit(0)
    os.close(write_end)
    returned = os.read(read_end, 1)[0]
    os.close(read_end)
    os.waitpid(pid, 0)
    tally.faults += 4
    tally.unreported += returned + (open(manifest, "rb").read() != before)
    add_rows(buffer, 120, 140)
    tally.wrong += served_wrong(buffer, 140)
    buffer.close()
    reopen_and_check(path, 140, tally)


def wrong_dtype_case(root: str, layout: str, tally: Tally) -> None:
    """add() of observations that are not real numbers (complex, datetime, numeric strings, objects): each must raise
    before anything is stored (a fault is not reported when the add returned)."""
    path = os.path.join(root, f"dtype-{layout}")
    tally.runs += 1
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)
    obs, next_obs, actions, rewards, dones, infos = transition(120)
    for bad in (obs + 1j, np.full(obs.shape, "2024-05-01", "datetime64[D]"), obs.astype(str), obs.astype(object)):
        tally.faults += 1
        try:
            buffer.add(bad, next_obs, actions, rewards, dones, infos)
            tally.unreported += 1
        except ValueError:
            pass
    tally.wrong += served_wrong(buffer, 120)
    add_rows(buffer, 120, 140)
    buffer.close()
    reopen_and_check(path, 140, tally)


def damaged_chunk_case(root: str, layout: str, tally: Tally) -> None:
    """A bit flipped in the second of three committed chunks: opening with verify="all" must refuse the directory,
    check_directory must name that chunk, and salvage must copy the other two bit-identical. *Transitions committed*
    counts the rows of the intact chunks (the disk destroyed the flipped chunk's rows)."""
    path = os.path.join(root, f"damaged-{layout}")
    tally.runs += 1
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 150)
    buffer.close()
    if layout == "single":
        data_file, offset = os.path.join(path, "rewards.bin"), (CHUNK + 7) * 4
    else:
        data_file, offset = os.path.join(path, f"chunk.{CHUNK:012d}.bin"), CHUNK * (12 + 12 + 8) + 7 * 4
    with open(data_file, "r+b") as file:
        file.seek(offset)
        byte = file.read(1)[0]
        file.seek(offset)
        file.write(bytes([byte ^ 0x10]))
    tally.faults += 1
    try:
        LifelongReplayBuffer.open(path, read_only=True, verify="all").close()
        tally.unreported += 1
    except BufferFormatError:
        pass
    report = LifelongReplayBuffer.check_directory(path)
    if [c.start for c in report.damaged] != [CHUNK]:
        tally.unreported += 1
    copy, _ = LifelongReplayBuffer.salvage(path, os.path.join(root, f"salvaged-{layout}"), read_only=True, verify="all")
    tally.committed += 2 * CHUNK
    kept = np.r_[0:CHUNK, 2 * CHUNK : 3 * CHUNK]
    want = expected(0, 3 * CHUNK)
    same = np.ones(len(kept), dtype=bool)
    for name in CHECKED:
        got = np.asarray(copy.read_range(name, 0, copy.size()))
        if got.shape[0] != len(kept):
            same[:] = False
            break
        same &= (got == want[name][kept]).reshape(len(kept), -1).all(axis=1)
    tally.recovered += int(same.sum())
    tally.wrong += int((~same).sum())
    copy.close()


def hostile_manifest_case(root: str, layout: str, tally: Tally) -> None:
    """manifest.json replaced by a hostile one (a row of 2**24 float64 elements, JSON nested 100,000 levels, a number
    of 5,000 digits), opened by a reader and by a writer: each must raise BufferFormatError naming the file (any other
    outcome, MemoryError or RecursionError included, counts as not reported) and write nothing; then the real
    manifest is put back."""
    path = os.path.join(root, f"hostile-{layout}")
    tally.runs += 1
    buffer = make_buffer(path, layout)
    add_rows(buffer, 0, 120)
    buffer.close()
    name = os.path.join(path, "manifest.json")
    saved = open(name, "rb").read()
    manifest = json.loads(saved)
    big = json.loads(saved)
    for field in ("observations", "next_observations"):
        big["fields"][field] = {"dtype": "<f8", "shape": [1 << 24]}
    hostile = [
        json.dumps(big).encode(),
        b"[" * 100_000 + b"]" * 100_000,
        json.dumps(manifest).replace('"next_stream_id": ', '"next_stream_id": 1' + "0" * 5000 + ', "x": ').encode(),
    ]
    for raw in hostile:
        for read_only in (True, False):
            with open(name, "wb") as file:
                file.write(raw)
            tally.faults += 1
            try:
                LifelongReplayBuffer.open(path, read_only=read_only).close()
                tally.unreported += 1
            except BufferFormatError as error:
                tally.unreported += name not in str(error) or open(name, "rb").read() != raw
            except Exception as error:  # what this case looks for: MemoryError, RecursionError, ...
                print(f"  hostile manifest {layout}: {type(error).__name__}", file=sys.stderr)
                tally.unreported += 1
    with open(name, "wb") as file:
        file.write(saved)
    reopen_and_check(path, 120, tally)


# ------------------------------------------------------------------------------------------------------------ SIGKILL
KILL_CHILD = r"""
import sys, types
import numpy as np
# the row store's modules import only numpy, the standard library and one another: load them without the package's
# __init__ (which imports torch and SB3), so that this process starts in a fraction of a second
for name, folder in (("sb3_lifelong", sys.argv[1]), ("sb3_lifelong.buffers", sys.argv[1] + "/buffers")):
    sys.modules[name] = types.ModuleType(name)
    sys.modules[name].__path__ = [folder]
from sb3_lifelong.buffers import rowstore
path, chunk, seed = sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
capacity = None if sys.argv[5] == "none" else int(sys.argv[5])
fields = {"observations": ("<f4", (4,)), "next_observations": ("<f4", (4,)), "actions": ("<f4", (2,)),
          "rewards": ("<f4", ()), "flags": ("|u1", ()), "sources": ("<u2", ()), "streams": ("<u4", ()),
          "widths": ("<u2", ())}
store = rowstore.RowStore(fields, path=path, chunk_size=chunk, capacity=capacity)
rng = np.random.default_rng(seed)
print("open", store.num_committed, flush=True)
while True:
    start = store.end
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


def sigkill_loop(root: str, layout: str, kills: int, seed: int, tally: Tally, env: dict[str, str]) -> None:
    rng = np.random.default_rng(seed)
    path = os.path.join(root, f"sigkill-{layout}")
    capacity = "none" if layout == "single" else "3000"
    committed_before = 0
    for trial in range(kills):
        chunk = int(rng.integers(5, 200))
        child = subprocess.Popen(
            [sys.executable, "-c", KILL_CHILD, PACKAGE_DIR, path, str(chunk), str(trial), capacity],
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        # most kills let the child open the directory first; every fourth one may hit it while it starts or creates it
        first_line = "" if trial % 4 == 0 else (child.stdout.readline() if child.stdout else "")
        time.sleep(float(rng.uniform(0.05, 0.4)))
        child.send_signal(signal.SIGKILL)
        out, _ = child.communicate()
        tally.faults += 1
        tally.runs += 1
        lines = (first_line + out).split("\n")
        opened = [int(line.split()[1]) for line in lines if line.startswith("open")]
        if opened and opened[0] != committed_before:  # the writer must continue exactly at the last commit
            print(f"  SIGKILL {layout}: reopened at {opened[0]}, expected {committed_before}", file=sys.stderr)
            tally.wrong += abs(opened[0] - committed_before)
        acknowledged = max([int(line.split()[1]) for line in lines if line.startswith("committed")], default=0)
        acknowledged = max(acknowledged, committed_before)
        if not os.path.exists(os.path.join(path, "manifest.json")):  # killed while creating the directory
            tally.committed += acknowledged
            continue
        store = reopen_store(path, acknowledged, tally)
        committed_before = store.num_committed
        store.close()


# --------------------------------------------------------------------------------------------------------------- main
def run(kills: int, seed: int) -> list[Tally]:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    rng = np.random.default_rng(seed)
    tallies: list[Tally] = []
    root = tempfile.mkdtemp(prefix="buffer_faults_")
    try:
        for layout in LAYOUTS:
            tally = Tally("SIGKILL", layout)
            sigkill_loop(root, layout, kills, seed, tally, env)
            tallies.append(tally)

            tally = Tally("disk full: data", layout)
            for budget in [0, *sorted(rng.integers(1, 800, 5).tolist())]:  # a flush of 20 rows writes 900 bytes
                write_fault(root, layout, tally, functools.partial(disk_full, budget=budget, names=data_files()), "flush")
            tallies.append(tally)

            tally = Tally("disk full: large add", layout)
            for budget in [0, *sorted(rng.integers(1, 6700, 5).tolist())]:  # the add writes 150 rows, 6,750 bytes
                write_fault(root, layout, tally, functools.partial(disk_full, budget=budget, names=data_files()), "add")
            tallies.append(tally)

            tally = Tally("disk full: manifest", layout)
            for budget in (0, 40, 200, 600):
                write_fault(
                    root, layout, tally, functools.partial(disk_full, budget=budget, names={"manifest.json.tmp"}), "flush"
                )
            tallies.append(tally)

            tally = Tally("manifest fsync/rename", layout)

            def manifest_fd(fd: int) -> bool:
                return os.readlink(f"/proc/self/fd/{fd}").endswith("manifest.json.tmp")

            write_fault(root, layout, tally, lambda p: failing("fsync", errno.EIO, manifest_fd), "flush")
            write_fault(root, layout, tally, lambda p: failing("replace", errno.ENOSPC, lambda *a: True), "flush")
            tallies.append(tally)

            tally = Tally("directory fsync", layout)
            directory_fsync_case(root, layout, tally)
            tallies.append(tally)

            tally = Tally("Ctrl-C after the rename", layout)
            for operation in ("flush", "add"):
                interrupt_case(root, layout, tally, operation)
            tallies.append(tally)

            tally = Tally("reader fails after a commit", layout)
            for read_mode in ("mmap", "pread"):
                reader_fails_case(root, layout, tally, read_mode)
            tallies.append(tally)

            tally = Tally("second writer, first closes", layout)
            writer_race_case(root, layout, tally)
            tallies.append(tally)

            tally = Tally("file size limit", layout)
            file_size_limit_case(root, layout, tally, env)
            tallies.append(tally)

            tally = Tally("lost manifest", layout)
            lost_manifest_case(root, layout, tally)
            tallies.append(tally)

            tally = Tally("live overwrite", layout)
            live_overwrite_case(root, layout, tally, env)
            tallies.append(tally)

            tally = Tally("foreign directory", layout)
            foreign_directory_case(root, layout, tally)
            tallies.append(tally)

            tally = Tally("crash after save", layout)
            crash_after_save_case(root, layout, tally, env)
            tallies.append(tally)

            tally = Tally("planted symlinks", layout)
            planted_symlinks_case(root, layout, tally)
            tallies.append(tally)

            for case, function in (
                ("forked writer", forked_writer_case),
                ("add of non-real dtypes", wrong_dtype_case),
                ("damaged chunk: salvage", damaged_chunk_case),
                ("hostile manifest", hostile_manifest_case),
            ):
                tally = Tally(case, layout)
                function(root, layout, tally)
                tallies.append(tally)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return tallies


def table(tallies: list[Tally]) -> list[str]:
    lines = [
        "| case | layout | runs | faults injected | faults not reported | transitions committed | recovered bit-identical "
        "| lost | wrong rows served | foreign bytes written or deleted |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    total = Tally("**total**", "")
    for t in [*tallies, total]:
        lines.append(
            f"| {t.case} | {t.layout} | {t.runs} | {t.faults} | {t.unreported} | {t.committed:,} | {t.recovered:,} | "
            f"{t.lost:,} | {t.wrong:,} | {t.foreign:,} |"
        )
        if t is not total:
            for name in ("runs", "faults", "unreported", "committed", "recovered", "wrong", "foreign"):
                setattr(total, name, getattr(total, name) + getattr(t, name))
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kills", type=int, default=32, help="SIGKILLs per layout")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "faults", "buffer_faults.md"))
    args = parser.parse_args()
    if not os.path.isdir("/proc/self/fd"):
        sys.exit("needs Linux (/proc/self/fd)")
    started = time.perf_counter()
    tallies = run(args.kills, args.seed)
    elapsed = time.perf_counter() - started
    lines = table(tallies)
    print("\n".join(lines))
    print(f"{elapsed:.0f} s")
    command = (
        "OMP_NUM_THREADS=1 python benchmarks/buffer_faults.py"
        + (f" --kills {args.kills}" if args.kills != 32 else "")
        + (f" --seed {args.seed}" if args.seed else "")
    )
    ok = all(t.lost == 0 and t.wrong == 0 and t.unreported == 0 and t.foreign == 0 for t in tallies)
    report = [
        "# LifelongReplayBuffer under injected faults",
        "",
        f"Command: `{command}` ({datetime.date.today().isoformat()}, {elapsed:.0f} s; {platform.system()} "
        f"{platform.release()}, {os.cpu_count()} cores shared with other jobs, Python {platform.python_version()}, "
        f"numpy {np.__version__}).",
        "",
        *lines,
        "",
        "Result: "
        + (
            "every fault was reported, no committed transition was lost, no wrong row was served and no byte of a file "
            "that is not the buffer's was written or deleted."
            if ok
            else "FAILURES: see the columns faults not reported / lost / wrong / foreign bytes."
        ),
        "",
        *NOTES.strip().split("\n"),
    ]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as file:
        file.write("\n".join(report) + "\n")
    print(f"written to {args.out}")
    if not ok:
        sys.exit(1)


if __name__ == "__main__":
    main()
