"""
Parallel data sharing (the paper's appendix set-ups): two robots at the same time, then one distillation over all
their data, run by the paper's protocol (its runner and its report).

- ``--setup copy``: one agent learns Env-A; at the switch it is copied (policy, critic and replay buffer), and the
  two go on at the same time, the first in Env-B and the copy in Env-C. Their buffers are merged, keeping the shared
  Env-A part once.
- ``--setup independent``: one agent learns Env-A then Env-B while a second agent learns Env-C from scratch; their
  buffers are merged.

The students (CRR exp beta=1, the pipeline, and CRR indicator, the imbalance baseline) distill the merged buffer and
are evaluated in all three environments, beside the two collectors. The two collectors run side by side on two
workers (the default, ``--workers 2``: Ray workers when Ray is installed, a local process pool otherwise); on one
worker they run one after the other.

Usage::

    python examples/parallel_sharing.py --setup copy
    python examples/parallel_sharing.py --setup copy --workers 1     # the collectors one after the other
    python examples/parallel_sharing.py --setup independent --paper

It writes the protocol's layout into ``--output`` (default ``runs/parallel_sharing_<setup>_<preset>``):
``preset.json``, per seed the first collector (``collect``, ``buffer``), the second (``collect_agent2``,
``buffer_agent2``), the merged buffer (``share``, ``buffer_shared``) and one directory per student
(``distill_<student>``); then ``scores.csv``, ``report.md`` and the figures ``fig_*.png``. Run again, it skips the
jobs that have finished.
"""

import dataclasses
import sys

from sb3_lifelong.experiments.example import run_example
from sb3_lifelong.experiments.presets import PRESETS as PACKAGE_PRESETS
from sb3_lifelong.experiments.presets import Preset

NAMES = ("Env-A", "Env-B", "Env-C")
CPU_STAGES = ({}, {"hip_deformation": 0.3}, {"friction": 0.1})
#: the pipeline (CRR exp beta=1) and the imbalance baseline (CRR indicator)
STUDENTS = ("CRR_exp_beta1", "CRR_indicator")
SHARING = dict(env_names=NAMES, students=STUDENTS, online=False)
#: the set-ups (``--setup``), each the preset's sharing
SETUPS = {"copy": dict(sharing="copy"), "independent": dict(sharing="independent")}

PRESETS: dict[str, Preset] = {
    "quick": dataclasses.replace(
        PACKAGE_PRESETS["cpu"],
        **SHARING,
        stages=CPU_STAGES,
        stage_steps=(10_000, 20_000, 20_000),
        distill_steps=10_000,
        distill_eval_freq=1_000,
        sharing="copy",
        toy=True,
        note="10k steps of Env-A: too few to learn HalfCheetah (about 60k), so a run shows the pipeline.",
    ),
    "tiny": dataclasses.replace(
        PACKAGE_PRESETS["tiny"],
        **SHARING,
        stages=CPU_STAGES,
        stage_steps=(200, 200, 200),
        distill_eval_freq=20,  # a curve of six evaluations per student
        sharing="copy",
    ),
    "paper": dataclasses.replace(
        PACKAGE_PRESETS["paper"],
        **SHARING,
        stages=("default", "hip_0.3", "foot_1.6"),
        stage_steps=(200_000, 1_000_000, 1_000_000),
        sharing="copy",
        note="The paper's scale, two OP3 robots side by side: a GPU machine (--device cuda), or --workers N for the jobs.",
    ),
}


if __name__ == "__main__":
    sys.exit(run_example(PRESETS, __doc__, "parallel_sharing", setups=SETUPS, workers=2))
