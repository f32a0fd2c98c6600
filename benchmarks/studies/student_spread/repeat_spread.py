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

    python benchmarks/studies/student_spread/repeat_spread.py runs/paper_cpu_three_c51r3 \\
        --reference benchmarks/studies/paper_cpu_three/bounded_critic/comparison.csv --reference-where critic=categorical \\
        --output benchmarks/studies/paper_cpu_three_c51/repeat_spread.md
"""

import argparse
import json
import pathlib
from typing import Optional

import numpy as np
import pandas as pd

from sb3_lifelong.experiments.presets import split_repeat
from sb3_lifelong.experiments.scores import STUDENT_LAST, last_mean, seeds_of

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


def reference_scores(reference: pathlib.Path, envs: list[str], where: Optional[dict[str, str]] = None) -> pd.DataFrame:
    """
    The scores of another run of the same students, from its study directory or from a table of its scores.

    :param reference: a study directory (its repeat 0 is read), or a CSV with columns ``seed`` and ``student`` and
        either ``env`` and ``score`` (one row per environment) or one column per environment (as
        ``bounded_critic.py``'s ``comparison.csv``)
    :param envs: the study's environments (the columns of a wide table)
    :param where: keep only the CSV rows whose column equals the value (e.g. ``{"critic": "categorical"}``)
    :return: seed, student, env, score
    """
    if reference.is_dir():
        if where:
            raise ValueError(f"--reference-where filters a table of scores, and {reference} is a study directory")
        theirs = repeat_scores(reference)
        return theirs[theirs["repeat"] == 0][["seed", "student", "env", "score"]]
    table = pd.read_csv(reference)
    for column, value in (where or {}).items():
        if column not in table:
            raise ValueError(f"{reference} has no column {column!r} to filter on (it has {list(table)})")
        table = table[table[column].astype(str) == value]
    if {"env", "score"} <= set(table):
        long = table
    else:
        missing = [env for env in envs if env not in table]
        if missing:
            raise ValueError(f"{reference} has neither env/score columns nor a column for each of {missing}")
        long = table.melt(id_vars=["seed", "student"], value_vars=envs, var_name="env", value_name="score")
    if long.duplicated(["seed", "student", "env"]).any():
        raise ValueError(
            f"{reference} has more than one score per seed, student and environment: choose rows (--reference-where)"
        )
    return long[["seed", "student", "env", "score"]]


def reproduction(data: pd.DataFrame, theirs: pd.DataFrame) -> pd.DataFrame:
    """
    :param data: :func:`repeat_scores` of the study
    :param theirs: :func:`reference_scores`: another run of the same students on the same buffers
    :return: seed, student, env, the study's repeat-0 score, the reference's, and their difference
    """
    ours = data[data["repeat"] == 0]
    joined = ours.merge(theirs, on=["seed", "student", "env"], suffixes=("", "_reference"))
    joined["difference"] = joined["score"] - joined["score_reference"]
    return joined[["seed", "student", "env", "score", "score_reference", "difference"]]


def report(
    study: pathlib.Path,
    reference: Optional[pathlib.Path],
    pair: tuple[str, str],
    env: str,
    where: Optional[dict[str, str]] = None,
) -> str:
    """:return: the markdown of both readings (``where``: see :func:`reference_scores`)"""
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
        envs = json.loads((study / "preset.json").read_text())["env_names"]
        table = reproduction(data, reference_scores(reference, envs, where))
        chosen = "".join(f", rows with {column} = {value}" for column, value in (where or {}).items())
        lines += [
            "",
            f"## Repeat 0 against `{reference.name}`{chosen} (same buffers, settings and seeds)\n",
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
    parser.add_argument(
        "--reference", type=pathlib.Path, default=None, help="another run of the same students (R2): a study or a CSV"
    )
    parser.add_argument(
        "--reference-where", nargs="*", default=[], metavar="COLUMN=VALUE", help="keep only these rows of a CSV reference"
    )
    parser.add_argument("--pair", nargs=2, default=list(PAIR), help="the two students whose difference is read")
    parser.add_argument("--env", default="Env-A", help="the environment scored (default: Env-A)")
    parser.add_argument("--output", type=pathlib.Path, default=None, help="also write the markdown here")
    args = parser.parse_args()
    where = {}
    for condition in args.reference_where:
        column, equals, value = condition.partition("=")
        if not equals:
            parser.error(f"--reference-where takes COLUMN=VALUE, not {condition!r}")
        where[column] = value
    text = report(args.study, args.reference, tuple(args.pair), args.env, where)
    print(text)
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(text)


if __name__ == "__main__":
    main()
