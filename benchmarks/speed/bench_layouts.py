"""
What a buffer directory that keeps every row costs to sample, by layout: layout "single" (one file per field, what a
directory without a capacity is) against layout "chunked" (one file per flushed chunk, what a capacity gives; here a
capacity larger than the rows, so that nothing is evicted and both hold the same rows). The question it answers:
would chunk files do for a buffer without a capacity?

For each size, both directories are written with the same rows (Hopper-sized: 11 floats of observation, 3 of
action), then opened read-only and sampled, ``sample(256)``, in both read modes, the two layouts interleaved
(``--repeats`` rounds, the median kept), so that the machine's noise hits both. It also counts the file descriptors
the open reader holds. Prints a table and writes it (``--out``).

Usage (one thread; the directories go to a temporary folder that is deleted afterwards)::

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_layouts.py --out benchmarks/results/speed/layouts.md
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
import tempfile
import time

import gymnasium as gym
import numpy as np

from sb3_lifelong import LifelongReplayBuffer

OBS = gym.spaces.Box(-np.inf, np.inf, (11,), np.float32)
ACT = gym.spaces.Box(-1, 1, (3,), np.float32)


def write(path: str, rows: int, capacity: int | None, chunk_size: int) -> None:
    """``rows`` transitions in blocks of 1,000 (one env: rows of one stream)."""
    rng = np.random.default_rng(0)
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, capacity=capacity, chunk_size=chunk_size, device="cpu")
    for _ in range(rows // 1000):
        obs = rng.standard_normal((1000, 11)).astype(np.float32)
        for k in range(1000):
            buffer.add(obs[k : k + 1], obs[k : k + 1], rng.uniform(-1, 1, (1, 3)), rng.standard_normal(1), np.zeros(1), [{}])
    buffer.close()


def sample_ms(path: str, read_mode: str, batches: int) -> tuple[float, int, str, int]:
    """:return: ms per ``sample(256)``, the file descriptors the reader holds, its layout and its chunks"""
    before = len(os.listdir("/proc/self/fd"))
    reader = LifelongReplayBuffer.open(path, read_only=True, device="cpu", read_mode=read_mode)
    for _ in range(20):
        reader.sample(256)
    start = time.perf_counter()
    for _ in range(batches):
        reader.sample(256)
    elapsed = (time.perf_counter() - start) / batches * 1e3
    fds = len(os.listdir("/proc/self/fd")) - before
    layout, chunks = reader.store.layout, len(reader.store.chunks)
    reader.close()
    return elapsed, fds, layout, chunks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, nargs="+", default=[200_000, 1_000_000], help="transitions per directory")
    parser.add_argument("--chunk-size", type=int, default=10_000, help="rows per flushed chunk (the default)")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds; the median is kept")
    parser.add_argument("--batches", type=int, default=300, help="sample(256) calls timed per round")
    parser.add_argument("--out", default=None, help="write the table to this Markdown file")
    args = parser.parse_args()
    root = tempfile.mkdtemp(prefix="bench_layouts_")
    lines = [
        "| transitions | read mode | single: ms per sample(256) | chunked: ms per sample(256) | chunked / single "
        "| reader's file descriptors (single, chunked) | chunks |",
        "| ---: | --- | ---: | ---: | ---: | --- | ---: |",
    ]
    try:
        for rows in args.rows:
            paths = {"single": os.path.join(root, f"single_{rows}"), "chunked": os.path.join(root, f"chunked_{rows}")}
            write(paths["single"], rows, None, args.chunk_size)
            write(paths["chunked"], rows, 10 * rows, args.chunk_size)
            for read_mode in ("mmap", "pread"):
                times: dict[str, list[float]] = {"single": [], "chunked": []}
                fds, chunks = {}, 0
                for _ in range(args.repeats):
                    for name, path in paths.items():
                        ms, fds[name], layout, count = sample_ms(path, read_mode, args.batches)
                        assert layout == name, (layout, name)
                        times[name].append(ms)
                        chunks = count if name == "chunked" else chunks
                single, chunked = (float(np.median(times[name])) for name in ("single", "chunked"))
                lines.append(
                    f"| {rows:,} | {read_mode} | {single:.3f} | {chunked:.3f} | {chunked / single:.2f}x "
                    f"| {fds['single']}, {fds['chunked']} | {chunks} |"
                )
                print(lines[-1], flush=True)
            for path in paths.values():
                shutil.rmtree(path)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    flags = sorted({flag for flag in open("/proc/cpuinfo").read().split() if flag.startswith("amx") or flag == "avx512_bf16"})
    header = [
        "# Sampling a directory that keeps every row: one file per field against one file per chunk",
        "",
        f"Command: `OMP_NUM_THREADS=1 python benchmarks/speed/bench_layouts.py` ({datetime.date.today()}; "
        f"{platform.processor() or platform.machine()}, CPU flags {' '.join(flags) or 'none of amx/avx512_bf16'}; "
        f"chunks of {args.chunk_size:,} rows; median of {args.repeats} interleaved rounds of {args.batches} batches; "
        "2 cores shared with other jobs).",
        "",
    ]
    text = "\n".join(header + lines) + "\n"
    print(text)
    if args.out:
        with open(args.out, "w") as file:
            file.write(text)


if __name__ == "__main__":
    main()
