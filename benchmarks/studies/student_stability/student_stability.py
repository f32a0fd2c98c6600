"""
Can the pipeline's student be made stable? Variants of the exp beta=1 CRR student on one finished seed's buffer.

The ``cpu`` studies' students swing by hundreds between evaluations (``results/student_updates.md``). This trains
the study's own student and variants of it (round 1: lower learning rate, Polyak-averaged targets, advantages
normalised by their batch std, a larger temperature; round 2: an averaged actor for evaluation) on the same
lifetime buffer, each also on Env-A data alone (the C4b comparison), with the preset's number of updates, evaluated
every ``--eval-freq`` updates with the preset's episodes. ``--report`` applies the criteria written in
``results/student_stability.md`` before the runs.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/studies/student_stability/student_stability.py --study runs/paper_cpu_foot \
        --preset cpu_foot --seed 0 \\
        --output runs/student_stability
    python benchmarks/studies/student_stability/student_stability.py --report runs/student_stability
"""

import argparse
import dataclasses
import pathlib
from typing import Any

import numpy as np
import pandas as pd
import torch as th

from sb3_lifelong.experiments.presets import EXP, Student, load_presets
from sb3_lifelong.experiments.presets import PRESETS as PACKAGE_PRESETS
from sb3_lifelong.experiments.protocol import distill_on_study

#: the package's presets and the study's own (``cpu_foot``: ``benchmarks/studies/paper_cpu_foot/presets.py``)
PRESETS = {**PACKAGE_PRESETS, **load_presets(pathlib.Path(__file__).resolve().parents[1] / "paper_cpu_foot" / "presets.py")}

#: variant name -> (the student's CRR settings, the preset's fields changed)
VARIANTS: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "baseline": (EXP, {}),
    "lr_1e-4": (EXP, {"student_learning_rate": 1e-4}),
    "polyak": ({**EXP, "tau": 0.005, "target_update_interval": 1}, {}),
    "norm_adv": ({**EXP, "normalize_advantages": True}, {}),
    "beta_5": ({"advantage_transform": "exp", "beta": 5.0}, {}),
    # round 2: the same training as the baseline, evaluated with a moving average of the actor's weights
    "avg_1e-3": ({**EXP, "actor_averaging": 1e-3}, {}),
    "avg_3e-4": ({**EXP, "actor_averaging": 3e-4}, {}),
}
#: evaluations averaged at the end of a run (the last ``LAST`` evaluation points)
LAST = 5


def job_names(variants: list[str], a_only: bool) -> list[str]:
    return [name + suffix for name in variants for suffix in (("", "_A_only") if a_only else ("",))]


def train(study: pathlib.Path, preset_name: str, seed: int, jobs: list[str], eval_freq: int, output: pathlib.Path) -> None:
    """Train the variants ``jobs`` (names of :func:`job_names`) not trained yet on seed ``seed``'s buffer of ``study``."""
    for job in jobs:
        variant = job.removesuffix("_A_only")
        kwargs, changes = VARIANTS[variant]
        preset = dataclasses.replace(PRESETS[preset_name], distill_eval_freq=eval_freq, **changes)
        student = Student("CRR", dict(kwargs), ratio=(1, 0) if job.endswith("_A_only") else None, about=job)
        about = dict(preset=preset_name, changes=changes, kwargs=kwargs, ratio=student.ratio)
        distill_on_study(study, seed, output, {job: student}, preset, about=about)


def summary(output: pathlib.Path) -> pd.DataFrame:
    """:return: one row per (seed, job, env): mean and std of the last ``LAST`` evaluations"""
    rows = []
    for path in sorted(output.glob("seed_*/distill_*/eval.csv")):
        frame = pd.read_csv(path)
        for env, part in frame.groupby("env"):
            last = part.sort_values("timesteps")["mean_reward"].to_numpy()[-LAST:]
            rows.append(
                dict(
                    seed=int(path.parent.parent.name.split("_")[1]),
                    job=path.parent.name[len("distill_") :],
                    env=env,
                    last_mean=float(np.mean(last)),
                    last_std=float(np.std(last)),
                    evaluations=len(last),
                )
            )
    return pd.DataFrame(rows)


