"""
The presets of this study (the paper's three-stage set-up, at CPU and at its own scale), read by
:func:`sb3_lifelong.experiments.presets.load_presets`::

    python -m sb3_lifelong.experiments run --presets benchmarks/studies/paper_cpu_three/presets.py --preset NAME ...

The package itself keeps the presets users run (``demo``, ``tiny``, ``cpu``, ``paper``).
"""

import dataclasses
import pathlib

from sb3_lifelong.experiments.presets import PRESETS as PACKAGE_PRESETS
from sb3_lifelong.experiments.presets import Preset, load_presets

#: the paper_cpu study's Hopper protocol (the package's `cpu` preset until the forgetting screen), which this one varies
HOPPER_HIP = load_presets(pathlib.Path(__file__).resolve().parents[1] / "paper_cpu" / "presets.py")["cpu_hopper_hip"]

PRESETS: dict[str, Preset] = {}


# the paper's three-stage set-up (its appendix: Env-A 0.2M, Env-B 0.2M, Env-C 1M steps) at the cpu budgets: 0.2 : 0.2 : 1
# of 250k steps; the order follows the env-pair table: each switch hurts the policy of the stage before, and the
# Env-C (foot x2) policy is poor in both earlier environments (benchmarks/studies/env_pairs/results)
PRESETS["cpu_three"] = dataclasses.replace(
    HOPPER_HIP,
    stages=({}, {"friction": 0.2}, {"foot_scale": 2.0}),
    stage_steps=(50_000, 50_000, 250_000),
    env_names=("Env-A", "Env-B", "Env-C"),
    eval_episodes=10,
    students=("CRR_exp_beta1", "CRR_indicator", "BC"),
    online=False,
    note=(
        "Three stages (the paper's appendix): default robot, then the floor's friction 0.2, then the foot twice as long, "
        "in the proportions 0.2 : 0.2 : 1; the students that need no task boundaries only, no online baselines. Claims "
        "pre-registered in benchmarks/studies/paper_cpu_three/README.md before any seed ran."
    ),
)

# the same at the paper's scale, one preset per environment combination of its appendix (OP3; a GPU machine)
for _number, _stages in enumerate(
    (
        ("default", "hip_0.2", "hip_0.2+foot_1.6"),
        ("default", "hip_0.3", "hip_0.3+foot_1.6"),
        ("default", "foot_1.2", "foot_1.2+ground_0.1"),
    ),
    start=1,
):
    PRESETS[f"paper_three_{_number}"] = dataclasses.replace(
        PACKAGE_PRESETS["paper"],
        stages=_stages,
        stage_steps=(200_000, 200_000, 1_000_000),
        env_names=("Env-A", "Env-B", "Env-C"),
        students=PRESETS["cpu_three"].students,
        online=False,
        note=f"The paper's three-stage set-up, its environment combination {_number}, at its scale (a GPU machine).",
    )
