"""
What one student of the imbalance dose study costs on this machine: CRR at the study's settings (256x256 LayerNorm torso,
categorical critic, batch 256, HalfCheetah-sized input and action), with the indicator and with ``target_ess``,
timed in interleaved blocks of updates; the time of a 200k-update student and of the paper's 5M.

With ``--peer DIR`` the same students also run from another checkout of the package (e.g. a ``git worktree`` of an
earlier commit): each tree in its own process, their blocks interleaved, and the table gives the peer's time over
this tree's per block pair (the speed-up; median and range), so that a shared, noisy machine slows both alike.

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_student_cost.py      # -> benchmarks/results/speed/student_cost.json
    git worktree add /tmp/peer <commit> && OMP_NUM_THREADS=1 python benchmarks/speed/bench_student_cost.py --peer /tmp/peer
    OMP_NUM_THREADS=1 python benchmarks/speed/bench_student_cost.py --peer /tmp/peer --compile-losses   # this tree compiled
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

import numpy as np
import torch as th
from gymnasium import spaces

RESULTS = pathlib.Path(__file__).resolve().parents[1] / "results" / "speed" / "student_cost.json"
VARIANTS = {
    "indicator": dict(advantage_transform="indicator"),
    "target_ess=0.9": dict(advantage_transform="exp", target_ess=0.9),
}


def random_data(rows: int, obs_dim: int, action_dim: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return dict(
        observations=rng.normal(size=(rows, obs_dim)).astype(np.float32),
        actions=rng.uniform(-1, 1, (rows, action_dim)).astype(np.float32),
        rewards=rng.normal(size=rows).astype(np.float32),
        next_observations=rng.normal(size=(rows, obs_dim)).astype(np.float32),
        terminals=np.zeros(rows, bool),
        timeouts=np.zeros(rows, bool),
    )


def make_students(scoring_dtype: str, compile_losses: bool = False, train_dtype: str = "float32") -> dict:
    """The study's students on random HalfCheetah-sized data (with its 2 physical parameters appended), warmed up."""
    from sb3_lifelong import CRR

    data = random_data(50_000, 19, 6)
    policy_kwargs = dict(net_arch=[256, 256], layer_norm=True, distributional_critic=True, v_min=-500.0, v_max=3000.0)
    space = spaces.Box(-1, 1, (6,))
    models = {
        name: CRR.from_offline_data(
            data,
            env=None,
            action_space=space,
            policy_kwargs=policy_kwargs,
            batch_size=256,
            seed=0,
            device="cpu",  # the CPU even where a GPU is present
            compute=dict(
                scoring_dtype=scoring_dtype, compile_losses=True if compile_losses else "auto", train_dtype=train_dtype
            ),
            **kw,
        )
        for name, kw in VARIANTS.items()
    }
    for model in models.values():
        model.learn_offline(50, log_interval=0)  # warm-up (and the compilation)
    return models


def time_block(models: dict, updates: int) -> dict[str, float]:
    """:return: seconds per update of each student over one block of ``updates``"""
    seconds = {}
    for name, model in models.items():
        start = time.perf_counter()
        model.learn_offline(updates, log_interval=0, reset_num_timesteps=False)
        seconds[name] = (time.perf_counter() - start) / updates
    return seconds


def worker(scoring_dtype: str, compile_losses: bool) -> None:
    """One tree's students in a child process: a block per ``block N`` line on stdin, its times as JSON on stdout."""
    th.set_num_threads(1)
    models = make_students(scoring_dtype, compile_losses)
    import sb3_lifelong

    print(json.dumps({"ready": str(pathlib.Path(sb3_lifelong.__file__).parent.parent)}), flush=True)
    for line in sys.stdin:
        print(json.dumps(time_block(models, int(line.split()[1]))), flush=True)


