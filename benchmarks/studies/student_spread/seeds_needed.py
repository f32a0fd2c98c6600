"""
How many seeds would the paper study's comparisons need? From a study's per-seed scores (the ``scores.csv`` and
``extras.csv`` that ``python -m sb3_lifelong.experiments report --export`` writes), for each comparison behind a
pre-registered claim: the per-seed paired difference (first minus second, in return units, both from the same
seed's run), its mean and standard deviation, and the number of seeds a one-sided paired t-test (level 0.05, power
0.8) needs to detect

- a difference of 10 % of the second quantity's mean (the smallest margin the claims use: C4b's 90 %), and
- the difference observed so far (how many seeds would confirm what the seeds show now, if it is real).

The power is the t-test's, from the noncentral t distribution (``scipy.stats.nct``): with ``n`` seeds the test
rejects when the t statistic of the differences exceeds ``t.ppf(0.95, n - 1)``, and a true difference ``delta``
with per-seed standard deviation ``sd`` gives that statistic a noncentral t distribution with ``n - 1`` degrees of
freedom and noncentrality ``delta / sd * sqrt(n)``. The smallest ``n`` (at least 2) whose power reaches 0.8 is given.
The normal approximation ``((z_0.95 + z_0.8) * sd / delta)^2`` that this replaces is about two seeds short for
small and medium effects and half the seeds short for large ones (2 where the t-test needs 4 for ``delta = 2 sd``).

This is an analysis of the seeds run, written after them; it changes no claim or criterion.

Usage::

    python benchmarks/studies/student_spread/seeds_needed.py benchmarks/studies/paper_cpu_foot
"""

import argparse
import csv
import math
import pathlib
from collections import defaultdict
from typing import Callable, Optional

import numpy as np
from scipy import stats

LEVEL, POWER = 0.05, 0.8  # one-sided test

Scores = dict[int, dict[str, float]]  # seed -> "method|env" (scores) or metric (extras) -> value


def load(folder: pathlib.Path) -> Scores:
    """:return: per seed, every score (``"<method>|<env>"``) and extra metric of the study"""
    values: Scores = defaultdict(dict)
    with open(folder / "scores.csv", newline="") as handle:
        for row in csv.DictReader(handle):
            values[int(row["seed"])][f"{row['method']}|{row['env']}"] = float(row["score"])
    extras = folder / "extras.csv"
    if extras.exists():
        with open(extras, newline="") as handle:
            for row in csv.DictReader(handle):
                values[int(row["seed"])][row["metric"]] = float(row["value"])
    return dict(values)


def mean_over_envs(method: str) -> Callable[[dict[str, float]], Optional[float]]:
    def value(seed: dict[str, float]) -> Optional[float]:
        pair = [seed.get(f"{method}|Env-A"), seed.get(f"{method}|Env-B")]
        return None if None in pair else float(np.mean(pair))  # type: ignore[arg-type]

    return value


def key(name: str) -> Callable[[dict[str, float]], Optional[float]]:
    return lambda seed: seed.get(name)


#: (claim, what is compared, first, second): the claim holds in the direction "first > second"
COMPARISONS: list[tuple[str, str, Callable, Callable]] = [
    ("C2a", "online CRR beta=1 vs MPO, final Env-A", key("online CRR_exp_beta1|Env-A"), key("MPO|Env-A")),
    (
        "C2b",
        "MPO vs online CRR beta=1, mean Env-B over Stage 2",
        key("MPO|stage2_area|Env-B"),
        key("online CRR_exp_beta1|stage2_area|Env-B"),
    ),
    ("C3", "exp beta=1 student vs MPO, mean of Env-A and Env-B", mean_over_envs("CRR_exp_beta1"), mean_over_envs("MPO")),
    (
        "C3",
        "exp beta=1 student vs indicator student, mean of Env-A and Env-B",
        mean_over_envs("CRR_exp_beta1"),
        mean_over_envs("CRR_indicator"),
    ),
    (
        "C4a",
        "Env-A-only indicator student vs indicator student, Env-A",
        key("CRR_indicator_A_only|Env-A"),
        key("CRR_indicator|Env-A"),
    ),
    ("C4b", "exp beta=1 student vs indicator student, Env-A", key("CRR_exp_beta1|Env-A"), key("CRR_indicator|Env-A")),
    (
        "C5a",
        "Env-B rewards x 0.5 vs indicator student, Env-A",
        key("CRR_indicator_scale_rwd_B|Env-A"),
        key("CRR_indicator|Env-A"),
    ),
    ("C5b", "two actors vs indicator student, Env-A", key("CRR_indicator_two_actors|Env-A"), key("CRR_indicator|Env-A")),
    ("C5c", "BC vs indicator student, Env-A", key("BC|Env-A"), key("CRR_indicator|Env-A")),
    (
        "C5d",
        "indicator student sampled 1:1 vs 1:10, Env-A",
        key("CRR_indicator_ratio_1to1|Env-A"),
        key("CRR_indicator_ratio_1to10|Env-A"),
    ),
]


def power(n: int, effect: float, level: float = LEVEL) -> float:
    """
    :param n: seeds (pairs), at least 2
    :param effect: the true mean difference over the per-seed standard deviation of the differences
    :param level: the one-sided test's level
    :return: the probability that a one-sided paired t-test on ``n`` seeds rejects "no difference"
    """
    critical = stats.t.ppf(1 - level, n - 1)
    return float(stats.nct.sf(critical, n - 1, effect * math.sqrt(n)))


