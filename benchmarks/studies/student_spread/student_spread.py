"""
How much of the students' seed-to-seed spread is the student's own training? The same students trained with
several seeds on ONE finished seed's lifetime buffer, against the spread between the study's seeds.

In the ``cpu_foot`` study the per-seed differences behind the student claims have standard deviations of 130-345
(``results/paper_cpu_foot/seeds_needed.md``). Each study seed draws a new buffer *and* a new student training. If
most of that spread is the student's training, training each student a few times on its buffer and averaging
(cheap: a student costs a few minutes, a buffer half an hour) shrinks it; if most of it is the buffer, only more
collection seeds do. This script measures the first part: it trains the students named by ``--students`` with every
seed of ``--student-seeds`` on the buffer of seed ``--seed`` of a study (the preset's updates, evaluations and
episodes), and ``--report`` sets the spread of the difference of the pair ``--pair`` (default: exp beta=1 minus
indicator; their Env-A scores, paired by student seed, scored as the study scores them) against the study's
between-seed spread of the same difference.
The criteria are in ``results/student_spread.md``, written before the runs.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/studies/student_spread/student_spread.py --study runs/paper_cpu_foot --preset \
        cpu_foot --seed 0 \\
        --students CRR_exp_beta1 CRR_indicator --student-seeds 0 1 2 3 --output runs/student_spread
    python benchmarks/studies/student_spread/student_spread.py --report runs/student_spread --between \
        benchmarks/studies/paper_cpu_foot
"""

import argparse
import json
import pathlib

import numpy as np
import pandas as pd
import torch as th

from sb3_lifelong.experiments.presets import PRESETS as PACKAGE_PRESETS
from sb3_lifelong.experiments.presets import STUDENTS, load_presets
from sb3_lifelong.experiments.protocol import distill_on_study
from sb3_lifelong.experiments.scores import STUDENT_LAST, last_mean

#: the package's presets and the study's own (``cpu_foot``: ``benchmarks/studies/paper_cpu_foot/presets.py``)
PRESETS = {**PACKAGE_PRESETS, **load_presets(pathlib.Path(__file__).resolve().parents[1] / "paper_cpu_foot" / "presets.py")}

ENV = "Env-A"
#: the difference whose spread the criteria of ``results/student_spread.md`` judge
PAIR = ("CRR_exp_beta1", "CRR_indicator")


def job_name(student: str, student_seed: int) -> str:
    """:return: the job folder's name (after ``distill_``) of ``student`` trained with ``student_seed``"""
    return f"{student}__s{student_seed}"


def train(
    study: pathlib.Path, preset_name: str, seed: int, students: list[str], student_seeds: list[int], output: pathlib.Path
) -> None:
    """
    Train every (student, student seed) not trained yet on seed ``seed``'s buffer of ``study``.

    :param study: the study's output directory
    :param preset_name: its preset
    :param seed: the seed whose buffer is distilled
    :param students: names of :data:`STUDENTS`
    :param student_seeds: the seeds of the students' own training
    :param output: where the students go
    """
    preset = PRESETS[preset_name]
    for student_seed in student_seeds:  # the students of one student seed together: a stopped run stays paired
        for student in students:
            about = dict(preset=preset_name, student=student)
            jobs = {job_name(student, student_seed): STUDENTS[student]}
            distill_on_study(study, seed, output, jobs, preset, student_seed=student_seed, about=about)


def scores(output: pathlib.Path) -> pd.DataFrame:
    """:return: one row per finished (buffer seed, student, student seed): its Env-A score as the study's report"""
    rows = []
    for done in sorted(output.glob("seed_*/distill_*/done.json")):
        info = json.loads(done.read_text())
        frame = pd.read_csv(done.parent / "eval.csv")
        rows.append(
            dict(
                buffer_seed=info["buffer_seed"],
                student=info["student"],
                student_seed=info["student_seed"],
                score=last_mean(frame, ENV, STUDENT_LAST),
            )
        )
    return pd.DataFrame(rows)


def between_seed_sd(study: pathlib.Path, first: str, second: str) -> tuple[float, int]:
    """:return: the sd over the study's seeds of ``first - second`` (Env-A scores), and the number of seeds"""
    finals = pd.read_csv(study / "scores.csv")
    a = finals[(finals["method"] == first) & (finals["env"] == ENV)].set_index("seed")["score"]
    b = finals[(finals["method"] == second) & (finals["env"] == ENV)].set_index("seed")["score"]
    difference = (a - b).dropna()
    return float(difference.std(ddof=1)), len(difference)


