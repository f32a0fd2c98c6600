"""
Command line of the paper's two-stage protocol (and its three-stage variant: a study's own presets, ``--presets
benchmarks/studies/paper_cpu_three/presets.py --preset cpu_three``).

Run one seed (every job of it that has not finished yet)::

    python -m sb3_lifelong.experiments run --preset cpu --seed 0 --output runs/cpu

Several seeds at once, as a graph of jobs (Ray when installed, on this machine or a cluster; else a process pool)::

    python -m sb3_lifelong.experiments study --preset cpu --seeds 0 1 2 --workers 2 --output runs/cpu
    python -m sb3_lifelong.experiments study --preset cpu --seeds 0 1 2 --address HOST:6379 --output /shared/cpu

Gather the finished seeds into the tables, the pre-registered claims and the figures::

    python -m sb3_lifelong.experiments report runs/cpu --claims benchmarks/studies/paper_cpu/claims.py

List the jobs of a preset and what a seed costs::

    python -m sb3_lifelong.experiments list --preset cpu
"""

import argparse
import dataclasses
import pathlib
import sys
import time
from typing import Any, Literal, Optional

import torch as th

from sb3_lifelong.core.cli import plain_text
from sb3_lifelong.experiments import costs
from sb3_lifelong.experiments.presets import ONLINE, PRESETS, STUDENTS, Job, Preset, check_device, load_presets, resolve_device
from sb3_lifelong.experiments.protocol import record_settings, run_seed
from sb3_lifelong.experiments.report import export_results, write_report
from sb3_lifelong.experiments.runner import BACKENDS, run_study
from sb3_lifelong.experiments.scores import MalformedResultsError

DEVICE_HELP = (
    "where every model runs: cpu (the presets' default: small networks run fastest as one process per core), cuda, "
    "cuda:<k> (larger networks, e.g. the paper preset), or auto (cuda if torch sees a GPU, else cpu; the study records "
    "the one chosen); a study runs on one device"
)
REPEATS_HELP = "train each student this many times per seed (its own student seed each); the report scores the mean"
REUSE_HELP = "reuse this study's collection of the seed (same collection settings): its buffers are linked, only students run"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sb3_lifelong.experiments",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="command", required=True)

    run = commands.add_parser("run", help="run one seed of the protocol")
    run.add_argument(
        "--presets",
        default=None,
        metavar="FILE",
        help="a study's presets file (a presets.py defining PRESETS) whose presets --preset may name too",
    )
    run.add_argument(
        "--preset",
        default="cpu",
        help=f"the protocol's settings: {', '.join(sorted(PRESETS))} or one of --presets (default: cpu)",
    )
    run.add_argument("--seed", type=int, required=True, help="the seed: one seed is one self-contained command")
    run.add_argument("--output", required=True, help="the study's directory (seeds go into seed_<k>/ inside it)")
    run.add_argument(
        "--jobs",
        nargs="+",
        default=None,
        help="only these jobs (collect always runs first if it has not finished); see the 'list' command",
    )
    run.add_argument("--no-online", action="store_true", help="skip the online CRR baselines")
    run.add_argument("--stage-steps", type=int, nargs="+", default=None, help="override the environment steps of each stage")
    run.add_argument("--distill-steps", type=int, default=None, help="override the updates of every student")
    run.add_argument("--student-repeats", type=int, default=None, help=REPEATS_HELP)
    run.add_argument("--collection-from", default=None, metavar="STUDY", help=REUSE_HELP)
    run.add_argument(
        "--until",
        type=int,
        default=None,
        metavar="STEPS",
        help="pause the collection after this many environment steps (a checkpoint); the same command continues it",
    )
    run.add_argument("--progress-bar", action="store_true", help="a progress bar for every job (needs tqdm and rich)")
    run.add_argument("--threads", type=int, default=1, help="torch threads (default 1: more only slows small networks down)")
    run.add_argument("--device", default=None, help=DEVICE_HELP)

    study = commands.add_parser("study", help="several seeds as a parallel graph of jobs (Ray or a process pool)")
    study.add_argument(
        "--presets",
        default=None,
        metavar="FILE",
        help="a study's presets file (a presets.py defining PRESETS) whose presets --preset may name too",
    )
    study.add_argument(
        "--preset",
        default="cpu",
        help=f"the protocol's settings: {', '.join(sorted(PRESETS))} or one of --presets (default: cpu)",
    )
    study.add_argument("--seeds", type=int, nargs="+", required=True, help="the seeds of the study")
    study.add_argument("--output", required=True, help="the study's directory (on a cluster: a path every node sees)")
    study.add_argument("--workers", type=int, default=1, help="jobs at a time on this machine (one CPU each)")
    study.add_argument("--address", default=None, help="a Ray cluster to submit to, HOST:PORT (default: $RAY_ADDRESS)")
    study.add_argument(
        "--backend", choices=BACKENDS, default="auto", help="ray, process (a local pool), or auto: Ray when installed"
    )
    study.add_argument("--jobs", nargs="+", default=None, help="only these jobs of each seed (collect runs first)")
    study.add_argument("--no-online", action="store_true", help="skip the online CRR baselines")
    study.add_argument("--student-repeats", type=int, default=None, help=REPEATS_HELP)
    study.add_argument("--collection-from", default=None, metavar="STUDY", help=REUSE_HELP)
    study.add_argument("--no-report", action="store_true", help="do not write the report at the end")
    study.add_argument("--device", default=None, help=DEVICE_HELP)

    report = commands.add_parser("report", help="tables, claims and figures of every finished seed in a study")
    report.add_argument("output", help="the study's directory")
    report.add_argument("--no-plots", action="store_true", help="tables only")
    report.add_argument(
        "--seeds", type=int, nargs="+", default=None, help="only these seeds, into report_seeds_<k>_<l>.md (no figures)"
    )
    report.add_argument(
        "--claims",
        default=None,
        metavar="FILE",
        help="the study's claims file (a claims.py defining CLAIMS; default: the claims.py in the study's directory)",
    )
    report.add_argument(
        "--drop-malformed",
        action="store_true",
        help="leave out malformed rows of the result files (each named in a warning and in the report) instead of refusing",
    )
    report.add_argument(
        "--export", default=None, help="also copy the small result files (CSV, JSON, MD, PNG; no buffers) into this directory"
    )

    listing = commands.add_parser(
        "list", help="the jobs of one seed, and what a job and a seed took in earlier runs of the preset on this CPU"
    )
    listing.add_argument(
        "--presets",
        default=None,
        metavar="FILE",
        help="a study's presets file (a presets.py defining PRESETS) whose presets --preset may name too",
    )
    listing.add_argument("--preset", default="cpu")
    return parser


