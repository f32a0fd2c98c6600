"""
The pipeline on the forgetting screen's setting: does distilling the lifetime buffer get back the Env-A that MPO loses?

Pre-registered in ``README.md`` beside this script (seeds, the rule that continues a seed, claims, readings) before any
run. A seed runs in three commands, each one self-contained and continuing where it stopped::

    # 1. Stage 1 (Env-A, 60k steps, in 20k parts), then whether Env-A was learnt (the screen's rule)
    OMP_NUM_THREADS=1 python benchmarks/studies/pipeline_forgetting/pipeline.py stage1 --seed 10 --runs /work/runs
    # 2. Env-B (180k steps, in parts) from that Stage-1, only when Env-A was learnt
    OMP_NUM_THREADS=1 python benchmarks/studies/pipeline_forgetting/pipeline.py env-b --seed 10 --runs /work/runs \
        --candidate cheetah_back_reversed
    # 3. the online CRR baseline and the students (two student seeds each), through the experiments' study runner
    OMP_NUM_THREADS=1 python benchmarks/studies/pipeline_forgetting/pipeline.py rest --seed 10 --runs /work/runs \
        --candidate cheetah_back_reversed
    python benchmarks/studies/pipeline_forgetting/pipeline.py progress --runs /work/runs

Stage 1 does not depend on the candidate (the screen's design: the appended parameter column is 0 in Env-A whatever the
parameter), so it runs before the screen has chosen. Small results go to ``results/`` beside this script; buffers
and agents stay in ``--runs``.
"""

import argparse
import functools
import importlib.util
import json
import pathlib
import subprocess
import sys
import time
from typing import Any

STUDY = pathlib.Path(__file__).resolve().parent
RESULTS = STUDY / "results"
PRESETS_FILE = STUDY / "presets.py"
SCREEN_FILE = STUDY.parent / "forgetting_screen" / "screen.py"

#: the seeds, in the order they are started: fresh (the screen used 0-3); a seed continues past Env-A only when it
#: learnt Env-A, and seeds are added in this order until FIVE have (README)
SEEDS = tuple(range(10, 22))
LEARNT_SEEDS_WANTED = 5
#: the jobs of a seed after its collection (online CRR exp beta=1 and the two students, each trained twice)
REST_JOBS = (
    "online_CRR_exp_beta1",
    "distill_CRR_exp_beta1",
    "distill_CRR_indicator",
    "distill_CRR_exp_beta1__r1",
    "distill_CRR_indicator__r1",
)


def _load(path: pathlib.Path, name: str) -> Any:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@functools.cache
def screen() -> Any:
    """The forgetting screen's script (its collector, parts and Stage-1 rule are this study's)."""
    return _load(SCREEN_FILE, "forgetting_screen_script")


@functools.cache
def presets() -> dict[str, Any]:
    from sb3_lifelong.experiments.presets import load_presets

    return load_presets(PRESETS_FILE)


def study_preset(candidate: str) -> Any:
    name = f"pipeline_{candidate}"
    found = presets()
    if name not in found:
        raise SystemExit(f"no candidate {candidate!r}: one of {sorted(n.removeprefix('pipeline_') for n in found)}")
    return found[name]


def stage1_dir(runs: pathlib.Path, seed: int) -> pathlib.Path:
    return runs / "pipeline_forgetting" / "stage1" / f"seed_{seed}"


def study_dir(runs: pathlib.Path, candidate: str) -> pathlib.Path:
    return runs / "pipeline_forgetting" / candidate


def stage1_reading(eval_csv: pathlib.Path, switch: int) -> dict[str, Any]:
    """
    Whether Env-A was learnt at the switch, by the screen's rule: the mean of the last 5 Env-A evaluations at least
    1500 and their spread (sd / mean) at most 0.2.
    """
    rules = screen()
    evals = rules.last_evaluations(eval_csv, "Env-A", switch)
    threshold = rules.ROBOTS["cheetah"].threshold
    mean, spread, learnt = rules.stage1_level(evals, threshold)
    return dict(
        evals=evals,
        mean=mean,
        spread=spread,
        threshold=threshold,
        max_spread=rules.MAX_SPREAD,
        learnt=learnt and len(evals) == rules.LAST,
    )


def run_stage1(args: argparse.Namespace) -> dict[str, Any]:
    """Stage 1 of a seed (any candidate's preset: Env-A is the same), then its reading, written to ``results/``."""
    rules = screen()
    settings = study_preset("cheetah_back_reversed")  # Env-A and its collector: the same for every candidate
    switch = settings.stage_steps[0]
    run_dir = stage1_dir(pathlib.Path(args.runs), args.seed)
    if not (run_dir / "collect" / "stage1.zip").exists():
        rules.collect_in_parts(settings, args.seed, run_dir, switch)
    reading = dict(seed=args.seed, **stage1_reading(run_dir / "collect" / "eval.csv", switch))
    out = pathlib.Path(args.results) / "stage1" / f"seed_{args.seed}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(reading, indent=1) + "\n")
    (out.parent / f"seed_{args.seed}_eval.csv").write_text((run_dir / "collect" / "eval.csv").read_text())
    print(f"seed {args.seed}: Env-A {'learnt' if reading['learnt'] else 'not learnt'} "
          f"(last 5: {reading['mean']:.0f}, spread {reading['spread']:.2f}) -> {out}", flush=True)  # fmt: skip
    return reading


