"""
The presets of the pipeline study on the forgetting screen's setting (README beside this file), read by
:func:`sb3_lifelong.experiments.presets.load_presets`::

    python -m sb3_lifelong.experiments study --presets benchmarks/studies/pipeline_forgetting/presets.py \
        --preset pipeline_cheetah_back_reversed ...

One preset per HalfCheetah candidate the screen can select (``benchmarks/studies/forgetting_screen``): the collection
is the screen's to the last setting (its collector, budgets and evaluations), so a seed's Stage-1 is the same whichever
candidate follows; the study adds the online CRR baselines and the students, each trained twice (two student seeds).
"""

import dataclasses
import pathlib

from sb3_lifelong.experiments.presets import Preset, load_presets

#: the paper_cpu study's Hopper protocol (the package's `cpu` preset until the forgetting screen), which this one varies
HOPPER_HIP = load_presets(pathlib.Path(__file__).resolve().parents[1] / "paper_cpu" / "presets.py")["cpu_hopper_hip"]

#: the HalfCheetah candidates of the screen and their Env-B (Env-A is the nominal robot)
CHANGES = {
    "cheetah_back_reversed": {"leg_motor_scale": -1.0},
    "cheetah_back_knee_locked": {"joint_lock": 1.0},
}

PRESETS: dict[str, Preset] = {
    f"pipeline_{candidate}": dataclasses.replace(
        HOPPER_HIP,
        env_id="HalfCheetah-v5",
        stages=({}, dict(change)),
        stage_steps=(60_000, 180_000),
        eval_freq=5_000,
        eval_episodes=5,
        env_a_learnt=1500.0,
        max_switch_spread=0.2,
        value_gap=None,
        min_weight_ess=None,
        students=("CRR_exp_beta1", "CRR_indicator"),
        online=True,
        student_repeats=2,
        note=(
            f"The pipeline on the forgetting screen's {candidate} (benchmarks/studies/pipeline_forgetting/README.md): "
            "the screen's collector (HalfCheetah 60k Env-A + 180k Env-B), online CRR from the Stage-1 agent, two "
            "students with two student seeds each. A seed continues past Env-A only when it learnt Env-A there."
        ),
    )
    for candidate, change in CHANGES.items()
}
