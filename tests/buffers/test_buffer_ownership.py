"""
The lifetime buffer never destroys what it does not own: ``mode="overwrite"`` respects a live writer and deletes only
this package's buffer files, writes never follow a link planted in the directory, and a smaller capacity on reopening
evicts only when asked to.
"""

import json
import os
import warnings

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)
LAYOUTS = {"single": None, "chunked": 100_000}


def add_rows(buffer: LifelongReplayBuffer, start: int, stop: int) -> None:
    for k in range(start, stop):
        obs = np.array([[k, -k, 0.5 * k]], dtype=np.float32)
        action, reward = np.array([[0.1, -0.1]], np.float32), np.array([k * 0.01], np.float32)
        buffer.add(obs, obs + 1, action, reward, np.array([False]), [{}])


def assert_rows(buffer: LifelongReplayBuffer, count: int) -> None:
    assert buffer.size() == count
    np.testing.assert_array_equal(buffer.store.read_range("rewards", 0, count), (np.arange(count) * 0.01).astype(np.float32))
    np.testing.assert_array_equal(buffer.store.read_range("observations", 0, count)[:, 0], np.arange(count, dtype=np.float32))


def make(path, layout: str, **kwargs) -> LifelongReplayBuffer:
    return LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=50, capacity=LAYOUTS[layout], **kwargs)


def snapshot(directory) -> dict[str, bytes]:
    """Every file under ``directory`` (links as their target path), by relative name."""
    files = {}
    for root, _, names in os.walk(directory):
        for name in names:
            full = os.path.join(root, name)
            key = os.path.relpath(full, directory)
            files[key] = ("-> " + os.readlink(full)).encode() if os.path.islink(full) else open(full, "rb").read()
    return files


def reopen(path) -> LifelongReplayBuffer:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "recovered N transitions; discarded ..."
        return LifelongReplayBuffer.open(path, verify="all")


# ------------------------------------------------------------------------------------------------------ item 1
@pytest.mark.parametrize("layout", LAYOUTS)
def test_overwrite_is_refused_while_a_writer_is_live(tmp_path, layout):
    """Before: the directory was deleted and re-created under the live writer (its lock file became a new inode), whose
    next flush wrote into the new files: rows 0-99 read back as zeros."""
    path = tmp_path / "buffer"
    live = make(path, layout)
    add_rows(live, 0, 120)  # 100 committed, 20 pending
    before = snapshot(path)
    with pytest.raises(RuntimeError, match=r"is open for writing by another buffer"):
        make(path, layout, mode="overwrite")
    assert snapshot(path) == before  # nothing deleted
    add_rows(live, 120, 140)
    live.close()
    again = reopen(path)
    assert_rows(again, 140)
    again.close()


@pytest.mark.parametrize("layout", LAYOUTS)
def test_overwrite_of_a_closed_buffer_starts_empty_and_keeps_other_files(tmp_path, layout):
    path = tmp_path / "buffer"
    first = make(path, layout)
    add_rows(first, 0, 120)
    first.close()
    (path / "notes.txt").write_text("my notes on this run")
    (path / "plots").mkdir()
    (path / "plots" / "curve.png").write_bytes(b"png")
    fresh = make(path, layout, mode="overwrite")
    assert fresh.size() == 0
    add_rows(fresh, 0, 60)
    fresh.close()
    assert (path / "notes.txt").read_text() == "my notes on this run"  # not the buffer's: kept
    assert (path / "plots" / "curve.png").read_bytes() == b"png"
    again = reopen(path)
    assert_rows(again, 60)
    again.close()


# ------------------------------------------------------------------------------------------------------ item 2
FOREIGN_MANIFESTS = {
    "web app": '{"name": "My App", "short_name": "app", "start_url": "/index.html"}',
    "not json": "this is not json",
    "other format": json.dumps({"format": "sb3-lifelong-buffer", "version": 99}),
}


@pytest.mark.parametrize("manifest", FOREIGN_MANIFESTS)
def test_overwrite_refuses_a_directory_that_is_not_a_buffer(tmp_path, manifest):
    """Before: any directory holding a file named manifest.json was deleted, with every other file in it."""
    project = tmp_path / "web_project"
    (project / "static").mkdir(parents=True)
    (project / "manifest.json").write_text(FOREIGN_MANIFESTS[manifest])
    (project / "index.html").write_text("<html></html>")
    (project / "observations.bin").write_bytes(b"\x00" * 12)  # even a file named like a buffer's
    (project / "static" / "thesis.tex").write_text("\\chapter{Results}")
    before = snapshot(project)
    with pytest.raises(BufferFormatError, match=rf"refusing to overwrite {project}: mode='overwrite' deletes only"):
        make(project, "single", mode="overwrite")
    assert snapshot(project) == before  # nothing deleted, nothing created (no writer.lock)


