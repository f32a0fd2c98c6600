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
    # 4. once every seed is done: the experiments' report (the engine's verdicts), then the registered readings
    python -m sb3_lifelong.experiments report /work/runs/pipeline_forgetting/cheetah_back_reversed \
        --claims benchmarks/studies/pipeline_forgetting/claims.py
    python benchmarks/studies/pipeline_forgetting/pipeline.py summary --runs /work/runs --candidate cheetah_back_reversed

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

from sb3_lifelong.experiments.collection import collect_in_parts, paused_at

STUDY = pathlib.Path(__file__).resolve().parent
RESULTS = STUDY / "results"
PRESETS_FILE = STUDY / "presets.py"
#: the screen's readings and parts: last-LAST means, collections in parts of PART steps
LAST = 5
PART = 20_000

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
    """This study's own claims file, as a module (its thresholds and readings beside its claims)."""
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _print(message: str) -> None:
    print(message, flush=True)


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
    Whether Env-A was learnt at the switch, by the screen's rule (the runner's ``switch_reading``: the last 5 Env-A
    evaluations' mean at least the preset's ``env_a_learnt``, HalfCheetah's 1500, their spread at most 0.2).
    """
    from sb3_lifelong.experiments.scores import switch_reading

    settings = study_preset("cheetah_back_reversed")  # the thresholds: the same for every candidate
    return switch_reading(eval_csv, switch, settings.env_a_learnt, settings.max_switch_spread, LAST)


def run_stage1(args: argparse.Namespace) -> dict[str, Any]:
    """Stage 1 of a seed (any candidate's preset: Env-A is the same), then its reading, written to ``results/``."""
    settings = study_preset("cheetah_back_reversed")  # Env-A and its collector: the same for every candidate
    switch = settings.stage_steps[0]
    run_dir = stage1_dir(pathlib.Path(args.runs), args.seed)
    if not (run_dir / "collect" / "stage1.zip").exists():
        collect_in_parts(settings, args.seed, run_dir, switch, PART, log=_print)
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
        collect_in_parts(settings, args.seed, run_dir, sum(settings.stage_steps), PART, log=_print)
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
    from sb3_lifelong.experiments.jobs import release_directory

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
    lines = []
    for seed in SEEDS:
        record = results / "stage1" / f"seed_{seed}.json"
        if record.exists():
            state = "Env-A learnt" if json.loads(record.read_text())["learnt"] else "Env-A not learnt (stops here)"
        else:
            at = paused_at(stage1_dir(runs, seed))
            state = f"Stage 1 paused at {at:,}" if at else "not started"
        for candidate in sorted(n.removeprefix("pipeline_") for n in presets()):
            seed_dir = study_dir(runs, candidate) / f"seed_{seed}"
            if seed_dir.exists():
                done = sorted(p.parent.name for p in seed_dir.glob("*/done.json"))
                at = paused_at(seed_dir)
                collection = (
                    "collected" if "collect" in done else f"collection paused at {at:,}" if at else "collection not started"
                )
                state += f"; {candidate}: {collection}, done: {', '.join(done) or '-'}"
        lines.append(f"seed {seed}: {state}")
    print("\n".join(lines))
    return lines


# ------------------------------------------------------------------------------------------------ the summary
#: the students: exp, beta = 1 (the pipeline), and the indicator (the paper's baseline)
STUDENTS = ("CRR_exp_beta1", "CRR_indicator")
ENVS = ("Env-A", "Env-B")


def _stats(values: dict[int, float]) -> dict[str, Any]:
    """A per-seed series: its values, mean, sd and 95 % BCa interval (the report's :func:`bootstrap_ci`)."""
    import numpy as np

    from sb3_lifelong.experiments.statistics import bootstrap_ci

    finite = {seed: v for seed, v in sorted(values.items()) if np.isfinite(v)}
    data = list(finite.values())
    low, high = bootstrap_ci(data) if data else (float("nan"), float("nan"))
    return dict(
        values=finite,
        mean=float(np.mean(data)) if data else float("nan"),
        sd=float(np.std(data, ddof=1)) if len(data) > 1 else float("nan"),
        low=float(low),
        high=float(high),
    )


def claim_readings(study: Any) -> list[dict[str, Any]]:
    """
    Each registered claim read as the README says: its series over the testable seeds, the engine's verdict (the
    criterion on the mean) and the study's reading from the series' 95 % BCa interval (``claims.reading``).

    :param study: the study's scores (:func:`sb3_lifelong.experiments.scores.load_study`)
    :return: one row per claim
    """
    from sb3_lifelong.experiments.claims import PRECONDITIONS, evaluate_claims, testable_seeds

    claims = _load(STUDY / "claims.py", "pipeline_forgetting_claims")
    verdicts = {row["claim"]: row["verdict"] for row in evaluate_claims(study, claims.CLAIMS)}
    checks = {name: precondition.check(study) for name, precondition in PRECONDITIONS.items()}
    rows = []
    for claim in claims.CLAIMS:
        ((name, values),) = claim.values(study).items()  # each claim is one series (claims.py)
        testable = testable_seeds(study, claim, checks)
        if testable is not None:
            values = {seed: v for seed, v in values.items() if seed in testable[0]}
        stats = _stats(values)
        threshold, above = claims.THRESHOLDS[claim.name]
        verdict = verdicts[claim.name]
        rows.append(
            dict(claim=claim.name, series=name, threshold=threshold, claimed_side="above" if above else "below",
                 verdict=verdict, reading=claims.reading(claim.name, stats["low"], stats["high"], verdict), **stats)
        )  # fmt: skip
    return rows


def students_beside(study: Any) -> list[dict[str, Any]]:
    """
    Reported beside the claims: each student over MPO's end agent in each environment, in C3's terms (the indicator
    student read against C3's thresholds too, for the record), and the exp student minus the indicator student.
    """
    from sb3_lifelong.experiments.claims import ratio

    claims = _load(STUDY / "claims.py", "pipeline_forgetting_claims")
    rows = []
    for env, claim in zip(ENVS, [c.name for c in claims.CLAIMS if c.name.startswith("C3")]):
        for student in STUDENTS:
            stats = _stats(ratio(study.score(student, env), study.score("MPO", env)))
            rows.append(dict(series=f"{student} / MPO ({env})", reading=claims.reading(claim, stats["low"], stats["high"]),
                             **stats))  # fmt: skip
        exp, indicator = (study.score(student, env) for student in STUDENTS)
        stats = _stats({seed: exp[seed] - indicator[seed] for seed in exp if seed in indicator})  # paired by seed
        rows.append(dict(series=f"exp - indicator ({env})", reading="-", **stats))
    return rows


def training_scores(output: pathlib.Path, seeds: list[int]) -> Any:
    """:return: every student training's score (the mean of its last evaluations, as the report scores a repeat)"""
    import pandas as pd

    from sb3_lifelong.experiments.scores import STUDENT_LAST, last_mean, read_eval

    rows = []
    for seed in seeds:
        for student in STUDENTS:
            for repeat, job in enumerate((f"distill_{student}", f"distill_{student}__r1")):
                frame = read_eval(output, seed, job)
                if frame is not None:
                    for env in ENVS:
                        rows.append(dict(seed=seed, student=student, repeat=repeat, env=env,
                                         score=last_mean(frame, env, STUDENT_LAST)))  # fmt: skip
    return pd.DataFrame(rows, columns=["seed", "student", "repeat", "env", "score"])


def student_noise(trainings: Any) -> list[dict[str, Any]]:
    """
    The students' noise apart from the buffers': per student and environment, the sd between a seed's two student
    seeds (pooled over seeds: the root of the mean within-seed variance) against the sd over seeds of the two-training
    means.
    """
    import numpy as np

    rows = []
    for (student, env), part in trainings.groupby(["student", "env"], sort=True):
        complete = part.groupby("seed").filter(lambda group: len(group) == 2)
        per_seed = complete.groupby("seed")["score"]
        within = float(np.sqrt(per_seed.var(ddof=1).mean())) if len(complete) else float("nan")
        between = float(per_seed.mean().std(ddof=1)) if per_seed.ngroups > 1 else float("nan")
        rows.append(dict(student=student, env=env, seeds=per_seed.ngroups, within_sd=within, between_sd=between))
    return rows


def agents(output: pathlib.Path, seed: int, cache: pathlib.Path, episodes: int = 10) -> dict[str, Any]:
    """
    MPO's frozen Stage-1 agent against its end agent on the same seeded episodes (the screen's ``measure_agent``),
    measured once and kept in ``cache``.

    :param output: the study's directory
    :param seed: the seed
    :param cache: the JSON file of this seed's measurement
    :param episodes: episodes per environment
    """
    if cache.exists():
        return json.loads(cache.read_text())
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.experiments.branching import measure_agent

    settings = study_preset(output.name)
    run_dir = output / f"seed_{seed}"
    out: dict[str, Any] = dict(seed=seed, episodes=episodes)
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        for name in ("stage1", "final"):
            out.update(measure_agent(name, run_dir, buffer, settings, seed, episodes))
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps(out, indent=1) + "\n")
    return out


