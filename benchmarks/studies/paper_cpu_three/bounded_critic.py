"""
The study's CRR students again, with the paper's bounded critic: a categorical (distributional) critic whose support
holds every return of the data, ``[min(0, r_min), max(0, r_max)] / (1 - gamma)`` of each seed's buffer, 51 atoms.
Everything else is the study's: buffer, updates, batch, networks, seeds, evaluations.

The protocol's students use a mean-squared-error critic, which nothing stops from diverging on offline data; the
paper's is distributional. This script puts the two side by side on every finished seed of a study. Its output
folder is itself a study (MPO's curves and the BC student linked from the study, the two CRR students replaced), so
the study's report, claims and figures apply to it unchanged.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/studies/paper_cpu_three/bounded_critic.py train --study runs/paper_cpu_three \
        --seed K \\
        --output runs/paper_cpu_three_c51
    python benchmarks/studies/paper_cpu_three/bounded_critic.py report --study runs/paper_cpu_three --output \
        runs/paper_cpu_three_c51 \\
        --export benchmarks/studies/paper_cpu_three/bounded_critic
"""

import argparse
import json
import pathlib
import shutil

import pandas as pd

from sb3_lifelong.experiments.jobs import value_support
from sb3_lifelong.experiments.presets import PRESETS, STUDENTS, Preset, Student, load_presets, same_settings
from sb3_lifelong.experiments.protocol import distill_on_study
from sb3_lifelong.experiments.report import write_report
from sb3_lifelong.experiments.scores import STUDENT_LAST, last_mean

#: the study's CRR students, by their job names there, and what this script replaces them with
CATEGORICAL = {"distributional_critic": True}
LINKED = ("collect",)  # the online run whose buffer the students distil: the same MPO curves


def categorical(name: str) -> Student:
    """:return: the study's student ``name`` with a categorical critic on the data's return bounds"""
    student = STUDENTS[name]
    kwargs = dict(student.kwargs)
    kwargs["policy_kwargs"] = {**kwargs.get("policy_kwargs", {}), **CATEGORICAL}
    return Student(
        student.algorithm, kwargs, student.ratio, student.reward_scale, student.uses_boundaries, student.about + " (C51)"
    )


def study_preset(study: pathlib.Path) -> tuple[str, Preset]:
    """:return: the name and settings of the preset ``study`` was run with (its ``preset.json``)"""
    recorded = json.loads((study / "preset.json").read_text())
    own = load_presets(pathlib.Path(__file__).resolve().parent / "presets.py")
    for name, preset in {**PRESETS, **own}.items():
        if same_settings(recorded, json.loads(json.dumps(preset.describe()))):
            return name, preset
    raise ValueError(f"{study / 'preset.json'} matches no preset of this version of sb3_lifelong")


def crr_students(preset: Preset) -> list[str]:
    """:return: the preset's students that have a critic (CRR)"""
    names = preset.students if preset.students is not None else tuple(STUDENTS)
    return [name for name in names if STUDENTS[name].algorithm == "CRR"]


def train(study: pathlib.Path, seed: int, output: pathlib.Path) -> None:
    """
    Train the categorical-critic students of one finished seed of ``study`` into ``output``, linking what they share.

    :param study: the study's output directory
    :param seed: the seed whose buffer is distilled
    :param output: this diagnostic's study directory
    """
    name, preset = study_preset(study)
    output.mkdir(parents=True, exist_ok=True)
    recorded = json.loads((study / "preset.json").read_text())
    recorded["note"] = (
        f"Diagnostic of {study.name}: its CRR students retrained with a categorical critic on the data's return "
        "bounds (benchmarks/studies/paper_cpu_three/bounded_critic.py); MPO and the students without a critic are "
        "the study's own. " + recorded.get("note", "")
    )
    (output / "preset.json").write_text(json.dumps(recorded, indent=1))
    finished = [job for job in crr_students(preset) if (study / f"seed_{seed}" / f"distill_{job}" / "done.json").exists()]
    students = {job: categorical(job) for job in finished}  # the CRR students this seed of the study has
    distill_on_study(study, seed, output, students, preset, about=dict(preset=name, diagnostic="categorical critic"))
    run_dir = output / f"seed_{seed}"
    shared = [*LINKED, *(f"distill_{job}" for job in (preset.students or STUDENTS) if job not in crr_students(preset))]
    for job in shared:  # the study's own results for everything that has no critic to change
        link = run_dir / job
        if not link.exists() and (study / f"seed_{seed}" / job / "done.json").exists():
            link.symlink_to((study / f"seed_{seed}" / job).resolve())


