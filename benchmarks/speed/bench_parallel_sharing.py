"""
Parallel data sharing: two collectors side by side (Ray workers or a process pool) against one after the other in
one process, and a check that their merged buffer holds every collected transition exactly once.

The "copy" set-up of ``examples/parallel_sharing.py`` on the protocol's runner: one MPO agent learns Env-A, then it
and its copy collect at the same time in Env-B and Env-C (the jobs ``collect`` and ``collect_agent2``), each into its
own lifetime buffer on disk, then the ``share`` job merges them. Rounds alternate the order of the peers; the table
gives the collectors' wall time (Stage 2 only, including starting the workers), the environment steps per second of
both together, and the ratio to one worker (the two jobs one after the other) in the same round.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_parallel_sharing.py --rounds 2 --steps 2000
"""

import argparse
import collections
import dataclasses
import hashlib
import json
import pathlib
import platform
import statistics
import tempfile
import time

import numpy as np

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.experiments.presets import PRESETS
from sb3_lifelong.experiments.protocol import run_seed
from sb3_lifelong.experiments.runner import run_study

STAGES = ({}, {"hip_deformation": 0.3}, {"friction": 0.1})
FIELDS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")


def rows(data: dict[str, np.ndarray]) -> list[bytes]:
    """One digest per transition (every field, bit for bit)."""
    n = len(data["rewards"])
    return [hashlib.sha1(b"".join(np.ascontiguousarray(data[f][i]).tobytes() for f in FIELDS)).digest() for i in range(n)]


def check(run_dir: pathlib.Path, ancestor: int) -> dict[str, int]:
    """Compare the merged buffer (the ``share`` job's) with what each collector stored: lost and duplicated transitions."""
    names = ("buffer", "buffer_agent2", "buffer_shared")
    opened = [LifelongReplayBuffer.open(run_dir / name, read_only=True) for name in names]
    collected = rows(opened[0].to_d4rl(by_episode=False)) + rows(opened[1].to_d4rl(by_episode=False))[ancestor:]
    shared = rows(opened[2].to_d4rl(by_episode=False))
    for buffer in opened:
        buffer.close()
    want, got = collections.Counter(collected), collections.Counter(shared)
    return dict(
        collected=len(collected),
        shared=len(shared),
        lost=sum((want - got).values()),
        duplicated=sum((got - want).values()),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=2, help="interleaved rounds of the two peers")
    parser.add_argument("--steps", type=int, default=2_000, help="environment steps of each collector in Stage 2")
    parser.add_argument("--stage1", type=int, default=2_000, help="environment steps of Stage 1 (Env-A)")
    parser.add_argument("--backend", default="auto", choices=["auto", "ray", "process"], help="the parallel peer's backend")
    parser.add_argument("--output", default="benchmarks/results", help="where parallel_sharing.{md,json} go")
    args = parser.parse_args()

    preset = dataclasses.replace(
        PRESETS["cpu"],
        stages=STAGES,
        env_names=("Env-A", "Env-B", "Env-C"),
        stage_steps=(args.stage1, args.steps, args.steps),
        learning_starts=min(PRESETS["cpu"].learning_starts, args.stage1 // 2),
        eval_freq=args.stage1 + args.steps,  # evaluate once, at the end
        students=(),
        online=False,
        sharing="copy",
    )
    quiet = lambda line: None  # noqa: E731
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(args.rounds):
            order = (1, 2) if round_ % 2 == 0 else (2, 1)
            for workers in order:
                output = pathlib.Path(tmp) / f"r{round_}_w{workers}"
                run_seed(preset, round_, output, jobs=["collect"], log=quiet, until=args.stage1)  # Stage 1: not timed
                start = time.perf_counter()
                ran = run_study(preset, [round_], str(output), workers, backend=args.backend,
                                jobs=["collect", "collect_agent2"], log=quiet)  # fmt: skip
                seconds = time.perf_counter() - start
                failed = [key for key, result in ran.items() if result["error"]]
                if failed:
                    raise RuntimeError(f"round {round_}, {workers} worker(s): {failed} failed:\n{ran[failed[0]]['error']}")
                run_seed(preset, round_, output, jobs=["share"], log=quiet)
                run_dir = output / f"seed_{round_}"
                per = [
                    json.loads((run_dir / job / "done.json").read_text())["seconds"] for job in ("collect", "collect_agent2")
                ]
                timing = dict(workers=workers, backend=args.backend, steps_per_collector=args.steps, seconds=seconds)
                timing.update(env_steps_per_second=2 * args.steps / seconds, collector_seconds=per)
                row = dict(round=round_, **timing, **check(run_dir, args.stage1))
                results.append(row)
                print(
                    f"round {round_} workers {workers}: {row['seconds']:.1f} s, {row['env_steps_per_second']:.0f} steps/s, "
                    f"lost {row['lost']}, duplicated {row['duplicated']}",
                    flush=True,
                )

    lines = [
        "| round | workers | backend | collectors' wall time (s) | env steps/s (both) | ratio to 1 worker | per-collector s | collected | shared | lost | duplicated |",  # noqa: E501
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in results:
        peer = next(r for r in results if r["round"] == row["round"] and r["workers"] == 1)  # one worker: one after the other
        ratio = row["ratio"] = row["env_steps_per_second"] / peer["env_steps_per_second"]
        per = ", ".join(f"{s:.1f}" for s in row["collector_seconds"])
        lines.append(
            f"| {row['round']} | {row['workers']} | {row['backend'] if row['workers'] > 1 else 'one worker'} | "
            f"{row['seconds']:.1f} | {row['env_steps_per_second']:.0f} | {ratio:.2f}x | {per} | {row['collected']} | "
            f"{row['shared']} | {row['lost']} | {row['duplicated']} |"
        )
    ratios = [row["ratio"] for row in results if row["workers"] == 2]
    summary = f"median ratio, 2 workers / 1: {statistics.median(ratios):.2f}x over {len(ratios)} round(s)"
    table = "\n".join([*lines, "", summary])
    print(table)
    out = pathlib.Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    (out / "parallel_sharing.json").write_text(
        json.dumps(dict(args=vars(args), machine=platform.processor(), results=results), indent=1)
    )
    (out / "parallel_sharing.md").write_text(
        "# Parallel sharing: two collectors side by side vs one after the other\n\n"
        f"Command: `OMP_NUM_THREADS=1 python benchmarks/speed/bench_parallel_sharing.py --rounds {args.rounds} "
        f"--steps {args.steps} "
        f"--stage1 {args.stage1} --backend {args.backend}`\n\n"
        f"HalfCheetah-v5, the `cpu` preset's collector (MPO {'x'.join(map(str, preset.net_arch))}, {preset.num_samples} "
        f"samples, batch {preset.batch_size}), `copy` set-up on the protocol's runner: after "
        f"{args.stage1:,} steps in Env-A, two collectors of {args.steps:,} steps each (Env-B, Env-C), each into its own "
        "buffer on disk. Wall time of the two collectors, starting the workers included; lost / duplicated: transitions "
        "(every field, bit for bit) missing from or repeated in the merged buffer, against what each collector stored.\n\n"
        + table
        + "\n"
    )


if __name__ == "__main__":
    main()
