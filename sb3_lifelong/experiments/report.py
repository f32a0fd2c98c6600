"""
The report of a two-stage (or three-stage) study: its score tables, the pre-registered claims with their verdicts,
and ``report.md`` with the paper's figures (:mod:`sb3_lifelong.experiments.figures`).

The scores are each seed's (:mod:`sb3_lifelong.experiments.scores`); a table gives their mean +- std over seeds and
a 95 % BCa bootstrap interval of the mean, from ``scipy.stats.bootstrap``.

A claim that compares two methods also reports their paired difference: per seed (both from the same seed's
collection), its mean with a BCa interval, and on how many seeds the first is higher (rliable's "probability of
improvement" over seeds). The verdicts themselves are the pre-registered tests on the means.
"""

import inspect
import json
import pathlib
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np
import pandas as pd

from sb3_lifelong.experiments.figures import plot_study
from sb3_lifelong.experiments.scores import (
    ONLINE_LAST,
    ONLINE_LAST_STAGE1,
    STUDENT_LAST,
    SWITCH_SPREAD_EVALS,
    Study,
    load_study,
)

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
    """:return: ``mean +- std [low, high]`` over seeds"""
    data = np.asarray(values, dtype=float)
    if len(data) == 0:
        return "-"
    low, high = bootstrap_ci(list(data))
    return f"{data.mean():.0f} +- {data.std():.0f} [{low:.0f}, {high:.0f}]"


# ------------------------------------------------------------------------------------------------- claims
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


def _mean(series: dict[int, float]) -> float:
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


def _mean_over(study: Study, method: str, envs: Sequence[str]) -> dict[int, float]:
    per_env = [study.score(method, env) for env in envs]
    seeds = set.intersection(*(set(s) for s in per_env)) if per_env else set()
    return {s: float(np.mean([series[s] for series in per_env])) for s in seeds}


def _mean_over_envs(study: Study, method: str) -> dict[int, float]:
    return _mean_over(study, method, study.preset["env_names"])


#: the methods that need no task boundaries, compared by claim C3
LIFELONG_METHODS = ("MPO", "online CRR_indicator", "online CRR_exp_beta1", "CRR_exp_beta1", "CRR_indicator", "BC")