#: the seeds numpy accepts
MAX_SEED = 2**32 - 1


def _check_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """
    Refuse, with a message naming the problem and the path (``parser.error``: usage, message, exit status 2), the
    arguments that would otherwise fail later with a traceback, before anything is created.

    :param parser: the command line's parser
    :param args: its parsed arguments
    """
    if args.command in ("run", "study", "list"):
        try:
            available = {**PRESETS, **(load_presets(args.presets) if args.presets else {})}
        except (FileNotFoundError, ValueError) as error:
            parser.error(str(error))
        if args.preset not in available:
            parser.error(
                f"unknown preset {args.preset!r}: the presets are {sorted(available)} (a study's own: --presets FILE)"
            )
        args.settings = available[args.preset]
    seeds = [args.seed] if args.command == "run" else list(args.seeds or []) if args.command in ("study", "report") else []
    bad = [seed for seed in seeds if not 0 <= seed <= MAX_SEED]
    if bad:
        parser.error(f"seeds are ints in [0, 2**32 - 1] (numpy's range), got {bad[0]}")
    if args.command == "run" and args.stage_steps is not None:
        stages = len(args.settings.stages)
        if len(args.stage_steps) != stages:
            parser.error(f"--stage-steps needs one value per stage: preset {args.preset} has {stages}, got {args.stage_steps}")
    if args.command in ("run", "study"):
        _check_counts(parser, args)
        args.device = resolve_device(args.device)  # "auto": this machine's GPU if torch sees one, as the study records
        if args.device is not None:
            try:
                args.settings = dataclasses.replace(args.settings, device=args.device)
            except ValueError as error:
                parser.error(f"--device: {error}")
        try:
            check_device(args.settings.device)
        except ValueError as error:
            parser.error(f"preset {args.preset}: {error}")
        output = pathlib.Path(args.output)
        if output.exists() and not output.is_dir():
            parser.error(f"--output {output} exists and is not a directory: give the study's directory (created if missing)")
    if args.command == "report":
        output = pathlib.Path(args.output)
        if not output.is_dir():
            parser.error(f"{output}: no such directory (give the --output directory of a study)")
        if not (output / "preset.json").is_file():
            parser.error(
                f"{output} holds no study (no preset.json): give the --output directory of 'run' or 'study', once a seed "
                "has finished its collect job"
            )