def report(output: pathlib.Path, between: pathlib.Path, pair: tuple[str, str] = PAIR) -> str:
    """
    :param output: the folder :func:`train` wrote
    :param between: the reference study (its ``scores.csv`` gives the between-seed spread)
    :param pair: the two students whose difference (first minus second) is compared
    :return: a markdown table of every student seed's score and, per buffer, the within / between spread ratio
    :raises ValueError: the reference study has no between-seed spread of the two students compared
    """
    data = scores(output)
    if data.empty:
        raise FileNotFoundError(f"no finished student in {output}")
    lines = [
        f"| buffer seed | student | {ENV} score per student seed | mean | sd |",
        "| --- | --- | --- | --- | --- |",
    ]
    verdicts = []
    for buffer_seed, part in data.groupby("buffer_seed"):
        students = list(dict.fromkeys(part.sort_values("student_seed")["student"]))
        per_student = {s: part[part["student"] == s].set_index("student_seed")["score"].sort_index() for s in students}
        for student, values in per_student.items():
            cells = ", ".join(f"s{k}: {v:.0f}" for k, v in values.items())
            lines.append(
                f"| {buffer_seed} | {student} | {cells} | {values.mean():.0f} | "
                + (f"{values.std(ddof=1):.0f} |" if len(values) > 1 else "- |")
            )
        first, second = pair
        if first not in per_student or second not in per_student:
            continue
        difference = (per_student[first] - per_student[second]).dropna()
        if len(difference) < 2:
            continue
        within = float(difference.std(ddof=1))
        across, n_seeds = between_seed_sd(between, first, second)
        if not np.isfinite(across) or across <= 0:
            raise ValueError(
                f"no between-seed spread of `{first} - {second}` in {between / 'scores.csv'}: it needs both students "
                f"on at least 2 seeds with different differences, found {n_seeds} seed(s), sd {across}"
            )
        ratio = within / across
        if ratio >= 0.7:
            verdict = "student training dominates: average repeats"
        else:
            verdict = "the buffer dominates" if ratio <= 0.5 else "mixed"
        lines.append(
            f"| {buffer_seed} | {first} - {second} | "
            + ", ".join(f"s{k}: {v:+.0f}" for k, v in difference.items())
            + f" | {difference.mean():+.0f} | {within:.0f} |"
        )
        verdicts.append(
            f"- buffer {buffer_seed}: sd of `{first} - {second}` over {len(difference)} student seeds on one buffer "
            f"{within:.0f}; over the study's {n_seeds} seeds {across:.0f}; ratio {ratio:.2f}: **{verdict}**"
        )
    return "\n".join([*lines, "", *verdicts])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--study", type=pathlib.Path, help="a study with a finished collect job for --seed")
    parser.add_argument("--preset", default="cpu_foot", choices=sorted(PRESETS), help="the study's preset")
    parser.add_argument("--seed", type=int, default=0, help="the seed whose buffer is distilled")
    parser.add_argument("--students", nargs="+", default=["CRR_exp_beta1", "CRR_indicator"], choices=list(STUDENTS))
    parser.add_argument("--student-seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    parser.add_argument("--output", type=pathlib.Path, default=pathlib.Path("runs/student_spread"))
    parser.add_argument("--report", type=pathlib.Path, default=None, help="print the table of this output directory")
    parser.add_argument("--between", type=pathlib.Path, default=None, help="with --report: the study's exported results")
    parser.add_argument("--to", type=pathlib.Path, default=None, help="with --report: also write the table here")
    parser.add_argument("--pair", nargs=2, default=list(PAIR), choices=list(STUDENTS), help="with --report: first - second")
    args = parser.parse_args()
    if args.report is not None:
        if args.between is None:
            parser.error("--report needs --between (the study whose between-seed spread is the reference)")
        table = report(args.report, args.between, tuple(args.pair))
        print(table)
        if args.to is not None:
            args.to.write_text(table + "\n")
        return
    if args.study is None:
        parser.error("--study is needed to train")
    th.set_num_threads(1)
    train(args.study, args.preset, args.seed, args.students, args.student_seeds, args.output)


if __name__ == "__main__":
    main()
