"""
The bf16 kernel of this CPU against ``train_dtype="simulated_bfloat16"`` (the same layer's numbers from float32
products), on one 128 x 256 x 256 hidden layer, forward and backward: per tensor, the fraction of elements that differ,
the largest difference in bf16 rounding steps of the element, and the largest difference relative to the sum of the
absolute values of the products summed into the element (its conditioning; a reordered float32 sum differs by at most
K 2^-24 of it). ``tests/common/test_train_dtype.py`` bounds the difference by one step plus 2^-12 of that sum
(:func:`bounds_apart`), with this script's functions.

    OMP_NUM_THREADS=1 python benchmarks/speed/bf16_kernel_vs_simulation.py
"""

import torch as th
from torch import nn

from sb3_lifelong.numerics.fast_ops import HiddenLinear
from sb3_lifelong.numerics.hardware import machine_description

#: the tensors compared: the layer's output, then the gradients of a loss with respect to its input, weight and bias
NAMES = ("output", "input grad", "weight grad", "bias grad")


def rounded(t: th.Tensor) -> th.Tensor:
    """:return: ``t`` rounded to bf16 and back to float32"""
    return t.detach().to(th.bfloat16).float()


def weights_and_inputs() -> tuple[nn.Linear, th.Tensor]:
    """
    :return: the layer and its inputs, drawn from seed 0 in the order of the case measured on the AMX Xeon (a second
        layer's initialisation drawn, and not used, between the two)
    """
    th.manual_seed(0)
    layer = nn.Linear(256, 256)
    nn.Linear(256, 256)
    return layer, th.randn(128, 256)


def one_layer(compute: str) -> tuple[th.Tensor, ...]:
    """
    :param compute: ``"bfloat16"`` (the CPU's kernel), ``"simulated"`` (float32 products with bf16's roundings) or
        ``"float32"``
    :return: the layer's output and the gradients of ``sum(out * sin(out))`` (``sin`` of the output held fixed) with
        respect to its input, weight and bias (:data:`NAMES`), on the same weights and inputs (seed 0) whatever ``compute``
    """
    layer, inputs = weights_and_inputs()
    layer = HiddenLinear.of(layer)
    layer.compute_dtype = None if compute == "float32" else th.bfloat16
    layer.simulated = compute == "simulated"
    inputs.requires_grad_(True)
    out = layer(inputs)
    grads = th.autograd.grad((out * out.detach().sin()).sum(), [inputs, layer.weight, layer.bias])
    return (out.detach(), *grads)


def sums_of_terms(output: th.Tensor) -> tuple[th.Tensor, ...]:
    """
    :param output: the layer's output in bf16 (whose ``sin`` is the loss's gradient with respect to it)
    :return: per tensor of :data:`NAMES`, the sum of the absolute values of the bf16 products summed into each element
    """
    layer, inputs = weights_and_inputs()
    weight, bias, inputs = rounded(layer.weight), rounded(layer.bias), rounded(inputs)
    grad_out = rounded(output.sin()).abs()
    return (
        inputs.abs() @ weight.abs().T + bias.abs(),
        grad_out @ weight.abs(),
        grad_out.T @ inputs.abs(),
        grad_out.sum(0),
    )


def bounds_apart(a: th.Tensor, b: th.Tensor, terms: th.Tensor) -> th.Tensor:
    """
    :param terms: :func:`sums_of_terms`'s tensor for ``a`` and ``b``
    :return: |a - b| in units of the bound within which two bf16 products of the same inputs agree: one bf16 rounding
        step at their magnitude (2^-7 relative) plus 2^-12 of ``terms``, for the order and blocking of the sums (the
        AMX kernel of a Xeon, measured against the simulation: up to 2^-14 of ``terms``, on near-cancelling sums)
    """
    bound = th.maximum(a.abs(), b.abs()) * 2.0**-7 + terms * 2.0**-12
    return (a - b).abs() / bound.clamp_min(th.finfo(th.float32).tiny)


def main() -> None:
    print(machine_description())
    real, simulated, exact = (one_layer(compute) for compute in ("bfloat16", "simulated", "float32"))
    terms = sums_of_terms(real[0])
    print("| tensor | elements differing | largest, in bf16 steps of the element | largest / sum of terms | test bound used |")
    print("| --- | --- | --- | --- | --- |")
    for name, a, b, term in zip(NAMES, real, simulated, terms):
        difference, magnitude = (a - b).abs(), th.maximum(a.abs(), b.abs())
        steps = difference / (magnitude * 2.0**-7).clamp_min(1e-30)
        relative = float((difference / term).max())
        relative_text = f"2^{float(th.log2(th.tensor(relative))):.1f}" if relative > 0 else "0"
        print(
            f"| {name} | {float((difference > 0).float().mean()):.3%} | {float(steps.max()):.2f} | {relative_text} | "
            f"{float(bounds_apart(a, b, term).max()):.2f} |"
        )
    for name, a, b, term in zip(NAMES, real, exact, terms):
        print(f"float32's {name} against the kernel's, in the test's bound: {float(bounds_apart(a, b, term).max()):.2f} (> 1)")


if __name__ == "__main__":
    main()