CLAIMS: list[Claim] = [
    Claim(
        "C1 forgetting",
        "MPO's Env-A return at the end of Stage 2 is <= 70 % of its Env-A return at the switch",
        lambda s: {"end / switch": ratio(s.score("MPO", "Env-A"), s.extra("MPO|switch|Env-A"))},
        lambda m: m["end / switch"] <= 0.7,
        needs=("env_a_learnt", "steady"),
    ),
    Claim(
        "C2a conservative online CRR remembers",
        "online CRR (exp, beta=1) ends with a higher Env-A return than MPO",
        lambda s: {"CRR beta=1": s.score("online CRR_exp_beta1", "Env-A"), "MPO": s.score("MPO", "Env-A")},
        lambda m: m["CRR beta=1"] > m["MPO"],
        needs=("env_a_learnt",),
    ),
    Claim(
        "C2b conservative online CRR learns Env-B slower",
        "online CRR (exp, beta=1)'s mean Env-B return over Stage 2 is below MPO's",
        lambda s: {
            "CRR beta=1": s.extra("online CRR_exp_beta1|stage2_area|Env-B"),
            "MPO": s.extra("MPO|stage2_area|Env-B"),
        },
        lambda m: m["CRR beta=1"] < m["MPO"],
    ),
    Claim(
        "C3 the pipeline is best",
        "the CRR exp beta=1 student has the best mean over Env-A and Env-B of the lifelong methods "
        + "("
        + ", ".join(LIFELONG_METHODS)
        + ")",
        lambda s: {m: _mean_over_envs(s, m) for m in LIFELONG_METHODS},
        lambda m: all(m["CRR_exp_beta1"] >= v for k, v in m.items() if np.isfinite(v)),
        pairs=tuple(("CRR_exp_beta1", method) for method in LIFELONG_METHODS if method != "CRR_exp_beta1"),
    ),
    Claim(
        "C4a the imbalance drop",
        "the indicator student on Env-A + Env-B reaches <= 80 % of the Env-A-only indicator student in Env-A",
        lambda s: {"indicator / A-only": ratio(s.score("CRR_indicator", "Env-A"), s.score("CRR_indicator_A_only", "Env-A"))},
        lambda m: m["indicator / A-only"] <= 0.8,
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C4b beta=1 fixes it",
        "the exp beta=1 student on Env-A + Env-B reaches >= 90 % of the Env-A-only indicator student in Env-A",
        lambda s: {"exp beta=1 / A-only": ratio(s.score("CRR_exp_beta1", "Env-A"), s.score("CRR_indicator_A_only", "Env-A"))},
        lambda m: m["exp beta=1 / A-only"] >= 0.9,
        needs=("env_a_learnt", "value_gap", "conservative"),
    ),
    Claim(
        "C5a reward scale",
        "scaling Env-B's rewards by 0.5 raises the indicator student's Env-A return",
        lambda s: {"scaled": s.score("CRR_indicator_scale_rwd_B", "Env-A"), "baseline": s.score("CRR_indicator", "Env-A")},
        lambda m: m["scaled"] > m["baseline"],
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C5b two actors",
        "one actor per environment (shared critic) raises the indicator student's Env-A return",
        lambda s: {"two actors": s.score("CRR_indicator_two_actors", "Env-A"), "baseline": s.score("CRR_indicator", "Env-A")},
        lambda m: m["two actors"] > m["baseline"],
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C5c BC beats the indicator in Env-A",
        "behaviour cloning on Env-A + Env-B has a higher Env-A return than the indicator student",
        lambda s: {"BC": s.score("BC", "Env-A"), "indicator": s.score("CRR_indicator", "Env-A")},
        lambda m: m["BC"] > m["indicator"],
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C5d sampling ratio hurts the indicator",
        "the indicator student's Env-A return falls as Env-B's share grows: 1:1 > raw 1:5 > 1:10",
        lambda s: {
            "1:1": s.score("CRR_indicator_ratio_1to1", "Env-A"),
            "1:5": s.score("CRR_indicator", "Env-A"),
            "1:10": s.score("CRR_indicator_ratio_1to10", "Env-A"),
        },
        lambda m: m["1:1"] > m["1:5"] > m["1:10"],
        pairs=(("1:1", "1:5"), ("1:5", "1:10")),
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C5e beta=1 is robust to the ratio",
        "the exp beta=1 student's Env-A return at 1:10 is >= 90 % of its return at 1:1",
        lambda s: {
            "1:10 / 1:1": ratio(s.score("CRR_exp_beta1_ratio_1to10", "Env-A"), s.score("CRR_exp_beta1_ratio_1to1", "Env-A"))
        },
        lambda m: m["1:10 / 1:1"] >= 0.9,
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C6 overestimation on Env-A data",
        "the indicator student's average Q over Env-A data exceeds the Env-A-only student's",
        lambda s: {"indicator": s.extra("CRR_indicator|q|Env-A"), "A-only": s.extra("CRR_indicator_A_only|q|Env-A")},
        lambda m: m["indicator"] > m["A-only"],
    ),
]