def test_overwrite_refuses_a_manifest_that_is_a_link(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    real = make(elsewhere, "single")
    add_rows(real, 0, 60)
    real.close()
    path = tmp_path / "buffer"
    path.mkdir()
    os.symlink(elsewhere / "manifest.json", path / "manifest.json")
    with pytest.raises(BufferFormatError, match="is a link or not a regular file"):
        make(path, "single", mode="overwrite")
    again = reopen(elsewhere)
    assert_rows(again, 60)
    again.close()


# ------------------------------------------------------------------------------------------------------ item 4
@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_link_planted_at_the_temporary_manifest_is_never_written_through(tmp_path, layout):
    outside = tmp_path / "someone_elses_file.txt"
    outside.write_text("precious")
    path = tmp_path / "buffer"
    buffer = make(path, layout)
    add_rows(buffer, 0, 40)
    os.symlink(outside, path / "manifest.json.tmp")
    add_rows(buffer, 40, 120)  # commits twice
    buffer.close()
    assert outside.read_text() == "precious"
    assert not os.path.lexists(path / "manifest.json.tmp")
    again = reopen(path)
    assert_rows(again, 120)
    again.close()


def test_a_link_planted_at_the_next_chunk_file_is_never_written_through(tmp_path):
    """Before: the chunk's 4 KB of rows were written outside, and every reopen then failed (all rows unreadable)."""
    outside = tmp_path / "someone_elses_file.txt"
    outside.write_text("precious")
    path = tmp_path / "buffer"
    buffer = make(path, "chunked")
    add_rows(buffer, 0, 60)  # chunk 0 committed, the next one starts at row 50
    os.symlink(outside, path / "chunk.000000000050.bin")
    add_rows(buffer, 60, 130)
    buffer.close()
    assert outside.read_text() == "precious"
    assert not os.path.islink(path / "chunk.000000000050.bin")
    again = reopen(path)
    assert_rows(again, 130)
    again.close()


def test_a_field_file_replaced_by_a_link_is_never_written_through(tmp_path):
    outside = tmp_path / "someone_elses_file.txt"
    outside.write_text("precious")
    path = tmp_path / "buffer"
    buffer = make(path, "single")
    add_rows(buffer, 0, 60)
    os.rename(path / "rewards.bin", tmp_path / "rewards_moved.bin")
    os.symlink(outside, path / "rewards.bin")
    with pytest.raises(OSError, match=rf"{path}: flush\(\) failed before the commit"):
        buffer.flush()
    assert outside.read_text() == "precious"
    assert buffer.size() == 60  # the pending rows stay pending
    buffer.store._closed = True  # its directory was tampered with: do not flush again at garbage collection


@pytest.mark.parametrize("target_exists", [True, False])
def test_a_writer_lock_that_is_a_link_is_refused(tmp_path, target_exists):
    outside = tmp_path / "someone_elses_file.txt"
    if target_exists:
        outside.write_text("precious")
    path = tmp_path / "buffer"
    made = make(path, "single")
    add_rows(made, 0, 60)
    made.close()
    os.remove(path / "writer.lock")
    os.symlink(outside, path / "writer.lock")
    with pytest.raises(BufferFormatError, match=r"writer\.lock is a symbolic link"):
        LifelongReplayBuffer.open(path)
    if target_exists:
        assert outside.read_text() == "precious"
    else:
        assert not outside.exists()  # not created through the link either
    with LifelongReplayBuffer.open(path, read_only=True) as reader:  # readers take no lock
        assert_rows(reader, 60)


# ------------------------------------------------------------------------------------------------------ item 7
def test_reopening_with_a_smaller_capacity_evicts_only_when_asked(tmp_path):
    path = tmp_path / "buffer"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=50, capacity=1_000)
    add_rows(buffer, 0, 500)
    buffer.close()
    before = snapshot(path)
    with pytest.raises(ValueError, match=r"retains 500 transitions .*capacity=100 would evict the oldest 400 .*evict=True"):
        LifelongReplayBuffer.open(path, capacity=100)
    assert snapshot(path) == before  # nothing changed
    with LifelongReplayBuffer.open(path, capacity=600) as larger_than_held:  # evicts nothing: no opt-in needed
        assert larger_than_held.size() == 500 and larger_than_held.capacity == 600
    with LifelongReplayBuffer.open(path, capacity=100, evict=True) as smaller:
        assert smaller.size() == 100 and smaller.capacity == 100
        newest = (np.arange(400, 500) * 0.01).astype(np.float32)
        np.testing.assert_array_equal(smaller.store.read_range("rewards", 0, 100), newest)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_the_writer_lock_holds_where_there_is_no_fcntl(tmp_path, layout, monkeypatch):
    """Where ``fcntl`` does not exist (Windows) the writer lock goes through filelock: a second writer is still refused,
    and the lock is free again once the first closes (here simulated on POSIX, where filelock uses its own lock)."""
    from sb3_lifelong.buffers import layouts

    monkeypatch.setattr(layouts, "fcntl", None)
    path = tmp_path / "buffer"
    live = make(path, layout)
    add_rows(live, 0, 120)
    before = snapshot(path)
    with pytest.raises(RuntimeError, match=r"is open for writing by another buffer"):
        make(path, layout, mode="append")
    assert snapshot(path) == before
    live.close()
    again = make(path, layout, mode="append")  # the lock left with the writer that held it
    add_rows(again, 120, 140)
    again.close()
    reader = reopen(path)
    assert_rows(reader, 140)
    reader.close()