def _report(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """The ``report`` command: the study's tables, claims and figures (exit status 1 on a refusal, with its message)."""
    malformed: Literal["refuse", "drop"] = "drop" if args.drop_malformed else "refuse"
    try:
        text = write_report(
            pathlib.Path(args.output), plots=not args.no_plots, seeds=args.seeds, claims=args.claims, malformed=malformed
        )
    except FileNotFoundError as error:  # e.g. no seed has finished its collect job yet
        parser.exit(1, f"{parser.prog} report: error: {error}\n")
    except MalformedResultsError as error:  # a result file cut in the middle of a row, say: nothing is written
        parser.exit(1, f"{parser.prog} report: error: {error}\n")
    print(text)
    if args.seeds is None:
        print(f"wrote {args.output}/report.md, scores.csv, claims.csv and the figures")
    else:
        print(f"wrote {args.output}/report_seeds_*.md, scores_seeds_*.csv, claims_seeds_*.csv (seeds {args.seeds})")
    if args.export:
        copied = export_results(pathlib.Path(args.output), pathlib.Path(args.export))
        print(f"copied {len(copied)} result files into {args.export}")
    return 0


def _check_counts(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """
    Refuse counts below 1 and job names the preset does not have, before anything is written (a refused command leaves
    the output as it was, so the corrected command is not taken for a study of other settings).

    :param parser: the command line's parser
    :param args: its parsed arguments (``args.settings``: the preset)
    """
    counts = {
        "--stage-steps": getattr(args, "stage_steps", None) or [],
        "--distill-steps": [getattr(args, "distill_steps", None)],
        "--student-repeats": [args.student_repeats],
        "--until": [getattr(args, "until", None)],
        "--threads": [getattr(args, "threads", None)],
        "--workers": [getattr(args, "workers", None)],
    }
    for flag, values in counts.items():
        bad = [value for value in values if value is not None and value < 1]
        if bad:
            parser.error(f"{flag} must be at least 1, got {bad[0]}")
    if args.jobs:
        preset = args.settings
        if args.student_repeats is not None:
            preset = dataclasses.replace(preset, student_repeats=args.student_repeats)
        known = preset.jobs()
        unknown = [job for job in args.jobs if job not in known]
        if unknown:
            parser.error(f"unknown job {unknown[0]!r} for preset {args.preset}: its jobs are {known} (see the 'list' command)")


#: what ``list`` says of the jobs without a name of their own
UNNAMED_ABOUT = {
    "collect": "MPO through every stage",
    "collect_first": "the first robot: MPO in Env-A, then in Env-B (a sharing study)",
    "collect_agent2": "the second robot: MPO in Env-C, side by side with the first (a copy at the switch, or a new agent)",
    "share": "the two robots' buffers merged into the one the students distill",
}


def main(argv: Optional[list[str]] = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    _check_arguments(parser, args)
    if args.command == "list":
        preset = args.settings
        print(f"preset {args.preset}: {preset.env_id}, stages {list(preset.stages)}, steps {list(preset.stage_steps)}")
        times = costs.measured(preset.describe())
        for job in preset.jobs():
            parsed = Job.parse(job)
            if parsed.kind == "distill":
                repeat = parsed.repeat
                about = STUDENTS[parsed.name].about + (f" (repeat {repeat}, its own student seed)" if repeat else "")
            elif parsed.kind == "online":
                about = str(ONLINE[parsed.name])
            else:
                about = UNNAMED_ABOUT[parsed.kind if preset.sharing is None or parsed.kind != "collect" else "collect_first"]
            seconds = costs.estimate(job, times)
            print(f"  {job:<34} {'' if seconds is None else f'[{costs.minutes(seconds)}] '}{about}")
        print(_measured_cost(preset, times))
        if preset.minutes_per_seed is not None:
            print(f"one seed took {preset.minutes_per_seed:.0f} min on one core of the reference machine")
        if preset.note:
            print(preset.note)
        return 0
    if args.command == "report":
        return _report(parser, args)

    if args.command == "study":
        preset = args.settings
        if args.student_repeats is not None:
            preset = dataclasses.replace(preset, student_repeats=args.student_repeats)
        jobs = args.jobs or [j for j in preset.jobs() if not (args.no_online and Job.parse(j).kind == "online")]
        _check_study(parser, preset, pathlib.Path(args.output))
        start = time.perf_counter()
        reuse = args.collection_from
        results = run_study(
            preset, args.seeds, args.output, args.workers, args.address, args.backend, jobs, collection_from=reuse
        )
        failed = sorted(key for key, result in results.items() if result["error"])
        ran = sum(result["ran"] for result in results.values())
        minutes = (time.perf_counter() - start) / 60
        print(
            f"Study: {ran} job(s) ran, {len(results) - ran - len(failed)} were done already, {len(failed)} failed or not run "
            f"({minutes:.1f} min){': ' + ', '.join(failed) if failed else ''}"
        )
        if not args.no_report and any(result["ran"] or not result["error"] for result in results.values()):
            try:
                write_report(pathlib.Path(args.output))
            except MalformedResultsError as error:
                print(f"No report: {error}", file=sys.stderr)
                return 1
            print(f"Report: {args.output}/report.md")
        return 1 if failed else 0

    th.set_num_threads(args.threads)
    preset = args.settings
    changes: dict[str, Any] = {}
    if args.stage_steps is not None:
        changes["stage_steps"] = tuple(args.stage_steps)
    if args.distill_steps is not None:
        changes["distill_steps"] = args.distill_steps
    if args.student_repeats is not None:
        changes["student_repeats"] = args.student_repeats
    if changes:
        preset = dataclasses.replace(preset, **changes)
    every = [j for j in preset.jobs() if not (args.no_online and Job.parse(j).kind == "online")]
    jobs = args.jobs if args.jobs is not None else every
    output = pathlib.Path(args.output)
    online = sum(Job.parse(job).kind == "online" for job in jobs)
    steps = sum(preset.stage_steps) + online * sum(preset.stage_steps[1:])
    print(
        f"{len(preset.env_names)}-stage protocol, preset {args.preset}: {preset.env_id}, {' -> '.join(preset.env_names)}, "
        f"steps {list(preset.stage_steps)}, {len(set(jobs) | {'collect'})} jobs for seed {args.seed} "
        f"({steps:,} environment steps online, {preset.distill_steps:,} updates per student)"
    )
    if preset.note:
        print(preset.note)
    if preset.minutes_per_seed is not None and not changes:
        print(f"expect about {preset.minutes_per_seed:.0f} min on one core (measured on a 2-core AMD EPYC machine)")
    _check_study(parser, preset, output)
    start = time.perf_counter()
    ran = run_seed(
        preset,
        args.seed,
        output,
        jobs=jobs,
        progress_bar=args.progress_bar,
        log=lambda m: print(m, flush=True),
        collection_from=None if args.collection_from is None else pathlib.Path(args.collection_from),
        until=args.until,
    )
    print(_closing(output, args.seed, len(ran), (time.perf_counter() - start) / 60))
    return 0


def _check_study(parser: argparse.ArgumentParser, preset: Preset, output: pathlib.Path) -> None:
    """Record the study's settings, or exit with the reason when ``output`` holds a study of other settings."""
    try:
        record_settings(preset, output)
    except ValueError as error:
        parser.exit(2, f"{parser.prog}: error: {error}\n")


def _measured_cost(preset: Preset, times: dict[str, list[float]]) -> str:
    """:return: what ``list`` says a seed of ``preset`` costs on this kind of CPU, from the cost log of earlier runs"""
    where = costs.costs_file()
    if not times:
        return (
            f"No cost measured yet for these settings on this CPU ({costs.cpu_kind()}): "
            + (f"each finished job records its time in {where}" if where is not None else "the cost log is off")
            + f" (${costs.COSTS_VARIABLE} names it)"
        )
    runs = sum(len(values) for values in times.values())
    return (
        f"[time]: the median of earlier runs of these settings on this CPU ({costs.cpu_kind()}; {runs} job(s) in "
        f"{where}). A seed: {costs.remaining(preset.jobs(), times, left='')}"
    )


def _closing(output: pathlib.Path, seed: int, ran: int, minutes: float) -> str:
    """:return: what ``run`` prints at the end: what finished, where, and what comes next"""
    run_dir = output / f"seed_{seed}"
    lines = [f"Seed {seed}: {ran} job(s) finished in {minutes:.1f} min; results in {run_dir}"]
    student = run_dir / "distill_CRR_exp_beta1" / "student.zip"
    if student.exists():
        lines.append(f"The distilled policy (CRR exp beta=1): sb3_lifelong.CRR.load('{student}')")
    if (run_dir / "collect" / "done.json").exists():
        lines.append(f"Tables, claims and figures: python -m sb3_lifelong.experiments report {output}")
    else:  # paused (--until): nothing to report yet
        lines.append("The collection is paused: the same command (with a later --until, or none) continues it")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
