"""
Three environments one after the other (Env-A, Env-B, Env-C), then offline distillation of the whole buffer, run by
the paper's protocol: its runner (one ``collect`` job, then the students and the online baselines) and its report.

Usage::

    python examples/three_stage.py                    # quick: HalfCheetah, 10k steps per stage, on a CPU
    python examples/three_stage.py --paper            # OP3: default, hip 0.2 rad, hip 0.2 rad + feet x1.6
    python examples/three_stage.py --seeds 0 1 2 --workers 3 --per-source-actors

It writes the protocol's layout into ``--output`` (default ``runs/three_stage_<preset>``): ``preset.json``, and per seed
``seed_<k>/buffer`` (the lifetime buffer, its sources Env-A, Env-B, Env-C) and one directory per job (``collect``,
``distill_<student>``, ``online_<method>``: ``eval.csv``, ``q_sources.csv``, ``done.json``); then ``scores.csv``,
``report.md`` and the figures ``fig_*.png``. Run again, it skips the jobs that have finished;
``python -m sb3_lifelong.experiments report DIR`` rewrites the report.

The three-stage study with the pre-registered claims (Hopper, more students) is a preset of its study folder::

    S=benchmarks/studies/paper_cpu_three
    python -m sb3_lifelong.experiments run --presets $S/presets.py --preset cpu_three --seed K --output DIR
"""

import dataclasses
import sys

from sb3_lifelong.experiments.example import run_example
from sb3_lifelong.experiments.presets import PRESETS as PACKAGE_PRESETS
from sb3_lifelong.experiments.presets import Preset

NAMES = ("Env-A", "Env-B", "Env-C")
CPU_STAGES = ({}, {"hip_deformation": 0.3}, {"hip_deformation": 0.3, "friction": 0.1})
#: the students of every preset: the pipeline (CRR exp beta=1) and the imbalance baseline (CRR indicator)
STUDENTS = ("CRR_exp_beta1", "CRR_indicator")
#: the diagnostic student of ``--per-source-actors``: one actor per environment, one shared critic
PER_SOURCE_STUDENT = "CRR_indicator_two_actors"

#: the example's presets: the package's ``cpu``, ``tiny`` and ``paper`` with three stages
PRESETS: dict[str, Preset] = {
    "quick": dataclasses.replace(
        PACKAGE_PRESETS["cpu"],
        stages=CPU_STAGES,
        stage_steps=(10_000, 10_000, 10_000),
        env_names=NAMES,
        students=STUDENTS,
        toy=True,
        note="10k steps per stage: too few to learn Env-A on HalfCheetah (about 60k), so a run shows the pipeline.",
    ),
    "tiny": dataclasses.replace(
        PACKAGE_PRESETS["tiny"],
        stages=CPU_STAGES,
        stage_steps=(200, 200, 200),
        env_names=NAMES,
        students=STUDENTS,
        distill_eval_freq=20,  # a curve of six evaluations per student
    ),
    "paper": dataclasses.replace(
        PACKAGE_PRESETS["paper"],
        stages=("default", "hip_0.2", "hip_0.2+foot_1.6"),
        stage_steps=(200_000, 1_000_000, 1_000_000),
        env_names=NAMES,
        students=STUDENTS,
        note="The paper's scale, three stages (OP3): a GPU machine (--device cuda), or --workers N for the jobs.",
    ),
}


if __name__ == "__main__":
    sys.exit(run_example(PRESETS, __doc__, "three_stage", per_source_student=PER_SOURCE_STUDENT))