#: the claims of the three-stage set-up (Env-A, Env-B, Env-C; the paper's appendix), pre-registered in
#: benchmarks/studies/paper_cpu_three/README.md before any seed ran
THREE_STAGE_CLAIMS: list[Claim] = [
    Claim(
        "T1a forgetting Env-A",
        "MPO's Env-A return at the end of Stage 3 is <= 70 % of its Env-A return at the end of Stage 1",
        lambda s: {"end / switch": ratio(s.score("MPO", "Env-A"), s.extra("MPO|switch|Env-A"))},
        lambda m: m["end / switch"] <= 0.7,
        needs=("env_a_learnt", "steady"),
    ),
    Claim(
        "T1b forgetting Env-B",
        "MPO's Env-B return at the end of Stage 3 is <= 70 % of its Env-B return at the end of Stage 2",
        lambda s: {"end / switch": ratio(s.score("MPO", "Env-B"), s.extra("MPO|switch|Env-B"))},
        lambda m: m["end / switch"] <= 0.7,
        needs=("steady_b",),
    ),
    Claim(
        "T2a distillation recovers the earlier environments",
        "the CRR exp beta=1 student's mean return over Env-A and Env-B is above MPO's final one",
        lambda s: {
            "exp beta=1": _mean_over(s, "CRR_exp_beta1", ("Env-A", "Env-B")),
            "MPO": _mean_over(s, "MPO", ("Env-A", "Env-B")),
        },
        lambda m: m["exp beta=1"] > m["MPO"],
    ),
    Claim(
        "T2b distillation keeps the last environment",
        "the CRR exp beta=1 student's Env-C return is >= 80 % of MPO's final Env-C return",
        lambda s: {"student / MPO": ratio(s.score("CRR_exp_beta1", "Env-C"), s.score("MPO", "Env-C"))},
        lambda m: m["student / MPO"] >= 0.8,
    ),
    Claim(
        "T3a the imbalance drop",
        "the indicator student's Env-A return is <= 80 % of the exp beta=1 student's",
        lambda s: {"indicator / exp beta=1": ratio(s.score("CRR_indicator", "Env-A"), s.score("CRR_exp_beta1", "Env-A"))},
        lambda m: m["indicator / exp beta=1"] <= 0.8,
        needs=("env_a_learnt", "value_gap", "conservative"),
    ),
    Claim(
        "T3b exp beta=1 is the more reliable student",
        "the exp beta=1 student's mean return over the three environments is >= the indicator student's",
        lambda s: {"exp beta=1": _mean_over_envs(s, "CRR_exp_beta1"), "indicator": _mean_over_envs(s, "CRR_indicator")},
        lambda m: m["exp beta=1"] >= m["indicator"],
        needs=("conservative",),
    ),
]


def claims_of(preset: Mapping[str, Any]) -> list[Claim]:
    """:return: the pre-registered claims of a study's set-up: :data:`CLAIMS` for two stages, else the three-stage ones"""
    stages = len(preset["env_names"])
    if stages == 2:
        return CLAIMS
    if stages == 3:
        return THREE_STAGE_CLAIMS
    raise ValueError(f"no pre-registered claims for a study of {stages} environments (two or three)")


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


