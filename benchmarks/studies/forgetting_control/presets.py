"""
The two branches of the forgetting control (README beside this file), read by
:func:`sb3_lifelong.experiments.presets.load_presets`: the forgetting screen's collector on its closest candidate
(``benchmarks/studies/forgetting_screen``, ``cheetah_back_reversed``), with this study's budgets (120k steps of Env-A,
then 120k of Stage 2). Stage 2 is the change (``switched``) or the nominal value of the same parameter (``control``:
the same appended column, Env-A goes on). ``tests/studies/test_forgetting_control.py`` checks that each equals the
screen's preset for that candidate in everything but its stages, budgets and note.
"""

import dataclasses
import pathlib

from sb3_lifelong.experiments.presets import Preset, load_presets

#: the paper_cpu study's Hopper protocol, whose collector the screen (and so this study) runs on HalfCheetah
HOPPER_HIP = load_presets(pathlib.Path(__file__).resolve().parents[1] / "paper_cpu" / "presets.py")["cpu_hopper_hip"]

#: Stage 2 of each branch
BRANCHES: dict[str, dict[str, float]] = {"switched": {"leg_motor_scale": -1.0}, "control": {"leg_motor_scale": 1.0}}

PRESETS: dict[str, Preset] = {
    f"control_{branch}": dataclasses.replace(
        HOPPER_HIP,
        env_id="HalfCheetah-v5",
        stages=({}, dict(change)),
        stage_steps=(120_000, 120_000),
        eval_freq=5_000,  # the screen's evaluations: every 5k steps, 5 seeded episodes
        eval_episodes=5,
        env_a_learnt=1500.0,  # the screen's HalfCheetah threshold and steadiness
        max_switch_spread=0.2,
        students=(),
        online=False,
        note=f"forgetting control, {branch} (benchmarks/studies/forgetting_control/README.md)",
    )
    for branch, change in BRANCHES.items()
}
