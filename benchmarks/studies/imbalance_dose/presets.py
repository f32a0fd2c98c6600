"""
The presets of this study (the collections of the imbalance dose study), read by
:func:`sb3_lifelong.experiments.presets.load_presets`::

    python -m sb3_lifelong.experiments run --presets benchmarks/studies/imbalance_dose/presets.py --preset NAME ...

The package itself keeps the presets users run (``demo``, ``tiny``, ``cpu``, ``paper``).
"""

import dataclasses

from sb3_lifelong.experiments.presets import Preset

PRESETS: dict[str, Preset] = {}


# the dose-response study of the imbalance (benchmarks/studies/imbalance_dose/README.md, pre-registered before any run):
# the collector at MPO's defaults (256x256 LayerNorm torso, 20 samples), Env-A and Env-B 100k steps each; the
# imbalance is a dose applied by the students (Env-B sampling share, Env-B reward scale), not by the collection
PRESETS["dose_hopper"] = Preset(
    env_id="Hopper-v5",
    stages=({}, {"foot_scale": 2.0}),
    stage_steps=(100_000, 100_000),
    distill_steps=200_000,
    eval_freq=10_000,
    distill_eval_freq=25_000,
    eval_episodes=10,
    learning_starts=5_000,
    layer_norm=True,
    students=(),
    online=False,
    student_critic="categorical",
    note=(
        "Collection of the imbalance dose study (Hopper, foot x2); students: "
        "benchmarks/studies/imbalance_dose/imbalance_dose.py."
    ),
)
# the natural-value-gap candidate (no healthy reward); its episodes are 1000 steps long, so 5 evaluation episodes
PRESETS["dose_cheetah"] = dataclasses.replace(
    PRESETS["dose_hopper"],
    env_id="HalfCheetah-v5",
    eval_episodes=5,
    note=(
        "Collection of the imbalance dose study (HalfCheetah, foot x2); students: "
        "benchmarks/studies/imbalance_dose/imbalance_dose.py."
    ),
)

# the dose study's HalfCheetah pair with a long Env-B (benchmarks/studies/imbalance_dose/README.md, "Long Env-B"): the
# hip turned by 1 rad (the Env-A gait fails in Env-B: 4635 -> 199) and Env-B five times Env-A, as the paper's 200k : 1M;
# about 8 hours of collection on one core: run it in parts (`run --until STEPS`)
PRESETS["dose_cheetah_hip"] = dataclasses.replace(
    PRESETS["dose_cheetah"],
    stages=({}, {"hip_deformation": 1.0}),
    stage_steps=(100_000, 500_000),
    note=(
        "Collection of the imbalance dose study, long Env-B (HalfCheetah, hip +1 rad, 100k : 500k steps); about 8 hours "
        "on one core, so run it in parts with --until; students: "
        "benchmarks/studies/imbalance_dose/imbalance_dose.py --robot cheetah_hip."
    ),
)
