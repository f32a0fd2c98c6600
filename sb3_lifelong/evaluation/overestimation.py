"""
Overestimation measured against the truth: a critic's Q(s, a) on stored transitions minus the discounted return that
actually followed them in the stored episode (their Monte-Carlo return), per source of the data.

Q levels alone do not show overestimation (a source of better data has higher Q-values for good reasons); the gap to
the return the data really obtained does. In a lifelong run this gap is the forgetting risk of each source, with no
task boundary needed: a source whose gap grows is being extrapolated on, not learnt.

What the gap holds: ``Q(s, a)`` estimates the return of the stored action followed by the *current* policy, the
Monte-Carlo return is that of the action followed by the policy that *collected* the data. So the gap is the
current policy's improvement over the collector on that data plus the critic's error:
``Q_hat - G = (Q^pi - Q^behaviour) + (Q_hat - Q^pi)``. An improving learner has a positive gap on its own older data
even with an exact critic (MPO's critic at the end of Env-A: +56 on Hopper, +94 on HalfCheetah,
``benchmarks/studies/imbalance_dose/results``). Read it as a trend on a source the policy no longer improves on: when the
policy gets worse there (forgetting), the first term shrinks, so a gap that grows is the critic's error.
"""

import math
from typing import Any, NamedTuple, Optional

import numpy as np


def monte_carlo_horizon(gamma: float, tolerance: float = 0.01) -> int:
    """
    :param gamma: the discount factor, in ``(0, 1)``
    :param tolerance: the weight ``gamma^h`` below which the rest of an episode is ignored
    :return: the fewest steps ``h`` after which ``gamma^h < tolerance`` (459 for 0.99 and 0.01)
    """
    if not 0.0 < gamma < 1.0 or not 0.0 < tolerance < 1.0:
        raise ValueError(f"gamma and tolerance must be in (0, 1), got {gamma} and {tolerance}")
    horizon = math.ceil(math.log(tolerance) / math.log(gamma))
    # the logarithms' rounding: gamma^h may land on the tolerance (an exact power) or just either side of it
    while gamma**horizon >= tolerance:
        horizon += 1
    while horizon > 1 and gamma ** (horizon - 1) < tolerance:
        horizon -= 1
    return horizon


class MonteCarloReturns(NamedTuple):
    """The discounted return that followed each row of episode-ordered data, and whether it is complete enough."""

    #: ``sum_k gamma^k r_{t+k}`` up to the end of the row's stored episode, ``[n]`` (float64)
    returns: np.ndarray
    #: the return is the true one: its episode terminated, or at least ``horizon`` steps of it are stored, ``[n]``
    valid: np.ndarray


def discounted_returns(
    rewards: np.ndarray, terminals: np.ndarray, timeouts: np.ndarray, gamma: float, horizon: Optional[int] = None
) -> MonteCarloReturns:
    """
    The discounted Monte-Carlo return of every row of episode-ordered transitions (d4rl layout: each episode's rows
    contiguous, its last row a terminal or a timeout; a last row that is neither counts as a timeout).

    A row's return is *valid* when what is missing of it weighs nothing or little: its episode terminated (nothing
    follows a terminal), or at least ``horizon`` steps of the episode follow it (the missing tail weighs less than
    ``gamma^horizon`` of a return). Rows near a time-limit truncation are not valid: their true return goes on.

    :param rewards: ``[n]``
    :param terminals: ``[n]`` bool, the episode ended (no bootstrap)
    :param timeouts: ``[n]`` bool, the episode was cut (time limit, end of the stored data)
    :param gamma: the discount factor
    :param horizon: steps of stored future that make a truncated row's return valid (default:
        :func:`monte_carlo_horizon`)
    :return: the returns and their validity
    """
    rewards = np.asarray(rewards, dtype=np.float64).reshape(-1)
    terminals = np.asarray(terminals).reshape(-1).astype(bool)
    timeouts = np.asarray(timeouts).reshape(-1).astype(bool)
    if not (len(rewards) == len(terminals) == len(timeouts)):
        lengths = f"{len(rewards)}, {len(terminals)}, {len(timeouts)}"
        raise ValueError(f"rewards, terminals and timeouts differ in length: {lengths}")
    horizon = monte_carlo_horizon(gamma) if horizon is None else int(horizon)
    n = len(rewards)
    returns = np.empty(n, dtype=np.float64)
    valid = np.empty(n, dtype=bool)
    following, steps_left, terminated = 0.0, 0, False
    for t in range(n - 1, -1, -1):  # one pass backwards; an episode ends at a terminal, a timeout or the data's end
        if terminals[t] or timeouts[t] or t == n - 1:
            following, steps_left, terminated = 0.0, 0, bool(terminals[t])
        following = rewards[t] + gamma * following
        steps_left += 1
        returns[t] = following
        valid[t] = terminated or steps_left > horizon
    return MonteCarloReturns(returns, valid)


