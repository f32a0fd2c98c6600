"""
The presets of this study (the cpu protocol with the foot twice as long), read by
:func:`sb3_lifelong.experiments.presets.load_presets`::

    python -m sb3_lifelong.experiments run --presets benchmarks/studies/paper_cpu_foot/presets.py --preset NAME ...

The package itself keeps the presets users run (``demo``, ``tiny``, ``cpu``, ``paper``).
"""

import dataclasses
import pathlib

from sb3_lifelong.experiments.presets import Preset, load_presets

#: the paper_cpu study's Hopper protocol (the package's `cpu` preset until the forgetting screen), which this one varies
HOPPER_HIP = load_presets(pathlib.Path(__file__).resolve().parents[1] / "paper_cpu" / "presets.py")["cpu_hopper_hip"]

PRESETS: dict[str, Preset] = {}


# the cpu protocol with the one Env-B of the env-pair table that hurt in both directions, the foot twice as long
# (benchmarks/studies/env_pairs/results); evaluated on 10 episodes, as the 5 of `cpu` left the students' scores noisy
PRESETS["cpu_foot"] = dataclasses.replace(
    HOPPER_HIP,
    stages=({}, {"foot_scale": 2.0}),
    eval_episodes=10,
    note=(
        "Env-B: the foot twice as long, the candidate with a zero-shot drop in both directions (Env-A policy in "
        "Env-B -87 %, Env-B policy in Env-A -42 %, one seed each at 50k steps). Claims pre-registered in "
        "benchmarks/studies/paper_cpu_foot/README.md before any seed ran."
    ),
)
