"""
No task boundaries: the robot wears gradually. The right hip deforms linearly from 0 to 0.3 rad over the whole life
while MPO collects; the lifetime buffer is then distilled, run by the paper's protocol (its runner and its report).

The life is cut into three equal thirds only to read it: the collector's robot changes at every episode, never at a
third. Each third is evaluated on one robot: the first on the robot of the first step (hip 0), the second on the
robot of the middle of the life (0.15 rad), the last on the robot of the last step (0.3 rad). So the report's
"Env-A at the end against at the switch" is the robot's young self, remembered or not.

Usage::

    python examples/continuous_drift.py                 # quick: HalfCheetah, 30k steps of life, on a CPU
    python examples/continuous_drift.py --paper         # OP3: 1.2M steps (the paper's 200k + 1M), a GPU machine
    python examples/continuous_drift.py --seeds 0 1 --workers 2

It writes the protocol's layout into ``--output`` (default ``runs/continuous_drift_<preset>``): ``preset.json``, per
seed ``seed_<k>/buffer`` (the lifetime buffer, its sources the three thirds) and one directory per job (``collect``,
``distill_<student>``, ``online_<method>``); then ``scores.csv``, ``report.md`` and the figures ``fig_*.png``. Run
again, it skips the jobs that have finished.
"""

import dataclasses
import sys

from sb3_lifelong.experiments.example import run_example
from sb3_lifelong.experiments.presets import PRESETS as PACKAGE_PRESETS
from sb3_lifelong.experiments.presets import Preset

#: the right hip's deformation (rad) at the first and at the last step of the life
DRIFT = {"hip_deformation": (0.0, 0.3)}
#: the three thirds of the life, named by the hip of the robot each is evaluated on
NAMES = ("hip_0.00", "hip_0.15", "hip_0.30")
#: where each third's evaluation robot is in the life: its first step, its middle, its last step
EVAL_AT = (0.0, 0.5, 1.0)
#: the pipeline (CRR exp beta=1) and the imbalance baseline (CRR indicator)
STUDENTS = ("CRR_exp_beta1", "CRR_indicator")
DRIFTING = dict(stages=({}, {}, {}), env_names=NAMES, drift=DRIFT, drift_eval_at=EVAL_AT, students=STUDENTS)

PRESETS: dict[str, Preset] = {
    "quick": dataclasses.replace(
        PACKAGE_PRESETS["cpu"],
        **DRIFTING,
        stage_steps=(10_000, 10_000, 10_000),
        distill_steps=10_000,
        distill_eval_freq=1_000,
        toy=True,
        note="30k steps of life: too few to learn HalfCheetah (about 60k), so a run shows the pipeline.",
    ),
    "tiny": dataclasses.replace(PACKAGE_PRESETS["tiny"], **DRIFTING, stage_steps=(200, 200, 200), distill_eval_freq=20),
    "paper": dataclasses.replace(
        PACKAGE_PRESETS["paper"],
        **DRIFTING,
        stage_steps=(400_000, 400_000, 400_000),
        note="The paper's lifetime (1.2M steps) on OP3, its hip worn gradually: a GPU machine (--device cuda).",
    ),
}


if __name__ == "__main__":
    sys.exit(run_example(PRESETS, __doc__, "continuous_drift"))
