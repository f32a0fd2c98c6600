"""
A hostile ``manifest.json`` is refused with a ``BufferFormatError`` naming it, never a ``MemoryError``, a
``RecursionError`` or another exception: bounded size, nesting, numbers and row sizes, checked before anything is
parsed deeply or allocated; opening a directory allocates a bounded amount for its pending rows.
"""

import json
import math

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError, rowstore
from sb3_lifelong.buffers.manifest import MAX_ROW_BYTES

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)


def written(path) -> dict:
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=10)
    for k in range(25):
        obs = np.full((1, 3), k, np.float32)
        buffer.add(obs, obs + 1, np.zeros((1, 2), np.float32), np.array([k], np.float32), np.zeros(1), [{}])
    buffer.close()
    return json.loads((path / "manifest.json").read_text())


def big_row(manifest: dict) -> bytes:
    for name in ("observations", "next_observations"):
        manifest["fields"][name] = {"dtype": "<f8", "shape": [1 << 24]}
    return json.dumps(manifest).encode()


def number(manifest: dict, key: str, text: str) -> bytes:
    manifest[key] = 0
    return json.dumps(manifest).replace(f'"{key}": 0', f'"{key}": {text}').encode()


HOSTILE = {
    # before: MemoryError (a chunk of pending rows of 2 x 128 MiB each allocated when opening)
    "row of 2**24 float64": big_row,
    # before: RecursionError for writers (read-only opening caught it)
    "arrays nested 100k deep": lambda m: b"[" * 100_000 + b"]" * 100_000,
    "objects nested 100k deep": lambda m: b'{"a":' * 100_000 + b"1" + b"}" * 100_000,
    "nested inside a valid manifest": lambda m: json.dumps(m)
    .replace('"spaces": {', '"spaces": {"x": ' + "[" * 5000 + "]" * 5000 + ", ")
    .encode(),
    # before: ValueError (int digits limit) or, where there is none, a parse of quadratic time
    "a 5000-digit int": lambda m: number(m, "next_stream_id", "1" + "0" * 4999),
    "a 400-digit num_transitions": lambda m: number(m, "num_transitions", "9" * 400),
    # before: accepted (read-only), then a ValueError when the writer wrote its manifest back
    "a float out of range": lambda m: json.dumps(m).replace('"high": [', '"high": [1e400, ').encode(),
    # before: OverflowError while building the Discrete space
    "a Discrete of 10**30": lambda m: json.dumps(
        {**m, "spaces": {**m["spaces"], "action": {"type": "Discrete", "n": 10**30}}}
    ).encode(),
}


@pytest.mark.parametrize("read_only", [True, False])
@pytest.mark.parametrize("case", HOSTILE)
def test_hostile_manifest_is_a_format_error_naming_the_file(tmp_path, case, read_only):
    path = tmp_path / "b"
    raw = HOSTILE[case](written(path))
    (path / "manifest.json").write_bytes(raw)
    with pytest.raises(BufferFormatError, match=r"manifest\.json"):
        LifelongReplayBuffer.open(path, read_only=read_only)
    assert (path / "manifest.json").read_bytes() == raw  # nothing was written


def test_a_row_larger_than_the_bound_is_refused_when_creating(tmp_path):
    space = gym.spaces.Box(-1, 1, (MAX_ROW_BYTES // 8 + 1,), np.float64)
    with pytest.raises(BufferFormatError, match="more than the 67,108,864 a field's row may hold"):
        LifelongReplayBuffer(0, space, ACT, path=tmp_path / "b")
    assert not (tmp_path / "b" / "manifest.json").exists()


def test_opening_allocates_a_bounded_tail(tmp_path):
    """A writer of large rows allocates at most TAIL_PREALLOCATION bytes of pending rows when it opens (before: a whole
    chunk, here 10,000 rows of 2 x 16 MiB: MemoryError); a reader allocates none."""
    path = tmp_path / "b"
    manifest = written(path)
    for name in ("observations", "next_observations"):
        manifest["fields"][name] = {"dtype": "<f4", "shape": [1 << 22]}
    manifest["num_transitions"], manifest["chunks"], manifest["spaces"] = 0, [], {}
    (path / "manifest.json").write_text(json.dumps(manifest))
    for name in manifest["fields"]:
        (path / f"{name}.bin").write_bytes(b"")
    writer = LifelongReplayBuffer.open(path, chunk_size=10_000)
    assert sum(a.nbytes for a in writer.store._tail.values()) <= rowstore.TAIL_PREALLOCATION
    writer.close()
    reader = LifelongReplayBuffer.open(path, read_only=True)
    assert sum(a.nbytes for a in reader.store._tail.values()) == 0


@pytest.mark.parametrize("capacity", [None, 4, 1000])
def test_pending_rows_grow_up_to_a_chunk(tmp_path, monkeypatch, capacity):
    """The pending rows of a directory writer start smaller than a chunk when rows are large, and grow: every row is
    stored and committed as before, whatever the sizes of the adds (a capacity smaller than a chunk included)."""
    monkeypatch.setattr(rowstore, "TAIL_PREALLOCATION", 3 * 57)  # 3 rows of 57 bytes (obs 3 floats, ...)
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=10, capacity=capacity)
    assert len(buffer.store._tail["rewards"]) == 3
    k = 0
    for size in (1, 2, 3, 7, 12, 25, 4, 9, 1, 1, 30):
        index = np.arange(k, k + size)
        obs = np.stack([index, -index, index * 0.5], 1).astype(np.float32)
        buffer.add(obs, obs + 1, np.zeros((size, 2), np.float32), index.astype(np.float32), np.zeros(size), [{}] * size)
        k += size
        kept = k if capacity is None else min(k, capacity)
        np.testing.assert_array_equal(buffer.read_range("rewards", 0, buffer.size()), np.arange(k - kept, k))
    assert len(buffer.store._tail["rewards"]) <= 10
    buffer.close()
    reopened = LifelongReplayBuffer.open(path, read_only=True, verify="all")
    kept = k if capacity is None else min(k, capacity)
    np.testing.assert_array_equal(reopened.read_range("observations", 0, kept)[:, 0], np.arange(k - kept, k))
    assert math.isclose(float(reopened.read_range("rewards", kept - 1, kept)[0]), k - 1)
