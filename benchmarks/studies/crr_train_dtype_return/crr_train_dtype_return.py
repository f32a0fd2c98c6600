"""
Does bf16 in CRR's gradient passes keep its learning result? The fixed-dataset return of ``bench_crr.py``'s CRR
(Hopper-v5, ``crr_hopper_medium_replay.npz``) with ``train_dtype="float32"`` against a bf16 setting, seed by seed,
each run its own process (``bench_crr.py --impl ours``), the two settings interleaved per seed.

On a CPU without native bf16, ``--other simulated_bfloat16`` gives bf16's numbers from float32 products at float32's
speed (``HiddenLinear.simulated``; ``tests/common/test_train_dtype.py`` checks it against the bf16 kernel); on one with it,
``--other bfloat16`` runs the real thing.

Pre-registered before the runs (written into the results):

- precondition: the float32 students learn from the data, their mean return above the dataset episodes' mean
  (otherwise "not testable": a return nobody learnt cannot be kept or lost);
- pass: the paired difference (other minus float32, per seed) has a 95 % t interval that contains 0, and its mean
  is within one standard deviation of the float32 returns across seeds (the seed spread).

    OMP_NUM_THREADS=1 python benchmarks/studies/crr_train_dtype_return/crr_train_dtype_return.py --seeds 0 1 2 3 4 \
        --other simulated_bfloat16

Seeds may run as separate commands at once (``--seeds K --output DIR_K``, one core each), and ``--merge DIR_0 DIR_1
...`` then gives the verdict over them all.
"""

import argparse
import json
import pathlib
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).parent
RESULTS = HERE / "results"


def run(dtype: str, seed: int, updates: int, episodes: int, data: str) -> dict:
    """
    One ``bench_crr.py --impl ours`` run in its own process.

    :param dtype: its ``--train-dtype``
    :param seed: its seed
    :param updates: its number of updates
    :param episodes: its evaluation episodes
    :param data: the dataset (``.npz``)
    :return: the setting, seed, final return, updates/s of the training loop and the run's wall time
    """
    command = [sys.executable, str(HERE.parents[1] / "speed" / "bench_crr.py"), "--impl", "ours", "--updates", str(updates)]
    command += ["--eval-episodes", str(episodes), "--seed", str(seed), "--train-dtype", dtype, "--data", data]
    started = time.perf_counter()
    out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    result = json.loads(out.strip().splitlines()[-1])
    return {
        "dtype": dtype,
        "seed": seed,
        "return": result["return"],
        "updates_per_s": updates / result["seconds"],
        "wall_s": time.perf_counter() - started,
    }


def verdict(rows: list[dict], other: str, behaviour_mean: float) -> dict:
    """
    The pre-registered rule (the module's docstring), on the seeds run with both settings.

    :param rows: :func:`run`'s results
    :param other: the setting compared with float32
    :param behaviour_mean: the dataset episodes' mean return (the precondition's bar)
    :return: the paired statistics and ``verdict``: ``"pass"``, ``"fail"``, ``"not testable"`` (the float32
        students did not learn) or ``"too few seeds"`` (under 2 paired); and ``interval_within_spread``, the stricter
        reading added after the first run (the whole interval within one float32 standard deviation of 0), which a
        noisy run with an interval containing 0 does not meet
    """
    by = {(row["dtype"], row["seed"]): row["return"] for row in rows}
    seeds = sorted({row["seed"] for row in rows if ("float32", row["seed"]) in by and (other, row["seed"]) in by})
    if len(seeds) < 2:
        return {"seeds": seeds, "verdict": "too few seeds"}
    from sb3_lifelong.experiments.statistics import t_interval

    base_mean, spread, _, _ = t_interval([by["float32", seed] for seed in seeds])
    other_mean, other_std, _, _ = t_interval([by[other, seed] for seed in seeds])
    difference, _, low, high = t_interval([by[other, seed] - by["float32", seed] for seed in seeds])
    testable = base_mean > behaviour_mean
    passed = low <= 0.0 <= high and abs(difference) <= spread
    return {
        "seeds": seeds,
        "float32_mean": base_mean,
        "float32_std": spread,
        "other_mean": other_mean,
        "other_std": other_std,
        "difference_mean": difference,
        "difference_ci95": [low, high],
        "precondition_float32_above_data": testable,
        "verdict": ("pass" if passed else "fail") if testable else "not testable",
        "interval_within_spread": bool(-spread <= low and high <= spread),
    }


