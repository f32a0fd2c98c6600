"""
What a study's student repeats buy, and whether a repeat reproduces an earlier training of the same student.

A study run with ``student_repeats`` (e.g. the preset ``cpu_three_c51``) trains each student several times per
buffer, each repeat with its own student seed, and scores the mean. This script reads such a study:

- **the spread** (reading R1 of ``results/paper_cpu_three_c51/README.md``): per seed, the sd over the repeats of the
  difference of two students' scores in one environment (default: indicator minus exp beta=1 in Env-A), its mean over
  seeds, and the sd over seeds of the repeat-mean difference. If the repeats are what steadies a student claim, the
  second is about the first divided by sqrt(repeats), or less; if it is much more, the buffer carries the spread;
- **the reproduction** (reading R2), with ``--reference``: repeat 0 of each student against the same student of
  another run on the same buffers, with the same settings and seed (e.g. ``bounded_critic.py``'s output): the
  difference of their final returns in every environment (0 when training is deterministic).

sds use ddof=1 (sample sd), as ``student_spread.py``.

Usage::

    python benchmarks/repeat_spread.py runs/paper_cpu_three_c51r3 --reference runs/paper_cpu_three_c51 \\
        --output benchmarks/results/paper_cpu_three_c51/repeat_spread.md
"""

import argparse
import json
import pathlib
from typing import Optional

import numpy as np
import pandas as pd

from sb3_lifelong.experiments.report import STUDENT_LAST, last_mean, seeds_of, split_repeat

#: the difference R1 reads: the indicator student minus the exp beta=1 student, in Env-A (claim T3a's two students)
PAIR = ("CRR_indicator", "CRR_exp_beta1")


def repeat_scores(study: pathlib.Path) -> pd.DataFrame:
    """:return: one row per finished student job of ``study``: seed, student, repeat, env, score (as the report)"""
    preset = json.loads((study / "preset.json").read_text())
    rows = []
    for seed in seeds_of(study):
        for done in sorted((study / f"seed_{seed}").glob("distill_*/done.json")):
            student, repeat = split_repeat(done.parent.name[len("distill_") :])
            frame = pd.read_csv(done.parent / "eval.csv")
            for env in preset["env_names"]:
                rows.append(
                    dict(seed=seed, student=student, repeat=repeat, env=env, score=last_mean(frame, env, STUDENT_LAST))
                )
    return pd.DataFrame(rows, columns=["seed", "student", "repeat", "env", "score"])


def spread(data: pd.DataFrame, pair: tuple[str, str] = PAIR, env: str = "Env-A") -> tuple[pd.DataFrame, dict[str, float]]:
    """
    :param data: :func:`repeat_scores`
    :param pair: the difference ``first - second``
    :param env: the environment scored
    :return: per seed the difference of each repeat both students finished, its mean and sd over the repeats; and the
        summary: the mean within-seed sd, the sd over seeds of the seed means, the number of seeds and repeats
    """
    scores = data[data["env"] == env].pivot_table(index=["seed", "repeat"], columns="student", values="score")
    if pair[0] not in scores or pair[1] not in scores:
        raise ValueError(f"the study has no finished {pair[0]} and {pair[1]} students to compare (it has {list(scores)})")
    difference = (scores[pair[0]] - scores[pair[1]]).dropna().rename("difference").reset_index()
    per_seed = difference.groupby("seed")["difference"].agg(["mean", "std", "count", list])
    within = float(per_seed["std"].mean())
    between = float(per_seed["mean"].std(ddof=1)) if len(per_seed) > 1 else float("nan")
    repeats = int(per_seed["count"].min()) if len(per_seed) else 0
    return per_seed, dict(within=within, between=between, seeds=len(per_seed), repeats=repeats)


def reproduction(data: pd.DataFrame, reference: pathlib.Path) -> pd.DataFrame:
    """
    :param data: :func:`repeat_scores` of the study
    :param reference: another run of the same students on the same buffers (repeat 0 only is compared)
    :return: seed, student, env, the study's repeat-0 score, the reference's, and their difference
    """
    theirs = repeat_scores(reference)
    theirs = theirs[theirs["repeat"] == 0]
    ours = data[data["repeat"] == 0]
    joined = ours.merge(theirs, on=["seed", "student", "env"], suffixes=("", "_reference"))
    joined["difference"] = joined["score"] - joined["score_reference"]
    return joined[["seed", "student", "env", "score", "score_reference", "difference"]]


def report(study: pathlib.Path, reference: Optional[pathlib.Path], pair: tuple[str, str], env: str) -> str:
    """:return: the markdown of both readings"""
    data = repeat_scores(study)
    per_seed, summary = spread(data, pair, env)
    lines = [
        f"# Student repeats of `{study.name}`\n",
        f"## What the repeats buy: `{pair[0]} - {pair[1]}` in {env}\n",
        "| seed | difference per repeat (r0, r1, ...) | mean | sd over the repeats |",
        "| --- | --- | --- | --- |",
    ]
    for seed, row in per_seed.iterrows():
        cells = ", ".join(f"{value:+.0f}" for value in row["list"])
        sd = f"{row['std']:.0f}" if np.isfinite(row["std"]) else "-"
        lines.append(f"| {seed} | {cells} | {row['mean']:+.0f} | {sd} |")
    expected = summary["within"] / np.sqrt(max(summary["repeats"], 1))
    lines += [
        "",
        f"- mean sd over a seed's repeats (the student's own training): **{summary['within']:.0f}**",
        f"- sd over the {summary['seeds']} seeds of the repeat means: **{summary['between']:.0f}**",
        f"- what the repeats' own noise leaves in a mean of {summary['repeats']}: {summary['within']:.0f} / "
        f"sqrt({summary['repeats']}) = {expected:.0f}; the rest of the seed-to-seed sd is the buffer's",
    ]
    if reference is not None:
        table = reproduction(data, reference)
        lines += [
            "",
            f"## Repeat 0 against `{reference.name}` (same buffers, settings and seeds)\n",
            f"{len(table)} (seed, student, environment) scores compared; largest absolute difference "
            f"{table['difference'].abs().max() if len(table) else float('nan'):.1f}.\n",
            "| seed | student | env | this study | reference | difference |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        lines += [
            f"| {r.seed} | {r.student} | {r.env} | {r.score:.1f} | {r.score_reference:.1f} | {r.difference:+.1f} |"
            for r in table.itertuples()
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("study", type=pathlib.Path, help="a study run with student repeats")
    parser.add_argument("--reference", type=pathlib.Path, default=None, help="another run of the same students (R2)")
    parser.add_argument("--pair", nargs=2, default=list(PAIR), help="the two students whose difference is read")
    parser.add_argument("--env", default="Env-A", help="the environment scored (default: Env-A)")
    parser.add_argument("--output", type=pathlib.Path, default=None, help="also write the markdown here")
    args = parser.parse_args()
    text = report(args.study, args.reference, tuple(args.pair), args.env)
    print(text)
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(text)


if __name__ == "__main__":
    main()
