"""
Golden values of sampling through several buffers at once (``LifelongBufferView`` and ``merge_buffers``): three tiny
buffers whose every row is recognisable (its observation's first entry names the buffer and the row), shared source
ids spread over the buffers in runs of different lengths, and one source of weight 0. Every expected number is written
here from the rows (NumPy on the hand-made table), never by calling the code under test:

- a sampled transition is one stored row, all of it (observation, action, reward, next observation, done);
- each source's share of the samples is ``w_s N_s / sum_t w_t N_t`` (``set_sampling_weights``) within five binomial
  standard deviations, and the rows of a source are drawn uniformly (a chi-square bound), whatever run they sit in;
- ``read_range`` and the gather of scattered indices across the buffers' boundaries are the NumPy concatenation's rows;
- the n-step returns stop at the end of a buffer (and at a terminal or a timeout), with the discounts ``gamma^k``.
"""

from typing import Union

import numpy as np
import pytest
import torch as th
from testkit import ACT, OBS

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import LifelongBufferView, merge_buffers
from sb3_lifelong.buffers.manifest import FLAG_DONE, FLAG_TIMEOUT

GAMMA = 0.5
#: per buffer, its rows' sources in order (runs of different lengths: a per-run choice would not be uniform per source)
LAYOUT = [
    [0, 0, 0, 0, 1, 1, 0, 0],  # buffer 0: source 0 in two runs (4 and 2 rows), source 1 in one of 2 rows
    [1, 1, 1, 1, 1, 1, 2, 2, 2],  # buffer 1: source 1 (6 rows: 8 in all), source 2 (3 rows)
    [2, 2, 2, 2, 2, 3, 3],  # buffer 2: source 2 (5 rows: 8 in all), source 3 (2 rows, weight 0 below)
]
#: (buffer, row) -> episode end: a terminal, or a time-limit truncation (done and TimeLimit.truncated)
TERMINALS = {(0, 3), (1, 8), (2, 2)}
TIMEOUTS = {(0, 5), (1, 2)}
WEIGHTS = {0: 2.0, 1: 0.5, 2: 1.5, 3: 0.0}

Data = Union[LifelongBufferView, LifelongReplayBuffer]


def row_values(k: int, i: int, source: int) -> dict[str, np.ndarray]:
    """The row ``i`` of buffer ``k``: every field says which row it is (exact in float32)."""
    return {
        "observations": np.array([100.0 * k + i, source, 0.25 * i], dtype=np.float32),
        "next_observations": np.array([100.0 * k + i + 0.5, -source, 1.0 + k], dtype=np.float32),
        "actions": np.array([(i + 1) / 16.0, -k / 4.0], dtype=np.float32),
        "rewards": np.float32(1000.0 * k + i),
    }


def make_buffers() -> tuple[list[LifelongReplayBuffer], dict[str, np.ndarray]]:
    """:return: the three buffers and the table of all their rows, in order (the NumPy concatenation)"""
    buffers, table = [], {name: [] for name in ("observations", "next_observations", "actions", "rewards", "flags", "sources")}
    for k, sources in enumerate(LAYOUT):
        buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", n_steps=1)
        for i, source in enumerate(sources):
            buffer.set_source(source)
            row = row_values(k, i, source)
            done, truncated = (k, i) in TERMINALS | TIMEOUTS, (k, i) in TIMEOUTS
            buffer.add(
                row["observations"][None],
                row["next_observations"][None],
                row["actions"][None],
                np.array([row["rewards"]]),
                np.array([done]),
                [{"TimeLimit.truncated": truncated}],
            )
            for name, value in row.items():
                table[name].append(value)
            table["flags"].append(FLAG_DONE * done | FLAG_TIMEOUT * truncated)
            table["sources"].append(source)
        buffers.append(buffer)
    return buffers, {name: np.array(values) for name, values in table.items()}


