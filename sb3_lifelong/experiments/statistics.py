"""
The statistics of a study's reports and claims: the BCa bootstrap interval of a mean over seeds
(``scipy.stats.bootstrap``), Student's t interval, and the paired difference of two per-seed series.
"""

import inspect
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

BOOTSTRAP_RESAMPLES = 10_000


def _resampling(seed: int) -> dict[str, Any]:
    """:return: ``scipy.stats.bootstrap``'s random generator argument (``rng`` from scipy 1.15, ``random_state`` before)"""
    from scipy import stats

    name = "rng" if "rng" in inspect.signature(stats.bootstrap).parameters else "random_state"
    return {name: np.random.default_rng(seed)}


def bootstrap_ci(values: Sequence[float], level: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """
    BCa (bias-corrected and accelerated) bootstrap interval of the mean, resampling seeds with replacement
    (``scipy.stats.bootstrap``, ``BOOTSTRAP_RESAMPLES`` resamples). With a handful of seeds no interval is reliable:
    with two it is the range of their values.

    :param values: one value per seed (non-finite values are left out)
    :param level: coverage
    :param seed: seed of the resampling
    :return: the interval's bounds (NaN without values; the single value for one seed or identical values)
    """
    from scipy import stats

    data = np.asarray([v for v in values if np.isfinite(v)], dtype=float)
    if len(data) == 0:
        return float("nan"), float("nan")
    if len(data) == 1 or np.ptp(data) == 0:  # no spread to resample (BCa's acceleration is undefined)
        return float(data[0]), float(data[0])
    result = stats.bootstrap(
        (data,), np.mean, confidence_level=level, n_resamples=BOOTSTRAP_RESAMPLES, method="BCa", **_resampling(seed)
    )
    low, high = result.confidence_interval
    return float(low), float(high)


def t_interval(values: Sequence[float], level: float = 0.95) -> tuple[float, float, float, float]:
    """
    The mean over seeds with Student's t interval (what a pre-registered rule that names a t interval uses; the
    reports' own intervals are :func:`bootstrap_ci`).

    :param values: one value per seed
    :param level: coverage
    :return: mean, std (ddof 1), and the interval's bounds (NaN but the mean with fewer than two values)
    """
    from scipy import stats

    data = np.asarray(values, dtype=float)
    mean = float(data.mean()) if len(data) else float("nan")
    if len(data) < 2:
        return mean, float("nan"), float("nan"), float("nan")
    std = float(data.std(ddof=1))
    half = float(stats.t.ppf(0.5 + level / 2, len(data) - 1)) * std / float(np.sqrt(len(data)))
    return mean, std, mean - half, mean + half


def paired_difference(first: Mapping[int, float], second: Mapping[int, float], level: float = 0.95) -> dict[str, Any]:
    """
    The per-seed difference ``first - second`` over the seeds both have (paired by seed: both values come from the
    same seed's collection), with the BCa interval of its mean.

    :param first: seed -> value
    :param second: seed -> value
    :param level: coverage of the interval
    :return: ``n`` (paired seeds), ``mean``, ``low``, ``high`` (NaN without pairs) and ``wins``: the seeds on which
        ``first`` is higher, ties counting one half (``wins / n``: the probability of improvement over seeds)
    """
    seeds = sorted(s for s in first if s in second and np.isfinite(first[s]) and np.isfinite(second[s]))
    differences = np.asarray([first[s] - second[s] for s in seeds], dtype=float)
    low, high = bootstrap_ci(list(differences), level)
    wins = float(np.sum(differences > 0) + 0.5 * np.sum(differences == 0))
    mean = float(differences.mean()) if len(differences) else float("nan")
    return dict(n=len(seeds), mean=mean, low=low, high=high, wins=wins)


def describe(values: Sequence[float]) -> str:
    """
    :param values: one value per seed
    :return: ``mean +- std [low, high]`` over seeds; the value alone for one seed (no spread, no interval); ``-``
        without values
    """
    data = np.asarray(values, dtype=float)
    if len(data) == 0:
        return "-"
    if len(data) == 1:
        return f"{data[0]:.0f}"
    low, high = bootstrap_ci(list(data))
    return f"{data.mean():.0f} +- {data.std():.0f} [{low:.0f}, {high:.0f}]"
