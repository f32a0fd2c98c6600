"""
Elementwise operations that torch runs slowly on a CPU, written faster with the same result: ReLU on bfloat16 (an
integer clamp), and tanh (``2 sigmoid(2x) - 1``) for the no-grad passes (:func:`tanh_in_place`) and, with its exact
gradient, for the networks' LayerNorm torsos (:class:`Tanh`). Each falls back to torch's own operation wherever the
faster form does not apply (another dtype or device). And a LayerNorm with its tanh written for the compiler, one
pass from a low-precision input to a low-precision output (:func:`layer_norm_tanh_into`).
"""

from typing import Optional

import torch as th
import torch.nn.functional as F
from torch import nn


def relu_in_place(x: th.Tensor) -> th.Tensor:
    """
    ``x.relu_()``, faster for bfloat16 on CPU: bfloat16's elementwise kernels convert every element to float32 and
    back (``relu_`` on ``[5120, 256]`` took 2.5x as long as the same bits clamped as int16). A bfloat16 with its sign
    bit set is a negative int16, so clamping the int16 view at 0 zeroes exactly the negative numbers (and -0.0,
    and NaNs with the sign bit set; a NaN in a target pass is lost anyway).

    :param x: the tensor, changed in place
    :return: ``x``
    """
    if x.dtype == th.bfloat16 and x.device.type == "cpu" and x.is_contiguous():
        x.view(th.int16).clamp_min_(0)
        return x
    return x.relu_()


def tanh_in_place(x: th.Tensor) -> th.Tensor:
    """
    ``x.tanh_()`` as ``2 sigmoid(2x) - 1``, for float32 on CPU: torch's CPU ``tanh`` ran 3-4x slower than its
    ``sigmoid`` here (5.1 vs 1.2 ms on ``[5120, 256]``). The identity is exact; in float32 the two differ by about
    1e-7 absolutely (a relative error up to about 1e-3 for ``|x| < 1e-4``: what follows a tanh in a network is a
    ``Linear``, which sees the absolute error).

    :param x: the tensor, changed in place
    :return: ``x``
    """
    if x.dtype == th.float32 and x.device.type == "cpu":
        return _tanh_of_doubled(x.mul_(2.0))
    return x.tanh_()


def _tanh_of_doubled(doubled: th.Tensor) -> th.Tensor:
    """:return: ``tanh(x)`` from ``doubled = 2x``, in place: ``2 sigmoid(2x) - 1``"""
    return doubled.sigmoid_().mul_(2.0).sub_(1.0)


class _TanhBySigmoid(th.autograd.Function):
    """``tanh(x) = 2 sigmoid(2x) - 1`` forward; backward from the output, ``grad * (1 - y^2)``, as torch's tanh."""

    @staticmethod
    def forward(ctx: th.autograd.function.FunctionCtx, x: th.Tensor) -> th.Tensor:  # type: ignore[override]
        y = _tanh_of_doubled(x.mul(2.0))
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx: th.autograd.function.FunctionCtx, grad: th.Tensor) -> th.Tensor:  # type: ignore[override]
        (y,) = ctx.saved_tensors  # type: ignore[attr-defined]
        return th.ops.aten.tanh_backward(grad, y)


def fast_tanh(x: th.Tensor) -> th.Tensor:
    """
    ``th.tanh(x)``, differentiable, computed as :func:`tanh_in_place` does for a float32 CPU tensor (torch's own
    ``tanh`` elsewhere). Its gradient is torch's formula on the output, ``1 - y^2``; under ``torch.compile``, the
    same function written out of place, whose gradient autograd derives (equal up to rounding).

    :param x: the input (not changed)
    :return: ``tanh(x)``
    """
    if x.dtype == th.float32 and x.device.type == "cpu":
        if th.compiler.is_compiling():
            # out of place, its gradient derived by autograd: torch 2.11's compiler got the in-place autograd.Function's
            # gradient wrong on an AVX-512 (AMX) Xeon, by up to 30 % (benchmarks/results/speed/fast_paths.md)
            return 2.0 * th.sigmoid(2.0 * x) - 1.0
        return _TanhBySigmoid.apply(x)
    return th.tanh(x)


class Tanh(nn.Tanh):
    """
    ``nn.Tanh`` computed by :func:`fast_tanh`, the tanh of the LayerNorm torsos
    (:func:`sb3_lifelong.common.policies.mlp_layers`). Forward and backward on ``[1024, 256]`` float32 took about half
    of torch's time on an AMD EPYC (AVX2); within about 2e-7 of it. A subclass, so that code that looks for
    ``nn.Tanh`` finds it.
    """

    def forward(self, input: th.Tensor) -> th.Tensor:
        return fast_tanh(input)


