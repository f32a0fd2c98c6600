"""
The paper's experiments on this package: what a study runs (its presets, students and jobs, :mod:`.presets`), the
two-stage protocol (and its three-stage variant) as jobs (:mod:`.protocol`), a study's scores (:mod:`.scores`), the
report with the pre-registered claims (:mod:`.report`) and the figures (:mod:`.figures`).
Command line: ``python -m sb3_lifelong.experiments {run,study,report,list}``.
"""

from sb3_lifelong.experiments.claims import Claim, evaluate_claims, load_claims
from sb3_lifelong.experiments.presets import ONLINE, PRESETS, STUDENTS, Preset, Student, job_names
from sb3_lifelong.experiments.protocol import run_seed
from sb3_lifelong.experiments.report import write_report
from sb3_lifelong.experiments.scores import load_study

__all__ = [
    "ONLINE",
    "PRESETS",
    "STUDENTS",
    "Claim",
    "Preset",
    "Student",
    "evaluate_claims",
    "job_names",
    "load_claims",
    "load_study",
    "run_seed",
    "write_report",
]
