"""Tensor helpers shared by the algorithms: sample many actions per state and score them in one critic call."""

import functools
import os
import pathlib
from typing import Optional, Union

import torch as th
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn


def tile_obs(obs: PyTorchObs, num_samples: int) -> PyTorchObs:
    """
    Repeat a batch of observations ``num_samples`` times along the batch dimension, sample-major:
    row ``n * batch + b`` holds observation ``b``.

    :param obs: observations ``[batch, ...]`` (or a dict of them)
    :param num_samples: number of copies
    :return: observations ``[num_samples * batch, ...]``
    """
    if isinstance(obs, dict):
        return {key: tile_obs(value, num_samples) for key, value in obs.items()}  # type: ignore[misc]
    return obs.repeat(num_samples, *([1] * (obs.dim() - 1)))


def sample_gaussian(mean: th.Tensor, std: th.Tensor, num_samples: int) -> th.Tensor:
    """
    :param mean: ``[batch, action_dim]``
    :param std: ``[batch, action_dim]``
    :param num_samples: number of samples per state
    :return: samples ``[num_samples, batch, action_dim]`` (not clipped)
    """
    noise = th.randn((num_samples, *mean.shape), dtype=mean.dtype, device=mean.device)
    return mean.unsqueeze(0) + std.unsqueeze(0) * noise


def q_min(q_values: Union[tuple[th.Tensor, ...], list[th.Tensor]]) -> th.Tensor:
    """
    :param q_values: one ``[batch, 1]`` tensor per critic
    :return: the element-wise minimum over critics, ``[batch, 1]``
    """
    if len(q_values) == 1:
        return q_values[0]
    return th.min(th.cat(list(q_values), dim=1), dim=1, keepdim=True)[0]


def mlp_layers(
    input_dim: int, output_dim: int, net_arch: list[int], activation_fn: type[nn.Module], layer_norm: bool = False
) -> list[nn.Module]:
    """
    SB3's ``create_mlp``, or with ``layer_norm`` the torso of Acme's ``LayerNormMLP`` (its MPO's actor and critic
    networks): the first hidden layer is ``Linear -> LayerNorm -> tanh``, the others ``Linear -> activation_fn``.

    :param input_dim: Input features
    :param output_dim: Output units of a last ``Linear`` without activation (none if <= 0)
    :param net_arch: Hidden layer widths
    :param activation_fn: Activation of the hidden layers (all of them without ``layer_norm``; the later ones with)
    :param layer_norm: LayerNorm and tanh after the first hidden layer
    :return: the modules, for ``nn.Sequential``
    """
    if not layer_norm or not net_arch:
        return create_mlp(input_dim, output_dim, net_arch, activation_fn)
    first = [nn.Linear(input_dim, net_arch[0]), nn.LayerNorm(net_arch[0]), nn.Tanh()]
    return first + create_mlp(net_arch[0], output_dim, net_arch[1:], activation_fn)


def with_fast_optimizer(optimizer_class: type[th.optim.Optimizer], optimizer_kwargs: Optional[dict]) -> dict:
    """
    :param optimizer_class: the optimizer class a policy was given
    :param optimizer_kwargs: the keyword arguments it was given (None: none)
    :return: the keyword arguments, with Adam's fused implementation unless the user chose an implementation
    """
    kwargs = dict(optimizer_kwargs or {})
    if optimizer_class in (th.optim.Adam, th.optim.AdamW) and not {"fused", "foreach"} & set(kwargs):
        kwargs["fused"] = True
    return kwargs


SCORING_DTYPES = ("auto", "float32", "bfloat16")
#: narrowest hidden layer for which ``scoring_dtype="auto"`` picks bfloat16: below it the matrices are too small
#: for the faster arithmetic to pay for the conversions (64-wide layers ran 2x slower in bf16 on an AVX-512 CPU)
AUTO_BF16_MIN_WIDTH = 128


@functools.cache
def cpu_has_fast_bf16() -> bool:
    """:return: whether this CPU multiplies bfloat16 matrices natively (AVX-512 BF16 or AMX; Linux only)"""
    try:
        flags = pathlib.Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return " avx512_bf16" in flags or " amx_bf16" in flags


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


def machine_description() -> str:
    """:return: one line for a benchmark's results: CPU, its matrix flags, the bf16 kernel, torch and its threads"""
    import platform

    model = "unknown CPU"
    try:
        model = next(
            line.partition(":")[2].strip()
            for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        )
    except (OSError, StopIteration):
        model = platform.processor() or platform.machine()
    flags = ", ".join(cpu_matrix_flags()) or "none of " + "/".join(MATRIX_FLAGS)
    return (
        f"{model}; matrix flags: {flags}; oneDNN bf16 kernel: {onednn_bf16_kernel()}; "
        f"torch {th.__version__}, {th.get_num_threads()} thread(s)"
    )