def report(output: pathlib.Path) -> str:
    data = summary(output)
    lines = [
        f"| seed | student | Env-A: mean of last {LAST} | Env-A: std of last {LAST} | Env-B: mean | Env-B: std | "
        "Env-A / its A-only student | stable (both stds <= 0.5 x baseline) | C4b (ratio >= 0.9) | (A + B) / 2 | "
        "/ baseline's |",
        "| --- " * 11 + "|",
    ]
    mean_ab: dict[str, list[float]] = {}  # job -> (A + B) / 2 on each seed buffer that has the baseline too
    for seed, part in data.groupby("seed"):
        table = part.set_index(["job", "env"])
        base_std = {env: table.loc[("baseline", env), "last_std"] for env in ("Env-A", "Env-B")}
        for job in sorted({job for job, _ in table.index if not job.endswith("_A_only")}):
            a, b = table.loc[(job, "Env-A")], table.loc[(job, "Env-B")]
            a_only = table.loc[(f"{job}_A_only", "Env-A"), "last_mean"] if (f"{job}_A_only", "Env-A") in table.index else None
            ratio = a["last_mean"] / a_only if a_only and a_only > 0 else None
            stable = a["last_std"] <= 0.5 * base_std["Env-A"] and b["last_std"] <= 0.5 * base_std["Env-B"]
            both = (a["last_mean"] + b["last_mean"]) / 2
            base_both = (table.loc[("baseline", "Env-A"), "last_mean"] + table.loc[("baseline", "Env-B"), "last_mean"]) / 2
            mean_ab.setdefault(job, []).append(both)
            lines.append(
                f"| {seed} | {job} | {a['last_mean']:.0f} | {a['last_std']:.0f} | "
                f"{b['last_mean']:.0f} | {b['last_std']:.0f} | "
                + (f"{ratio:.2f} ({a_only:.0f}) | " if ratio is not None else "- | ")
                + ("-" if job == "baseline" else ("yes" if stable else "no"))
                + " | "
                + ("-" if ratio is None else ("yes" if ratio >= 0.9 else "no"))
                + f" | {both:.0f} | {both / base_both:.2f} |"
            )
    seeds = len(mean_ab.get("baseline", []))
    lines += [
        "",
        f"Mean over the {seeds} seed buffers of (A + B) / 2, and its ratio to the baseline's (round 2's criterion 2):",
        "",
    ]
    for job, values in sorted(mean_ab.items()):
        if len(values) == seeds:
            ratio = np.mean(values) / np.mean(mean_ab["baseline"])
            lines.append(f"- {job}: {np.mean(values):.0f} ({ratio:.2f} x baseline)")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--study", type=pathlib.Path, help="a finished study (its seed's buffer is read)")
    parser.add_argument("--preset", default="cpu_foot", choices=sorted(PRESETS), help="the study's preset")
    parser.add_argument("--seed", type=int, default=0, help="the seed whose buffer is distilled")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS), help="the variants")
    parser.add_argument("--no-a-only", action="store_true", help="skip the Env-A-only counterparts")
    parser.add_argument("--eval-freq", type=int, default=2_500, help="evaluation period, in updates")
    parser.add_argument("--output", type=pathlib.Path, default=pathlib.Path("runs/student_stability"), help="output")
    parser.add_argument("--report", type=pathlib.Path, default=None, help="print the table of this output directory")
    parser.add_argument("--to", type=pathlib.Path, default=None, help="with --report: also write the table here")
    args = parser.parse_args()
    if args.report is not None:
        table = report(args.report)
        print(table)
        if args.to is not None:
            args.to.write_text(table + "\n")
        return
    if args.study is None:
        parser.error("--study is needed to train")
    th.set_num_threads(1)
    train(args.study, args.preset, args.seed, job_names(args.variants, not args.no_a_only), args.eval_freq, args.output)


if __name__ == "__main__":
    main()
