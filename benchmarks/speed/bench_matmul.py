"""
What the CPU's matrix units give the networks' shapes: float32 against bfloat16 matrix products, one thread.

The shapes are the passes of an update (batch 256, 256-wide hidden layers, N=20 action samples per state, an
OP3/HalfCheetah-sized input): the target pass's hidden layer ``5120 x 256 x 256``, its first layer
``5120 x 23 x 256``, its output layer ``5120 x 256 x 1`` and a batch pass ``256 x 256 x 256``. For each shape, four
ways to multiply, and three ways to compute a whole layer (product, bias and ReLU), timed in interleaved rounds so
that a shared machine slows all alike:

- ``fp32``: ``torch.matmul(a, w, out=...)`` in float32;
- ``bf16``: the same in bfloat16 (oneDNN's AMX kernel on a CPU that has AMX);
- ``bf16 addmm``: ``torch.addmm(bias, a, w, out=...)`` in bfloat16 (the bias added by the product);
- ``bf16 autocast``: ``nn.Linear`` under ``torch.autocast("cpu", bfloat16)`` (casts input and weight every call);
- ``fp32 layer``: ``addmm(bias, a, w, out=...)`` then an in-place ReLU, in float32 (the eager layer of today's passes);
- ``fp32 fused`` / ``bf16 fused``: oneDNN's inner product with the bias and the ReLU fused in
  (``torch.ops.mkldnn._linear_pointwise``, a private op) on a weight laid out once
  (``torch.ops.mkldnn._reorder_linear_weight``), as a target pass that lays its weights out at each target sync
  would run; ``n/a`` where this CPU's oneDNN refuses it (bf16 without AVX-512 or AMX).

The table gives GFLOP/s (median over rounds), bf16's speed over float32's, and the fused bf16 layer's over the
float32 layer's. The machine line names the
CPU, its matrix flags and the oneDNN kernel that ran the bf16 product.

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_matmul.py      # -> benchmarks/results/speed/matmul.json
"""

import argparse
import json
import math
import pathlib
import statistics
import time
from typing import Callable, Optional

import torch as th

from sb3_lifelong.numerics.hardware import machine_description

RESULTS = pathlib.Path(__file__).resolve().parents[1] / "results" / "speed" / "matmul.json"
SHAPES = {
    "target hidden 5120x256x256": (5120, 256, 256),
    "target first 5120x23x256": (5120, 23, 256),
    "target output 5120x256x1": (5120, 256, 1),
    "batch hidden 256x256x256": (256, 256, 256),
}
WAYS = ("fp32", "bf16", "bf16 addmm", "bf16 autocast", "fp32 layer", "fp32 fused", "bf16 fused")


def fused_layer(a: th.Tensor, w: th.Tensor, bias: th.Tensor) -> Optional[Callable[[], object]]:
    """
    :return: a function that computes ``relu(a @ w + bias)`` with oneDNN's fused inner product on a weight laid out
        once, or None where this CPU's oneDNN (or this torch) refuses it for ``a``'s dtype
    """
    mkldnn = getattr(th.ops, "mkldnn", None)
    try:
        packed = mkldnn._reorder_linear_weight(w.t().contiguous(), a.shape[0])
        call = lambda: mkldnn._linear_pointwise(a, packed, bias, "relu", [], "")  # noqa: E731
        result = call()
    except (AttributeError, RuntimeError):
        return None
    expected = th.relu(th.addmm(bias.float(), a.float(), w.float()))
    error = (result.float() - expected).abs().max().item() / expected.std().item()
    if error > (1e-4 if a.dtype == th.float32 else 5e-2):  # bf16 rounds inputs to 8 bits of mantissa
        raise AssertionError(f"the fused {a.dtype} layer is off by {error:.2g} of the output's std")
    return call


def make_call(way: str, m: int, k: int, n: int) -> Optional[Callable[[], object]]:
    """
    :return: a function that runs one product of shape ``m x k x n`` the given way, outputs allocated once (None: this
        machine cannot run it that way)
    """
    generator = th.Generator().manual_seed(0)
    a = th.randn(m, k, generator=generator)
    w = th.randn(k, n, generator=generator) / k**0.5
    bias = th.randn(n, generator=generator)
    if way == "fp32":
        out = th.empty(m, n)
        return lambda: th.matmul(a, w, out=out)
    if way == "bf16":
        a16, w16, out16 = a.bfloat16(), w.bfloat16(), th.empty(m, n, dtype=th.bfloat16)
        return lambda: th.matmul(a16, w16, out=out16)
    if way == "bf16 addmm":
        a16, w16, b16, out16 = a.bfloat16(), w.bfloat16(), bias.bfloat16(), th.empty(m, n, dtype=th.bfloat16)
        return lambda: th.addmm(b16, a16, w16, out=out16)
    if way == "bf16 autocast":
        layer = th.nn.Linear(k, n)

        def call() -> object:
            with th.no_grad(), th.autocast("cpu", dtype=th.bfloat16):
                return layer(a)

        return call
    if way == "fp32 layer":
        out = th.empty(m, n)
        return lambda: th.addmm(bias, a, w, out=out).relu_()
    if way in ("fp32 fused", "bf16 fused"):
        dtype = th.float32 if way == "fp32 fused" else th.bfloat16
        return fused_layer(a.to(dtype), w.to(dtype), bias.to(dtype))
    raise ValueError(f"unknown way {way!r}; expected one of {WAYS}")


def seconds_per_call(call: Callable[[], object], min_time: float) -> float:
    """:return: the mean seconds of one call, over as many calls as fill ``min_time``"""
    call()
    calls, start = 0, time.perf_counter()
    while True:
        call()
        calls += 1
        elapsed = time.perf_counter() - start
        if elapsed >= min_time:
            return elapsed / calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    parser.add_argument("--min-time", type=float, default=0.2, help="seconds per timing")
    parser.add_argument("--output", default=str(RESULTS))
    args = parser.parse_args()
    th.set_num_threads(1)

    made = {(shape, way): make_call(way, *dims) for shape, dims in SHAPES.items() for way in WAYS}
    calls = {key: call for key, call in made.items() if call is not None}
    times: dict[tuple[str, str], list[float]] = {key: [] for key in calls}
    for _ in range(args.rounds):
        for key, call in calls.items():
            times[key].append(seconds_per_call(call, args.min_time))

    machine = machine_description()
    print(machine)
    rows = []
    header = (
        "| shape (M x K x N) | " + " | ".join(f"{way} GFLOP/s" for way in WAYS) + " | bf16 / fp32 | bf16 fused / fp32 layer |"
    )
    print(header)
    print("|" + " --- |" * (len(WAYS) + 3))
    for shape, (m, k, n) in SHAPES.items():
        rate = {way: 2 * m * k * n / statistics.median(times[shape, way]) / 1e9 if (shape, way) in times else math.nan
                for way in WAYS}  # fmt: skip
        rows.append(dict(shape=shape, m=m, k=k, n=n, gflops=rate))
        cells = " | ".join("n/a" if math.isnan(rate[way]) else f"{rate[way]:.0f}" for way in WAYS)
        fused = rate["bf16 fused"] / rate["fp32 layer"]
        print(
            f"| {shape} | {cells} | {rate['bf16'] / rate['fp32']:.2f}x | {'n/a' if math.isnan(fused) else f'{fused:.2f}x'} |"
        )
    result = dict(command=f"OMP_NUM_THREADS=1 python benchmarks/speed/bench_matmul.py --rounds {args.rounds}", machine=machine)
    result["rows"] = rows
    pathlib.Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(args.output).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