def seeds_for(sd: float, delta: float, level: float = LEVEL, target: float = POWER) -> float:
    """
    :param sd: the standard deviation of the per-seed differences
    :param delta: the difference to detect
    :param level: the one-sided test's level
    :param target: the power wanted
    :return: the smallest number of seeds (at least 2) with which a one-sided paired t-test detects ``delta`` with
        power ``target`` (inf when ``delta`` is not positive)
    """
    if delta <= 0:
        return math.inf
    if sd <= 0:
        return 2.0  # no spread: any difference shows
    effect = delta / sd
    low, high = 1, 2  # power(low) < target <= power(high)
    while power(high, effect, level) < target:
        low, high = high, high * 2
    while high - low > 1:
        middle = (low + high) // 2
        low, high = (middle, high) if power(middle, effect, level) < target else (low, middle)
    return float(high)


def table(values: Scores) -> list[str]:
    lines = [
        "| claim | comparison (first vs second) | seeds | per-seed difference | mean | sd | seeds for 10 % of second "
        "| seeds for the observed difference |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for claim, what, first, second in COMPARISONS:
        pairs = [(first(seed), second(seed)) for _, seed in sorted(values.items())]
        pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
        if len(pairs) < 2:
            continue
        differences = np.array([a - b for a, b in pairs])
        sd = float(differences.std(ddof=1))
        ten_percent = 0.1 * abs(float(np.mean([b for _, b in pairs])))
        observed = float(differences.mean())
        lines.append(
            f"| {claim} | {what} | {len(pairs)} | {', '.join(f'{d:+.0f}' for d in differences)} | {observed:+.0f} | "
            f"{sd:.0f} | {seeds_for(sd, ten_percent):.0f} | "
            + (f"{seeds_for(sd, abs(observed)):.0f}" + (" (reverse direction)" if observed < 0 else ""))
            + " |"
        )
    return lines


def student_scores(folder: pathlib.Path, last: int) -> Scores:
    """
    :return: per seed, every student's score as the mean of its last ``last`` evaluations (read from the students'
        ``eval.csv``; the study's own score is the mean of the last two), and every other score as in :func:`load`
    """
    values = load(folder)
    for path in sorted(folder.glob("seed_*/distill_*/eval.csv")):
        if not (path.parent / "done.json").exists():  # a student still training (as :func:`load`, finished jobs only)
            continue
        seed, method = int(path.parent.parent.name.split("_")[1]), path.parent.name[len("distill_") :]
        rows: dict[str, list[tuple[int, float]]] = defaultdict(list)
        with open(path, newline="") as handle:
            for row in csv.DictReader(handle):
                rows[row["env"]].append((int(row["timesteps"]), float(row["mean_reward"])))
        for env, curve in rows.items():
            values.setdefault(seed, {})[f"{method}|{env}"] = float(np.mean([r for _, r in sorted(curve)[-last:]]))
    return values


#: the comparisons whose both sides are students (their scores depend on how many evaluations are averaged)
STUDENT_CLAIMS = ("C4a", "C4b", "C5a", "C5b", "C5c", "C5d")


def scoring_table(folder: pathlib.Path, lasts: tuple[int, ...] = (1, 2, 3, 4, 6)) -> list[str]:
    """:return: for each student comparison, the sd of its per-seed differences and the seeds for a 10 % effect when
    a student's score averages its last K evaluations, for each K of ``lasts``"""
    header = " | ".join(f"K={k}: sd / seeds" for k in lasts)
    lines = [f"| claim | comparison (first vs second) | {header} |", "| --- | --- |" + " --- |" * len(lasts)]
    scored = {k: student_scores(folder, k) for k in lasts}
    for claim, what, first, second in COMPARISONS:
        if claim not in STUDENT_CLAIMS:
            continue
        cells = []
        for k in lasts:
            pairs = [(first(seed), second(seed)) for _, seed in sorted(scored[k].items())]
            pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
            if len(pairs) < 2:
                cells.append("-")
                continue
            sd = float(np.std([a - b for a, b in pairs], ddof=1))
            cells.append(f"{sd:.0f} / {seeds_for(sd, 0.1 * abs(float(np.mean([b for _, b in pairs])))):.0f}")
        lines.append(f"| {claim} | {what} | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("study", type=pathlib.Path, help="a folder with the study's scores.csv (and extras.csv)")
    parser.add_argument("--output", type=pathlib.Path, help="markdown file (default: <study>/seeds_needed.md)")
    args = parser.parse_args()
    values = load(args.study)
    lines = table(values)
    print("\n".join(lines))
    output = args.output or args.study / "seeds_needed.md"
    output.write_text(
        "# Seeds needed for the study's comparisons\n\n"
        f"`python benchmarks/studies/student_spread/seeds_needed.py {args.study}` on seeds {sorted(values)}. Paired "
        "per seed; one-sided test, "
        "level 0.05, power 0.8, paired t-test (power from the noncentral t; at least 2). An analysis of the seeds run, "
        "written after them: it changes no claim or criterion.\n\n" + "\n".join(lines) + "\n"
    )
    if any(args.study.glob("seed_*/distill_*/eval.csv")):
        scoring = scoring_table(args.study)
        print("\n".join(scoring))
        with open(output, "a") as handle:
            handle.write(
                "\n## The student comparisons when a student's score averages more evaluations\n\n"
                "The study scores a student by the mean of its last two evaluations (K=2). Below, the same per-seed "
                "differences with K = 1, 2, 3, 4 and 6 of a student's 7 evaluations (the earlier ones are taken before "
                "the student has converged, so a large K also scores learning speed): the sd of the differences and the "
                "seeds a paired test needs for a 10 % effect. For designing the next study; no verdict is read from it.\n\n"
                + "\n".join(scoring)
                + "\n"
            )
    print(f"written to {output}")


if __name__ == "__main__":
    main()
