"""
A buffer has an identity: a random id written in its manifest when it is created, kept by every later writer, and a
reader whose directory now holds another buffer (deleted and created again at the same path) refuses to refresh
instead of serving old and new rows together. Buffers created before ids existed keep working (identity unknown).
"""

import json
import shutil

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)
LAYOUTS = {"single": None, "chunked": 1000}


def add_rows(buffer: LifelongReplayBuffer, start: int, stop: int) -> None:
    for k in range(start, stop):
        obs = np.full((1, 3), k, dtype=np.float32)
        buffer.add(obs, obs + 1, np.zeros((1, 2), np.float32), np.array([k], np.float32), np.array([False]), [{}])


def written(path, layout: str, rows: int, first: int = 0) -> str:
    """A closed buffer of ``rows`` rows (rewards ``first``, ``first + 1``, ...) at ``path``; its id."""
    with LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=5, capacity=LAYOUTS[layout], mode="append") as buffer:
        add_rows(buffer, first, first + rows)
        return buffer.buffer_id


def manifest(path) -> dict:
    return json.loads((path / "manifest.json").read_text())


@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_buffer_gets_an_id_at_creation_and_keeps_it(tmp_path, layout):
    buffer_id = written(tmp_path / "buffer", layout, 7)
    assert isinstance(buffer_id, str) and len(buffer_id) == 32 and int(buffer_id, 16) >= 0
    assert manifest(tmp_path / "buffer")["buffer_id"] == buffer_id
    assert written(tmp_path / "buffer", layout, 3, first=7) == buffer_id  # reopened and appended to: the same buffer
    assert manifest(tmp_path / "buffer")["buffer_id"] == buffer_id and manifest(tmp_path / "buffer")["num_transitions"] == 10
    assert written(tmp_path / "other", layout, 7) != buffer_id
    with LifelongReplayBuffer(0, OBS, ACT, path=tmp_path / "buffer", capacity=LAYOUTS[layout], mode="overwrite") as fresh:
        assert fresh.buffer_id not in (None, buffer_id)  # deleted and created again: another buffer
    assert LifelongReplayBuffer(0, OBS, ACT).buffer_id is None  # in memory


@pytest.mark.parametrize("read_mode", ["mmap", "pread"])
@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_reader_refuses_to_refresh_once_its_buffer_was_replaced(tmp_path, layout, read_mode):
    """Before: the new buffer (more rows, same fields) passed refresh's checks, and the reader served the old rows it
    had mapped together with the new buffer's rows."""
    path = tmp_path / "buffer"
    written(path, layout, 10)
    reader = LifelongReplayBuffer.open(path, read_only=True, read_mode=read_mode)
    written(path, layout, 5, first=10)
    assert reader.refresh() == 15  # the same buffer, grown: followed
    shutil.rmtree(path)
    written(path, layout, 30, first=100)  # another buffer at the same path, with more rows
    with pytest.raises(BufferFormatError, match=r"now holds another buffer .*deleted and created again.*open it again"):
        reader.refresh()
    np.testing.assert_array_equal(reader.read_range("rewards", 0, reader.size()), np.arange(15))  # still what it read
    reader.close()
    with LifelongReplayBuffer.open(path, read_only=True, read_mode=read_mode) as again:
        np.testing.assert_array_equal(again.read_range("rewards", 0, 30), np.arange(100, 130))


def strip_id(path) -> None:
    """Make ``path`` a buffer as written before buffers had an id."""
    document = manifest(path)
    del document["buffer_id"]
    (path / "manifest.json").write_text(json.dumps(document))


@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_buffer_without_an_id_keeps_working(tmp_path, layout):
    path = tmp_path / "buffer"
    written(path, layout, 10)
    strip_id(path)
    reader = LifelongReplayBuffer.open(path, read_only=True)
    assert reader.buffer_id is None and reader.size() == 10
    assert written(path, layout, 5, first=10) is None  # a writer keeps it as it is: no id is made up later
    assert "buffer_id" not in manifest(path)
    assert reader.refresh() == 15
    np.testing.assert_array_equal(reader.read_range("rewards", 0, 15), np.arange(15))
    shutil.rmtree(path)
    written(path, layout, 30, first=100)  # replaced by a buffer that has an id: told apart
    with pytest.raises(BufferFormatError, match="now holds another buffer"):
        reader.refresh()
    reader.close()


def test_a_replaced_buffer_without_ids_is_caught_when_its_rows_go_down(tmp_path):
    """Without ids the replacement can only be seen when the new buffer holds fewer rows (documented)."""
    path = tmp_path / "buffer"
    written(path, "single", 10)
    strip_id(path)
    reader = LifelongReplayBuffer.open(path, read_only=True)
    shutil.rmtree(path)
    written(path, "single", 4)
    strip_id(path)
    with pytest.raises(BufferFormatError, match="committed rows went down from 10 to 4: the buffer was replaced"):
        reader.refresh()
    reader.close()


@pytest.mark.parametrize("bad", [17, "not-hex", "ABCDEF0123456789ABCDEF0123456789", "0" * 31])
def test_a_malformed_id_is_refused(tmp_path, bad):
    path = tmp_path / "buffer"
    written(path, "single", 3)
    document = manifest(path)
    document["buffer_id"] = bad
    (path / "manifest.json").write_text(json.dumps(document))
    with pytest.raises(BufferFormatError, match="'buffer_id' must be 32 lowercase hexadecimal digits"):
        LifelongReplayBuffer.open(path, read_only=True)
