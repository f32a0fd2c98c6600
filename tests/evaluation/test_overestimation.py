"""Overestimation against the truth: Q(s, a) minus the discounted Monte-Carlo return of the stored episode."""

import csv

import numpy as np
import pytest
import torch as th

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.evaluation.overestimation import MonteCarloProbe, discounted_returns, monte_carlo_horizon


def test_horizon():
    assert monte_carlo_horizon(0.99) == 459 and 0.99**459 < 0.01 < 0.99**458
    with pytest.raises(ValueError, match="gamma"):
        monte_carlo_horizon(1.0)


def test_discounted_returns_hand_computed():
    rewards = [1.0, 1.0, 1.0, 2.0, 2.0, 4.0]
    terminals = [0, 0, 1, 0, 0, 0]
    timeouts = [0, 0, 0, 0, 1, 0]  # episode 2 is cut by a time limit; episode 3 is cut by the end of the data
    mc = discounted_returns(np.array(rewards), np.array(terminals), np.array(timeouts), gamma=0.5, horizon=1)
    np.testing.assert_allclose(mc.returns, [1.75, 1.5, 1.0, 3.0, 2.0, 4.0])
    # a terminated episode's returns are complete; a cut one's only with more than `horizon` steps stored after them
    assert mc.valid.tolist() == [True, True, True, True, False, False]
    with pytest.raises(ValueError, match="length"):
        discounted_returns(np.ones(3), np.zeros(2), np.zeros(3), 0.9)


def two_source_buffer() -> LifelongReplayBuffer:
    """Source 0: episodes of 3 steps with reward 1 (terminated); source 1: one of 4 steps with reward 2."""
    n_obs = 2
    rows = dict(observations=[], actions=[], rewards=[], next_observations=[], terminals=[], timeouts=[], sources=[])
    for source, length, reward, episodes in ((0, 3, 1.0, 2), (1, 4, 2.0, 1)):
        for _ in range(episodes):
            for t in range(length):
                rows["observations"].append(np.full(n_obs, 10 * source + t, dtype=np.float32))
                rows["next_observations"].append(np.full(n_obs, 10 * source + t + 1, dtype=np.float32))
                rows["actions"].append(np.zeros(1, dtype=np.float32))
                rows["rewards"].append(reward)
                rows["terminals"].append(t == length - 1)
                rows["timeouts"].append(False)
                rows["sources"].append(source)
    return LifelongReplayBuffer.from_d4rl({k: np.asarray(v) for k, v in rows.items()}, normalized_actions=True)


class ConstantCritic(th.nn.Module):
    def __init__(self, value: float):
        super().__init__()
        self.value = value

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        return (th.full((len(obs), 1), self.value),)


def test_probe_measures_each_source_against_its_returns():
    gamma = 0.5
    probe = MonteCarloProbe(two_source_buffer(), gamma, per_source=100)
    results = probe.measure(ConstantCritic(3.0))
    returns_0 = [1.75, 1.5, 1.0]
    returns_1 = [2 * (1 + 0.5 + 0.25 + 0.125), 2 * (1 + 0.5 + 0.25), 2 * 1.5, 2.0]
    assert results[0].n == 6 and results[1].n == 4
    assert results[0].mc_return == pytest.approx(np.mean(returns_0))
    assert results[1].mc_return == pytest.approx(np.mean(returns_1))
    assert results[0].overestimation == pytest.approx(3.0 - np.mean(returns_0))
    assert results[1].overestimation == pytest.approx(3.0 - np.mean(returns_1))
    # a reward scale on source 1 scales its returns (the critic of a student trained on scaled rewards)
    scaled = MonteCarloProbe(two_source_buffer(), gamma, per_source=100, reward_scale={1: 3.0}).measure(ConstantCritic(0.0))
    assert scaled[1].mc_return == pytest.approx(3 * np.mean(returns_1))
    assert scaled[0].mc_return == pytest.approx(np.mean(returns_0))


def test_probe_samples_at_most_per_source_and_keeps_its_sample():
    probe = MonteCarloProbe(two_source_buffer(), 0.5, per_source=2, seed=3)
    first = probe.measure(ConstantCritic(0.0))
    assert first[0].n == 2 and first[1].n == 2
    assert probe.measure(ConstantCritic(0.0)) == first  # same data: same sample


