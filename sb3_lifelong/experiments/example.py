"""
The command line of an example that runs a study of its own presets (``examples/three_stage.py``,
``examples/continuous_drift.py``, ``examples/parallel_sharing.py``): one parser and one ``main`` over the runner
(``runner.run_study``) and the report (:func:`~sb3_lifelong.experiments.write_report`),
so that every example writes the protocol's layout and report.

An example defines its presets by name (the same number of stages each) and calls
:func:`~sb3_lifelong.experiments.example.run_example`::

    sys.exit(run_example(PRESETS, __doc__, "three_stage"))
"""

import argparse
import dataclasses
import pathlib
import sys
from collections.abc import Mapping, Sequence
from typing import Any, Optional

from sb3_lifelong.core.cli import plain_text
from sb3_lifelong.experiments.presets import Preset, check_device, resolve_device
from sb3_lifelong.experiments.report import write_report
from sb3_lifelong.experiments.runner import BACKENDS, run_study

__all__ = ["example_arguments", "positive", "run_example", "seed"]


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


def example_arguments(
    presets: Mapping[str, Preset],
    doc: Optional[str],
    name: str,
    per_source_student: Optional[str] = None,
    argv: Optional[Sequence[str]] = None,
    setups: Optional[Mapping[str, Mapping[str, Any]]] = None,
    workers: int = 1,
) -> tuple[argparse.Namespace, Preset]:
    """
    :param presets: the example's presets by name (``quick``, the default; ``paper``, also ``--paper``; ``tiny``, for
        the tests), each with the same number of stages
    :param doc: the example's docstring (its ``--help``)
    :param name: the example's name: the default output is ``runs/<name>_<preset>`` (``runs/<name>_<setup>_<preset>``
        with ``setups``)
    :param per_source_student: a student that ``--per-source-actors`` adds to the preset's (None: no such flag)
    :param argv: the arguments (None: the command line's)
    :param setups: the example's set-ups by name (``--setup``, the first the default), each the preset settings it
        changes (None: no such flag)
    :param workers: the default of ``--workers``
    :return: the arguments and the preset they make (exits with a usage error on bad input, before anything runs)
    """
    stage_counts = {len(preset.stages) for preset in presets.values()}
    if len(stage_counts) != 1 or "quick" not in presets:
        raise ValueError(f"an example's presets have one number of stages and a 'quick' one, got {dict(presets)}")
    stages = stage_counts.pop()
    parser = argparse.ArgumentParser(description=plain_text(doc or ""), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--preset",
        choices=sorted(presets),
        default="quick",
        help="quick: HalfCheetah on a CPU; paper: the OP3 set-up of the paper (GPU-scale); tiny: seconds, for the tests",
    )
    if "paper" in presets:
        parser.add_argument("--paper", action="store_const", const="paper", dest="preset", help="same as --preset paper")
    if setups:
        parser.add_argument("--setup", choices=list(setups), default=next(iter(setups)), help="the set-up (see above)")
    where = f"runs/{name}_<setup>_<preset>" if setups else f"runs/{name}_<preset>"
    parser.add_argument("--output", default=None, help=f"output directory (default: {where})")
    parser.add_argument("--seeds", type=seed, nargs="+", default=[0], help="the seeds (default: 0)")
    parser.add_argument("--workers", type=positive, default=workers, help="jobs at a time on this machine (one CPU each)")
    parser.add_argument(
        "--backend", choices=BACKENDS, default="auto", help="ray, process (a local pool), or auto: Ray if installed"
    )
    parser.add_argument("--device", default=None, help="where every model runs: cpu (the default), cuda, cuda:<k> or auto")
    parser.add_argument(
        "--stage-steps", type=positive, nargs=stages, default=None, metavar="STEPS", help="environment steps of each stage"
    )
    parser.add_argument("--distill-steps", type=positive, default=None, help="offline updates of every student")
    parser.add_argument("--eval-freq", type=positive, default=None, help="evaluation period of the online methods (steps)")
    parser.add_argument("--distill-eval-freq", type=positive, default=None, help="evaluation period of the students (updates)")
    if any(preset.online for preset in presets.values()):  # (a sharing study has none)
        parser.add_argument("--no-baselines", action="store_true", help="skip the online CRR baselines")
    if per_source_student is not None:
        parser.add_argument(
            "--per-source-actors",
            action="store_true",
            help=f"also distil with one actor per environment and a shared critic (the diagnostic {per_source_student})",
        )
    parser.add_argument("--no-plots", action="store_true", help="write the scores and the report, no figures")
    args = parser.parse_args(argv)
    preset = presets[args.preset]
    args.device = resolve_device(args.device)
    changes: dict[str, Any] = dict(
        stage_steps=None if args.stage_steps is None else tuple(args.stage_steps),
        distill_steps=args.distill_steps,
        eval_freq=args.eval_freq,
        distill_eval_freq=args.distill_eval_freq,
        device=args.device,
    )
    changes = {key: value for key, value in changes.items() if value is not None}
    if setups:
        changes.update(setups[args.setup])
    if getattr(args, "no_baselines", False):
        changes["online"] = False
    if getattr(args, "per_source_actors", False):
        changes["students"] = (*(preset.students or ()), per_source_student)
    try:
        preset = dataclasses.replace(preset, **changes)
        check_device(preset.device)
    except ValueError as error:  # a device that torch does not know, or that this machine does not have
        parser.error(f"--device: {error}")
    return args, preset


def run_example(
    presets: Mapping[str, Preset],
    doc: Optional[str],
    name: str,
    per_source_student: Optional[str] = None,
    argv: Optional[Sequence[str]] = None,
    setups: Optional[Mapping[str, Mapping[str, Any]]] = None,
    workers: int = 1,
) -> int:
    """
    Run an example: its preset's jobs for every seed (those already finished are skipped), then the report.

    :param presets: the example's presets (see :func:`example_arguments`)
    :param doc: the example's docstring
    :param name: the example's name
    :param per_source_student: a student that ``--per-source-actors`` adds (None: no such flag)
    :param argv: the arguments (None: the command line's)
    :param setups: the example's set-ups (see :func:`example_arguments`)
    :param workers: the default of ``--workers``
    :return: the exit status: 0 done, 1 a job failed, 2 the output holds a study of other settings
    """
    args, preset = example_arguments(presets, doc, name, per_source_student, argv, setups, workers)
    default = f"runs/{name}_{args.setup}_{args.preset}" if setups else f"runs/{name}_{args.preset}"
    output = pathlib.Path(args.output or default)
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