def resolve_scoring_dtype(scoring_dtype: str, critic: nn.Module, device: th.device) -> th.dtype:
    """
    The precision of the no-grad passes that score sampled actions.

    :param scoring_dtype: ``"float32"`` (exact), ``"bfloat16"``, or ``"auto"``: bfloat16 where the hardware
        multiplies it natively (a CUDA GPU with bf16, a CPU with AVX-512 BF16 or AMX) and every hidden layer of
        the critic is at least ``AUTO_BF16_MIN_WIDTH`` wide, float32 otherwise
    :param critic: the critic whose Q-networks will be scored
    :param device: the device the critic lives on
    :return: the torch dtype
    """
    if scoring_dtype not in SCORING_DTYPES:
        raise ValueError(f"scoring_dtype must be one of {SCORING_DTYPES}, got {scoring_dtype!r}")
    if scoring_dtype != "auto":
        return getattr(th, scoring_dtype)
    if not isinstance(critic, ContinuousCritic):
        return th.float32
    hidden: list[int] = []
    for q_net in critic.q_networks:
        hidden += [m.out_features for m in q_net.modules() if isinstance(m, nn.Linear)][:-1]
    wide = bool(hidden) and min(hidden) >= AUTO_BF16_MIN_WIDTH
    native = th.cuda.is_bf16_supported() if device.type == "cuda" else device.type == "cpu" and cpu_has_fast_bf16()
    return th.bfloat16 if wide and native else th.float32


class LowPrecisionCopy:
    """
    A copy of a critic's Q-network weights in a lower precision (bfloat16), for the no-grad passes that score
    many sampled actions. The copy does not follow the critic by itself: call :meth:`sync` after every change
    of the critic's weights (a target update, an optimizer step, a load).

    :param critic: the critic (``ContinuousCritic``)
    :param dtype: the precision of the copy
    """

    def __init__(self, critic: ContinuousCritic, dtype: th.dtype = th.bfloat16) -> None:
        self.critic = critic
        self.dtype = dtype
        self.weights: dict[int, tuple[th.Tensor, Optional[th.Tensor]]] = {}
        self.layers = self._hidden_layers()
        for module in self.layers:
            bias = None if module.bias is None else module.bias.detach().to(dtype)
            # stored transposed and contiguous: the layout addmm reads fastest
            self.weights[id(module)] = (module.weight.detach().t().contiguous().to(dtype), bias)

    def _hidden_layers(self) -> list[nn.Linear]:
        """
        Every ``Linear`` of the Q-networks but the last of each: the output layer stays in the critic's precision,
        so that Q is not rounded to bf16 as a whole (bf16 keeps 8 bits: a Q of 300 would be off by up to 1).
        """
        layers = []
        for q_net in self.critic.q_networks:
            linears = [module for module in q_net.modules() if isinstance(module, nn.Linear)]
            layers += linears[:-1]
        return layers

    @th.no_grad()
    def sync(self) -> None:
        """Copy the critic's current weights into the low-precision copy (in place, no allocation)."""
        for module in self.layers:
            weight, bias = self.weights[id(module)]
            weight.copy_(module.weight.t())
            if bias is not None:
                bias.copy_(module.bias)


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


def _reused_buffer(
    critic: nn.Module, key: tuple[int, int, int], shape: tuple[int, ...], like: th.Tensor, dtype: Optional[th.dtype] = None
) -> th.Tensor:
    """
    A tensor kept on the critic under ``key`` and reused across gradient steps (a fresh ``[num_samples * batch, 256]``
    tensor per call costs more in page faults than the work written into it); made again when the shape, dtype or
    device changes.

    :param critic: the module that keeps the buffers
    :param key: ``(q-network index, module position, rows)``
    :param shape: the tensor's shape
    :param like: a tensor of the device (and, unless ``dtype`` is given, the dtype) wanted
    :param dtype: the dtype wanted
    :return: the buffer (uninitialised when new)
    """
    buffers: dict[tuple[int, int, int], th.Tensor] = critic.__dict__.setdefault("_no_grad_buffers", {})
    dtype = like.dtype if dtype is None else dtype
    out = buffers.get(key)
    if out is None or out.shape != shape or out.dtype != dtype or out.device != like.device:
        out = buffers[key] = like.new_empty(shape, dtype=dtype)
    return out


