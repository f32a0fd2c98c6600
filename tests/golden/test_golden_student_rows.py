"""
Golden rows of a study's students (issue "Tests that check values, not a path against itself"): the rows of the
lifetime buffer that a student of :data:`sb3_lifelong.experiments.presets.STUDENTS` actually trains on, through the
study's own job (:func:`~sb3_lifelong.experiments.protocol.distill_student`, which opens the seed's ``buffer`` and
sets the student's sampling ratio).

The buffer is written here: 300 rows of Env-A (source 0), then 100 of Env-B (source 1), and every field of row ``r``
says ``r`` (its observation, next observation, action and reward), so that each row of every batch the student's
update gets (CRR's ``_sample``, recorded) is identified, and its source read from the order the rows were written in,
not from the buffer. The expected share of Env-A in the batches is written by hand for each student (``a : b`` of
``ratio`` whatever the sources' sizes; the raw sizes, 300 : 100, without one) and checked with a binomial tolerance of
5 standard deviations over all the batches; a student of one source must see that source's rows only, every one of
them.
"""

import dataclasses
import math
import pathlib
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import CRR, LifelongReplayBuffer
from sb3_lifelong.experiments import PRESETS
from sb3_lifelong.experiments.protocol import distill_student

N_A, N_B = 300, 100
N_ROWS = N_A + N_B
UPDATES, BATCH = 100, 64
#: the tiny study's student, with UPDATES updates of BATCH rows and no evaluation in between (it would not change a row)
PRESET = dataclasses.replace(PRESETS["tiny"], distill_steps=UPDATES, distill_eval_freq=10 * UPDATES, student_batch_size=BATCH)
N_SIGMAS = 5.0

#: the share of Env-A rows in a student's batches, by hand: 1:10 is 1 / 11 and 1:1 is 1 / 2 of the rows whatever the
#: sources' sizes; without a ratio, the raw sizes
ENV_A_SHARE = {
    "CRR_indicator_A_only": 1.0,
    "CRR_indicator_B_only": 0.0,
    "CRR_indicator_ratio_1to10": 1 / 11,
    "CRR_indicator_ratio_1to1": 1 / 2,
    "CRR_indicator": N_A / N_ROWS,
    "CRR_indicator_two_actors": N_A / N_ROWS,
}


def row_observation(rows: np.ndarray) -> np.ndarray:
    """The observation of rows ``rows``: Hopper's 11 numbers, the first ``r / N_ROWS``, the others 0."""
    obs = np.zeros((len(rows), 11))
    obs[:, 0] = rows / N_ROWS
    return obs


def row_action(rows: np.ndarray) -> np.ndarray:
    action = np.zeros((len(rows), 3), np.float32)
    action[:, 0] = 2 * rows / N_ROWS - 1
    return action


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> pathlib.Path:
    """A seed's directory whose lifetime ``buffer`` holds N_A rows of Env-A (source 0), then N_B of Env-B (source 1)."""
    run_dir = tmp_path_factory.mktemp("student_rows") / "seed_0"
    run_dir.mkdir()
    env = gym.make(PRESET.env_id)  # the study's robot: its spaces, which the student's evaluations need
    with LifelongReplayBuffer(0, env.observation_space, env.action_space, path=run_dir / "buffer", device="cpu") as buffer:
        for source, name, rows in ((0, "Env-A", range(N_A)), (1, "Env-B", range(N_A, N_ROWS))):
            buffer.set_source(source, name=name)
            for row in rows:
                r = np.array([row])
                obs = row_observation(r)
                next_obs = obs.copy()
                next_obs[:, 1] = 1.0
                buffer.add(obs, next_obs, row_action(r), np.array([row / N_ROWS]), np.array([False]), [{}])
        assert buffer.source_counts() == {0: N_A, 1: N_B}
    env.close()
    return run_dir


