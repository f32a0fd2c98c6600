"""
The bf16 kernel of this CPU against ``train_dtype="simulated_bfloat16"`` (the same layer's numbers from float32
products), on one 128 x 256 x 256 hidden layer, forward and backward: per tensor, the fraction of elements that differ,
the largest difference in bf16 rounding steps of the element, and the largest difference relative to the sum of the
absolute values of the products summed into the element (its conditioning; a reordered float32 sum differs by at most
K 2^-24 of it). ``tests/test_train_dtype.py`` bounds the difference by one step plus 2^-12 of that sum.

    OMP_NUM_THREADS=1 python benchmarks/bf16_kernel_vs_simulation.py
"""

import torch as th
import torch.nn.functional as F
from torch import nn

from sb3_lifelong.common.fast_ops import HiddenLinear
from sb3_lifelong.common.hardware import machine_description


def rounded(t: th.Tensor) -> th.Tensor:
    return t.detach().to(th.bfloat16).float()


def main() -> None:
    print(machine_description())
    th.manual_seed(0)
    layers = {}
    for simulated in (False, True):
        layers[simulated] = HiddenLinear.of(nn.Linear(256, 256))
        layers[simulated].compute_dtype, layers[simulated].simulated = th.bfloat16, simulated
    layers[True].load_state_dict(layers[False].state_dict())
    x = th.randn(128, 256)
    results = {}
    for simulated, layer in layers.items():
        inp = x.clone().requires_grad_(True)
        out = layer(inp)
        grads = th.autograd.grad((out * out.detach().sin()).sum(), [inp, layer.weight, layer.bias])
        results[simulated] = (out.detach(), *grads)
    weight, bias, inputs = rounded(layers[False].weight), rounded(layers[False].bias), rounded(x)
    grad_out = rounded(results[True][0].sin()).abs()
    terms = (inputs.abs() @ weight.abs().T + bias.abs(), grad_out @ weight.abs(), grad_out.T @ inputs.abs(), grad_out.sum(0))
    exact = F.linear(x, layers[False].weight, layers[False].bias).detach()
    print("| tensor | elements differing | largest, in bf16 steps of the element | largest / sum of terms | test bound used |")
    print("| --- | --- | --- | --- | --- |")
    rows = zip(("output", "input grad", "weight grad", "bias grad"), results[False], results[True], terms)
    for name, real, simulated, term in rows:
        difference, magnitude = (real - simulated).abs(), th.maximum(real.abs(), simulated.abs())
        steps = difference / (magnitude * 2.0**-7).clamp_min(1e-30)
        bound = magnitude * 2.0**-7 + term * 2.0**-12
        relative = float((difference / term).max())
        relative_text = f"2^{float(th.log2(th.tensor(relative))):.1f}" if relative > 0 else "0"
        print(
            f"| {name} | {float((difference > 0).float().mean()):.3%} | {float(steps.max()):.2f} | {relative_text} | "
            f"{float((difference / bound).max()):.2f} |"
        )
    difference = (exact - results[False][0]).abs()
    bound = th.maximum(exact.abs(), results[False][0].abs()) * 2.0**-7 + terms[0] * 2.0**-12
    print(f"float32's output against the kernel's, in the test's bound: {float((difference / bound).max()):.2f} (must be > 1)")


if __name__ == "__main__":
    main()
