"""
Benchmark of LifelongReplayBuffer against SB3's ReplayBuffer.

1. sample(256) throughput on 1M transitions (in memory and in a directory, ``read_mode="mmap"`` and ``"pread"``),
   vs SB3 ``ReplayBuffer``;
2. add() cost per transition (one env, SB3-style calls);
3. RSS and disk of 10M transitions of OP3-sized observations (60 floats) written to a directory and sampled
   (memory maps, positioned reads).

Usage (one BLAS/torch thread, the directory goes to a temporary folder that is deleted afterwards)::

    OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 python benchmarks/speed/bench_buffer.py --big 10000000 --out \
        benchmarks/results/speed/buffer.md
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import shutil
import tempfile
import time

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_lifelong import LifelongReplayBuffer

OBS_DIM, ACT_DIM = 60, 20
OBS = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
ACT = gym.spaces.Box(-1, 1, (ACT_DIM,), np.float32)


def rss() -> dict[str, float]:
    """Current RSS of this process in MiB (total, anonymous, file-backed mapped pages)."""
    values = {}
    with open("/proc/self/status") as file:
        for line in file:
            key = line.split(":")[0]
            if key in ("VmRSS", "RssAnon", "RssFile", "VmHWM"):
                values[key] = int(line.split()[1]) / 1024
    return values


def rows(start: int, count: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "observations": rng.standard_normal((count, OBS_DIM), dtype=np.float32),
        "next_observations": rng.standard_normal((count, OBS_DIM), dtype=np.float32),
        "actions": rng.uniform(-1, 1, (count, ACT_DIM)).astype(np.float32),
        "rewards": rng.standard_normal(count, dtype=np.float32),
        "flags": (rng.random(count) < 0.001).astype(np.uint8),
        "sources": (np.arange(start, start + count) // 1_000_000).astype(np.uint16),
        "streams": np.zeros(count, np.uint32),
        "widths": np.ones(count, np.uint16),
    }


def fill_bulk(buffer: LifelongReplayBuffer, total: int, block: int = 100_000) -> None:
    rng = np.random.default_rng(0)
    for start in range(0, total, block):
        buffer.append_rows(rows(start, min(block, total - start), rng))
    buffer.flush()


def time_sampling(buffer, n_batches: int, batch_size: int = 256) -> float:
    buffer.sample(batch_size)
    start = time.perf_counter()
    for _ in range(n_batches):
        buffer.sample(batch_size)
    return n_batches / (time.perf_counter() - start)


def bench_sampling(size: int, n_batches: int, tmp: str) -> list[tuple[str, float]]:
    rng = np.random.default_rng(0)
    sb3 = ReplayBuffer(size, OBS, ACT, device="cpu", n_envs=1)
    data = rows(0, size, rng)
    sb3.observations[:, 0] = data["observations"]
    sb3.next_observations[:, 0] = data["next_observations"]
    sb3.actions[:, 0] = data["actions"]
    sb3.rewards[:, 0] = data["rewards"]
    sb3.dones[:, 0] = data["flags"]
    sb3.full = True
    memory = LifelongReplayBuffer(size, OBS, ACT, device="cpu")
    memory.append_rows(data)
    disk = LifelongReplayBuffer(size, OBS, ACT, device="cpu", path=os.path.join(tmp, "sample1m"), chunk_size=100_000)
    disk.append_rows(data)
    disk.flush()
    del data
    pread = LifelongReplayBuffer.open(os.path.join(tmp, "sample1m"), read_only=True, device="cpu", read_mode="pread")
    results = [
        ("SB3 ReplayBuffer", time_sampling(sb3, n_batches)),
        ("LifelongReplayBuffer (memory)", time_sampling(memory, n_batches)),
        ("LifelongReplayBuffer (directory, mmap)", time_sampling(disk, n_batches)),
        ("LifelongReplayBuffer (directory, pread)", time_sampling(pread, n_batches)),
    ]
    pread.close()
    memory3 = LifelongReplayBuffer(size, OBS, ACT, device="cpu", n_steps=3)
    memory3.store, memory3._runs = memory.store, memory._runs
    results.append(("LifelongReplayBuffer (memory, n_steps=3)", time_sampling(memory3, n_batches)))
    memory.set_sampling_weights({0: 2.0})
    results.append(("LifelongReplayBuffer (memory, source weights)", time_sampling(memory, n_batches)))
    disk.close()
    return results


def bench_add(n_adds: int, tmp: str) -> list[tuple[str, float]]:
    rng = np.random.default_rng(1)
    obs = rng.standard_normal((n_adds, 1, OBS_DIM), dtype=np.float32)
    act = rng.uniform(-1, 1, (n_adds, 1, ACT_DIM)).astype(np.float32)
    rew = np.zeros((n_adds, 1), np.float32)
    done = np.zeros((n_adds, 1), bool)
    infos = [{"stage": 0, "dynamics_params": {"mass": 1.0}}]
    buffers = [
        ("SB3 ReplayBuffer", ReplayBuffer(n_adds, OBS, ACT, device="cpu")),
        ("LifelongReplayBuffer (memory)", LifelongReplayBuffer(n_adds, OBS, ACT, device="cpu")),
        (
            "LifelongReplayBuffer (directory, chunk 10k, fsync)",
            LifelongReplayBuffer(n_adds, OBS, ACT, device="cpu", path=os.path.join(tmp, "add")),
        ),
    ]
    results = []
    for name, buffer in buffers:
        start = time.perf_counter()
        for i in range(n_adds):
            buffer.add(obs[i], obs[i], act[i], rew[i], done[i], infos)
        results.append((name, (time.perf_counter() - start) / n_adds * 1e6))
    return results


def bench_big(total: int, n_batches: int, tmp: str) -> dict[str, float]:
    path = os.path.join(tmp, "big")
    before = rss()
    start = time.perf_counter()
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=path, chunk_size=100_000)
    fill_bulk(buffer, total)
    write_s = time.perf_counter() - start
    after_write = rss()
    buffer.close()
    result: dict[str, float] = {}
    readers: list[tuple[str, dict]] = [
        ("read_mode=mmap (default)", {}),
        ("read_mode=pread", {"read_mode": "pread"}),
    ]
    for label, kwargs in readers:
        gc.collect()  # the previous reader's maps are gone: RssFile is back to the libraries'
        start = time.perf_counter()
        reader = LifelongReplayBuffer.open(path, read_only=True, device="cpu", **kwargs)
        result[f"open s ({label})"] = time.perf_counter() - start
        peak = {"VmRSS": 0.0, "RssAnon": 0.0, "RssFile": 0.0}
        start = time.perf_counter()
        for k in range(n_batches):
            reader.sample(256)
            if k % 20 == 0:
                now = rss()
                peak = {key: max(peak[key], now[key]) for key in peak}
        result[f"sample(256) batches/s ({label})"] = n_batches / (time.perf_counter() - start)
        result[f"peak VmRSS MiB while sampling ({label})"] = peak["VmRSS"]
        result[f"peak RssAnon MiB while sampling ({label})"] = peak["RssAnon"]
        result[f"peak RssFile MiB while sampling ({label})"] = peak["RssFile"]
        reader.close()
        del reader
    disk = sum(os.path.getsize(os.path.join(path, f)) for f in os.listdir(path))
    return {
        "transitions": total,
        "write s (bulk append, chunks of 100k, fsync)": write_s,
        "disk GiB": disk / 2**30,
        "VmRSS MiB before": before["VmRSS"],
        "VmRSS MiB after writing": after_write["VmRSS"],
        **result,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=1_000_000, help="transitions for the sampling benchmark")
    parser.add_argument("--batches", type=int, default=2000, help="sample(256) calls per measurement")
    parser.add_argument("--adds", type=int, default=20_000, help="add() calls for the add benchmark")
    parser.add_argument("--big", type=int, default=10_000_000, help="transitions of the RSS/disk benchmark (0: skip)")
    parser.add_argument("--tmp", default=None, help="folder for the directories (default: a new folder in /tmp)")
    parser.add_argument("--out", default=None, help="write a markdown table here")
    args = parser.parse_args()
    th.set_num_threads(1)
    tmp = tempfile.mkdtemp(prefix="bench_buffer_", dir=args.tmp)
    try:
        lines = [f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch threads 1", ""]
        sampling = bench_sampling(args.size, args.batches, tmp)
        base = sampling[0][1]
        lines += [f"### sample(256) on {args.size:,} transitions (obs {OBS_DIM} floats, action {ACT_DIM})", ""]
        lines += ["| buffer | batches/s | vs SB3 |", "| --- | ---: | ---: |"]
        lines += [f"| {name} | {rate:,.0f} | {rate / base:.2f}x |" for name, rate in sampling]
        adds = bench_add(args.adds, tmp)
        lines += ["", f"### add() cost, 1 env, {args.adds:,} calls", "", "| buffer | us / transition |", "| --- | ---: |"]
        lines += [f"| {name} | {cost:.1f} |" for name, cost in adds]
        if args.big:
            big = bench_big(args.big, args.batches, tmp)
            lines += ["", f"### {args.big:,} transitions in a directory (obs {OBS_DIM} floats)", "", "| metric | value |"]
            lines += ["| --- | ---: |"] + [f"| {key} | {value:,.2f} |" for key, value in big.items()]
        text = "\n".join(lines)
        print(text)
        if args.out:
            with open(args.out, "w") as file:
                file.write(text + "\n")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
