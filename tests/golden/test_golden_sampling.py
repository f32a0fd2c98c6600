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


# ---------------------------------------------------------------------------------------------- n-step rows by hand
# Two envs side by side for seven add() calls (row = 2 t + env). Env 0 ends an episode (terminal) at t = 2 and moves
# from Env-A (source 0) to Env-B (source 1) at t = 4; env 1 is in Env-B throughout and is truncated by a time limit at
# t = 3. Env-B's rewards are scaled by 2 at sampling time.
GAMMA_BY_HAND = 0.5
RAW = {0: [1, 2, 3, 4, 5, 6, 7], 1: [10, 20, 30, 40, 50, 60, 70]}
SCALED = {0: [1, 2, 3, 4, 10, 12, 14], 1: [20, 40, 60, 80, 100, 120, 140]}  # each step by its own source's scale
# (t, env): (return, steps taken, t of the row bootstrapped from, terminal, t of the data's next action or None)
BY_HAND = {
    (0, 0): (1 + 0.5 * 2 + 0.25 * 3, 3, 2, 1.0, None),  # three steps, the third ends the episode
    (1, 0): (2 + 0.5 * 3, 2, 2, 1.0, None),
    (2, 0): (3, 1, 2, 1.0, None),
    (3, 0): (4 + 0.5 * 10 + 0.25 * 12, 3, 5, 0.0, 6),  # Env-A's step, then two Env-B steps at Env-B's scale
    (4, 0): (10 + 0.5 * 12 + 0.25 * 14, 3, 6, 0.0, None),  # the last row: no next action known
    (5, 0): (12 + 0.5 * 14, 2, 6, 0.0, None),  # the buffer's end shortens the return
    (6, 0): (14, 1, 6, 0.0, None),
    (0, 1): (20 + 0.5 * 40 + 0.25 * 60, 3, 2, 0.0, 3),
    (1, 1): (40 + 0.5 * 60 + 0.25 * 80, 3, 3, 0.0, None),  # ends on the truncation: bootstraps, no next action
    (2, 1): (60 + 0.5 * 80, 2, 3, 0.0, None),
    (3, 1): (80, 1, 3, 0.0, None),
    (4, 1): (100 + 0.5 * 120 + 0.25 * 140, 3, 6, 0.0, None),
    (5, 1): (120 + 0.5 * 140, 2, 6, 0.0, None),
    (6, 1): (140, 1, 6, 0.0, None),
}


def two_env_buffer(n_steps: int) -> LifelongReplayBuffer:
    buffer = LifelongReplayBuffer(0, OBS, ACT, n_envs=2, n_steps=n_steps, gamma=GAMMA_BY_HAND)
    for t in range(7):
        obs = np.array([[t, e, 0.0] for e in (0, 1)], np.float32)
        next_obs = np.array([[t + 0.5, e, 1.0] for e in (0, 1)], np.float32)
        actions = np.array([[t / 10 + e / 100, -t / 10] for e in (0, 1)], np.float32)
        rewards = np.array([RAW[0][t], RAW[1][t]], np.float32)
        dones = np.array([t == 2, t == 3])
        infos = [{"stage": 0 if t < 4 else 1}, {"stage": 1, "TimeLimit.truncated": t == 3}]
        buffer.add(obs, next_obs, actions, rewards, dones, infos)
    buffer.set_reward_scale({1: 2.0})
    return buffer


def test_n_step_rows_of_interleaved_envs_by_hand() -> None:
    """
    Catches a return that scales every step by the first step's source, chains into the other env's rows (the
    successor of a row is n_envs rows on), runs past a terminal or a truncation, treats a truncation as terminal,
    reads the next observation of the wrong row or the next action across an episode end or past the last row.
    """
    buffer = two_env_buffer(n_steps=3)
    keys = sorted(BY_HAND)
    rows = np.array([2 * t + e for t, e in keys])
    samples = buffer._get_samples_and_sources(rows, None, next_actions=True)[0]
    want = [BY_HAND[k] for k in keys]
    np.testing.assert_allclose(samples.rewards.numpy()[:, 0], [w[0] for w in want], rtol=1e-6)
    np.testing.assert_allclose(samples.discounts.numpy()[:, 0], [0.5 ** w[1] for w in want], rtol=1e-6)
    np.testing.assert_array_equal(samples.dones.numpy()[:, 0], [w[3] for w in want])
    np.testing.assert_array_equal(samples.next_observations.numpy(), [[w[2] + 0.5, e, 1.0] for (_, e), w in zip(keys, want)])
    np.testing.assert_array_equal(samples.observations.numpy(), [[t, e, 0.0] for t, e in keys])
    np.testing.assert_array_equal(samples.next_action_mask.numpy()[:, 0], [float(w[4] is not None) for w in want])
    next_actions = [[0.0, 0.0] if w[4] is None else [w[4] / 10 + e / 100, -w[4] / 10] for (_, e), w in zip(keys, want)]
    np.testing.assert_allclose(samples.next_actions.numpy(), next_actions, rtol=1e-6)


def test_one_step_rows_of_interleaved_envs_by_hand() -> None:
    """One step: each row's own scaled reward, terminal only where the episode ended without a truncation, and the
    same env's next action where its episode goes on."""
    buffer = two_env_buffer(n_steps=1)
    rows = np.arange(14)
    samples, sources = buffer._get_samples_and_sources(rows, None, next_actions=True)
    np.testing.assert_array_equal(samples.rewards.numpy()[:, 0], [SCALED[r % 2][r // 2] for r in rows])
    np.testing.assert_array_equal(samples.dones.numpy()[:, 0], [float(r == 4) for r in rows])  # (t 2, env 0)
    np.testing.assert_array_equal(sources, [0, 1, 0, 1, 0, 1, 0, 1, 1, 1, 1, 1, 1, 1])
    known = [r not in (4, 7, 12, 13) for r in rows]  # the terminal, the truncation, the last row of each env
    np.testing.assert_array_equal(samples.next_action_mask.numpy()[:, 0], np.array(known, np.float32))
    want = [[(r // 2 + 1) / 10 + (r % 2) / 100, -(r // 2 + 1) / 10] if k else [0.0, 0.0] for r, k in zip(rows, known)]
    np.testing.assert_allclose(samples.next_actions.numpy(), want, rtol=1e-6)
    assert samples.discounts is None
    buffer.set_reward_scale(None)
    np.testing.assert_array_equal(buffer._get_samples(rows).rewards.numpy()[:, 0], [RAW[r % 2][r // 2] for r in rows])


def test_source_counts_by_id_and_by_name() -> None:
    buffer = two_env_buffer(n_steps=1)
    assert buffer.source_counts() == {0: 4, 1: 10}
    assert buffer.source_counts(by_name=True) == {"Env-A": 4, "Env-B": 10}
    buffer.name_source(0, "Env-B")
    with pytest.raises(ValueError, match=r"sources 0 and 1 are both named 'Env-B': use source_counts\(\) \(by id\)"):
        buffer.source_counts(by_name=True)
