"""
The claim engine: a study's pre-registered claims (:class:`Claim`: per-seed series and a test on their means), the
preconditions under which each is testable (:data:`PRECONDITIONS`, thresholds from the study's preset), and their
verdicts (:func:`evaluate_claims`).

The claims themselves are data of their study, not of the library: each study folder holds a ``claims.py`` that
defines ``CLAIMS`` with the helpers of this module (``benchmarks/studies/paper_cpu/claims.py``, say), and
:func:`load_claims` reads it by its path. The report of a study directory uses the ``claims.py`` beside its seeds,
or the file given to ``report --claims``.
"""

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Callable, Optional, Union

import numpy as np

from sb3_lifelong.experiments.presets import read_study_file
from sb3_lifelong.experiments.scores import SWITCH_SPREAD_EVALS, Study
from sb3_lifelong.experiments.statistics import bootstrap_ci, paired_difference


@dataclass
class Claim:
    """
    A pre-registered claim: per-seed values, and a test on their means.

    :param name: short name (``"C2a ..."``)
    :param statement: the pre-registered criterion, in words
    :param values: the named per-seed series of a study
    :param test: the criterion, on the means of the series
    :param pairs: the series compared (first, second), each reported as a paired difference per seed (see
        :func:`paired_difference`); None: the first series against each other one (none for a single series, e.g. a
        per-seed ratio, which is paired already)
    :param needs: the preconditions the claim is testable under (names in :data:`PRECONDITIONS`): it is tested on
        the seeds where each of them that the study's preset states holds (:func:`testable_seeds`)
    """

    name: str
    statement: str
    values: Callable[[Study], dict[str, dict[int, float]]]
    test: Callable[[dict[str, float]], bool]
    pairs: Optional[Sequence[tuple[str, str]]] = None
    needs: tuple[str, ...] = ()

    def compared(self, names: Sequence[str]) -> list[tuple[str, str]]:
        """
        :param names: the names of the claim's series
        :return: the pairs of series whose paired difference the report gives
        """
        if self.pairs is not None:
            return list(self.pairs)
        return [(names[0], other) for other in names[1:]]


def series_mean(series: dict[int, float]) -> float:
    """:return: the mean of a per-seed series over its finite values (NaN without one)"""
    values = [v for v in series.values() if np.isfinite(v)]
    return float(np.mean(values)) if values else float("nan")


def ratio(numerator: dict[int, float], denominator: dict[int, float]) -> dict[int, float]:
    """
    Per-seed ratios of two returns. A seed whose denominator is not positive has no ratio ("reaches 80 % of a
    return of -2" means nothing, and such a ratio flips sign and swamps the mean): it is left out, and
    :func:`undefined_ratios` names it in the report.
    """
    return {s: numerator[s] / denominator[s] for s in numerator if s in denominator and denominator[s] > 0}


def undefined_ratios(numerator: dict[int, float], denominator: dict[int, float]) -> dict[int, float]:
    """:return: seed -> denominator, for the seeds :func:`ratio` leaves out (denominator <= 0)"""
    return {s: denominator[s] for s in numerator if s in denominator and not denominator[s] > 0}


def mean_over(study: Study, method: str, envs: Sequence[str]) -> dict[int, float]:
    """:return: seed -> the method's mean score over ``envs``, on the seeds scored in every one of them"""
    per_env = [study.score(method, env) for env in envs]
    seeds = set.intersection(*(set(s) for s in per_env)) if per_env else set()
    return {s: float(np.mean([series[s] for series in per_env])) for s in seeds}


def mean_over_envs(study: Study, method: str) -> dict[int, float]:
    """:return: seed -> the method's mean score over every environment of the study"""
    return mean_over(study, method, study.preset["env_names"])


