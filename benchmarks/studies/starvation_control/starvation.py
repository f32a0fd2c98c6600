"""
The starvation control of the imbalance study's S2: is the indicator student's Env-A drop at a 1:20 share the
imbalance, or only fewer Env-A draws?

Pre-registered in ``README.md`` beside this script (variants, seeds, readings) before any run. On a finished seed of
the pipeline study (``benchmarks/studies/pipeline_forgetting``), four CRR indicator students are trained on its
lifetime buffer (read-only, linked), each with two student seeds:

* ``S2_indicator_1to5``: Env-A : Env-B sampled 1:5, batch 256, 30,000 updates (the reference);
* ``S2_indicator_1to20``: 1:20, batch 256, 30,000 updates (the dose: 3.5 times fewer Env-A draws);
* ``S2_indicator_1to20_batch896``: 1:20, batch 896, 30,000 updates (Env-A draws matched by a larger batch);
* ``S2_indicator_1to20_updates105k``: 1:20, batch 256, 105,000 updates (Env-A draws matched by more updates).

Usage (one buffer seed per command; a stopped command continues from its last evaluation)::

    OMP_NUM_THREADS=1 python benchmarks/studies/starvation_control/starvation.py run --seed 10 \\
        --study /work/runs/pipeline_forgetting/cheetah_back_reversed --output /work/runs/starvation_control
    python benchmarks/studies/starvation_control/starvation.py report --output /work/runs/starvation_control
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

STUDY = pathlib.Path(__file__).resolve().parent
RESULTS = STUDY / "results"
PIPELINE_PRESETS = STUDY.parent / "pipeline_forgetting" / "presets.py"
PRESET = "pipeline_cheetah_back_reversed"

ENVS = ("Env-A", "Env-B")
#: a drop of less than this fraction of the 1:5 student's Env-A return counts as none (the equivalence margin)
MARGIN = 0.05
#: seeds needed before anything is read, and the most that are run (the pipeline's continuing seeds, in order)
MIN_SEEDS, MAX_SEEDS = 3, 5
#: the student seeds of every variant on a buffer: repeat k trains with the buffer seed + 1000 k
REPEATS = 2


class Variant(NamedTuple):
    """One student of the control: its Env-A : Env-B sampling share, batch size and number of updates."""

    ratio: tuple[int, int]
    batch_size: int
    updates: int

    def env_a_draws(self) -> float:
        """:return: the Env-A rows a training draws, in expectation (each row's source is drawn with the share)"""
        a, b = self.ratio
        return self.batch_size * self.updates * a / (a + b)

    def env_b_draws(self) -> float:
        """:return: the Env-B rows a training draws, in expectation"""
        a, b = self.ratio
        return self.batch_size * self.updates * b / (a + b)


#: the four students, by job name (``distill_<name>``; the second student seed is ``<name>__r1``)
VARIANTS: dict[str, Variant] = {
    "S2_indicator_1to5": Variant((1, 5), 256, 30_000),
    "S2_indicator_1to20": Variant((1, 20), 256, 30_000),
    "S2_indicator_1to20_batch896": Variant((1, 20), 896, 30_000),
    "S2_indicator_1to20_updates105k": Variant((1, 20), 256, 105_000),
}
REFERENCE, DOSE, BATCH, UPDATES = VARIANTS
#: the two ways of matching the Env-A draws, each read on its own
MATCHED = {"batch": BATCH, "updates": UPDATES}


def job_name(variant: str, repeat: int) -> str:
    """:return: the job folder's name (after ``distill_``) of ``variant`` trained with its ``repeat``-th student seed"""
    return variant if repeat == 0 else f"{variant}__r{repeat}"


def preset_of(variant: Variant) -> Any:
    """:return: the pipeline study's preset with the variant's batch size and updates (everything else as it is)"""
    from sb3_lifelong.experiments.presets import load_presets

    return dataclasses.replace(
        load_presets(PIPELINE_PRESETS)[PRESET], student_batch_size=variant.batch_size, distill_steps=variant.updates
    )


def train(study: pathlib.Path, seed: int, output: pathlib.Path) -> None:
    """
    Train every variant with every student seed on seed ``seed``'s buffer of ``study``; the first student seed of all
    four variants first, so that a stopped run leaves complete sets.
    """
    from sb3_lifelong.experiments.presets import STUDENTS, Student
    from sb3_lifelong.experiments.protocol import REPEAT_SEED_STRIDE, distill_on_study

    indicator = STUDENTS["CRR_indicator"]
    for repeat in range(REPEATS):
        for name, variant in VARIANTS.items():
            student = Student("CRR", dict(indicator.kwargs), ratio=variant.ratio, uses_boundaries=True, about=name)
            about = dict(variant=name, repeat=repeat, batch_size=variant.batch_size, updates=variant.updates)
            distill_on_study(
                study,
                seed,
                output,
                {job_name(name, repeat): student},
                preset_of(variant),
                student_seed=seed + repeat * REPEAT_SEED_STRIDE,
                about=about,
            )


# ----------------------------------------------------------------------------------------------------- reading
def scores(output: pathlib.Path) -> pd.DataFrame:
    """
    :param output: the folder :func:`train` wrote
    :return: one row per finished (buffer seed, variant, repeat, environment): the score as the pipeline study's
        report scores a student (the mean of its last 2 evaluations)
    """
    from sb3_lifelong.experiments.scores import STUDENT_LAST, last_mean, read_log

    rows = []
    for done in sorted(output.glob("seed_*/distill_*/done.json")):
        info = json.loads(done.read_text())
        if info.get("variant") not in VARIANTS:
            continue
        frame = read_log(done.parent / "eval.csv")
        for env in ENVS:
            score = last_mean(frame, env, STUDENT_LAST)
            rows.append(dict(seed=info["buffer_seed"], variant=info["variant"], repeat=info["repeat"], env=env, score=score))
    return pd.DataFrame(rows, columns=["seed", "variant", "repeat", "env", "score"])


def complete_means(data: pd.DataFrame) -> pd.DataFrame:
    """
    :return: seed x (variant, env) table of the mean over the student seeds, only for the seeds that have every
        variant with all :data:`REPEATS` student seeds (the first :data:`MAX_SEEDS` of them)
    """
    counts = data.groupby(["seed", "variant", "env"])["score"].count()
    full = counts[counts == REPEATS].reset_index().groupby("seed").size()
    seeds = sorted(int(s) for s, n in full.items() if n == len(VARIANTS) * len(ENVS))[:MAX_SEEDS]
    kept = data[data["seed"].isin(seeds)]
    return kept.groupby(["seed", "variant", "env"])["score"].mean().unstack(["variant", "env"])


def interval(values: list[float]) -> dict[str, float]:
    """:return: ``n``, ``mean``, ``sd`` and the 95 % Student t interval (``low``, ``high``) of the values"""
    from sb3_lifelong.experiments.statistics import t_interval

    mean, sd, low, high = t_interval(values)
    return dict(n=len(values), mean=mean, sd=sd, low=low, high=high)


def inside(summary: dict[str, float], margin: float = MARGIN) -> bool:
    """:return: whether the interval lies within (-margin, +margin): equivalent to zero"""
    return bool(math.isfinite(summary["low"]) and -margin < summary["low"] and summary["high"] < margin)


def above(summary: dict[str, float]) -> bool:
    """:return: whether the interval lies above zero"""
    return bool(math.isfinite(summary["low"]) and summary["low"] > 0)


def drop_reading(drop: dict[str, float]) -> str:
    """
    S2 on this setting: the dose's Env-A drop ``D = 1 - R(1:20) / R(1:5)``.

    :return: ``drop`` (interval above 0), ``no drop`` (interval within the margin), ``inconclusive``, or
        ``too few seeds``
    """
    if drop["n"] < MIN_SEEDS:
        return "too few seeds"
    if above(drop):
        return "drop"
    if inside(drop):
        return "no drop"
    return "inconclusive"


def control_reading(drop: dict[str, float], left: dict[str, float], recovered: dict[str, float]) -> str:
    """
    One matched variant's reading (README, "How it reads").

    :param drop: ``D = 1 - R(1:20) / R(1:5)`` over seeds
    :param left: ``H = 1 - R(matched) / R(1:5)``: the drop left when the Env-A draws are matched
    :param recovered: ``G = (R(matched) - R(1:20)) / R(1:5)``: the part of the drop matching gives back
    :return: ``starvation``, ``imbalance``, ``both``, ``inconclusive``, or ``not testable (...)`` when the dose
        gives no drop to explain
    """
    if drop["n"] < MIN_SEEDS:
        return "too few seeds"
    if not above(drop):
        return f"not testable (no drop to explain: D = {drop['mean']:+.3f} [{drop['low']:+.3f}, {drop['high']:+.3f}])"
    gone, nothing_back = inside(left), inside(recovered)
    if gone and nothing_back:  # the drop is within twice the margin: the two readings cannot be told apart
        return "inconclusive"
    if gone:
        return "starvation"
    if nothing_back:
        return "imbalance"
    if above(left) and above(recovered):
        return "both"
    return "inconclusive"


def answer(readings: dict[str, str]) -> str:
    """
    The answer for S2 (README, "How it reads"): ``starvation`` or ``imbalance`` only when every matched way gives that
    reading; otherwise each reading as measured (once, when the ways agree).

    :param readings: matched way -> its :func:`control_reading`
    """
    values = set(readings.values())
    if len(values) == 1:  # the ways agree: that reading, once
        return values.pop()
    return "; ".join(f"by {way}: {reading}" for way, reading in readings.items())


def series(means: pd.DataFrame) -> dict[str, dict[int, float]]:
    """:return: the per-seed series the readings use: ``D``, and ``H_<way>``, ``G_<way>`` for each matched way"""
    reference = means[(REFERENCE, "Env-A")]
    dose = means[(DOSE, "Env-A")]
    out = {"D": {int(s): float(1 - dose[s] / reference[s]) for s in means.index}}
    for way, variant in MATCHED.items():
        matched = means[(variant, "Env-A")]
        out[f"H_{way}"] = {int(s): float(1 - matched[s] / reference[s]) for s in means.index}
        out[f"G_{way}"] = {int(s): float((matched[s] - dose[s]) / reference[s]) for s in means.index}
    return out


def student_noise(data: pd.DataFrame, seeds: list[int]) -> pd.DataFrame:
    """
    :return: per variant and environment: the sd between a buffer's two student seeds (pooled over buffers) and the sd
        over buffers of the two-seed means
    """
    rows = []
    kept = data[data["seed"].isin(seeds)]
    for (variant, env), part in kept.groupby(["variant", "env"]):
        per_seed = part.groupby("seed")["score"]
        within = float(np.sqrt(per_seed.var(ddof=1).mean())) if len(part) else float("nan")
        between = float(per_seed.mean().std(ddof=1)) if per_seed.ngroups > 1 else float("nan")
        rows.append(dict(variant=variant, env=env, within_sd=within, between_sd=between))
    return pd.DataFrame(rows)


def report(output: pathlib.Path, results: pathlib.Path) -> str:
    """
    Read every finished student of ``output``, write ``starvation.csv`` (every training) and ``results.md`` (the
    table, the series, the readings) to ``results``.

    :return: the markdown written
    :raises FileNotFoundError: no finished student in ``output``
    """
    data = scores(output)
    if data.empty:
        raise FileNotFoundError(f"no finished student of this control in {output}")
    results.mkdir(parents=True, exist_ok=True)
    data.sort_values(["seed", "variant", "repeat", "env"]).to_csv(results / "starvation.csv", index=False)
    means = complete_means(data)
    seeds = [int(s) for s in means.index]
    lines = ["# Starvation control: results (generated by `starvation.py report`)", ""]
    lines += [f"Seeds with every variant and both student seeds: {seeds or 'none'} (readings need {MIN_SEEDS}).", ""]
    lines += ["## Returns (mean of the two student seeds; each the mean of its last 2 evaluations)", ""]
    lines += ["| seed | " + " | ".join(f"{v} {e}" for v in VARIANTS for e in ENVS) + " |"]
    lines += ["| --- " * (1 + len(VARIANTS) * len(ENVS)) + "|"]
    for seed in seeds:
        lines.append(f"| {seed} | " + " | ".join(f"{means.loc[seed, (v, e)]:.0f}" for v in VARIANTS for e in ENVS) + " |")
    lines += ["", "## Draws per training (expectation)", "", "| variant | batch | updates | Env-A rows | Env-B rows |"]
    lines += ["| --- | --- | --- | --- | --- |"]
    for name, variant in VARIANTS.items():
        lines.append(
            f"| {name} | {variant.batch_size} | {variant.updates:,} | {variant.env_a_draws() / 1e6:.2f} M "
            f"| {variant.env_b_draws() / 1e6:.2f} M |"
        )
    if seeds:
        per_seed = series(means)
        summaries = {key: interval([values[s] for s in seeds]) for key, values in per_seed.items()}
        lines += ["", "## Series (fractions of the 1:5 student's Env-A return; mean, sd, 95 % t interval)", ""]
        lines += ["| series | " + " | ".join(f"seed {s}" for s in seeds) + " | mean +- sd [95 % interval] |"]
        lines += ["| --- " * (2 + len(seeds)) + "|"]
        for key, values in per_seed.items():
            summary = summaries[key]
            cells = " | ".join(f"{values[s]:+.3f}" for s in seeds)
            if math.isfinite(summary["low"]):
                spread = f"+- {summary['sd']:.3f} [{summary['low']:+.3f}, {summary['high']:+.3f}]"
            else:
                spread = "(one seed: no interval)"
            lines.append(f"| {key} | {cells} | {summary['mean']:+.3f} {spread} |")
        lines += ["", '## Readings (README, "How it reads"; margin +-' + f"{MARGIN})", ""]
        lines.append(f"- S2 on this setting (the dose's Env-A drop D): **{drop_reading(summaries['D'])}**")
        readings = {way: control_reading(summaries["D"], summaries[f"H_{way}"], summaries[f"G_{way}"]) for way in MATCHED}
        for way, reading in readings.items():
            lines.append(f"- matched by {way}: **{reading}**")
        lines.append(f"- the answer for S2 (both ways must agree): **{answer(readings)}**")
        noise = student_noise(data, seeds)
        lines += ["", "## The students' noise apart from the buffers'", "", "| variant | env | within sd | between sd |"]
        lines += ["| --- | --- | --- | --- |"]
        for row in noise.itertuples():
            lines.append(f"| {row.variant} | {row.env} | {row.within_sd:.0f} | {row.between_sd:.0f} |")
    text = "\n".join(lines) + "\n"
    (results / "results.md").write_text(text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train the four variants, two student seeds each, on one buffer seed")
    run.add_argument("--seed", type=int, required=True)
    run.add_argument("--study", type=pathlib.Path, required=True, help="the pipeline study's output (its buffers)")
    run.add_argument("--output", type=pathlib.Path, default=pathlib.Path("runs/starvation_control"))
    show = sub.add_parser("report", help="the table and the readings")
    show.add_argument("--output", type=pathlib.Path, default=pathlib.Path("runs/starvation_control"))
    show.add_argument("--results", type=pathlib.Path, default=RESULTS)
    args = parser.parse_args()
    if args.command == "run":
        import torch as th

        th.set_num_threads(1)
        train(args.study, args.seed, args.output)
    else:
        print(report(args.output, args.results))


if __name__ == "__main__":
    main()