def merged(parts: list[dict]) -> tuple[list[dict], str, str, int, int]:
    """
    The runs of several saved results (seeds run as separate commands) as one set.

    :param parts: the saved results (``OUTPUT/OTHER.json``), each with its runs
    :return: the runs, the machine, the commands (joined), the updates and the evaluation episodes
    :raises SystemExit: where the parts differ in machine, updates or evaluation episodes, or a seed's run of one
        setting appears twice
    """
    settings = {(part["machine"], part["updates"], part["eval_episodes"]) for part in parts}
    if len(settings) != 1:
        raise SystemExit(f"--merge: the runs differ in machine, updates or evaluation episodes: {sorted(settings)}")
    rows = [row for part in parts for row in part["runs"]]
    seeds = [(row["dtype"], row["seed"]) for row in rows]
    if len(set(seeds)) != len(seeds):
        raise SystemExit(f"--merge: a seed's run appears twice: {sorted(seeds)}")
    # each part's command is its arguments to python, as a run records them; the report puts the first's "python" before
    command = " ; OMP_NUM_THREADS=1 python ".join(part["command"] for part in parts)
    return rows, parts[0]["machine"], command, parts[0]["updates"], parts[0]["eval_episodes"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--other", default="simulated_bfloat16", choices=["bfloat16", "simulated_bfloat16"])
    parser.add_argument("--updates", type=int, default=5_000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--data", default=str(HERE.parents[1] / "results" / "speed" / "crr_hopper_medium_replay.npz"))
    parser.add_argument("--output", default=str(RESULTS / "crr_train_dtype_return"))
    parser.add_argument("--summarise", action="store_true", help="no runs: the tables again from OUTPUT/OTHER.json's runs")
    parser.add_argument(
        "--merge",
        nargs="+",
        metavar="DIR",
        help="no runs: the verdict over the runs in each DIR/OTHER.json (seeds run as separate commands), into OUTPUT",
    )
    args = parser.parse_args()
    from sb3_lifelong.numerics.hardware import machine_description

    output = pathlib.Path(args.output)
    behaviour = json.loads(pathlib.Path(args.data).with_suffix(".json").read_text())
    behaviour_mean = float(behaviour["dataset_mean_return"])
    if args.summarise or args.merge:
        parts = [json.loads((pathlib.Path(d) / f"{args.other}.json").read_text()) for d in args.merge or [output]]
        rows, machine, command, args.updates, args.eval_episodes = merged(parts)
    else:
        rows, machine, command = [], machine_description(), " ".join(sys.argv)
        for seed in args.seeds:
            order = ("float32", args.other) if seed % 2 == 0 else (args.other, "float32")  # interleaved
            for dtype in order:
                rows.append(run(dtype, seed, args.updates, args.eval_episodes, args.data))
                print(json.dumps(rows[-1]), flush=True)
    result = {
        "machine": machine,
        "command": command,
        "updates": args.updates,
        "eval_episodes": args.eval_episodes,
        "dataset_mean_return": behaviour_mean,
        "runs": rows,
        **verdict(rows, args.other, behaviour_mean),
    }
    output.mkdir(parents=True, exist_ok=True)
    (output / f"{args.other}.json").write_text(json.dumps(result, indent=2) + "\n")
    if result["verdict"] == "too few seeds":
        print(json.dumps(result))
        return
    lines = [
        f"# CRR's fixed-dataset return, float32 against {args.other} gradient passes",
        "",
        f"Machine: {result['machine']}",
        "",
        f"Command: `OMP_NUM_THREADS=1 python {result['command']}`",
        "",
        "| seed | float32 return | " + args.other + " return | difference | float32 updates/s | other updates/s |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    by = {(row["dtype"], row["seed"]): row for row in rows}
    for seed in result["seeds"]:
        a, b = by["float32", seed], by[args.other, seed]
        lines.append(
            f"| {seed} | {a['return']:.1f} | {b['return']:.1f} | {b['return'] - a['return']:+.1f} | "
            f"{a['updates_per_s']:.0f} | {b['updates_per_s']:.0f} |"
        )
    low, high = result["difference_ci95"]
    lines += [
        "",
        f"float32 {result['float32_mean']:.1f} +- {result['float32_std']:.1f}; {args.other} "
        f"{result['other_mean']:.1f} +- {result['other_std']:.1f}; paired difference {result['difference_mean']:+.1f} "
        f"(95 % t interval [{low:+.1f}, {high:+.1f}]); dataset episodes' mean {behaviour_mean:.1f}.",
        "",
        "Pre-registered in the script before the runs. Precondition: the float32 students' mean return is above the "
        "dataset episodes' mean (else not testable). Pass: the paired difference's 95 % t interval contains 0 and its "
        "mean is within the float32 seed spread (one standard deviation).",
        "",
        f"Verdict: **{result['verdict']}**. The whole interval within the float32 spread (a stricter reading, added "
        f"after the first run): {'yes' if result['interval_within_spread'] else 'no'}.",
        "",
    ]
    (output / f"{args.other}.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