@dataclass(frozen=True)
class Precondition:
    """
    What must hold on a seed for a claim to be testable there, with its threshold in the study's preset.

    :param setting: the preset's setting that holds the threshold (None there: the precondition is not checked)
    :param statement: the precondition in words, with ``{threshold}``
    :param values: the per-seed measurement the threshold applies to
    :param at_most: the threshold is an upper bound (the measurement must not exceed it); else a lower bound
    """

    setting: str
    statement: str
    values: Callable[[Study], dict[int, float]]
    at_most: bool = False

    def check(self, study: Study) -> Optional[tuple[str, dict[int, float], set[int]]]:
        """:return: None when the preset states no threshold; else its statement, the values, the seeds it holds on"""
        threshold = study.preset.get(self.setting)
        if threshold is None:
            return None
        values = self.values(study)
        held = {
            seed
            for seed, value in values.items()
            if not np.isnan(value) and (value <= threshold if self.at_most else value >= threshold)
        }
        return self.statement.format(threshold=f"{threshold:g}"), values, held


def _value_gap(study: Study) -> dict[int, float]:
    """the discounted return of the last environment's data over Env-A's (the collector's Monte-Carlo measurement)"""
    last = study.preset["env_names"][-1]
    return ratio(study.extra(f"data|mc_return|{last}"), study.extra("data|mc_return|Env-A"))


def _steady(env: str) -> Precondition:
    """:return: the precondition that MPO left ``env`` at a level (``Preset.max_switch_spread``)"""
    return Precondition(
        "max_switch_spread",
        f"MPO left {env} steadily (the spread, std / mean, of its last {SWITCH_SPREAD_EVALS} {env} evaluations before "
        + "it left it <= {threshold})",
        lambda s: s.extra(f"MPO|switch_spread|{env}"),
        at_most=True,
    )


#: the preconditions of the claims (:attr:`Claim.needs`), each checked where the study's preset states its threshold
PRECONDITIONS: dict[str, Precondition] = {
    "env_a_learnt": Precondition(
        "env_a_learnt", "Env-A learnt (MPO's Env-A return at the switch >= {threshold})", lambda s: s.extra("MPO|switch|Env-A")
    ),
    "value_gap": Precondition(
        "value_gap",
        "a value gap (the discounted return of the last environment's data / Env-A's >= {threshold})",
        _value_gap,
    ),
    "conservative": Precondition(
        "min_weight_ess",
        "the exp beta=1 student stays close to the data (its weights' effective sample size >= {threshold} of a batch)",
        lambda s: s.extra("CRR_exp_beta1|weight_ess"),
    ),
    "steady": _steady("Env-A"),
    "steady_b": _steady("Env-B"),
}


def testable_seeds(
    study: Study, claim: Claim, checks: Mapping[str, Optional[tuple[str, dict[int, float], set[int]]]]
) -> Optional[tuple[set[int], list[str], bool]]:
    """
    :param checks: each precondition's :meth:`Precondition.check` on the study, by name
    :return: None when the study checks none of the claim's preconditions; else the seeds where every checked one was
        measured and holds, a line per precondition (its statement, where it held, each seed's value, the seeds with
        no value yet), and whether the claim is *not testable*: every seed of the study measured a failure of one
    """
    checked = [check for check in (checks[name] for name in claim.needs) if check is not None]
    if not checked:
        return None
    seeds, failed = set(study.seeds), set()
    notes = []
    for statement, values, held in checked:
        measured = {seed for seed, value in values.items() if not np.isnan(value)}  # inf too: a spread with no level
        seeds &= held
        failed |= measured - held
        per_seed = ", ".join(
            f"s{seed}: {values[seed]:.2f}" if abs(values[seed]) < 10 else f"s{seed}: {values[seed]:.0f}"
            for seed in sorted(measured)
        )
        unmeasured = sorted(set(study.seeds) - measured)
        notes.append(
            f"{statement}: held on {len(held)} of {len(measured)} measured seeds ({per_seed or 'none measured'})"
            + (f"; not measured on {', '.join(f's{seed}' for seed in unmeasured)}" if unmeasured else "")
        )
    return seeds, notes, bool(study.seeds) and failed >= set(study.seeds)