def _cell(stats: dict[str, Any], digits: int) -> str:
    def number(value: float) -> str:
        return f"{value:+.{digits}f}"

    return f"{number(stats['mean'])} +- {stats['sd']:.{digits}f} [{number(stats['low'])}, {number(stats['high'])}]"


def _per_seed(values: dict[int, float], digits: int) -> str:
    return ", ".join(f"s{seed}: {value:.{digits}f}" for seed, value in values.items())


def summary(args: argparse.Namespace) -> str:
    """
    The registered readings and what is reported beside them, from a study whose seeds are done:
    ``results/summary.md``, ``results/readings.csv``, ``results/trainings.csv`` and ``results/agents/seed_<k>.json``.
    Run the experiments' report first (README, "How to run"): the summary reads the same scores.
    """
    import pandas as pd

    from sb3_lifelong.experiments.scores import load_study

    output, results = study_dir(pathlib.Path(args.runs), args.candidate), pathlib.Path(args.results)
    study = load_study(output)
    complete = [s for s in study.seeds if all((output / f"seed_{s}" / job / "done.json").exists() for job in REST_JOBS)]
    if complete != study.seeds:
        raise SystemExit(f"seeds {sorted(set(study.seeds) - set(complete))} have not finished `rest`: run it first")
    readings, beside = claim_readings(study), students_beside(study)
    trainings = training_scores(output, study.seeds)
    noise = student_noise(trainings)
    measured = [agents(output, seed, results / "agents" / f"seed_{seed}.json") for seed in study.seeds]
    lines = [
        "# The pipeline on `" + args.candidate + "`: the registered readings (generated by `pipeline.py summary`)",
        "",
        f"Seeds: {study.seeds}. Each claim is read from the 95 % BCa interval of its series' mean over the testable "
        'seeds (README, "How each claim reads"): *holds* when the whole interval is on the claimed side of the '
        "threshold, *fails* when it is on the other side, *inconclusive* otherwise. The engine's verdict is the "
        "criterion on the mean alone.",
        "",
        "| claim | series: per seed | mean +- sd [95 % BCa] | threshold, claimed side | engine | reading |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for row in readings:
        digits = 0 if abs(row["mean"]) >= 10 else 2
        lines.append(
            f"| {row['claim']} | {row['series']}: {_per_seed(row['values'], digits)} | {_cell(row, digits)} | "
            f"{row['threshold']:g}, {row['claimed_side']} | {row['verdict']} | **{row['reading']}** |"
        )
    lines += ["", "## Beside the claims (they decide nothing)", "", "### Both students in C3's terms", "",
              "| series: per seed | mean +- sd [95 % BCa] | C3's reading, for the record |",
              "| --- | --- | --- |"]  # fmt: skip
    for row in beside:
        digits = 0 if abs(row["mean"]) >= 10 else 2
        lines.append(f"| {row['series']}: {_per_seed(row['values'], digits)} | {_cell(row, digits)} | {row['reading']} |")
    lines += ["", "### The students' noise apart from the buffers'", "",
              "Within: the sd between a seed's two student seeds, pooled over seeds. Between: the sd over seeds of the "
              "two-training means.", "", "| student | env | seeds | within sd | between sd |",
              "| --- | --- | --- | --- | --- |"]  # fmt: skip
    for row in noise:
        sds = f"{row['within_sd']:.0f} | {row['between_sd']:.0f}"
        lines.append(f"| {row['student']} | {row['env']} | {row['seeds']} | {sds} |")
    lines += ["", "### MPO's frozen Stage-1 agent against its end agent, on the same seeded episodes", "",
              f"{measured[0]['episodes']} episodes per environment, seeded as the collection's evaluations; the critic's "
              "overestimation of Env-A data is its mean Q minus the discounted return that followed (Monte Carlo).", "",
              "| seed | Stage-1 agent, Env-A | end agent, Env-A | end / Stage-1 | Stage-1 agent, Env-B (zero-shot) "
              "| end agent, Env-B | overestimation of Env-A data: Stage-1 critic -> end critic |",
              "| --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    ratios = {}
    for m in measured:
        ratios[m["seed"]] = m["final_same_episodes_Env-A"] / m["stage1_same_episodes_Env-A"]
        lines.append(
            f"| {m['seed']} | {m['stage1_same_episodes_Env-A']:.0f} | {m['final_same_episodes_Env-A']:.0f} | "
            f"{ratios[m['seed']]:.2f} | {m['stage1_same_episodes_Env-B']:.0f} | {m['final_same_episodes_Env-B']:.0f} | "
            f"{m['stage1_overestimation_Env-A']:+.1f} -> {m['final_overestimation_Env-A']:+.1f} |"
        )
    lines.append(f"| mean +- sd [95 % BCa] | | | {_cell(_stats(ratios), 2)} | | | |")
    text = "\n".join(lines) + "\n"
    results.mkdir(parents=True, exist_ok=True)
    (results / "summary.md").write_text(text)
    pd.DataFrame([{**row, "values": json.dumps(row["values"])} for row in readings + beside]).to_csv(
        results / "readings.csv", index=False
    )
    trainings.to_csv(results / "trainings.csv", index=False)
    print(text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("stage1", "env-b", "rest", "progress", "summary"):
        command = sub.add_parser(name)
        command.add_argument("--runs", default="runs", help="where buffers and agents go")
        command.add_argument("--results", default=str(RESULTS), help="where the small results go")
        if name not in ("progress", "summary"):
            command.add_argument("--seed", type=int, required=True)
        if name in ("env-b", "rest", "summary"):
            command.add_argument("--candidate", required=True, help="the screen's selection")
    args = parser.parse_args()
    handlers = {"stage1": run_stage1, "env-b": run_env_b, "rest": run_rest, "progress": progress, "summary": summary}
    result = handlers[args.command](args)
    sys.exit(result if isinstance(result, int) else 0)


if __name__ == "__main__":
    main()
