"""
Golden values of the Monte-Carlo overestimation probe (``sb3_lifelong.evaluation.overestimation``) on buffers filled
the way SB3 fills them, with episodes that end in every way: a termination (``done``), a time-limit truncation
(``done`` with ``info["TimeLimit.truncated"]``, stored as the buffer's timeout flag) and an episode still running at
the buffer's write head; two envs interleaved row by row, each its own source. The existing tests feed
``discounted_returns`` d4rl columns directly or buffers whose episodes all terminate; these go through the buffer's
export and the probe, with every return written here by hand (gamma = 0.5, rewards exact in binary):

- a terminated episode's rows get their whole discounted return and are all valid, however close to the end;
- a truncated (or unfinished) episode's rows get the discounted return of the stored future, and are valid only
  with at least ``horizon`` steps of the episode after them (``discounted_returns``'s rule);
- no return chains across an episode end, an env's stream, or two buffers of a view;
- ``monte_carlo_horizon(gamma)`` is the default horizon of the probe.
"""

import math
from typing import Optional

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import LifelongBufferView
from sb3_lifelong.evaluation.overestimation import MonteCarloProbe, discounted_returns, monte_carlo_horizon

GAMMA, HORIZON = 0.5, 2
OBS_SPACE = gym.spaces.Box(-1e4, 1e4, (2,), np.float32)
ACTION_SPACE = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

#: per env (= source), its episodes in order: (rewards, how the episode ends)
EPISODES = {
    0: [([1.0, 2.0, 4.0], "terminated"), ([8.0, 4.0, 2.0, 6.0], "truncated"), ([2.0, 2.0, 2.0], "running")],
    1: [([10.0, 4.0], "terminated"), ([1.0, 3.0, 5.0, 7.0, 9.0], "truncated"), ([0.5, 0.25, 1.0], "running")],
}
#: per env, the discounted return of each row (gamma = 0.5), by hand, and whether it is valid (horizon 2)
HAND = {
    0: [
        # terminated: 1 + 2/2 + 4/4, 2 + 4/2, 4 (all valid: nothing follows a terminal)
        (3.0, True), (4.0, True), (4.0, True),
        # truncated after 4 steps: 8 + 4/2 + 2/4 + 6/8, 4 + 2/2 + 6/4, 2 + 6/2, 6 (the last two: under 2 steps follow)
        (11.25, True), (6.5, True), (5.0, False), (6.0, False),
        # still running (the write head): 2 + 2/2 + 2/4, 2 + 2/2, 2
        (3.5, True), (3.0, False), (2.0, False),
    ],
    1: [
        # terminated: 10 + 4/2, 4
        (12.0, True), (4.0, True),
        # truncated after 5 steps: 1 + 3/2 + 5/4 + 7/8 + 9/16, 3 + 5/2 + 7/4 + 9/8, 5 + 7/2 + 9/4, 7 + 9/2, 9
        (5.1875, True), (8.375, True), (10.75, True), (11.5, False), (9.0, False),
        # still running: 0.5 + 0.25/2 + 1/4, 0.25 + 1/2, 1
        (0.875, True), (0.75, False), (1.0, False),
    ],
}  # fmt: skip


def code(env: int, step: int) -> float:
    """The first observation entry of env ``env``'s ``step``-th row: names the row (the critics below read it)."""
    return 100.0 * env + step


def fill(buffer: LifelongReplayBuffer, episodes: dict[int, list[tuple[list[float], str]]], base: int = 0) -> None:
    """Add the episodes of every env at once (``n_envs`` = number of envs), as SB3's collection does."""
    flat = {
        env: [(reward, i == len(rewards) - 1 and end != "running", i == len(rewards) - 1 and end == "truncated")
              for rewards, end in eps for i, reward in enumerate(rewards)]
        for env, eps in episodes.items()
    }  # fmt: skip
    steps = {len(rows) for rows in flat.values()}
    assert len(steps) == 1, "every env has as many rows"
    envs = sorted(flat)
    for t in range(steps.pop()):
        obs = np.array([[code(base + env, t), env] for env in envs], dtype=np.float32)
        buffer.add(
            obs,
            obs + np.float32(0.5),
            np.zeros((len(envs), 1), dtype=np.float32),
            np.array([flat[env][t][0] for env in envs], dtype=np.float32),
            np.array([flat[env][t][1] for env in envs]),
            [{"TimeLimit.truncated": flat[env][t][2], "stage": env} for env in envs],
        )