def start_worker(tree: pathlib.Path, scoring_dtype: str, compile_losses: bool) -> subprocess.Popen:
    tree = tree.resolve()  # the worker runs in the tree: a relative path would be read from there
    # the tree first, then whatever path the caller had (where its dependencies may live)
    path = os.pathsep.join([str(tree)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []))
    env = {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, __file__, "--worker", "--scoring-dtype", scoring_dtype]
    command += ["--compile-losses"] if compile_losses else []
    child = subprocess.Popen(command, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=tree)
    assert child.stdout is not None
    ready = json.loads(child.stdout.readline())["ready"]
    if pathlib.Path(ready).resolve() != tree.resolve():
        raise RuntimeError(f"the worker for {tree} imported the package from {ready}")
    return child


def ask(child: subprocess.Popen, updates: int) -> dict[str, float]:
    assert child.stdin is not None and child.stdout is not None
    child.stdin.write(f"block {updates}\n")
    child.stdin.flush()
    return json.loads(child.stdout.readline())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--blocks", type=int, default=5, help="interleaved blocks per variant")
    parser.add_argument("--updates", type=int, default=200, help="updates per block")
    parser.add_argument("--peer", default=None, help="another checkout of the package, timed interleaved with this one")
    parser.add_argument("--scoring-dtype", default="auto", help="the students' scoring_dtype")
    parser.add_argument(
        "--compile-losses", action="store_true", help="this tree's students with compile_losses=True (not the peer's)"
    )
    parser.add_argument("--output", default=str(RESULTS))
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.scoring_dtype, args.compile_losses)
        return
    from sb3_lifelong.numerics.hardware import machine_description

    here = pathlib.Path(__file__).resolve().parents[2]  # the checkout
    trees = {"this tree": here} | ({"peer": pathlib.Path(args.peer)} if args.peer else {})
    children = {
        name: start_worker(tree, args.scoring_dtype, args.compile_losses and name == "this tree")
        for name, tree in trees.items()
    }
    seconds: dict[str, dict[str, list[float]]] = {tree: {name: [] for name in VARIANTS} for tree in trees}
    for _ in range(args.blocks):
        for tree, child in children.items():
            for name, value in ask(child, args.updates).items():
                seconds[tree][name].append(value)
    for child in children.values():
        assert child.stdin is not None
        child.stdin.close()
        child.wait()
    command = (
        "OMP_NUM_THREADS=1 python benchmarks/speed/bench_student_cost.py"
        + " ".join(
            [""] + [f"--{key} {value}" for key, value in (("peer", args.peer), ("scoring-dtype", args.scoring_dtype)) if value]
        )
        + (" --compile-losses" if args.compile_losses else "")
    )
    result: dict = {"machine": machine_description(), "command": command, "blocks": args.blocks, "updates": args.updates}
    lines = [result["machine"], "", f"`{command}`", ""]
    lines += [
        "| student | ms per update (median block) | 200k updates | 5M updates (the paper) |"
        + (" peer ms | speed-up (peer / this, median [min, max] of block pairs) |" if args.peer else "")
    ]
    lines.append("| --- " * (6 if args.peer else 4) + "|")
    for name in VARIANTS:
        ms = float(np.median(seconds["this tree"][name])) * 1e3
        entry = dict(
            ms_per_update=ms,
            blocks_ms=[v * 1e3 for v in seconds["this tree"][name]],
            minutes_200k=ms * 2e5 / 6e4,
            hours_5M=ms * 5e6 / 3.6e6,
        )
        row = f"| {name} | {ms:.1f} | {ms * 2e5 / 6e4:.0f} min | {ms * 5e6 / 3.6e6:.1f} h |"
        if args.peer:
            peer = seconds["peer"][name]
            ratios = [p / t for p, t in zip(peer, seconds["this tree"][name])]
            entry.update(peer_blocks_ms=[v * 1e3 for v in peer], speedup_blocks=ratios)
            row += f" {np.median(peer) * 1e3:.1f} | {np.median(ratios):.2f}x [{min(ratios):.2f}, {max(ratios):.2f}] |"
        result[name] = entry
        lines.append(row)
    pathlib.Path(args.output).write_text(json.dumps(result, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