class SourceOverestimation(NamedTuple):
    """One source's measurement."""

    q_mean: float
    mc_return: float
    overestimation: float
    n: int


class MonteCarloProbe:
    """
    A fixed sample of each source's stored transitions with their Monte-Carlo returns, to measure a critic's
    overestimation per source: mean ``Q(s, a) - G`` over the sample (:func:`discounted_returns`).

    The sample is drawn anew when the data has grown since the last measurement (during collection), and kept while
    it has not (offline), so that successive measurements of a student are on the same transitions.

    :param data: a ``LifelongReplayBuffer`` or a view / merge of them (anything with ``to_d4rl`` and ``size``)
    :param gamma: the discount factor of the returns (the critic's)
    :param per_source: transitions sampled per source (at most; all the valid ones if fewer)
    :param horizon: see :func:`discounted_returns`
    :param reward_scale: per-source reward scale (source id -> factor) the critic was trained with
    :param seed: seed of the sample
    """

    def __init__(
        self,
        data: Any,
        gamma: float,
        per_source: int = 2048,
        horizon: Optional[int] = None,
        reward_scale: Optional[dict[int, float]] = None,
        seed: int = 0,
    ):
        if per_source < 1:
            raise ValueError(f"per_source must be >= 1, got {per_source}")
        if not hasattr(data, "to_d4rl"):
            raise TypeError(
                f"MonteCarloProbe needs episode-ordered data with sources (a LifelongReplayBuffer), got {type(data).__name__}"
            )
        self.data = data
        self.gamma = gamma
        self.per_source = per_source
        self.horizon = monte_carlo_horizon(gamma) if horizon is None else horizon
        self.reward_scale = {int(k): float(v) for k, v in (reward_scale or {}).items()}
        self.seed = seed
        self._size = -1
        self._sample: dict[int, dict[str, np.ndarray]] = {}

    def refresh(self) -> None:
        """Draw the sample again if the data has grown (or shrunk) since it was drawn."""
        size = int(self.data.size())
        if size == self._size:
            return
        self._size = size
        self._sample = {}
        if size == 0:
            return
        columns = self.data.to_d4rl(by_episode=True, normalized_actions=True)
        sources = np.asarray(columns["sources"]).reshape(-1)
        scale = np.ones(len(sources))
        for source, factor in self.reward_scale.items():
            scale[sources == source] = factor
        mc = discounted_returns(
            columns["rewards"].reshape(-1) * scale, columns["terminals"], columns["timeouts"], self.gamma, self.horizon
        )
        rng = np.random.default_rng(self.seed)
        for source in np.unique(sources):
            rows = np.flatnonzero((sources == source) & mc.valid)
            if len(rows) == 0:
                continue
            rows = np.sort(rng.choice(rows, size=min(self.per_source, len(rows)), replace=False))
            self._sample[int(source)] = dict(
                observations=columns["observations"][rows], actions=columns["actions"][rows], returns=mc.returns[rows]
            )

    def measure(self, critic: Any, device: Any = "cpu", normalizer: Any = None) -> dict[int, SourceOverestimation]:
        """
        :param critic: an SB3-style critic, ``critic(obs, actions)`` -> a tuple of ``[n, 1]`` Q-values (the first is used)
        :param device: where the critic lives
        :param normalizer: the ``VecNormalize`` the critic was trained behind (its ``normalize_obs`` is applied to the
            stored observations; the returns stay in the stored rewards' units)
        :return: source id -> the mean Q-value, the mean Monte-Carlo return and their difference on its sample
        """
        import torch as th

        self.refresh()
        results = {}
        for source, rows in self._sample.items():
            stored = rows["observations"] if normalizer is None else normalizer.normalize_obs(rows["observations"])
            obs = th.as_tensor(stored, dtype=th.float32, device=device)
            actions = th.as_tensor(rows["actions"], dtype=th.float32, device=device)
            with th.no_grad():
                q_values = critic(obs, actions)[0].flatten().double().cpu().numpy()
            q_mean, mc_mean = float(q_values.mean()), float(rows["returns"].mean())
            results[source] = SourceOverestimation(q_mean, mc_mean, float(np.mean(q_values - rows["returns"])), len(q_values))
        return results
