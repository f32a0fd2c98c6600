"""
Parallel data sharing (the paper's appendix set-ups), then one distillation over all the robots' data.

- ``--setup copy``: one agent learns Env-A; it is then copied (policy, critic and replay buffer) into two agents
  that continue at the same time in Env-B and in Env-C. The buffers are merged, keeping the shared Env-A part once.
- ``--setup independent``: one agent learns Env-A then Env-B while a second agent learns Env-C from scratch. The
  two buffers are viewed as one (no copy) for the distillation.

The two collectors run side by side (``--workers 2``, the default: Ray workers when Ray is installed, a local
process pool otherwise), each into its own lifetime buffer on disk; ``--workers 1`` runs them one after the other.

Usage::

    python examples/parallel_sharing.py --setup copy
    python examples/parallel_sharing.py --setup copy --workers 1     # the collectors one after the other
    python examples/parallel_sharing.py --setup independent --paper
"""

import argparse
import pathlib

from sb3_lifelong.experiments.runner import BACKENDS
from sb3_lifelong.experiments.sequential import (
    add_common_arguments,
    finish,
    now,
    prepare_output,
    resolve_config,
    set_threads,
)
from sb3_lifelong.experiments.sharing import SETUPS, run_sharing

STAGES = {
    "quick": [{}, {"hip_deformation": 0.3}, {"friction": 0.1}],
    "tiny": [{}, {"hip_deformation": 0.3}, {"friction": 0.1}],
    "paper": ["default", "hip_0.3", "foot_1.6"],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(parser)
    parser.add_argument(
        "--setup",
        choices=SETUPS,
        default="copy",
        help="copy: one agent learns Env-A, then two copies learn Env-B and Env-C; independent: A -> B, and C from scratch",
    )
    parser.add_argument("--workers", type=int, default=2, help="collectors at a time (1: one after the other)")
    parser.add_argument("--backend", choices=BACKENDS, default="auto", help="ray, process (a local pool) or auto")
    args = parser.parse_args()
    set_threads()
    config = resolve_config(args)
    output = pathlib.Path(args.output or f"runs/parallel_{args.setup}_{args.preset}")
    prepare_output(output, config, args.overwrite, setup=args.setup)
    start = now()
    rows = run_sharing(config, args.setup, STAGES[args.preset], output, workers=args.workers, backend=args.backend)
    finish(output, rows, config, now() - start, plots=not args.no_plots)


if __name__ == "__main__":
    main()
