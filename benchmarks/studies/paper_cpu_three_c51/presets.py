"""
The presets of this study (cpu_three with categorical students, each trained three times), read by
:func:`sb3_lifelong.experiments.presets.load_presets`::

    python -m sb3_lifelong.experiments run --presets benchmarks/studies/paper_cpu_three_c51/presets.py --preset NAME ...

The package itself keeps the presets users run (``demo``, ``tiny``, ``cpu``, ``paper``).
"""

import dataclasses
import pathlib

from sb3_lifelong.experiments.presets import Preset, load_presets

THREE = load_presets(pathlib.Path(__file__).resolve().parent.parent / "paper_cpu_three" / "presets.py")
PRESETS: dict[str, Preset] = {}


# cpu_three again with what its first study asked for: the paper's kind of critic for the CRR students (a categorical
# one on the data's return bounds: no student diverged with it, benchmarks/studies/paper_cpu_three/bounded_critic) and
# every student trained three times per buffer and scored by the mean (most of a student's spread is its own training,
# benchmarks/studies/student_spread/student_spread.md); its collection is cpu_three's, so cpu_three's buffers can be reused
PRESETS["cpu_three_c51"] = dataclasses.replace(
    THREE["cpu_three"],
    student_critic="categorical",
    student_repeats=3,
    note=(
        "cpu_three's set-up and claims, with categorical-critic CRR students each trained three times per buffer and "
        "scored by the mean. Pre-registered in benchmarks/studies/paper_cpu_three_c51/README.md before any seed ran."
    ),
)
