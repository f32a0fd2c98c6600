"""
Parallel data sharing: two collectors side by side (Ray workers or a process pool) against one after the other in
one process, and a check that their merged buffer holds every collected transition exactly once.

The "copy" set-up of ``examples/parallel_sharing.py``: one MPO agent learns Env-A, then it and its copy collect
at the same time in Env-B and Env-C, each into its own lifetime buffer on disk. Rounds alternate the order of the
peers; the table gives the collectors' wall time (Stage 2 only, including starting the workers), the environment
steps per second of both together, and the ratio to the one-process run of the same round.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_parallel_sharing.py --rounds 2 --steps 2000
"""

import argparse
import collections
import hashlib
import json
import pathlib
import platform
import statistics
import tempfile

import numpy as np

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import merge_buffers
from sb3_lifelong.experiments.sequential import EXAMPLE_CONFIGS
from sb3_lifelong.experiments.sharing import run_sharing

STAGES = [{}, {"hip_deformation": 0.3}, {"friction": 0.1}]
FIELDS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")


def rows(data: dict[str, np.ndarray]) -> list[bytes]:
    """One digest per transition (every field, bit for bit)."""
    n = len(data["rewards"])
    return [hashlib.sha1(b"".join(np.ascontiguousarray(data[f][i]).tobytes() for f in FIELDS)).digest() for i in range(n)]


def check(run_dir: pathlib.Path, ancestor: int) -> dict[str, int]:
    """Compare the merged buffer with what each collector stored: lost and duplicated transitions."""
    opened = [LifelongReplayBuffer.open(run_dir / name, read_only=True) for name in ("buffer_agent1", "buffer_agent2")]
    merged = merge_buffers(opened, starts=[0, ancestor])
    collected = rows(opened[0].to_d4rl(by_episode=False)) + rows(opened[1].to_d4rl(by_episode=False))[ancestor:]
    shared = rows(merged.to_d4rl(by_episode=False))
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

    config = dict(EXAMPLE_CONFIGS["quick"], stage_steps=[args.stage1, args.steps], distill_steps=0, preset="quick")
    config["learning_starts"] = min(config["learning_starts"], args.stage1 // 2)
    config["eval_freq"] = args.stage1 + args.steps  # evaluate once, at the end
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(args.rounds):
            order = (1, 2) if round_ % 2 == 0 else (2, 1)
            for workers in order:
                output = pathlib.Path(tmp) / f"r{round_}_w{workers}"
                run_sharing({**config, "seeds": [round_]}, "copy", STAGES, output, workers=workers, backend=args.backend,
                            distill_students=False, log=lambda line: None)  # fmt: skip
                run_dir = output / f"seed_{round_}"
                timing = json.loads((run_dir / "collectors.json").read_text())
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
        peer = next(r for r in results if r["round"] == row["round"] and r["workers"] == 1)
        ratio = row["ratio"] = row["env_steps_per_second"] / peer["env_steps_per_second"]
        per = ", ".join(f"{s:.1f}" for s in row["collector_seconds"])
        lines.append(
            f"| {row['round']} | {row['workers']} | {row['backend'] if row['workers'] > 1 else 'in process'} | "
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
        "HalfCheetah-v5, the `quick` settings of the examples (MPO 64x64, 10 samples, batch 128), `copy` set-up: after "
        f"{args.stage1:,} steps in Env-A, two collectors of {args.steps:,} steps each (Env-B, Env-C), each into its own "
        "buffer on disk. Wall time of the two collectors, starting the workers included; lost / duplicated: transitions "
        "(every field, bit for bit) missing from or repeated in the merged buffer, against what each collector stored.\n\n"
        + table
        + "\n"
    )


if __name__ == "__main__":
    main()
