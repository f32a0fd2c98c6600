"""
Where a dose-study student's update spends its time, and what two of its choices are worth: the study's CRR
(``bench_student_cost.make_students``: 256x256 LayerNorm torso, categorical critic, batch 256, HalfCheetah sizes, the
indicator transform, ``scoring_dtype="auto"``).

- ``profile``: the milliseconds per update, then torch's profiler table (by operator, then by operator and shape)
  over 100 updates, eager or compiled.
- ``compare``: interleaved blocks of updates of several variants of the same student, each block's time and the first
  variant's time over each other's per block pair: eager against compiled; or (``--online-copy``) the online critic's
  bf16 copy fused (the default where oneDNN fuses bf16), unfused, or none (float32 baseline pass); or
  (``--train-dtype``) the gradient passes' hidden products in float32 against bfloat16 (``train_dtype``); or
  (``--cpp-wrapper``) the compiled update with inductor's Python wrapper (the default) against its C++ wrapper, which
  calls the kernels from C++ rather than Python.

    OMP_NUM_THREADS=1 python benchmarks/speed/student_anatomy.py profile --compile-losses
    OMP_NUM_THREADS=1 python benchmarks/speed/student_anatomy.py compare
    OMP_NUM_THREADS=1 python benchmarks/speed/student_anatomy.py compare --online-copy --compile-losses
    OMP_NUM_THREADS=1 python benchmarks/speed/student_anatomy.py compare --train-dtype --compile-losses
    OMP_NUM_THREADS=1 python benchmarks/speed/student_anatomy.py compare --cpp-wrapper

The online-copy variants need a CPU with native bf16 (elsewhere ``"auto"`` scores in float32 and there is no copy).
"""

import argparse
import statistics
import time
import warnings

import torch as th
from bench_student_cost import make_students

from sb3_lifelong.numerics.hardware import machine_description
from sb3_lifelong.numerics.scoring import LowPrecisionCopy


def student(compile_losses: bool, online_copy: str = "default", train_dtype: str = "float32"):
    """:return: the indicator student, warmed up, with its online critic's copy and its gradient passes as asked"""
    model = make_students("auto", compile_losses=compile_losses, train_dtype=train_dtype)["indicator"]
    if online_copy != "default":
        copies = model.__dict__.get("_scoring_copies", [])
        if model._online_scoring_copy is None:
            raise SystemExit("this CPU scores in float32 (no native bf16): there is no online copy to vary")
        copies.remove(model._online_scoring_copy)
        model._online_scoring_copy = None
        if online_copy == "unfused":
            model._online_scoring_copy = LowPrecisionCopy(model.critic, th.bfloat16, fused=False)
            copies.append(model._online_scoring_copy)
    model.learn_offline(100, log_interval=0, reset_num_timesteps=False)
    forward = model._forward
    print(
        f"{'compiled' if compile_losses else 'eager'}, online copy {online_copy}, {train_dtype}: compiled update in use "
        f"{forward.compiled is not None and forward.checked}; {forward.failure or 'no failure'}",
        flush=True,
    )
    return model


def ms_per_update(model, updates: int) -> float:
    start = time.perf_counter()
    model.learn_offline(updates, log_interval=0, reset_num_timesteps=False)
    return (time.perf_counter() - start) / updates * 1e3


def profile(args: argparse.Namespace) -> None:
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    model = student(args.compile_losses)
    print("ms per update:", " ".join(f"{ms_per_update(model, args.updates):.2f}" for _ in range(3)))
    with torch_profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        model.learn_offline(100, log_interval=0, reset_num_timesteps=False)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    print(prof.key_averages(group_by_input_shape=True).table(sort_by="self_cpu_time_total", row_limit=25))


def compare(args: argparse.Namespace) -> None:
    if args.online_copy:
        variants = {kind: student(args.compile_losses, kind) for kind in ("default", "unfused", "none")}
    elif args.train_dtype:
        variants = {dtype: student(args.compile_losses, train_dtype=dtype) for dtype in ("float32", "bfloat16")}
    elif args.cpp_wrapper:
        with th._inductor.config.patch(cpp_wrapper=True):  # the compilation happens in the warm-up, inside this
            cpp = student(True)
        variants = {"python wrapper": student(True), "C++ wrapper": cpp}
    else:
        variants = {"eager": student(False), "compiled": student(True)}
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(args.blocks):
        for name, model in variants.items():
            times[name].append(ms_per_update(model, args.updates))
    first = next(iter(times.values()))
    print(f"| variant | ms per update, median of {args.blocks} blocks of {args.updates} | first / this, median [min, max] |")
    print("| --- | --- | --- |")
    for name, values in times.items():
        ratios = [a / b for a, b in zip(first, values)]
        print(
            f"| {name} | {statistics.median(values):.2f} | {statistics.median(ratios):.2f}x "
            f"[{min(ratios):.2f}, {max(ratios):.2f}] |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=["profile", "compare"])
    parser.add_argument("--compile-losses", action="store_true", help="the compiled update (profile, the variants)")
    parser.add_argument("--online-copy", action="store_true", help="compare the online copy's variants")
    parser.add_argument("--train-dtype", action="store_true", help="compare float32 and bfloat16 gradient passes")
    parser.add_argument("--cpp-wrapper", action="store_true", help="compare inductor's Python and C++ wrappers (compiled)")
    parser.add_argument("--blocks", type=int, default=6)
    parser.add_argument("--updates", type=int, default=200, help="updates per block")
    args = parser.parse_args()
    th.set_num_threads(1)
    warnings.filterwarnings("ignore", message=".*deprecated.*")
    print(machine_description(), flush=True)
    profile(args) if args.mode == "profile" else compare(args)


if __name__ == "__main__":
    main()