def final_q(run_dir: pathlib.Path, job: str) -> float:
    """:return: the largest average Q over the sources at the student's last measurement (NaN if none)"""
    path = run_dir / f"distill_{job}" / "q_sources.csv"
    if not path.exists():
        return float("nan")
    frame = pd.read_csv(path)
    return float(frame[frame["timesteps"] == frame["timesteps"].max()]["q_mean"].max()) if len(frame) else float("nan")


def comparison(study: pathlib.Path, output: pathlib.Path) -> pd.DataFrame:
    """
    :return: one row per (seed, student, critic): the final return in each environment (as the study's report
        scores it), the largest final average Q over the sources, and the return bound ``max(0, r_max) / (1 - gamma)``
        of that seed's data, beyond which a Q-value has diverged
    """
    from sb3_lifelong import LifelongReplayBuffer

    _, preset = study_preset(study)
    rows = []
    for run_dir in sorted(output.glob("seed_*")):
        seed = int(run_dir.name.split("_")[1])
        with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
            bound = value_support(buffer.reward_range(), 0.99)["v_max"]
        for job in crr_students(preset):
            for critic, folder in (("MSE", study / run_dir.name), ("categorical", run_dir)):
                if not (folder / f"distill_{job}" / "done.json").exists():
                    continue
                evals = pd.read_csv(folder / f"distill_{job}" / "eval.csv")
                row = dict(seed=seed, student=job, critic=critic, q_final_max=final_q(folder, job), q_bound=bound)
                row.update({env: last_mean(evals, env, STUDENT_LAST) for env in preset.env_names})
                rows.append(row)
    return pd.DataFrame(rows)


def report(study: pathlib.Path, output: pathlib.Path, export: pathlib.Path | None) -> str:
    """
    Write the diagnostic's own study report (claims, figures) and the side-by-side table.

    :param study: the study
    :param output: this diagnostic's study directory
    :param export: where to copy the small results (optional)
    :return: the side-by-side table as markdown
    """
    write_report(output)
    table = comparison(study, output)
    if table.empty:
        raise FileNotFoundError(f"no finished categorical-critic student in {output}")
    table["diverged"] = table["q_final_max"] > table["q_bound"]
    cells = [[f"{v:.0f}" if isinstance(v, float) else str(v) for v in row] for row in table.itertuples(index=False)]
    lines = ["| " + " | ".join(table.columns) + " |", "|" + " --- |" * len(table.columns)]
    text = "\n".join(lines + ["| " + " | ".join(row) + " |" for row in cells])
    (output / "comparison.md").write_text(text + "\n")
    table.to_csv(output / "comparison.csv", index=False)
    if export is not None:
        export.mkdir(parents=True, exist_ok=True)
        for name in ("report.md", "claims.csv", "scores.csv", "comparison.md", "comparison.csv"):
            shutil.copy(output / name, export / name)
        for figure in output.glob("fig_*.png"):
            shutil.copy(figure, export / figure.name)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("command", choices=["train", "report"])
    parser.add_argument("--study", type=pathlib.Path, required=True, help="a study with finished seeds")
    parser.add_argument("--output", type=pathlib.Path, required=True, help="this diagnostic's directory")
    parser.add_argument("--seed", type=int, nargs="+", default=[0], help="train: the seeds whose buffers are distilled")
    parser.add_argument("--export", type=pathlib.Path, help="report: copy the small results here")
    args = parser.parse_args()
    if args.command == "train":
        import torch as th

        th.set_num_threads(1)
        for seed in args.seed:
            train(args.study, seed, args.output)
    else:
        print(report(args.study, args.output, args.export))


if __name__ == "__main__":
    main()