def evaluate_claims(study: Study, claims: Sequence[Claim]) -> list[dict[str, Any]]:
    """
    :param study: the study
    :param claims: its pre-registered claims (a study's ``claims.py``, :func:`load_claims`)
    :return: one row per claim: the series (per seed, mean, CI), and reproduced / not reproduced / no data, or *not
        testable* when on every seed a precondition the study checks was measured and failed (:func:`testable_seeds`);
        a claim is tested on the seeds where its preconditions were measured and hold (none yet: no data), and its
        row says which held where
    """
    rows = []
    checks = {name: precondition.check(study) for name, precondition in PRECONDITIONS.items()}
    for claim in claims:
        series = claim.values(study)
        testable = testable_seeds(study, claim, checks)
        if testable is not None:
            seeds = testable[0]
            series = {name: {seed: v for seed, v in values.items() if seed in seeds} for name, values in series.items()}
        means = {name: series_mean(values) for name, values in series.items()}
        complete = all(np.isfinite(v) for v in means.values()) and all(series.values())
        verdict = ("reproduced" if claim.test(means) else "not reproduced") if complete else "no data"
        if testable is not None and testable[2]:
            verdict = "not testable"
        details = []
        for name, values in series.items():
            # a seed without a value has no score yet, or no ratio (its denominator is not positive, see ratio)
            per_seed = ", ".join(
                "s{}: {}".format(
                    s, "n/a" if s not in values else f"{values[s]:.2f}" if abs(values[s]) < 10 else f"{values[s]:.0f}"
                )
                for s in sorted(set(study.seeds) | set(values))
            )
            fmt = "{:.2f}" if abs(means[name]) < 10 else "{:.0f}"
            if len(values) > 1:
                low, high = bootstrap_ci(list(values.values()))
                details.append(f"{name}: {fmt.format(means[name])} [{fmt.format(low)}, {fmt.format(high)}] ({per_seed})")
            elif values:  # one seed: its value, no interval (the seed named when the study has others)
                details.append(
                    f"{name}: {fmt.format(means[name])}" + (f", 1 seed ({per_seed})" if len(study.seeds) > 1 else "")
                )
            else:
                details.append(f"{name}: no data")
        paired = [describe_pair(a, b, paired_difference(series[a], series[b])) for a, b in claim.compared(list(series))]
        row = dict(
            claim=claim.name, statement=claim.statement, verdict=verdict, values="; ".join(details), paired="; ".join(paired)
        )
        if any(check is not None for check in checks.values()):  # a preset with thresholds: a column, "-" where none is needed
            row["precondition"] = "; ".join(testable[1]) if testable is not None else "-"
        rows.append(row)
    return rows


def describe_pair(first: str, second: str, difference: Mapping[str, Any]) -> str:
    """
    :param first: the first series' name
    :param second: the second series' name
    :param difference: :func:`paired_difference` of the two
    :return: ``first - second: mean [low, high], first higher on k of n seeds`` (one seed: ``first - second: mean,
        1 seed``, no interval)
    """
    if difference["n"] == 0:
        return f"{first} - {second}: no paired seeds"
    fmt = "{:+.2f}" if abs(difference["mean"]) < 10 else "{:+.0f}"
    if difference["n"] == 1:
        return f"{first} - {second}: {fmt.format(difference['mean'])}, 1 seed"
    wins = f"{difference['wins']:g}"
    return (
        f"{first} - {second}: {fmt.format(difference['mean'])} [{fmt.format(difference['low'])}, "
        f"{fmt.format(difference['high'])}], {first} higher on {wins} of {difference['n']} seeds"
    )


def load_claims(path: Union[str, os.PathLike]) -> list[Claim]:
    """
    Read a study's claims file: a Python file that defines ``CLAIMS``, a list of :class:`Claim` (it is run, as any
    Python file: load only your own studies' files).

    :param path: the file (a study folder's ``claims.py``)
    :return: its claims
    """
    claims = read_study_file(path, "CLAIMS")
    if not isinstance(claims, list) or not all(isinstance(claim, Claim) for claim in claims):
        raise ValueError(f"{path} must define CLAIMS, a list of sb3_lifelong.experiments.claims.Claim")
    return claims