def test_source_q_callback_logs_overestimation(tmp_path):
    from sb3_lifelong import CRR
    from sb3_lifelong.evaluation.callbacks import SourceQCallback

    buffer = two_source_buffer()
    model = CRR.from_offline_data(buffer, batch_size=4, policy_kwargs=dict(net_arch=[8]), seed=0, gamma=0.5)
    callback = SourceQCallback(log_freq=5, batch_size=64, log_path=tmp_path / "q.csv", data=buffer)
    model.learn_offline(10, callback=callback, log_interval=0)
    with open(tmp_path / "q.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4 and {row["source"] for row in rows} == {"0", "1"}
    for row in rows:
        assert float(row["overestimation"]) == pytest.approx(float(row["q_probe"]) - float(row["mc_return"]), abs=1e-4)
    assert {"diagnostics/overestimation/source_0", "diagnostics/overestimation/source_1"} <= set(model.logger.name_to_value)


class SourceCritic(th.nn.Module):
    """Q = 7 on source 1's observations (10 and above in ``two_source_buffer``), 0 on source 0's."""

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        return ((obs[:, :1] >= 10).float() * 7.0,)


def test_source_q_callback_averages_each_source_over_its_own_rows(tmp_path):
    from sb3_lifelong import CRR
    from sb3_lifelong.evaluation.callbacks import SourceQCallback

    buffer = two_source_buffer()
    model = CRR.from_offline_data(buffer, batch_size=4, policy_kwargs=dict(net_arch=[8]), seed=0, gamma=0.5)
    callback = SourceQCallback(log_freq=5, batch_size=64, data=buffer)
    model.learn_offline(5, callback=callback, log_interval=0)  # sets the callback up
    model.critic = SourceCritic()
    assert callback.measure() == {"source_0": 0.0, "source_1": 7.0}  # a mask mixing the sources would not give these
    last = {row["source"]: row for row in callback.results[-2:]}
    returns_0 = np.mean([1.75, 1.5, 1.0])  # as in test_probe_measures_each_source_against_its_returns
    returns_1 = np.mean([2 * (1 + 0.5 + 0.25 + 0.125), 2 * (1 + 0.5 + 0.25), 2 * 1.5, 2.0])
    assert last[0]["mc_return"] == pytest.approx(returns_0) and last[1]["mc_return"] == pytest.approx(returns_1)
    assert last[0]["overestimation"] == pytest.approx(0.0 - returns_0)
    assert last[1]["overestimation"] == pytest.approx(7.0 - returns_1)
    assert model.logger.name_to_value["diagnostics/q_mean/source_1"] == 7.0


def test_source_q_callback_widens_an_older_file_and_keeps_its_rows(tmp_path):
    from sb3_lifelong import CRR
    from sb3_lifelong.evaluation.callbacks import Q_CSV_FIELDS, SourceQCallback

    path = tmp_path / "q.csv"
    path.write_text("timesteps,source,name,q_mean,n\n0,0,a,1.0,3\n")
    buffer = two_source_buffer()
    model = CRR.from_offline_data(buffer, batch_size=4, policy_kwargs=dict(net_arch=[8]), seed=0)
    model.learn_offline(5, callback=SourceQCallback(log_freq=5, batch_size=64, log_path=path, data=buffer), log_interval=0)
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0]) == Q_CSV_FIELDS and all(len(row) == len(Q_CSV_FIELDS) for row in rows)
    assert rows[0] == dict(timesteps="0", source="0", name="a", q_mean="1.0", n="3", q_probe="", mc_return="",
                           overestimation="", n_mc="")  # fmt: skip
    assert len(rows) == 3 and all(float(row["overestimation"]) == pytest.approx(
        float(row["q_probe"]) - float(row["mc_return"]), abs=1e-4) for row in rows[1:])  # fmt: skip
    other = tmp_path / "other.csv"  # a file of other columns keeps them
    other.write_text("timesteps,source,name,q_mean,n,extra\n")
    model.learn_offline(5, callback=SourceQCallback(log_freq=5, batch_size=64, log_path=other, data=buffer), log_interval=0)
    assert other.read_text().splitlines()[0] == "timesteps,source,name,q_mean,n,extra"
    empty = tmp_path / "empty.csv"  # an empty file (a run stopped before its first row) is written as a new one
    empty.write_text("")
    model.learn_offline(5, callback=SourceQCallback(log_freq=5, batch_size=64, log_path=empty, data=buffer), log_interval=0)
    assert empty.read_text().splitlines()[0] == ",".join(Q_CSV_FIELDS)


def test_probe_applies_the_observation_normaliser():
    class Shift:
        def normalize_obs(self, obs):
            return obs + 100.0

    class ObsCritic(th.nn.Module):
        def forward(self, obs, actions):
            return (obs[:, :1],)

    probe = MonteCarloProbe(two_source_buffer(), 0.5, per_source=100)
    raw, shifted = probe.measure(ObsCritic()), probe.measure(ObsCritic(), normalizer=Shift())
    assert shifted[0].q_mean == pytest.approx(raw[0].q_mean + 100.0)
    assert shifted[0].mc_return == raw[0].mc_return
