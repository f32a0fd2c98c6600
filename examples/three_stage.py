"""
Three environments one after the other (Env-A, Env-B, Env-C), then offline distillation of the whole buffer, run by
the paper's protocol: its runner (one ``collect`` job, then the students and the online baselines) and its report.

Usage::

    python examples/three_stage.py                    # quick: HalfCheetah, 10k steps per stage, on a CPU
    python examples/three_stage.py --paper            # OP3: default, hip 0.2 rad, hip 0.2 rad + feet x1.6
    python examples/three_stage.py --seeds 0 1 2 --workers 3 --per-source-actors

It writes the protocol's layout into ``--output`` (default ``runs/three_stage_<preset>``): ``preset.json``, and per seed
``seed_<k>/buffer`` (the lifetime buffer, its sources Env-A, Env-B, Env-C) and one directory per job (``collect``,
``distill_<student>``, ``online_<method>``: ``eval.csv``, ``q_sources.csv``, ``done.json``); then ``scores.csv``,
``report.md`` and the figures ``fig_*.png``. Run again, it skips the jobs that have finished;
``python -m sb3_lifelong.experiments report DIR`` rewrites the report.

The three-stage study with the pre-registered claims (Hopper, more students) is a preset of its study folder::

    S=benchmarks/studies/paper_cpu_three
    python -m sb3_lifelong.experiments run --presets $S/presets.py --preset cpu_three --seed K --output DIR
"""

import argparse
import dataclasses
import pathlib
import sys
from typing import Any

import torch as th

from sb3_lifelong.core.cli import plain_text
from sb3_lifelong.experiments.presets import PRESETS as PACKAGE_PRESETS
from sb3_lifelong.experiments.presets import Preset, check_device
from sb3_lifelong.experiments.report import write_report
from sb3_lifelong.experiments.runner import BACKENDS, run_study

NAMES = ("Env-A", "Env-B", "Env-C")
CPU_STAGES = ({}, {"hip_deformation": 0.3}, {"hip_deformation": 0.3, "friction": 0.1})
#: the students of every preset: the pipeline (CRR exp beta=1) and the imbalance baseline (CRR indicator)
STUDENTS = ("CRR_exp_beta1", "CRR_indicator")
#: the diagnostic student of ``--per-source-actors``: one actor per environment, one shared critic
PER_SOURCE_STUDENT = "CRR_indicator_two_actors"

#: the example's presets: the package's ``cpu``, ``tiny`` and ``paper`` with three stages
PRESETS: dict[str, Preset] = {
    "quick": dataclasses.replace(
        PACKAGE_PRESETS["cpu"],
        stages=CPU_STAGES,
        stage_steps=(10_000, 10_000, 10_000),
        env_names=NAMES,
        students=STUDENTS,
        toy=True,
        note="10k steps per stage: too few to learn Env-A on HalfCheetah (about 60k), so a run shows the pipeline.",
    ),
    "tiny": dataclasses.replace(
        PACKAGE_PRESETS["tiny"],
        stages=CPU_STAGES,
        stage_steps=(200, 200, 200),
        env_names=NAMES,
        students=STUDENTS,
        distill_eval_freq=20,  # a curve of six evaluations per student
    ),
    "paper": dataclasses.replace(
        PACKAGE_PRESETS["paper"],
        stages=("default", "hip_0.2", "hip_0.2+foot_1.6"),
        stage_steps=(200_000, 1_000_000, 1_000_000),
        env_names=NAMES,
        students=STUDENTS,
        note="The paper's scale, three stages (OP3): a GPU machine (--device cuda), or --workers N for the jobs.",
    ),
}


def positive(text: str) -> int:
    """
    :param text: a command-line value
    :return: it as an int of at least 1
    :raises argparse.ArgumentTypeError: when it is not one
    """
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def seed(text: str) -> int:
    """
    :param text: a command-line value
    :return: it as a seed numpy accepts, an int in ``[0, 2**32 - 1]``
    :raises argparse.ArgumentTypeError: when it is not one
    """
    value = int(text)
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"seeds are ints in [0, 2**32 - 1], got {value}")
    return value


def parse_arguments() -> tuple[argparse.Namespace, Preset]:
    """:return: the command line's arguments and the preset they make (exits with a usage error on bad input)"""
    parser = argparse.ArgumentParser(description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="quick",
        help="quick: HalfCheetah on a CPU; paper: the OP3 set-up of the paper (GPU-scale); tiny: seconds, for the tests",
    )
    parser.add_argument("--paper", action="store_const", const="paper", dest="preset", help="same as --preset paper")
    parser.add_argument("--output", default=None, help="output directory (default: runs/three_stage_<preset>)")
    parser.add_argument("--seeds", type=seed, nargs="+", default=[0], help="the seeds (default: 0)")
    parser.add_argument("--workers", type=positive, default=1, help="jobs at a time on this machine (one CPU each)")
    parser.add_argument(
        "--backend", choices=BACKENDS, default="auto", help="ray, process (a local pool), or auto: Ray if installed"
    )
    parser.add_argument("--device", default=None, help="where every model runs: cpu (the default), cuda, cuda:<k> or auto")
    parser.add_argument(
        "--stage-steps", type=positive, nargs=3, default=None, metavar="STEPS", help="environment steps of each stage"
    )
    parser.add_argument("--distill-steps", type=positive, default=None, help="offline updates of every student")
    parser.add_argument("--eval-freq", type=positive, default=None, help="evaluation period of the online methods (steps)")
    parser.add_argument("--distill-eval-freq", type=positive, default=None, help="evaluation period of the students (updates)")
    parser.add_argument("--no-baselines", action="store_true", help="skip the online CRR baselines")
    parser.add_argument(
        "--per-source-actors",
        action="store_true",
        help=f"also distil with one actor per environment and a shared critic (the diagnostic {PER_SOURCE_STUDENT})",
    )
    parser.add_argument("--no-plots", action="store_true", help="write the scores and the report, no figures")
    args = parser.parse_args()
    preset = PRESETS[args.preset]
    if args.device == "auto":
        args.device = "cuda" if th.cuda.is_available() else "cpu"
    changes: dict[str, Any] = dict(
        stage_steps=None if args.stage_steps is None else tuple(args.stage_steps),
        distill_steps=args.distill_steps,
        eval_freq=args.eval_freq,
        distill_eval_freq=args.distill_eval_freq,
        device=args.device,
    )
    changes = {key: value for key, value in changes.items() if value is not None}
    if args.no_baselines:
        changes["online"] = False
    if args.per_source_actors:
        changes["students"] = (*STUDENTS, PER_SOURCE_STUDENT)
    try:
        preset = dataclasses.replace(preset, **changes)
        check_device(preset.device)
    except ValueError as error:  # a device that torch does not know, or that this machine does not have
        parser.error(f"--device: {error}")
    return args, preset


def main() -> int:
    args, preset = parse_arguments()
    output = pathlib.Path(args.output or f"runs/three_stage_{args.preset}")
    try:
        results = run_study(preset, args.seeds, str(output), args.workers, backend=args.backend)
    except ValueError as error:  # e.g. the output holds a study of other settings
        print(f"error: {error}", file=sys.stderr)
        return 2
    failed = sorted(key for key, result in results.items() if result["error"])
    if failed:
        print(f"{len(failed)} job(s) failed or did not run: {', '.join(failed)}", file=sys.stderr)
        return 1
    print(write_report(output, plots=not args.no_plots))
    print(f"wrote {output}/report.md, scores.csv" + ("" if args.no_plots else " and the figures"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
