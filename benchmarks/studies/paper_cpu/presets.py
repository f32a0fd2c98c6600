"""
The preset of this study: the paper's two-stage protocol at CPU scale on Hopper with the hip deformed. It was the
package's ``cpu`` preset until the forgetting screen (``benchmarks/studies/forgetting_screen``) chose the setting
``cpu`` runs now; the studies that derived from it (``paper_cpu_foot``, ``paper_cpu_three``, the screen and the
pipeline study's collector) read it here::

    python -m sb3_lifelong.experiments run --presets benchmarks/studies/paper_cpu/presets.py --preset cpu_hopper_hip ...
"""

from sb3_lifelong.experiments.presets import Preset

PRESETS: dict[str, Preset] = {
    # one core of a CPU machine: Hopper with the hip deformed, Env-B five times Env-A; the claims' preconditions are
    # the dose study's (benchmarks/studies/imbalance_dose/README.md): Env-A learnt from a return of 1000 (P1 on Hopper:
    # a hop that moves forward; this study's MPO had about 690 and 400 at the switch), a value gap of 1.1 (P3), a
    # conservative student at an ESS of 0.8 (P4); a steady Env-A at the switch, its last 3 evaluations within a spread
    # of 0.2 (the switch score, the mean of the last two, then has a standard error of about 0.14 of itself, so that
    # C1's "end / switch <= 0.7" is about two of them below an unchanged level)
    "cpu_hopper_hip": Preset(
        env_id="Hopper-v5",
        env_a_learnt=1000.0,
        value_gap=1.1,
        min_weight_ess=0.8,
        max_switch_spread=0.2,
        stages=({}, {"hip_deformation": 0.3}),
        stage_steps=(50_000, 250_000),
        distill_steps=30_000,
        eval_freq=10_000,
        distill_eval_freq=5_000,
        eval_episodes=5,
        net_arch=(128, 128),
        batch_size=128,
        student_batch_size=256,
        num_samples=10,
        learning_rate=1e-3,
        learning_starts=2_000,
    ),
}
