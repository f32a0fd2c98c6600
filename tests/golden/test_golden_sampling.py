"""
Golden values of per-source sampling's run index (``buffers/sampling.py``'s ``RunIndex``) and of a merge of parts of
buffers: every expected number is computed here from the rows' sources (NumPy run lengths on the hand-made sequence),
never by calling the code under test. The cases reach what an ordinary test does not: a long life of many short runs
whose evicted runs are compacted away, an in-memory buffer erased and refilled, and a merge of the later part of
each buffer.
"""

import numpy as np
import pytest
from testkit import ACT, OBS

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import merge_buffers
from sb3_lifelong.buffers.sampling import RunIndex


def add_row(buffer: LifelongReplayBuffer, value: float) -> None:
    """one transition whose observations are all ``value``"""
    obs = np.full((1, *OBS.shape), value, np.float32)
    buffer.add(obs, obs, np.zeros((1, *ACT.shape), np.float32), np.zeros(1), np.zeros(1), [{}])


def np_runs(sources: np.ndarray, first: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """the runs of ``sources[first:]``: start (from ``first``), length and source of each"""
    kept = sources[first:]
    if len(kept) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.concatenate([[0], np.flatnonzero(kept[1:] != kept[:-1]) + 1])
    return starts, np.diff(np.append(starts, len(kept))), kept[starts]


@pytest.mark.parametrize("seed", [0, 1])
def test_the_run_index_of_a_long_life_of_short_runs_with_eviction(seed: int) -> None:
    """Hundreds of runs (the index compacts the evicted ones once they are most of it), read at every eviction point."""
    rng = np.random.default_rng(seed)
    lengths = rng.integers(1, 6, size=400)
    sources = np.repeat(np.arange(400) % 3 + (rng.integers(0, 2, size=400) * 3), lengths)
    index = RunIndex()
    at = 0
    for size in rng.integers(1, 40, size=10_000):  # appended in blocks of any size, as add() and append_rows() do
        if at >= len(sources):
            break
        index.extend(sources[at : at + size])
        at = min(at + size, len(sources))
    assert index.total == len(sources)
    for first in [0, 1, 7, len(sources) // 3, len(sources) // 2, 2 * len(sources) // 3, len(sources) - 2]:
        got = index.runs(first)  # eviction only moves forward: each read is from a later first row
        expected = np_runs(sources, first)
        for name, a, b in zip(("starts", "lengths", "sources"), got, expected):
            np.testing.assert_array_equal(a, b, err_msg=f"{name} from row {first}")
    assert index.count < 400  # the runs of evicted rows were forgotten for good


def test_an_erased_buffer_samples_its_new_rows_by_source() -> None:
    """``reset()`` of an in-memory buffer starts its run index again at row 0: per-source sampling stays exact."""
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu")
    for source, count in ((0, 4), (1, 3)):
        buffer.set_source(source)
        for _ in range(count):
            add_row(buffer, -1.0)
    buffer.reset()
    rows = [(0, 3), (1, 2), (0, 1)]  # after the erase: 3 rows of source 0, 2 of source 1, 1 of source 0
    values = []
    for source, count in rows:
        buffer.set_source(source)
        for _ in range(count):
            value = float(len(values))
            values.append((value, source))
            add_row(buffer, value)
    assert buffer.size() == 6
    buffer.set_sampling_weights({0: 0.0, 1: 1.0})
    drawn = buffer.sample(200).observations[:, 0].numpy()
    assert set(drawn.tolist()) == {3.0, 4.0}  # the rows of source 1, each of them, nothing else
    buffer.set_sampling_weights({0: 1.0, 1: 0.0})
    assert set(buffer.sample(300).observations[:, 0].numpy().tolist()) == {0.0, 1.0, 2.0, 5.0}


def test_a_merge_of_the_later_parts_holds_exactly_their_rows() -> None:
    """``merge_buffers(..., starts=...)``: the rows from each start on, in order; its size and buffer_size: their count."""
    buffers, expected = [], []
    for k, (count, start) in enumerate(((6, 2), (5, 0), (7, 4))):
        buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu")
        for i in range(count):
            add_row(buffer, 100.0 * k + i)
            if i >= start:
                expected.append(100.0 * k + i)
        buffers.append(buffer)
    merged = merge_buffers(buffers, starts=[2, 0, 4])
    assert merged.size() == merged.buffer_size == len(expected) == 4 + 5 + 3
    np.testing.assert_array_equal(merged.read_range("observations", 0, merged.size())[:, 0], expected)