def _run_mlp_no_grad(
    critic: nn.Module,
    index: int,
    mlp: nn.Module,
    inputs: th.Tensor,
    low_precision: Optional[LowPrecisionCopy] = None,
    first: int = 0,
    owned: bool = False,
) -> th.Tensor:
    """
    Evaluate a ``Linear``/activation stack without autograd, writing every ``Linear`` output into a buffer kept
    on the critic (reused across gradient steps) and applying ReLUs in place. Same result, bit for bit, as
    ``mlp(inputs)``, without allocating (and page-faulting in) several ``[num_samples * batch, 256]``
    temporaries per call. With ``low_precision`` the layers use its weights (``inputs`` must have its dtype).
    ``first``: start at this module of ``mlp`` (the earlier ones were applied by the caller, into ``inputs``, which
    it owns when ``owned``: activations then run in place on it).
    """
    x = inputs
    module: nn.Module
    for position, module in enumerate(mlp):  # type: ignore[arg-type]
        if position < first:
            continue
        if isinstance(module, nn.Linear):
            if low_precision is not None and id(module) in low_precision.weights:
                weight_t, bias = low_precision.weights[id(module)]
            else:
                weight_t, bias = module.weight.t(), module.bias
                if x.dtype != module.weight.dtype:  # the output layer of a low-precision pass: back to float32
                    key = (index, -position, x.shape[0])
                    x = _reused_buffer(critic, key, tuple(x.shape), x, module.weight.dtype).copy_(x)
            out = _reused_buffer(critic, (index, position, x.shape[0]), (x.shape[0], module.out_features), x)
            if bias is not None:
                th.addmm(bias, x, weight_t, out=out)
            else:
                th.mm(x, weight_t, out=out)
            x, owned = out, True
        elif isinstance(module, nn.ReLU) and owned:
            relu_in_place(x)
        elif isinstance(module, nn.LayerNorm) and low_precision is not None and x.dtype == low_precision.dtype:
            # normalised in the layer's own precision (its statistics over a row need more than bf16's 8 bits); with
            # the tanh that follows it in a LayerNorm torso, both in float32 on reused buffers, then one conversion
            after = mlp[position + 1] if position + 1 < len(mlp) else None  # type: ignore[arg-type,index]
            followed_by_tanh = isinstance(after, nn.Tanh)
            x, owned = _layer_norm_no_grad(critic, (index, position), module, x, followed_by_tanh), True
            if followed_by_tanh:
                first = position + 2  # the tanh is applied
        else:
            x, owned = module(x), False
    return x


def tanh_in_place(x: th.Tensor) -> th.Tensor:
    """
    ``x.tanh_()`` as ``2 sigmoid(2x) - 1``, for float32 on CPU: torch's CPU ``tanh`` ran 4x slower than its
    ``sigmoid`` here (5.1 vs 1.2 ms on ``[5120, 256]``). The identity is exact; in float32 the two differ by about
    1e-7 absolutely (a relative error up to about 1e-3 for ``|x| < 1e-4``, below bfloat16's rounding). Meant for
    no-grad low-precision passes, whose output is rounded to bfloat16 next.

    :param x: the tensor, changed in place
    :return: ``x``
    """
    if x.dtype == th.float32 and x.device.type == "cpu":
        return x.mul_(2.0).sigmoid_().mul_(2.0).sub_(1.0)
    return x.tanh_()


def _layer_norm_no_grad(
    critic: nn.Module, key: tuple[int, int], module: nn.LayerNorm, x: th.Tensor, then_tanh: bool
) -> th.Tensor:
    """
    ``module(x)`` (and the tanh after it when ``then_tanh``) for a low-precision ``x``: normalised in float32 into
    reused buffers (a fresh ``[5120, 256]`` tensor per call cost more in page faults than the arithmetic), returned
    in ``x``'s dtype in another reused buffer.
    """
    index, position = key
    rows, shape = x.shape[0], tuple(x.shape)
    wide = _reused_buffer(critic, (index, -1000 - position, rows), shape, x, th.float32).copy_(x)
    normed = _reused_buffer(critic, (index, -2000 - position, rows), shape, x, th.float32)
    stats = (rows, 1) if len(module.normalized_shape) == 1 and x.dim() == 2 else None
    if stats is not None and module.weight is not None and module.bias is not None:
        mean = _reused_buffer(critic, (index, -3000 - position, rows), stats, x, th.float32)
        rstd = _reused_buffer(critic, (index, -4000 - position, rows), stats, x, th.float32)
        th.ops.aten.native_layer_norm.out(
            wide, list(module.normalized_shape), module.weight, module.bias, module.eps, out0=normed, out1=mean, out2=rstd
        )
    else:
        normed.copy_(module(wide))
    if then_tanh:
        tanh_in_place(normed)
    return _reused_buffer(critic, (index, -5000 - position, rows), shape, x).copy_(normed)


