"""
The paper's experiments on this package: the two-stage protocol (and its three-stage variant) as jobs
(:mod:`.protocol`), the report with the pre-registered claims (:mod:`.report`) and the figures (:mod:`.figures`).
Command line: ``python -m sb3_lifelong.experiments {run,report,list}``.
"""

from sb3_lifelong.experiments.protocol import ONLINE, PRESETS, STUDENTS, Preset, Student, job_names, run_seed
from sb3_lifelong.experiments.report import CLAIMS, THREE_STAGE_CLAIMS, claims_of, load_study, write_report

__all__ = [
    "CLAIMS",
    "ONLINE",
    "PRESETS",
    "STUDENTS",
    "THREE_STAGE_CLAIMS",
    "Preset",
    "Student",
    "claims_of",
    "job_names",
    "load_study",
    "run_seed",
    "write_report",
]
