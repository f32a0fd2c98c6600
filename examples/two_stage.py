"""
The two-stage lifelong experiment: the robot trains in Env-A, then its dynamics change (Env-B).

Compares, on both environments: MPO continuing online (it "forgets" Env-A although its buffer keeps every
Env-A transition), the conservative online baselines CRR (indicator) and CRR (exp, beta=1) continuing from the
same Stage-1 agent, and the Offline Distillation Pipeline: the MPO collector's whole buffer distilled offline by
CRR (exp, beta=1; and indicator, which suffers from the imbalanced data).

Usage::

    python examples/two_stage.py                      # quick CPU preset (HalfCheetah, minutes)
    python examples/two_stage.py --seeds 0 1 2        # the same, three seeds
    python examples/two_stage.py --paper              # OP3, hip deformed by 0.3 rad, 0.2M + 1M steps, 3 seeds
"""

import argparse
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

from lifelong_common import (
    add_common_arguments,
    add_per_source_argument,
    finish,
    now,
    resolve_config,
    run_sequential,
    set_threads,
)

STAGES = {
    "quick": [{}, {"hip_deformation": 0.3}],
    "tiny": [{}, {"hip_deformation": 0.3}],
    "paper": ["default", "hip_0.3"],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(parser)
    add_per_source_argument(parser)
    args = parser.parse_args()
    set_threads()
    config = resolve_config(args)
    output = pathlib.Path(args.output or f"runs/two_stage_{args.preset}")
    output.mkdir(parents=True, exist_ok=True)
    start = now()
    rows = run_sequential(config, STAGES[args.preset], ["Env-A", "Env-B"], output, baselines=not args.no_baselines)
    finish(output, rows, config, now() - start, plots=not args.no_plots)


if __name__ == "__main__":
    main()