class HiddenLinear(nn.Linear):
    """
    An ``nn.Linear`` between two hidden layers (:func:`sb3_lifelong.common.policies.mlp_layers` makes every such layer
    one), whose product can run in a lower precision in the passes that record gradients: with ``compute_dtype`` set
    (bfloat16), the input, weight and bias are rounded to it, multiplied there, and the output comes back in float32;
    the gradients flow back through the roundings to the float32 parameters (mixed precision, as under
    ``torch.autocast``, for these layers only: the first layer, the output layers, LayerNorm and the losses stay
    float32). Passes without gradients (predictions, targets) and other dtypes run in the layer's own precision.
    ``compute_dtype`` is not part of the state: the algorithm sets it (``train_dtype``).

    With :attr:`simulated`, the product gives the same numbers from float32 arithmetic: the input, weight and bias are
    rounded to ``compute_dtype`` and back, multiplied in float32 (a product of two bf16 numbers is exact in float32,
    and the hardware's bf16 products sum in float32 too), and the output is rounded; in the backward pass the incoming
    gradient and the gradients it gives are rounded the same way (autograd's rule for the casts). Only the sums differ
    from a bf16 kernel's, in order and, on AMX, in how they accumulate: a result can differ by one bf16 rounding step,
    and where a sum nearly cancels by up to 2^-14 of the sum of its terms' absolute values (measured on an AMX Xeon;
    ``benchmarks/speed/bf16_kernel_vs_simulation.py``). It costs about a float32 product, where a CPU without native bf16
    emulates it several times slower: it measures what bf16 does to learning on any hardware. Eager only:
    ``torch.compile`` fuses a round trip through bf16 away.
    """

    #: the precision of the product in passes that record gradients; None: the layer's own
    compute_dtype: Optional[th.dtype] = None
    #: give ``compute_dtype``'s roundings around a float32 product instead of multiplying in ``compute_dtype``
    simulated: bool = False

    @classmethod
    def of(cls, layer: nn.Linear) -> "HiddenLinear":
        """:return: ``layer`` as a :class:`HiddenLinear`, with the same parameter tensors (nothing initialised again)"""
        hidden = cls.__new__(cls)
        hidden.__dict__.update(layer.__dict__)
        return hidden

    def forward(self, input: th.Tensor) -> th.Tensor:
        dtype = self.compute_dtype
        if dtype is None or input.dtype != th.float32 or not th.is_grad_enabled():
            return F.linear(input, self.weight, self.bias)
        if self.simulated:
            bias = None if self.bias is None else _round_trip(self.bias, dtype)
            return _round_trip(F.linear(_round_trip(input, dtype), _round_trip(self.weight, dtype), bias), dtype)
        bias = None if self.bias is None else self.bias.to(dtype)
        return F.linear(input.to(dtype), self.weight.to(dtype), bias).float()


def _round_trip(x: th.Tensor, dtype: th.dtype) -> th.Tensor:
    """:return: ``x`` rounded to ``dtype`` and back to float32; its gradient is rounded the same way (autograd)"""
    return x.to(dtype).float()


def layer_norm_tanh_into(x: th.Tensor, weight: th.Tensor, bias: th.Tensor, eps: float, out: th.Tensor) -> th.Tensor:
    """
    ``tanh(layer_norm(x))`` over the last dimension, computed in float32 and written into ``out`` in its dtype: for
    ``torch.compile``, which makes it one loop over the rows that reads ``x`` (bf16) and writes ``out`` (bf16) with
    no float32 tensor in between. The tanh is ``2 sigmoid(2y) - 1`` in float32 (torch's and inductor's tanh are slow on
    CPUs), so the result is the float32 one rounded once to ``out``'s dtype.

    :param x: ``[rows, features]``
    :param weight: the LayerNorm's scale ``[features]``
    :param bias: its shift ``[features]``
    :param eps: its epsilon
    :param out: ``[rows, features]``, overwritten
    :return: ``out``
    """
    wide = x.float()
    mean = wide.mean(dim=-1, keepdim=True)
    centred = wide - mean
    variance = centred.square().mean(dim=-1, keepdim=True)
    normed = centred * th.rsqrt(variance + eps) * weight + bias
    return out.copy_(2.0 * th.sigmoid(2.0 * normed) - 1.0)