def key_of(observations: np.ndarray) -> np.ndarray:
    """:return: the table index of each observation (its first entry is ``100 * buffer + row``)"""
    starts = np.cumsum([0] + [len(sources) for sources in LAYOUT])
    code = observations[:, 0].astype(np.int64)
    return starts[code // 100] + code % 100


def data_of(kind: str, buffers: list[LifelongReplayBuffer], n_steps: int = 1) -> Data:
    if kind == "view":
        return LifelongBufferView(buffers, n_steps=n_steps, gamma=GAMMA)
    return merge_buffers(buffers, n_steps=n_steps, gamma=GAMMA)


@pytest.mark.parametrize("kind", ["view", "merged"])
@pytest.mark.parametrize("weighted", [True, False])
def test_weighted_samples_are_whole_rows_in_the_requested_shares_and_uniform_per_source(kind: str, weighted: bool) -> None:
    """
    Catches a gather that mixes rows across buffers (an observation of one row with another's action or reward), an
    index offset across a boundary, weights applied per run or per row instead of per source, a row never drawn (a
    start or length off by one), a weight of 0 still drawn, and timeouts reported as terminal dones.
    """
    buffers, table = make_buffers()
    data = data_of(kind, buffers)
    total = len(table["rewards"])
    assert data.size() == total
    counts_per_source = np.bincount(table["sources"])
    if weighted:
        data.set_sampling_weights(WEIGHTS)
        mass = counts_per_source * np.array([WEIGHTS[s] for s in range(len(counts_per_source))])
    else:
        mass = counts_per_source.astype(float)
    shares = mass / mass.sum()
    np.random.seed(0)
    batches, batch = 40, 1000
    seen, seen_sources = [], []
    for _ in range(batches):
        samples, sources = data.sample(batch, return_sources=True)
        obs = samples.observations.numpy()
        index = key_of(obs)
        # (a) the whole transition is the stored row the observation names, with that row's source
        np.testing.assert_array_equal(obs, table["observations"][index])
        np.testing.assert_array_equal(samples.actions.numpy(), table["actions"][index])
        np.testing.assert_array_equal(samples.next_observations.numpy(), table["next_observations"][index])
        np.testing.assert_array_equal(samples.rewards.numpy()[:, 0], table["rewards"][index])
        terminal = ((table["flags"] & FLAG_DONE) != 0) & ((table["flags"] & FLAG_TIMEOUT) == 0)
        np.testing.assert_array_equal(samples.dones.numpy()[:, 0], terminal[index].astype(np.float32))
        np.testing.assert_array_equal(sources.numpy(), table["sources"][index])
        seen.append(index)
        seen_sources.append(sources.numpy())
    index, sources = np.concatenate(seen), np.concatenate(seen_sources)
    n = len(index)
    # (b) each source's share within 5 binomial standard deviations (a share of 0: never drawn)
    got = np.bincount(sources, minlength=len(shares))
    tolerance = 5.0 * np.sqrt(n * shares * (1.0 - shares))
    assert np.all(np.abs(got - n * shares) <= tolerance), (got / n, shares)
    if weighted:
        assert got[3] == 0 and np.abs(shares - counts_per_source / total).max() > 0.1  # the weights matter here
    # (c) within a source, every row drawn and the counts uniform: chi-square under df + 6 sqrt(2 df)
    rows = np.bincount(index, minlength=total)
    for source in np.flatnonzero(shares > 0):
        mine = rows[table["sources"] == source]
        assert mine.min() > 0, (source, mine)
        expected = mine.sum() / len(mine)
        chi2 = float(((mine - expected) ** 2 / expected).sum())
        df = len(mine) - 1
        assert chi2 < df + 6.0 * np.sqrt(2.0 * df), (source, mine, chi2)


@pytest.mark.parametrize("kind", ["view", "merged"])
def test_read_range_and_gather_across_the_boundaries_are_the_concatenation(kind: str) -> None:
    """
    Catches ``read_range`` pieces taken with the wrong offsets (a row repeated or dropped at a boundary, the wrong
    buffer's rows), a gather of scattered indices that puts rows back in the wrong places, and streams of different
    buffers that collide (n-step returns would then chain across buffers).
    """
    buffers, table = make_buffers()
    data = data_of(kind, buffers)
    total = len(table["rewards"])
    stored = {name: table[name] for name in ("observations", "next_observations", "actions", "rewards", "sources")}
    stored["flags"] = table["flags"].astype(np.uint8)
    # boundaries at 8 and 17: ranges inside one buffer, across one boundary, across both, empty, everything
    for start, stop in [(0, total), (6, 10), (7, 8), (8, 17), (3, 20), (16, 18), (17, 17), (23, 24)]:
        for name, values in stored.items():
            got = np.asarray(data.read_range(name, start, stop))
            np.testing.assert_array_equal(got.reshape(values[start:stop].shape), values[start:stop], err_msg=f"{name}")
    streams = np.asarray(data.read_range("streams", 0, total)).astype(np.int64)
    owner = np.repeat(np.arange(len(LAYOUT)), [len(sources) for sources in LAYOUT])
    for k in range(len(LAYOUT)):  # one env per buffer: one stream id per buffer, none shared by two buffers
        assert len(set(streams[owner == k].tolist())) == 1
    assert len(set(streams.tolist())) == len(LAYOUT)
    scattered = np.array([23, 0, 8, 7, 17, 16, 9, 8, 22, 5])  # unsorted, repeated, on both sides of each boundary
    rows = data._gather_rows(("observations", "actions", "rewards", "next_observations", "flags", "sources"), scattered)
    for name in ("observations", "actions", "rewards", "next_observations", "sources"):
        np.testing.assert_array_equal(rows[name].reshape(stored[name][scattered].shape), stored[name][scattered], name)
    np.testing.assert_array_equal(rows["flags"], stored["flags"][scattered])
    np.testing.assert_array_equal(data._gather(("streams",), scattered)["streams"].astype(np.int64), streams[scattered])


@pytest.mark.parametrize("kind", ["view", "merged"])
def test_n_step_returns_stop_at_a_buffers_end_and_at_episode_ends(kind: str) -> None:
    """
    Catches n-step returns that chain from one buffer's last row into the next buffer's first, that run past a
    terminal or a timeout, or that use the wrong discount, next observation or done for a shortened return.
    """
    buffers, table = make_buffers()
    data = data_of(kind, buffers, n_steps=3)
    r = table["rewards"].astype(np.float64)
    g = GAMMA
    # index: (return, steps taken, row of the next observation, terminal done), written from LAYOUT / TERMINALS / TIMEOUTS
    expected = {
        0: (r[0] + g * r[1] + g**2 * r[2], 3, 2, 0.0),  # three steps inside buffer 0
        2: (r[2] + g * r[3], 2, 3, 1.0),  # row 3 is a terminal
        4: (r[4] + g * r[5], 2, 5, 0.0),  # row 5 is a timeout: stop, bootstrap (not terminal)
        6: (r[6] + g * r[7], 2, 7, 0.0),  # row 7 is buffer 0's last: never into buffer 1's row 8
        7: (r[7], 1, 7, 0.0),
        8: (r[8] + g * r[9] + g**2 * r[10], 3, 10, 0.0),  # buffer 1's first row, three steps in it (10 is a timeout)
        15: (r[15] + g * r[16], 2, 16, 1.0),  # buffer 1's row 8 (index 16) is a terminal
        16: (r[16], 1, 16, 1.0),
        17: (r[17] + g * r[18] + g**2 * r[19], 3, 19, 1.0),  # buffer 2's row 2 (index 19) is a terminal
        21: (r[21] + g * r[22] + g**2 * r[23], 3, 23, 0.0),
        23: (r[23], 1, 23, 0.0),  # the last row of all
    }
    index = np.array(sorted(expected))
    samples = data._get_samples(index)
    want_return = np.array([expected[i][0] for i in index])
    want_discount = np.array([g ** expected[i][1] for i in index])
    want_next = table["next_observations"][[expected[i][2] for i in index]]
    want_done = np.array([expected[i][3] for i in index])
    np.testing.assert_allclose(samples.rewards.numpy()[:, 0], want_return, rtol=1e-6)
    np.testing.assert_allclose(samples.discounts.numpy()[:, 0], want_discount, rtol=1e-6)
    np.testing.assert_array_equal(samples.next_observations.numpy(), want_next)
    np.testing.assert_array_equal(samples.dones.numpy()[:, 0], want_done)
    np.testing.assert_array_equal(samples.observations.numpy(), table["observations"][index])
    assert isinstance(samples.rewards, th.Tensor) and samples.rewards.dtype == th.float32


def test_a_view_presents_sb3s_buffer_attributes_and_its_default_discount() -> None:
    """What code written for SB3's ``ReplayBuffer`` reads of a view: one env, no capacity of its own, no memory
    optimisation, time-limit truncations not terminal; and n-step returns discounted by 0.99 unless told."""
    buffers, _ = make_buffers()
    view = LifelongBufferView(buffers, n_steps=2)
    assert (view.n_envs, view.buffer_size, view.optimize_memory_usage, view.handle_timeout_termination) == (1, 0, False, True)
    np.random.seed(0)
    discounts = {round(float(d), 6) for d in view.sample(400).discounts.numpy().ravel()}
    assert discounts == {0.99, round(0.99**2, 6)}


def test_an_empty_range_of_a_view_reads_no_row() -> None:
    buffers, table = make_buffers()
    view = LifelongBufferView(buffers)
    for start in (0, 5, 8, len(table["rewards"])):  # inside a buffer, at a boundary, at the end
        rows = view.read_range("rewards", start, start)
        assert rows.shape == (0,) and rows.dtype == table["rewards"].dtype, start


def test_merge_copies_in_blocks_the_rows_asked_and_keeps_each_inputs_streams_apart(monkeypatch) -> None:
    """Blocks of 3 rows (the module's ``COPY_BLOCK``, set small here) over inputs of 8, 6, 9 and 7 rows, from rows 2,
    0, 0 and 7 to rows 8, 6, 6 and 7: the merged rows are those rows of the inputs, in order; its capacity is their
    count; no stream id of one input is another input's (the second input has three env streams, more than the ids the
    first one used)."""
    from sb3_lifelong.buffers import views

    monkeypatch.setattr(views, "COPY_BLOCK", 3)
    buffers, table = make_buffers()
    extra = LifelongReplayBuffer(0, OBS, ACT, device="cpu", n_envs=3)
    for i in range(2):
        obs = np.stack([row_values(3, 3 * i + e, 0)["observations"] for e in range(3)])
        extra.add(obs, obs, np.zeros((3, 2), np.float32), np.full(3, 3000.0 + i), np.zeros(3), [{}] * 3)
    inputs = [buffers[0], extra, buffers[1], buffers[2]]
    starts, stops = [2, 0, 0, 7], [8, 6, 6, 7]
    merged = merge_buffers(inputs, starts=starts, stops=stops)
    rewards = table["rewards"]
    expected = [rewards[2:8], [3000.0] * 3 + [3001.0] * 3, rewards[8 : 8 + 6], rewards[17 + 7 : 17 + 7]]
    np.testing.assert_array_equal(merged.read_range("rewards", 0, merged.size()), np.concatenate(expected))
    assert merged.size() == merged.buffer_size == 6 + 6 + 6 + 0
    streams = merged.read_range("streams", 0, merged.size()).astype(np.int64)
    owners = [set(part.tolist()) for part in np.split(streams, [6, 12])]
    assert len(owners[1]) == 3  # the second input's three env streams stay three
    assert not owners[0] & owners[1] and not owners[0] & owners[2] and not owners[1] & owners[2], owners


def test_merge_refuses_starts_that_are_not_one_index_per_buffer_and_takes_a_start_at_the_end() -> None:
    buffers, _ = make_buffers()
    with pytest.raises(
        ValueError, match=r"starts must give one index in \[0, size\] per buffer: got \[0\] for sizes \[8, 9, 7\]"
    ):
        merge_buffers(buffers, starts=[0])
    with pytest.raises(ValueError, match="starts must give one index"):
        merge_buffers(buffers, starts=[0, 0, 8])
    merged = merge_buffers(buffers, starts=[8, 0, 7])  # nothing of the first and the last: the ancestor kept once
    assert merged.size() == 9