def learnt(results: pathlib.Path, seed: int) -> bool:
    record = results / "stage1" / f"seed_{seed}.json"
    if not record.exists():
        raise SystemExit(f"seed {seed}: no Stage-1 reading at {record}: run `stage1 --seed {seed}` first")
    return bool(json.loads(record.read_text())["learnt"])


def run_env_b(args: argparse.Namespace) -> None:
    """Env-B of a seed whose Stage-1 learnt Env-A: the Stage-1 adopted into the study, then collected in parts."""
    from sb3_lifelong.experiments.branching import adopt_stage1
    from sb3_lifelong.experiments.collection import finished_collection

    if not learnt(pathlib.Path(args.results), args.seed):
        raise SystemExit(f"seed {args.seed}: Env-A was not learnt at the switch; by the README it does not continue")
    settings = study_preset(args.candidate)
    run_dir = study_dir(pathlib.Path(args.runs), args.candidate) / f"seed_{args.seed}"
    if (run_dir / "collect" / "done.json").exists():
        print(f"seed {args.seed}: the collection is done ({run_dir / 'collect' / 'done.json'})", flush=True)
        return
    if not run_dir.exists():
        adopt_stage1(settings, stage1_dir(pathlib.Path(args.runs), args.seed), run_dir)
    start = time.perf_counter()
    if not finished_collection(settings, run_dir):
        screen().collect_in_parts(settings, args.seed, run_dir, sum(settings.stage_steps))
    mark_collection_done(settings, args.seed, run_dir, time.perf_counter() - start)


def mark_collection_done(settings: Any, seed: int, run_dir: pathlib.Path, seconds: float) -> None:
    """
    Write the finished collection's ``done.json`` as the experiments' runner writes it, so that the study's other
    jobs (``rest``) start from it, and release its directory. The parts above run the collector directly, which
    does not write it.

    :param seconds: the seconds of the call that finished it (earlier parts are not counted)
    :raises SystemExit: the collection has not finished (no final checkpoint, no buffer holding every step)
    """
    from sb3_lifelong.core.atomic import write_json_atomic
    from sb3_lifelong.experiments.collection import finished_collection
    from sb3_lifelong.experiments.ownership import release_directory

    evidence = finished_collection(settings, run_dir)
    if not evidence:
        raise SystemExit(f"seed {seed}: the collection in {run_dir} has not finished: run `env-b --seed {seed}` again")
    record = dict(job="collect", seed=seed, seconds=seconds, preset=settings.describe(), finished_by=evidence)
    write_json_atomic(run_dir / "collect" / "done.json", record)
    release_directory(run_dir / "collect")
    print(f"seed {seed}: collection done -> {run_dir / 'collect' / 'done.json'}", flush=True)


def run_rest(args: argparse.Namespace) -> int:
    """The online baseline and the students of a seed whose collection is done (the experiments' study runner)."""
    output = study_dir(pathlib.Path(args.runs), args.candidate)
    if not (output / f"seed_{args.seed}" / "collect" / "done.json").exists():
        raise SystemExit(f"seed {args.seed}: the collection is not done: run `env-b --seed {args.seed}` first")
    command = [
        sys.executable, "-m", "sb3_lifelong.experiments", "study", "--presets", str(PRESETS_FILE),
        "--preset", f"pipeline_{args.candidate}", "--seeds", str(args.seed), "--output", str(output),
        "--workers", "1", "--backend", "process", "--student-repeats", "2", "--no-report", "--jobs", "collect", *REST_JOBS,
    ]  # fmt: skip
    print(" ".join(command), flush=True)
    return subprocess.call(command)


def progress(args: argparse.Namespace) -> list[str]:
    """Where each seed stands."""
    runs, results = pathlib.Path(args.runs), pathlib.Path(args.results)
    rules = screen()
    lines = []
    for seed in SEEDS:
        record = results / "stage1" / f"seed_{seed}.json"
        if record.exists():
            state = "Env-A learnt" if json.loads(record.read_text())["learnt"] else "Env-A not learnt (stops here)"
        else:
            at = rules.paused_at(stage1_dir(runs, seed))
            state = f"Stage 1 paused at {at:,}" if at else "not started"
        for candidate in sorted(n.removeprefix("pipeline_") for n in presets()):
            seed_dir = study_dir(runs, candidate) / f"seed_{seed}"
            if seed_dir.exists():
                done = sorted(p.parent.name for p in seed_dir.glob("*/done.json"))
                at = rules.paused_at(seed_dir)
                collection = (
                    "collected" if "collect" in done else f"collection paused at {at:,}" if at else "collection not started"
                )
                state += f"; {candidate}: {collection}, done: {', '.join(done) or '-'}"
        lines.append(f"seed {seed}: {state}")
    print("\n".join(lines))
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("stage1", "env-b", "rest", "progress"):
        command = sub.add_parser(name)
        command.add_argument("--runs", default="runs", help="where buffers and agents go")
        command.add_argument("--results", default=str(RESULTS), help="where the small results go")
        if name != "progress":
            command.add_argument("--seed", type=int, required=True)
        if name in ("env-b", "rest"):
            command.add_argument("--candidate", required=True, help="the screen's selection")
    args = parser.parse_args()
    handlers = {"stage1": run_stage1, "env-b": run_env_b, "rest": run_rest, "progress": progress}
    result = handlers[args.command](args)
    sys.exit(result if isinstance(result, int) else 0)


if __name__ == "__main__":
    main()