def evaluate_claims(study: Study) -> list[dict[str, Any]]:
    """
    :return: one row per claim: the series (per seed, mean, CI), and reproduced / not reproduced / no data, or *not
        testable* when on every seed a precondition the study checks was measured and failed (:func:`testable_seeds`);
        a claim is tested on the seeds where its preconditions were measured and hold (none yet: no data), and its
        row says which held where
    """
    rows = []
    checks = {name: precondition.check(study) for name, precondition in PRECONDITIONS.items()}
    for claim in claims_of(study.preset):
        series = claim.values(study)
        testable = testable_seeds(study, claim, checks)
        if testable is not None:
            seeds = testable[0]
            series = {name: {seed: v for seed, v in values.items() if seed in seeds} for name, values in series.items()}
        means = {name: _mean(values) for name, values in series.items()}
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
            low, high = bootstrap_ci(list(values.values()))
            fmt = "{:.2f}" if abs(means[name]) < 10 else "{:.0f}"
            details.append(
                f"{name}: {fmt.format(means[name])} [{fmt.format(low)}, {fmt.format(high)}] ({per_seed})"
                if values
                else f"{name}: no data"
            )
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
    :return: ``first - second: mean [low, high], first higher on k of n seeds``
    """
    if difference["n"] == 0:
        return f"{first} - {second}: no paired seeds"
    fmt = "{:+.2f}" if abs(difference["mean"]) < 10 else "{:+.0f}"
    wins = f"{difference['wins']:g}"
    return (
        f"{first} - {second}: {fmt.format(difference['mean'])} [{fmt.format(difference['low'])}, "
        f"{fmt.format(difference['high'])}], {first} higher on {wins} of {difference['n']} seeds"
    )


# ------------------------------------------------------------------------------------------------- tables
def score_table(study: Study) -> str:
    envs = study.preset["env_names"]
    header = "| method | kind | " + " | ".join(envs) + " | mean over envs | seeds |"
    lines = [header, "|" + " --- |" * (len(envs) + 4)]
    order = list(dict.fromkeys(study.finals["method"])) if len(study.finals) else []
    order.sort(key=lambda m: (0 if m == "MPO" else 1 if m.startswith("online") else 2))
    for method in order:
        kind = study.finals[study.finals["method"] == method]["kind"].iloc[0]
        cells = [describe(list(study.score(method, env).values())) for env in envs]
        overall = _mean_over_envs(study, method)
        lines.append(
            f"| {method} | {kind} | " + " | ".join(cells) + f" | {describe(list(overall.values()))} | {len(overall)} |"
        )
    return "\n".join(lines)


def weights_table(study: Study) -> str:
    """
    :return: each student's regression weights, per seed: their effective sample size (a fraction of a batch: 1 is
        behaviour cloning, small is greedy) and their share at the clip, the means of its last logged values; "" when
        no student logged them
    """
    metrics = sorted(set(study.extras["metric"])) if len(study.extras) else []
    methods = sorted({metric.rsplit("|", 1)[0] for metric in metrics if metric.endswith("|weight_ess")})
    if not methods:
        return ""
    lines = [
        "| student | weights' effective sample size (per seed) | share at the clip (per seed) |",
        "| --- | --- | --- |",
    ]
    for method in methods:
        cells = []
        for column in ("weight_ess", "weight_clip_frac"):
            values = study.extra(f"{method}|{column}")
            per_seed = ", ".join(f"s{seed}: {value:.2f}" for seed, value in sorted(values.items()))
            cells.append(f"{_mean(values):.2f} ({per_seed})" if values else "-")
        lines.append(f"| {method} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines)


def forgetting_table(study: Study) -> str:
    """
    :return: for each seed and each environment MPO left: its return there when it left (the switch score) and how
        steady it was then, its return there at the end, their ratio (what the forgetting claims read), and the
        collector's overestimation of that environment's data when it left and at the end (a source whose
        overestimation grows is being forgotten); "" without MPO scores
    """
    envs = study.preset["env_names"][:-1]
    if not any(study.extra(f"MPO|switch|{env}") for env in envs):
        return ""
    lines = [
        "| seed | environment | when MPO left it | spread then | at the end | end / switch "
        "| overestimation of its data: when MPO left it -> at the end |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]

    def cell(values: Mapping[int, float], seed: int, form: str) -> str:
        value = values.get(seed, float("nan"))
        return form.format(value) if np.isfinite(value) else ("inf" if value == np.inf else "-")

    for env in envs:
        switch, spread, end = (
            study.extra(f"MPO|switch|{env}"),
            study.extra(f"MPO|switch_spread|{env}"),
            study.score("MPO", env),
        )
        over_switch, over_end = study.extra(f"MPO|overestimation_switch|{env}"), study.extra(f"MPO|overestimation_end|{env}")
        forgetting = ratio(end, switch)
        for seed in study.seeds:
            overestimation = f"{cell(over_switch, seed, '{:+.1f}')} -> {cell(over_end, seed, '{:+.1f}')}"
            lines.append(
                f"| {seed} | {env} | {cell(switch, seed, '{:.0f}')} | {cell(spread, seed, '{:.2f}')} | "
                f"{cell(end, seed, '{:.0f}')} | {cell(forgetting, seed, '{:.2f}')} | {overestimation} |"
            )
    return "\n".join(lines)


def claims_table(rows: list[dict[str, Any]]) -> str:
    """:return: the claims as a markdown table (with a precondition column when the rows have one)"""
    checked = any("precondition" in r for r in rows)
    lines = [
        "| claim | pre-registered criterion | verdict | values: mean [95 % BCa CI] (per seed) "
        "| paired by seed: mean difference [95 % BCa CI], seeds on which the first is higher |"
        + (" precondition |" if checked else ""),
        "| --- | --- | --- | --- | --- |" + (" --- |" if checked else ""),
    ]
    lines += [
        f"| {r['claim']} | {r['statement']} | **{r['verdict']}** | {r['values']} | {r.get('paired') or '-'} |"
        + (f" {r.get('precondition', '-')} |" if checked else "")
        for r in rows
    ]
    return "\n".join(lines)


def incomplete_repeats(study: Study) -> list[str]:
    """:return: one line per seed and student scored on fewer repeats than the study trains (some still running)"""
    wanted = int(study.preset.get("student_repeats", 1))
    students = study.finals[study.finals["kind"] == "student"].drop_duplicates(["seed", "method"])
    lines = [
        f"seed {row.seed}: {row.method} on {row.repeats} of {wanted} repeats"
        for row in students.itertuples()
        if row.repeats < wanted
    ]
    for seed in study.seeds:  # the preset's students with no finished repeat on a seed
        trained = set(students[students["seed"] == seed]["method"])
        lines += [
            f"seed {seed}: {name} on 0 of {wanted} repeats"
            for name in study.preset.get("students") or ()
            if name not in trained
        ]
    return lines


def write_report(output: pathlib.Path, plots: bool = True, seeds: Optional[Sequence[int]] = None) -> str:
    """
    Write ``scores.csv``, ``claims.csv``, ``report.md`` and the figures into ``output``.

    :param output: the study's directory
    :param plots: draw the figures
    :param seeds: report these seeds only, into ``report_seeds_<k>_<l>.md`` (and the CSV files of the same suffix;
        no figures), beside the report of every seed
    :return: the markdown report
    """
    study = load_study(output, seeds)
    if not study.seeds:
        raise FileNotFoundError(f"no finished seed in {output} (a seed counts once its collect job is done)")
    suffix = "" if seeds is None else "_seeds_" + "_".join(str(seed) for seed in study.seeds)
    plots = plots and seeds is None
    study.finals.to_csv(output / f"scores{suffix}.csv", index=False)
    study.extras.to_csv(output / f"extras{suffix}.csv", index=False)
    claims = evaluate_claims(study)
    pd.DataFrame(claims).to_csv(output / f"claims{suffix}.csv", index=False)
    partial = incomplete_repeats(study)
    text = (
        f"# {len(study.preset['env_names'])}-stage study: {study.preset['env_id']}, seeds {study.seeds}\n\n"
        f"Stages: {json.dumps(study.preset['stages'])}; steps {study.preset['stage_steps']}; "
        f"{study.preset['distill_steps']:,} updates per student"
        + (
            f", each student trained {study.preset['student_repeats']} times per seed and scored by the mean.\n\n"
            if study.preset.get("student_repeats", 1) > 1
            else ".\n\n"
        )
        + (f"{study.preset['note']}\n\n" if study.preset.get("note") else "")
        + (
            "**Not every repeat has finished**; these students are scored on the repeats that have: "
            + "; ".join(partial)
            + ".\n\n"
            if partial
            else ""
        )
        + "## Final returns\n\nmean +- std over seeds [95 % BCa bootstrap CI of the mean]; online methods: mean of the last "
        + f"{ONLINE_LAST} evaluations, students: mean of the last {STUDENT_LAST}.\n\n"
        + score_table(study)
        + (
            "\n\n## What MPO kept of the environments it left\n\nWhen it left: the mean of its last "
            + f"{ONLINE_LAST_STAGE1} evaluations there; spread: std / mean of its last {SWITCH_SPREAD_EVALS} in the "
            + "second half of that stage; at the end: the mean of its last "
            + f"{ONLINE_LAST}; overestimation: the collector's mean Q minus the discounted return that followed, on "
            + f"that environment's data.\n\n{forgetting}"
            if (forgetting := forgetting_table(study))
            else ""
        )
        + (f"\n\n## The students' weights\n\n{weights}" if (weights := weights_table(study)) else "")
        + "\n\n## Claims\n\n"
        + claims_table(claims)
        + "\n"
    )
    if plots:
        paths = plot_study(study)
        text += "\n## Figures\n\n" + "\n".join(f"![{p.stem}]({p.name})" for p in paths) + "\n"
    (output / f"report{suffix}.md").write_text(text)
    return text


#: the files of a study that are worth keeping (in git, say): no buffers, no models
SMALL_FILES = ("*.csv", "*.json", "*.md", "*.png")


def export_results(output: pathlib.Path, destination: pathlib.Path) -> list[pathlib.Path]:
    """
    Copy a study's small result files (CSV, JSON, Markdown, PNG; no buffers, no models, nothing of a job that has
    not finished) into ``destination``, keeping their layout, so that its results can be committed without its data.

    :return: the copied files
    """
    copied = []
    for pattern in SMALL_FILES:
        for path in output.rglob(pattern):
            parts = path.relative_to(output).parts
            if any(part.startswith("buffer") or part.startswith(".") for part in parts):
                continue  # buffers, and what a crash left half-made (e.g. an unfinished adopted collection)
            if len(parts) > 2 and parts[0].startswith("seed_") and not (output / parts[0] / parts[1] / "done.json").exists():
                continue  # a job that has not finished: its partial curves would read as results
            target = destination / path.relative_to(output)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, target)
            copied.append(target)
    return copied