def two_env_buffer() -> LifelongReplayBuffer:
    buffer = LifelongReplayBuffer(0, OBS_SPACE, ACTION_SPACE, device="cpu")
    fill(buffer, EPISODES)
    return buffer


class LookupCritic(th.nn.Module):
    """``Q(s, a)`` = the hand-computed return of the row ``s`` names, plus ``invalid_offset`` on rows not valid."""

    def __init__(self, table: dict[float, tuple[float, bool]], invalid_offset: float = 1000.0) -> None:
        super().__init__()
        self.table, self.invalid_offset = table, invalid_offset

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        values = []
        for key in obs[:, 0].tolist():
            value, valid = self.table[key]
            values.append(value if valid else value + self.invalid_offset)
        return (th.tensor(values, dtype=th.float64).reshape(-1, 1),)


def hand_table(base: int = 0) -> dict[float, tuple[float, bool]]:
    return {code(base + env, t): row for env, rows in HAND.items() for t, row in enumerate(rows)}


def test_discounted_returns_of_a_buffer_with_truncated_and_running_episodes_by_hand() -> None:
    """
    Catches a truncation treated as a termination (its last rows valid), a timeout flag lost in the buffer or its
    export (the truncated episode's return chained into the next episode's), a running episode at the write head not
    cut (chained into the other env's rows), a missing discount, and the rule ``steps after >= horizon`` off by one.
    """
    buffer = two_env_buffer()
    columns = buffer.to_d4rl(by_episode=True, normalized_actions=True)
    # the export's episode order: env 0's rows, then env 1's (each env's stream contiguous)
    want_codes = [code(env, t) for env in HAND for t in range(len(HAND[env]))]
    np.testing.assert_array_equal(columns["observations"][:, 0], want_codes)
    mc = discounted_returns(columns["rewards"], columns["terminals"], columns["timeouts"], GAMMA, HORIZON)
    want = np.array([row[0] for env in HAND for row in HAND[env]])
    valid = np.array([row[1] for env in HAND for row in HAND[env]])
    np.testing.assert_allclose(mc.returns, want, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(mc.valid, valid)
    # the buffer stores the truncation as a timeout and the termination as a terminal (the SB3 convention)
    ends = {t for t, row in enumerate(columns["terminals"]) if row}
    assert ends == {2, 11}
    assert set(np.flatnonzero(columns["timeouts"]).tolist()) == {6, 9, 16, 19}  # truncations, then the write heads


def test_probe_measures_only_valid_rows_against_their_hand_computed_returns() -> None:
    """
    Catches a probe that samples rows near a truncation (their return is cut short), drops valid rows (a terminated
    episode's last ones), mixes the two sources' rows, or pairs a row's Q with another row's return.
    """
    buffer = two_env_buffer()
    table = hand_table()
    critic = LookupCritic(table)
    results = MonteCarloProbe(buffer, GAMMA, per_source=100, horizon=HORIZON).measure(critic)
    assert set(results) == {0, 1}
    for source, rows in HAND.items():
        kept = [value for value, valid in rows if valid]
        got = results[source]
        assert got.n == len(kept) == 6
        assert got.mc_return == pytest.approx(np.mean(kept), abs=1e-12)
        assert got.q_mean == pytest.approx(np.mean(kept), abs=1e-12)  # no row of an invalid return (they read +1000)
        assert got.overestimation == pytest.approx(0.0, abs=1e-12)
    # one row at a time: each sampled row's Q (its own hand return) minus its return is 0, and every valid row comes up
    drawn: dict[int, set[float]] = {0: set(), 1: set()}
    for seed in range(40):
        probe = MonteCarloProbe(buffer, GAMMA, per_source=1, horizon=HORIZON, seed=seed)
        for source, got in probe.measure(critic).items():
            assert got.n == 1 and got.overestimation == pytest.approx(0.0, abs=1e-12), (seed, source)
            drawn[source].add(got.mc_return)
    for source, rows in HAND.items():
        assert drawn[source] == {value for value, valid in rows if valid}


def test_probe_of_a_view_never_chains_one_buffers_running_episode_into_the_next() -> None:
    """
    Catches a view whose export orders or joins the streams of two buffers as one (the first buffer's running episodes
    would then take the second buffer's first rewards as their future, and become valid).
    """
    first, second = two_env_buffer(), LifelongReplayBuffer(0, OBS_SPACE, ACTION_SPACE, device="cpu")
    fill(second, EPISODES, base=10)  # the same episodes again, named 1000 + ... and 1100 + ...
    view = LifelongBufferView([first, second])
    columns = view.to_d4rl(by_episode=True, normalized_actions=True)
    mc = discounted_returns(columns["rewards"], columns["terminals"], columns["timeouts"], GAMMA, HORIZON)
    want = np.array([row[0] for env in HAND for row in HAND[env]] * 2)
    valid = np.array([row[1] for env in HAND for row in HAND[env]] * 2)
    np.testing.assert_allclose(mc.returns, want, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(mc.valid, valid)
    critic = LookupCritic({**hand_table(), **hand_table(base=10)})
    for source, got in MonteCarloProbe(view, GAMMA, per_source=100, horizon=HORIZON).measure(critic).items():
        kept = [value for value, valid in HAND[source] if valid] * 2
        assert got.n == 12 and got.overestimation == pytest.approx(0.0, abs=1e-12)
        assert got.mc_return == pytest.approx(np.mean(kept), abs=1e-12)


@pytest.mark.parametrize("horizon", [None, 10])
def test_default_horizon_is_monte_carlo_horizon_on_a_long_truncated_episode(horizon: Optional[int]) -> None:
    """
    Catches a probe that ignores its ``horizon`` or defaults it to something else than ``monte_carlo_horizon(gamma)``
    (44 for 0.9: the first ``h`` with ``0.9^h < 0.01``), or a horizon counted from the episode's start.
    """
    gamma, length = 0.9, 50
    assert monte_carlo_horizon(gamma) == 44 and gamma**44 < 0.01 < gamma**43
    assert monte_carlo_horizon(0.5) == 7 and monte_carlo_horizon(0.5, 0.3) == 2  # 0.5^2 = 0.25 < 0.3 < 0.5
    buffer = LifelongReplayBuffer(0, OBS_SPACE, ACTION_SPACE, device="cpu")
    fill(buffer, {0: [([1.0] * length, "truncated"), ([2.0, 2.0], "terminated")]})
    used = 44 if horizon is None else horizon
    # reward 1 for 50 steps then cut: G_t = (1 - 0.9^(50 - t)) / (1 - 0.9), valid with 50 - t - 1 >= h steps after t
    table = {code(0, t): ((1.0 - gamma ** (length - t)) / (1.0 - gamma), length - t > used) for t in range(length)}
    table.update({code(0, length): (2.0 + gamma * 2.0, True), code(0, length + 1): (2.0, True)})
    kept = [value for value, valid in table.values() if valid]
    assert len(kept) == length - used + 2
    result = MonteCarloProbe(buffer, gamma, per_source=1000, horizon=horizon).measure(LookupCritic(table))[0]
    assert result.n == len(kept)
    assert result.mc_return == pytest.approx(np.mean(kept), rel=1e-12)
    assert result.overestimation == pytest.approx(0.0, abs=1e-9)
    assert math.isclose(result.q_mean, result.mc_return, rel_tol=1e-12)


# ---------------------------------------------------------------------------------------------------------------------
# The horizon at exact powers, the probe's arguments and the units of the actions it scores (mutation survivors)
# ---------------------------------------------------------------------------------------------------------------------


#: a tolerance one float above 0.95 ** 98, where the logarithms' estimate (99) is one step too far
JUST_ABOVE = math.nextafter(0.95**98, 1.0)


@pytest.mark.parametrize(
    "gamma, tolerance, horizon",
    [(0.5, 0.25, 3), (0.5, 0.125, 4), (0.25, 0.0625, 3), (0.9, 0.9, 2), (0.95, JUST_ABOVE, 98), (0.99, 0.01, 459)],
)
def test_the_horizon_at_an_exact_power_is_the_first_below_the_tolerance(gamma, tolerance, horizon) -> None:
    """``gamma ** h < tolerance <= gamma ** (h - 1)``, also where a power equals the tolerance exactly."""
    assert monte_carlo_horizon(gamma, tolerance) == horizon
    assert gamma**horizon < tolerance <= gamma ** (horizon - 1)


def test_a_probe_of_no_rows_per_source_is_refused() -> None:
    with pytest.raises(ValueError, match="per_source must be >= 1, got 0"):
        MonteCarloProbe(two_env_buffer(), GAMMA, per_source=0)


class ActionCritic(th.nn.Module):
    """``Q(s, a)`` = the action it is given (its first entry)."""

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        return (actions[:, :1].double(),)


def test_the_probe_scores_the_actions_in_the_critics_units() -> None:
    """The critic sees the stored actions as they are stored, normalised to [-1, 1] (as SB3 stores them and trains on
    them), not turned back into the env's units (0.75 is 1.5 of [-2, 2])."""
    buffer = LifelongReplayBuffer(0, OBS_SPACE, gym.spaces.Box(-2.0, 2.0, (1,), np.float32), device="cpu")
    for t in range(6):
        obs = np.array([[code(0, t), 0.0]], dtype=np.float32)
        buffer.add(obs, obs, np.array([[0.75]], np.float32), np.array([1.0]), np.array([t == 5]), [{}])
    got = MonteCarloProbe(buffer, GAMMA, per_source=10, horizon=HORIZON).measure(ActionCritic())[0]
    assert got.n == 6 and got.q_mean == pytest.approx(0.75, abs=1e-7)


@pytest.mark.parametrize("gamma, tolerance", [(0.0, 0.01), (1.0, 0.01), (0.99, 0.0), (0.99, 1.0)])
def test_the_horizon_needs_gamma_and_tolerance_strictly_inside_0_1(gamma, tolerance) -> None:
    with pytest.raises(ValueError, match="gamma and tolerance must be in"):
        monte_carlo_horizon(gamma, tolerance)


class CodeCritic(th.nn.Module):
    """``Q(s, a)`` = the code of the row ``s`` (its first observation entry)."""

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        return (obs[:, :1].double(),)


def test_a_source_with_one_valid_row_and_a_buffer_of_one_row_are_measured() -> None:
    """The probe measures data of a single row, and a source whose only valid row is one (edges of the size checks)."""
    single = LifelongReplayBuffer(0, OBS_SPACE, ACTION_SPACE, device="cpu")
    fill(single, {0: [([3.0], "terminated")]})
    got = MonteCarloProbe(single, GAMMA, horizon=HORIZON).measure(CodeCritic())
    assert list(got) == [0] and got[0].n == 1 and got[0].mc_return == 3.0 and got[0].q_mean == code(0, 0)
    # env 1: a terminated one-step episode (valid), then one step still running (under the horizon: not valid)
    two = LifelongReplayBuffer(0, OBS_SPACE, ACTION_SPACE, device="cpu")
    fill(two, {0: [([1.0, 2.0], "terminated")], 1: [([5.0], "terminated"), ([1.0], "running")]})
    got = MonteCarloProbe(two, GAMMA, horizon=HORIZON).measure(CodeCritic())
    assert (got[0].n, got[0].mc_return) == (2, (2.0 + 2.0) / 2)  # 1 + 2/2 and 2
    assert (got[1].n, got[1].mc_return, got[1].q_mean) == (1, 5.0, code(1, 0))


def test_the_probes_default_sample_is_2048_rows_of_a_source_drawn_with_seed_0() -> None:
    """2,100 one-step episodes, each row's reward its index: the default sample is 2,048 of them, the rows NumPy's
    generator of seed 0 picks (so its mean return is theirs)."""
    n = 2_100
    buffer = LifelongReplayBuffer(0, OBS_SPACE, ACTION_SPACE, device="cpu")
    fill(buffer, {0: [([float(i)], "terminated") for i in range(n)]})
    got = MonteCarloProbe(buffer, GAMMA).measure(CodeCritic())[0]
    picked = np.random.default_rng(0).choice(np.arange(n), size=2_048, replace=False)
    assert got.n == 2_048
    assert got.mc_return == pytest.approx(picked.mean(), rel=1e-12) and got.q_mean == pytest.approx(picked.mean(), rel=1e-6)
    assert abs(np.random.default_rng(1).choice(np.arange(n), size=2_048, replace=False).mean() - picked.mean()) > 0.01
