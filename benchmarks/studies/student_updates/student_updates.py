"""
Are the CPU protocol's students undertrained? The same students on the same lifetime buffer with more updates.

Trains students of the ``cpu`` preset (``sb3_lifelong/experiments/presets.py``) on a finished seed's buffer with
``--updates`` gradient steps instead of the preset's 30,000, evaluated every ``--eval-freq`` updates in both
environments (the same evaluation as the study), into ``<output>/seed_<k>/distill_<student>/``; ``--report`` prints
and writes the table of returns against updates for every seed and student found.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/studies/student_updates/student_updates.py --study runs/paper_cpu --seed 0 \\
        --students CRR_exp_beta1 CRR_indicator BC --output runs/student_updates
    python benchmarks/studies/student_updates/student_updates.py --report runs/student_updates --to \
        benchmarks/studies/student_updates/student_updates.md
"""

import argparse
import dataclasses
import pathlib
import time

import pandas as pd
import torch as th

from sb3_lifelong.core.atomic import write_json_atomic
from sb3_lifelong.experiments.presets import load_presets
from sb3_lifelong.experiments.protocol import distill_student


def train(study: pathlib.Path, seed: int, students: list[str], updates: int, eval_freq: int, output: pathlib.Path) -> None:
    hopper_hip = load_presets(pathlib.Path(__file__).resolve().parents[1] / "paper_cpu" / "presets.py")["cpu_hopper_hip"]
    preset = dataclasses.replace(hopper_hip, distill_steps=updates, distill_eval_freq=eval_freq)
    run_dir = output / f"seed_{seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    link = run_dir / "buffer"  # the study's buffer, read-only
    if not link.exists():
        link.symlink_to((study / f"seed_{seed}" / "buffer").resolve())
    for name in students:
        if (run_dir / f"distill_{name}" / "done.json").exists():
            continue
        start = time.perf_counter()
        print(f"seed {seed}: {name}, {updates:,} updates", flush=True)
        distill_student(name, preset, seed, run_dir)
        seconds = time.perf_counter() - start
        write_json_atomic(str(run_dir / f"distill_{name}" / "done.json"), dict(seconds=seconds, updates=updates))
        print(f"seed {seed}: {name} done in {seconds / 60:.1f} min", flush=True)


def report(output: pathlib.Path) -> str:
    frames = []
    for path in sorted(output.glob("seed_*/distill_*/eval.csv")):
        frame = pd.read_csv(path)
        frame["seed"] = int(path.parent.parent.name.split("_")[1])
        frame["student"] = path.parent.name[len("distill_") :]
        frames.append(frame)
    data = pd.concat(frames)
    table = data.pivot_table(index=["student", "seed", "env"], columns="timesteps", values="mean_reward")
    lines = ["| student | seed | env | " + " | ".join(f"{int(t):,}" for t in table.columns) + " |"]
    lines.append("| --- " * (3 + len(table.columns)) + "|")
    for (student, seed, env), values in table.iterrows():
        lines.append(f"| {student} | {seed} | {env} | " + " | ".join(f"{v:.0f}" for v in values) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--study", type=pathlib.Path, help="a study directory of the cpu preset (its seed's buffer is read)")
    parser.add_argument("--seed", type=int, default=0, help="the seed whose buffer is distilled")
    parser.add_argument("--students", nargs="+", default=["CRR_exp_beta1", "CRR_indicator", "BC"], help="students")
    parser.add_argument("--updates", type=int, default=100_000, help="gradient updates of every student")
    parser.add_argument("--eval-freq", type=int, default=10_000, help="evaluation period, in updates")
    parser.add_argument("--output", type=pathlib.Path, default=pathlib.Path("runs/student_updates"), help="output")
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
    train(args.study, args.seed, args.students, args.updates, args.eval_freq, args.output)


if __name__ == "__main__":
    main()
