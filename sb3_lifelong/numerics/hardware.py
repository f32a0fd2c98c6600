"""
What this machine multiplies fast: whether the CPU has native bfloat16 (what ``scoring_dtype="auto"`` asks,
:func:`sb3_lifelong.numerics.scoring.resolve_scoring_dtype`), and the one line the benchmarks record of the CPU, its
matrix flags, oneDNN's bf16 kernel and torch (:func:`machine_description`).
"""

import functools
import os
import pathlib

import torch as th


@functools.cache
def cpu_has_fast_bf16() -> bool:
    """:return: whether this CPU multiplies bfloat16 matrices natively (AVX-512 BF16 or AMX; Linux only)"""
    try:
        flags = pathlib.Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return " avx512_bf16" in flags or " amx_bf16" in flags


def cuda_has_native_bf16() -> bool:
    """:return: whether the current CUDA GPU multiplies bfloat16 natively (Ampere and later), not by emulation"""
    try:
        return bool(th.cuda.is_bf16_supported(including_emulation=False))
    except TypeError:  # a torch whose check has no such argument (it then counts native support only)
        return bool(th.cuda.is_bf16_supported())


#: the ``train_dtype`` that gives bfloat16's numbers from float32 products
#: (:attr:`sb3_lifelong.numerics.fast_ops.HiddenLinear.simulated`)
SIMULATED_BFLOAT16 = "simulated_bfloat16"

#: what ``train_dtype`` accepts (:func:`resolve_train_dtype`)
TRAIN_DTYPES = ("float32", "bfloat16", SIMULATED_BFLOAT16, "auto")


def resolve_train_dtype(train_dtype: str, device: th.device) -> th.dtype:
    """
    The precision of the hidden-to-hidden products in the passes that record gradients
    (:class:`sb3_lifelong.numerics.fast_ops.HiddenLinear`).

    :param train_dtype: ``"float32"``, ``"bfloat16"``, ``"simulated_bfloat16"`` (bfloat16's roundings around float32
        products, the same numbers as ``"bfloat16"`` at float32's speed: to measure what bf16 does to learning on
        hardware without it; it resolves to bfloat16), or ``"auto"``: bfloat16 where the hardware multiplies it
        natively (a CPU with AVX-512 BF16 or AMX, a CUDA GPU with bf16), float32 elsewhere
    :param device: where the networks live
    :return: the torch dtype
    :raises ValueError: ``train_dtype`` is none of :data:`TRAIN_DTYPES`
    """
    if train_dtype not in TRAIN_DTYPES:
        raise ValueError(f"train_dtype must be one of {TRAIN_DTYPES}, got {train_dtype!r}")
    if train_dtype == SIMULATED_BFLOAT16:
        return th.bfloat16
    if train_dtype != "auto":
        return getattr(th, train_dtype)
    native = cuda_has_native_bf16() if device.type == "cuda" else device.type == "cpu" and cpu_has_fast_bf16()
    return th.bfloat16 if native else th.float32


#: the CPU flags that decide how fast the networks' matrix products run (what the benchmarks report)
MATRIX_FLAGS = ("amx_bf16", "amx_tile", "amx_int8", "avx512_bf16", "avx512f", "avx2", "fma")


def cpu_matrix_flags() -> list[str]:
    """:return: which of :data:`MATRIX_FLAGS` this CPU has (Linux ``/proc/cpuinfo``; empty elsewhere)"""
    try:
        text = pathlib.Path("/proc/cpuinfo").read_text()
    except OSError:
        return []
    line = next((line for line in text.splitlines() if line.startswith("flags")), "")
    present = set(line.partition(":")[2].split())
    return [flag for flag in MATRIX_FLAGS if flag in present]


def onednn_bf16_kernel(timeout: float = 120.0) -> str:
    """
    The oneDNN kernel that runs a bfloat16 matrix product with this torch build, read from ``ONEDNN_VERBOSE`` in a
    child process (e.g. ``brg_matmul:avx10_1_512_amx`` on an AMX CPU).

    :param timeout: seconds the child may take
    :return: the kernel's name, or a sentence saying that oneDNN did not run the product (torch's own kernel then)
    """
    import subprocess
    import sys

    code = "import torch; torch.set_num_threads(1); a = torch.randn(256, 256, dtype=torch.bfloat16); a @ a"
    env = {**os.environ, "ONEDNN_VERBOSE": "1", "OMP_NUM_THREADS": "1"}
    try:
        result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as error:
        return f"unknown ({type(error).__name__})"
    for line in (result.stdout + result.stderr).splitlines():
        fields = line.split(",")
        if "exec" in fields and "matmul" in fields:
            return fields[fields.index("matmul") + 1]
    return "none: oneDNN did not run the bf16 product (torch's own kernel)"


@functools.cache
def fused_products_supported(dtype: th.dtype) -> bool:
    """
    Whether oneDNN can run a ``Linear`` layer as one fused product (bias and ReLU as post-ops, on a weight laid out
    once) in ``dtype`` on this CPU: torch's private ``mkldnn._linear_pointwise`` and ``mkldnn._reorder_linear_weight``
    exist, and for bfloat16 oneDNN reports native support (AVX-512 or AMX; it refuses bf16 on an AVX2 CPU). The
    answer is checked by running a small product once, so a build whose ops are missing or broken reads False.

    :param dtype: ``torch.float32`` or ``torch.bfloat16``
    :return: whether :class:`sb3_lifelong.numerics.scoring.LowPrecisionCopy` can use the fused products
    """
    mkldnn = getattr(th.ops, "mkldnn", None)
    if mkldnn is None or not th.backends.mkldnn.is_available() or dtype not in (th.float32, th.bfloat16):
        return False
    try:
        if dtype == th.bfloat16 and not mkldnn._is_mkldnn_bf16_supported():
            return False
        weight, bias, x = th.ones(8, 8, dtype=dtype), th.zeros(8, dtype=dtype), th.ones(4, 8, dtype=dtype)
        out = mkldnn._linear_pointwise(x, mkldnn._reorder_linear_weight(weight, 4), bias, "relu", [], "")
    except (AttributeError, RuntimeError, NotImplementedError):
        return False
    return bool(out.shape == (4, 8) and th.all(out == 8))


def cpu_model() -> str:
    """:return: the CPU's model name (Linux ``/proc/cpuinfo``; elsewhere what ``platform`` knows)"""
    import platform

    try:
        return next(
            line.partition(":")[2].strip()
            for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        )
    except (OSError, StopIteration):
        return platform.processor() or platform.machine() or "unknown CPU"


def machine_description() -> str:
    """:return: one line for a benchmark's results: CPU, its matrix flags, the bf16 kernel, torch and its threads"""
    model = cpu_model()
    flags = ", ".join(cpu_matrix_flags()) or "none of " + "/".join(MATRIX_FLAGS)
    return (
        f"{model}; matrix flags: {flags}; oneDNN bf16 kernel: {onednn_bf16_kernel()}; "
        f"torch {th.__version__}, {th.get_num_threads()} thread(s)"
    )