def trained_rows(name: str, run_dir: pathlib.Path, monkeypatch) -> tuple[list[np.ndarray], list[Any]]:
    """
    Run the study's job of student ``name`` and return the row of every sample of every batch its updates got, with
    the actor each row was routed to (None without one actor per source).
    """
    batches: list[np.ndarray] = []
    heads: list[Any] = []
    sample = CRR._sample

    def recording_sample(self: CRR, batch_size: int) -> Any:
        replay_data, batch_heads = sample(self, batch_size)
        obs = replay_data.observations.cpu().double().numpy()
        rows = np.rint(obs[:, 0] * N_ROWS).astype(np.int64)
        # every field of the sample is its row's (no field from another row)
        np.testing.assert_allclose(obs, row_observation(rows), atol=1e-6)
        next_obs = replay_data.next_observations.cpu().numpy()
        np.testing.assert_allclose(next_obs[:, :2], np.stack([rows / N_ROWS, np.ones(len(rows))], axis=1), atol=1e-6)
        np.testing.assert_allclose(replay_data.actions.cpu().numpy(), row_action(rows), atol=1e-6)
        np.testing.assert_allclose(replay_data.rewards.cpu().numpy().ravel(), rows / N_ROWS, atol=1e-6)
        batches.append(rows)
        heads.append(None if batch_heads is None else batch_heads.cpu().numpy())
        return replay_data, batch_heads

    monkeypatch.setattr(CRR, "_sample", recording_sample)
    distill_student(name, PRESET, 0, run_dir, log=lambda message: None)
    return batches, heads


def assert_uniform_over(rows: np.ndarray, first: int, count: int) -> None:
    """``rows`` are draws uniform over ``first .. first + count - 1``: their mean within N_SIGMAS standard errors."""
    assert ((rows >= first) & (rows < first + count)).all()
    standard_error = math.sqrt((count**2 - 1) / 12 / len(rows))
    assert abs(rows.mean() - (first + (count - 1) / 2)) <= N_SIGMAS * standard_error


@pytest.mark.parametrize("name", list(ENV_A_SHARE))
def test_a_students_batches_hold_the_sources_in_its_registered_shares(name: str, run_dir: pathlib.Path, monkeypatch) -> None:
    """
    The rows a student trains on: Env-A's only (every batch, every row) for A-only, Env-B's only for B-only, 1 : 10 and
    1 : 1 of Env-A : Env-B for the ratio students, 300 : 100 for the whole-buffer ones, each source's rows drawn
    uniformly. Fails if the ratio is not applied (or applied to another buffer than the student's), if the weights are
    the ratio itself rather than the ratio over the sources' sizes (1:10 would give 300 : 1000), if the ratio is
    reversed, or if a source's rows are drawn from the wrong range.
    """
    batches, heads = trained_rows(name, run_dir, monkeypatch)
    assert len(batches) == UPDATES and all(len(rows) == BATCH for rows in batches)  # the preset's updates and batch size
    rows = np.concatenate(batches)
    is_a = rows < N_A  # the buffer was written Env-A first
    share = ENV_A_SHARE[name]
    n = len(rows)
    if share in (0.0, 1.0):  # one source only: every row of every batch is its, and each of its rows is drawn
        assert is_a.all() if share == 1.0 else not is_a.any()
        own = range(N_A) if share == 1.0 else range(N_A, N_ROWS)
        assert set(rows.tolist()) == set(own)
    else:
        tolerance = N_SIGMAS * math.sqrt(n * share * (1 - share))
        assert abs(int(is_a.sum()) - n * share) <= tolerance, f"{is_a.sum()} Env-A rows of {n}, expected {n * share:.0f}"
    if share > 0:
        assert_uniform_over(rows[is_a], 0, N_A)
    if share < 1:
        assert_uniform_over(rows[~is_a], N_A, N_B)
    if name == "CRR_indicator_two_actors":  # each row trains its own source's actor: Env-A's the first, Env-B's the second
        routed = np.concatenate(heads)
        np.testing.assert_array_equal(routed, np.where(is_a, 0, 1))
    else:
        assert all(batch_heads is None for batch_heads in heads)
