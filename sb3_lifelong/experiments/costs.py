"""
What a job costs, measured: every finished job of ``run`` and ``study`` adds a line (its settings' fingerprint, the job,
its seconds, the CPU) to a small cost log, so that ``list --preset P`` and the progress lines of a later run can say
how long a job and a seed take on this kind of CPU, from earlier runs of the same settings.

The log is ``$SB3_LIFELONG_COSTS`` when set (an empty value: no log), else ``~/.cache/sb3_lifelong/job_costs.jsonl``.
It holds timings only; a log that cannot be written or read is skipped (the run goes on, with no estimate).
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
import re
import statistics
from collections.abc import Sequence
from typing import Any, Optional

from sb3_lifelong.numerics.hardware import cpu_matrix_flags, cpu_model

#: the environment variable naming the cost log (empty: none)
COSTS_VARIABLE = "SB3_LIFELONG_COSTS"


def costs_file() -> Optional[pathlib.Path]:
    """:return: the cost log (None: switched off by an empty ``$SB3_LIFELONG_COSTS``)"""
    value = os.environ.get(COSTS_VARIABLE)
    if value is not None:
        return pathlib.Path(value) if value else None
    return pathlib.Path.home() / ".cache" / "sb3_lifelong" / "job_costs.jsonl"


def cpu_kind() -> str:
    """:return: this CPU's model name and the flags that decide its speed (how the costs of two machines are told apart)"""
    flags = [flag for flag in cpu_matrix_flags() if flag.startswith(("amx", "avx512_bf16"))]
    return cpu_model() + (f" ({', '.join(flags)})" if flags else "")


def fingerprint(settings: dict[str, Any]) -> str:
    """:return: a short fingerprint of a preset's settings (``Preset.describe()``)"""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]


def job_key(job: str) -> str:
    """:return: what a job's cost is filed under: its name without the repeat suffix (a repeat costs as the first)"""
    return re.sub(r"__r\d+$", "", job)


def record(settings: dict[str, Any], job: str, seconds: float) -> bool:
    """
    Add a finished job's cost to the log.

    :param settings: the preset's settings (``Preset.describe()``)
    :param job: the job
    :param seconds: its wall time
    :return: whether it was written
    """
    path = costs_file()
    if path is None:
        return False
    line = {"preset": fingerprint(settings), "job": job_key(job), "seconds": round(float(seconds), 2), "cpu": cpu_kind()}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a", encoding="utf-8") as handle:
            handle.write(json.dumps(line) + "\n")
    except OSError:
        return False
    return True


def measured(settings: dict[str, Any]) -> dict[str, list[float]]:
    """:return: the seconds the log holds for each job of these settings, measured on this kind of CPU"""
    path, wanted, cpu = costs_file(), fingerprint(settings), cpu_kind()
    found: dict[str, list[float]] = {}
    if path is None:
        return found
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return found
    for text in lines:
        try:
            line = json.loads(text)
            if line["preset"] == wanted and line["cpu"] == cpu:
                found.setdefault(str(line["job"]), []).append(float(line["seconds"]))
        except (ValueError, KeyError, TypeError):
            continue  # a torn or foreign line
    return found


def estimate(job: str, times: dict[str, list[float]]) -> Optional[float]:
    """
    :param job: a job
    :param times: seconds per job key (:func:`measured`, and the jobs finished in this run)
    :return: the median seconds of that job, else of the other students (the same number of updates), else None
    """
    key = job_key(job)
    if times.get(key):
        return statistics.median(times[key])
    if key.startswith("distill_"):
        students = [seconds for name, values in times.items() if name.startswith("distill_") for seconds in values]
        if students:
            return statistics.median(students)
    return None


def minutes(seconds: float) -> str:
    """:return: a duration as a person plans with it"""
    if seconds < 60:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


def remaining(jobs: Sequence[str], times: dict[str, list[float]], left: str = " left") -> str:
    """
    :param jobs: the jobs still to run
    :param times: seconds per job key (:func:`measured`, and the jobs finished in this run)
    :param left: the word after the estimate
    :return: what ``jobs`` will take, with an estimate where one is known (empty when there is no job)
    """
    if not jobs:
        return ""
    known = [estimate(job, times) for job in jobs]
    total = sum(seconds for seconds in known if seconds is not None)
    unknown = [job for job, seconds in zip(jobs, known) if seconds is None]
    if not unknown:
        return f"about {minutes(total)}{left} for {len(jobs)} job(s)"
    if len(unknown) == len(jobs):
        return f"{len(jobs)} job(s){left}, no measured time for them yet"
    return (
        f"about {minutes(total)}{left} for {len(jobs) - len(unknown)} of {len(jobs)} job(s); not measured yet: "
        + ", ".join(unknown)
    )