#: the first layer is split into a per-state and a per-sample product (:func:`_first_layer_split`) when the
#: features are at least this wide and at least twice the action: measured on this CPU, the first layer 3x faster
#: for OP3-sized inputs (68 + 20; the whole pass 1.18x, benchmarks/results/scoring_split.md), and slower than one
#: product for Hopper-sized ones (11 + 3)
SPLIT_MIN_FEATURES = 32


def _first_layer_split(
    critic: nn.Module, index: int, q_net: nn.Module, features: th.Tensor, actions: th.Tensor, low_precision: LowPrecisionCopy
) -> th.Tensor:
    """
    The first ``Linear`` of a Q-network over ``num_samples`` actions per state, without repeating the state's
    part: ``W [s; a] + b = (W_s s + b) + W_a a``, the first term once per state (``[batch, hidden]``) and
    broadcast over the samples. Same values as the stacked product up to the summation order (a low-precision
    pass only). What follows the layer (a ReLU, or the LayerNorm torso's LayerNorm and tanh) is the caller's.

    :param features: ``[batch, features_dim]``, in the copy's dtype
    :param actions: ``[num_samples * batch, action_dim]``, sample-major (row ``n * batch + b``), in the copy's dtype
    :return: the layer's output ``[num_samples * batch, hidden]`` (a reused buffer)
    """
    weight_t, bias = low_precision.weights[id(q_net[0])]  # type: ignore[index]
    width = features.shape[1]
    per_state = th.mm(features, weight_t[:width])
    if bias is not None:
        per_state.add_(bias)
    out = _reused_buffer(critic, (index, 0, actions.shape[0]), (actions.shape[0], weight_t.shape[1]), actions)
    th.mm(actions, weight_t[width:], out=out)
    out.view(-1, features.shape[0], out.shape[1]).add_(per_state)
    return out


def _splits_first_layer(
    q_net: nn.Module, features_dim: int, action_dim: int, low_precision: Optional[LowPrecisionCopy]
) -> bool:
    modules = list(q_net)  # type: ignore[call-overload]
    return (
        low_precision is not None
        and features_dim >= max(SPLIT_MIN_FEATURES, 2 * action_dim)
        and len(modules) > 2
        and isinstance(modules[0], nn.Linear)
        and id(modules[0]) in low_precision.weights
    )


def score_actions(
    critic: ContinuousCritic, obs: PyTorchObs, actions: th.Tensor, low_precision: Optional[LowPrecisionCopy] = None
) -> th.Tensor:
    """
    Q-values of several actions per state, in a single critic call over ``num_samples * batch`` rows.
    Actions are clipped to the normalised bounds ``[-1, 1]`` first, as the environment would clip them.

    Without autograd (target computations) the features are extracted once per state rather than once per
    sample, and the critic's MLPs run on reused buffers (see ``_run_mlp_no_grad``).

    :param critic: the critic (minimum over its Q-networks is taken)
    :param obs: observations ``[batch, ...]``
    :param actions: ``[num_samples, batch, action_dim]``
    :param low_precision: a synchronised low-precision copy of ``critic``: without autograd the Q-networks run
        in its precision (the features and the result stay float32)
    :return: Q-values ``[num_samples, batch]``
    """
    num_samples, batch_size, action_dim = actions.shape
    flat_actions = actions.reshape(num_samples * batch_size, action_dim).clamp(-1.0, 1.0)
    if th.is_grad_enabled() or not isinstance(critic, ContinuousCritic):
        return q_min(critic(tile_obs(obs, num_samples), flat_actions)).reshape(num_samples, batch_size)
    features = critic.extract_features(obs, critic.features_extractor)
    q_values = []
    q_input = split_inputs = None
    for index, q_net in enumerate(critic.q_networks):
        if _splits_first_layer(q_net, features.shape[1], action_dim, low_precision):
            assert low_precision is not None
            if split_inputs is None:  # converted once for all the Q-networks
                split_inputs = (features.to(low_precision.dtype), flat_actions.to(low_precision.dtype))
            hidden = _first_layer_split(critic, index, q_net, *split_inputs, low_precision)
            q_values.append(_run_mlp_no_grad(critic, index, q_net, hidden, low_precision, first=1, owned=True))
            continue
        if q_input is None:
            q_input = th.cat([features.repeat(num_samples, 1), flat_actions], dim=1)
            if low_precision is not None:
                q_input = q_input.to(low_precision.dtype)
        q_values.append(_run_mlp_no_grad(critic, index, q_net, q_input, low_precision))
    # copy out of the reused buffer (the result outlives the next call), in the critic's own precision
    return q_min(q_values).reshape(num_samples, batch_size).to(features.dtype, copy=True)
