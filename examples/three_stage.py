"""
Three environments one after the other (Env-A, Env-B, Env-C), then offline distillation of the whole buffer.

Usage::

    python examples/three_stage.py                    # quick CPU preset (HalfCheetah, minutes)
    python examples/three_stage.py --paper            # OP3: default, hip 0.2 rad, hip 0.2 rad + feet x1.6

The three-stage study with the pre-registered claims (Hopper, students, report and figures) is a preset of its study
folder, run by the paper's protocol::

    S=benchmarks/studies/paper_cpu_three
    python -m sb3_lifelong.experiments run --presets $S/presets.py --preset cpu_three --seed K --output DIR
"""

import argparse
import pathlib

from sb3_lifelong.experiments.sequential import (
    add_common_arguments,
    add_per_source_argument,
    finish,
    now,
    prepare_output,
    resolve_config,
    run_sequential,
    set_threads,
)

STAGES = {
    "quick": [{}, {"hip_deformation": 0.3}, {"hip_deformation": 0.3, "friction": 0.1}],
    "tiny": [{}, {"hip_deformation": 0.3}, {"hip_deformation": 0.3, "friction": 0.1}],
    "paper": ["default", "hip_0.2", "hip_0.2+foot_1.6"],
}
STAGE_STEPS = {"quick": [10_000, 10_000, 10_000], "tiny": [200, 200, 200], "paper": [200_000, 1_000_000, 1_000_000]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(parser)
    add_per_source_argument(parser)
    args = parser.parse_args()
    set_threads()
    if args.stage_steps is None:
        args.stage_steps = STAGE_STEPS[args.preset]
    config = resolve_config(args)
    output = pathlib.Path(args.output or f"runs/three_stage_{args.preset}")
    prepare_output(output, config, args.overwrite)
    start = now()
    rows = run_sequential(config, STAGES[args.preset], ["Env-A", "Env-B", "Env-C"], output, baselines=not args.no_baselines)
    finish(output, rows, config, now() - start, plots=not args.no_plots)


if __name__ == "__main__":
    main()
