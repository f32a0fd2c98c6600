"""
Scoring sampled actions: the Q-values of ``num_samples`` actions per state in one critic call (:func:`score_actions`),
which MPO's E-step and target and CRR's advantage baseline and TD target all rest on, and the CPU engine that makes
its no-grad pass cheap (:func:`network_outputs`), for SB3's ``ContinuousCritic`` and for any critic that says how its
Q-networks' outputs become Q-values (a ``q_values_of`` method: the categorical critic's expected value, see
:func:`runs_no_grad_pass`):

- the features are extracted once per state, not once per sample;
- the Q-networks' ``Linear`` layers write into buffers kept on the critic and reused across gradient steps, and the
  activations run in place (:func:`_run_mlp_no_grad`), bit for bit ``mlp(inputs)``;
- with a :class:`LowPrecisionCopy` (``scoring_dtype``, :func:`resolve_scoring_dtype`) the hidden layers run in
  bfloat16, a LayerNorm and its tanh in float32 (:func:`_layer_norm_no_grad`; or as one compiled kernel), the
  output layer in float32; the first layer is then split into a per-state and a per-sample product when the
  features are wide (:func:`_first_layer_split`); where oneDNN fuses them (a CPU with AVX-512 or AMX), each hidden layer is one
  product with its bias and ReLU as post-ops, on weights laid out once per sync (:meth:`LowPrecisionCopy.fused_linear`;
  its outputs are new tensors, not the reused buffers).

**The reused buffers.** They live in ``critic.__dict__["_no_grad_buffers"]``, a dict keyed
``(q-network index, slot, rows)``, where ``rows`` is the pass's ``num_samples * batch`` and ``slot`` says which
tensor of the pass it holds, from the position ``p`` of a module in its Q-network (an ``nn.Sequential``):

- ``p``: the output of the ``Linear`` at ``p`` (``0`` also for the split first layer);
- ``-p``: the input of the ``Linear`` at ``p`` converted to its weights' precision (the float32 output layer after
  a low-precision pass);
- ``LAYER_NORM_INPUT - p``, ``LAYER_NORM_OUTPUT - p``, ``LAYER_NORM_MEAN - p``, ``LAYER_NORM_RSTD - p``: for the
  LayerNorm at ``p`` in a low-precision pass, its input in float32, its normalised output in float32 (the tanh
  applied in place), and its row statistics; ``LAYER_NORM_RESULT - p``: that output back in the pass's precision.

A buffer is made again when its shape, dtype or device changes (:func:`_reused_buffer`); it is uninitialised
when new, and every pass writes it whole before reading it.
"""

import warnings
from typing import Callable, Optional, Union, cast

import torch as th
from stable_baselines3.common.policies import BaseModel, ContinuousCritic
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn

from sb3_lifelong.numerics.compiling import LazyCompiled
from sb3_lifelong.numerics.fast_ops import layer_norm_tanh_into, relu_in_place, tanh_in_place
from sb3_lifelong.numerics.hardware import cpu_has_fast_bf16, cuda_has_native_bf16, fused_products_supported

SCORING_DTYPES = ("auto", "float32", "bfloat16")
#: narrowest hidden layer for which ``scoring_dtype="auto"`` picks bfloat16: below it the matrices are too small
#: for the faster arithmetic to pay for the conversions (64-wide layers ran 2x slower in bf16 on an AVX-512 CPU)
AUTO_BF16_MIN_WIDTH = 128

#: the slots of a LayerNorm's buffers (see the module's description), below every ``Linear``'s ``-p``
LAYER_NORM_INPUT, LAYER_NORM_OUTPUT, LAYER_NORM_MEAN, LAYER_NORM_RSTD, LAYER_NORM_RESULT = -1000, -2000, -3000, -4000, -5000


def tile_obs(obs: PyTorchObs, num_samples: int) -> PyTorchObs:
    """
    Repeat a batch of observations ``num_samples`` times along the batch dimension, sample-major:
    row ``n * batch + b`` holds observation ``b``.

    :param obs: observations ``[batch, ...]`` (or a dict of them)
    :param num_samples: number of copies
    :return: observations ``[num_samples * batch, ...]``
    """
    if isinstance(obs, dict):
        return {key: value.repeat(num_samples, *([1] * (value.dim() - 1))) for key, value in obs.items()}
    return obs.repeat(num_samples, *([1] * (obs.dim() - 1)))


def q_min(q_values: Union[tuple[th.Tensor, ...], list[th.Tensor]]) -> th.Tensor:
    """
    :param q_values: one ``[batch, 1]`` tensor per critic
    :return: the element-wise minimum over critics, ``[batch, 1]``
    """
    if len(q_values) == 1:
        return q_values[0]
    return th.min(th.cat(list(q_values), dim=1), dim=1, keepdim=True)[0]


def runs_no_grad_pass(critic: nn.Module) -> bool:
    """
    Whether :func:`score_actions` runs ``critic``'s no-grad pass itself (features once per state, reused buffers, a
    low-precision copy): for SB3's ``ContinuousCritic``, and for an SB3 ``BaseModel`` with ``q_networks`` (``nn.Sequential``
    each, called on ``[features, actions]`` as SB3's are) and a ``q_values_of(output)`` method that turns a
    Q-network's output ``[rows, ...]`` into Q-values ``[rows, 1]`` (the categorical critic's expected value). Any
    other critic is scored by calling it.

    :param critic: the critic
    :return: whether the engine runs it
    """
    if isinstance(critic, ContinuousCritic):
        return True
    return isinstance(critic, BaseModel) and callable(getattr(critic, "q_values_of", None)) and bool(_q_networks(critic))


def uses_engine(critic: nn.Module, low_precision: Optional["LowPrecisionCopy"] = None) -> bool:
    """
    :return: whether a pass of ``critic`` now runs on the engine: without autograd, for a critic it runs
        (:func:`runs_no_grad_pass`). While ``torch.compile`` traces the code, only a pass with a low-precision copy
        does (run eagerly, a break in the graph: the compiled graph would lose the bf16 products); a float32 pass is
        then traced as the critic's own call (inductor plans its buffers; the engine's reused buffers and ``out=``
        products would break its graph)
    """
    if th.is_grad_enabled() or not runs_no_grad_pass(critic):
        return False
    return low_precision is not None or not th.compiler.is_compiling()


def _q_networks(critic: nn.Module) -> list[nn.Module]:
    """:return: the critic's Q-networks (its ``q_networks`` list; empty without one)"""
    return list(getattr(critic, "q_networks", []))


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
    if not runs_no_grad_pass(critic):
        return th.float32
    hidden: list[int] = []
    for q_net in _q_networks(critic):
        hidden += [m.out_features for m in q_net.modules() if isinstance(m, nn.Linear)][:-1]
    wide = bool(hidden) and min(hidden) >= AUTO_BF16_MIN_WIDTH
    native = cuda_has_native_bf16() if device.type == "cuda" else device.type == "cpu" and cpu_has_fast_bf16()
    return th.bfloat16 if wide and native else th.float32


class LowPrecisionCopy:
    """
    A copy of a critic's Q-network weights in a lower precision (bfloat16), for the no-grad passes that score
    many sampled actions. The copy does not follow the critic by itself: call :meth:`sync` after every change
    of the critic's weights (a target update, an optimizer step, a load).

    With ``fused``, each hidden ``Linear`` runs as one oneDNN product on a weight laid out once per :meth:`sync`,
    with its bias and the ReLU after it as post-ops (:meth:`fused_linear`), instead of ``addmm`` then an in-place
    ReLU: on an AMX CPU the separate bias copy, the ReLU pass and the weight's layout per call cost more than the
    bf16 product itself (``benchmarks/results/speed/fast_paths.md``).

    :param critic: a critic the engine runs (:func:`runs_no_grad_pass`)
    :param dtype: the precision of the copy
    :param fused: run the hidden layers as fused oneDNN products; ``None`` (default): where they are supported
        (:func:`~sb3_lifelong.numerics.hardware.fused_products_supported`) and the copy is bfloat16 on a CPU;
        ``True`` raises a ``ValueError`` where they are not supported

    With :attr:`compile_layer_norm` (an algorithm sets it on the ``train`` calls whose update it compiles, see
    ``compile_losses``), each LayerNorm of the LayerNorm torso and its tanh run as one compiled kernel from the copy's
    activations to the next layer's input (:func:`~sb3_lifelong.numerics.fast_ops.layer_norm_tanh_into`), instead of a
    conversion to float32, the LayerNorm, the tanh and a conversion back; it is compiled at its first use (seconds)
    and a failed compilation warns once and leaves the eager way.
    """

    def __init__(self, critic: nn.Module, dtype: th.dtype = th.bfloat16, fused: Optional[bool] = None) -> None:
        self.critic = critic
        self.dtype = dtype
        self.weights: dict[int, tuple[th.Tensor, Optional[th.Tensor]]] = {}
        self.layers = self._hidden_layers()
        for module in self.layers:
            bias = None if module.bias is None else module.bias.detach().to(dtype)
            # stored transposed and contiguous: the layout addmm reads fastest
            self.weights[id(module)] = (module.weight.detach().t().contiguous().to(dtype), bias)
        on_cpu = all(parameter.device.type == "cpu" for parameter in critic.parameters())
        supported = on_cpu and fused_products_supported(dtype)
        if fused and not supported:
            raise ValueError(
                f"fused products in {dtype} are not supported here: they need the critic on a CPU and oneDNN's fused "
                f"{dtype} inner product (bfloat16 needs AVX-512 or AMX); pass fused=None to use them where they are"
            )
        self.fused = (supported and dtype == th.bfloat16) if fused is None else bool(fused)
        #: run each LayerNorm and its tanh as one compiled kernel (set per ``train`` call by the algorithm)
        self.compile_layer_norm = False
        self._layer_norm_tanh = LazyCompiled(layer_norm_tanh_into, "the scoring copy's LayerNorm and tanh")
        # the fused layers' weights in oneDNN's layout, made at their first use after a sync (from the copy's weights)
        self._packed: dict[int, th.Tensor] = {}

    def _hidden_layers(self) -> list[nn.Linear]:
        """
        Every ``Linear`` of the Q-networks but the last of each: the output layer stays in the critic's precision,
        so that Q is not rounded to bf16 as a whole (bf16 keeps 8 bits: a Q of 300 would be off by up to 1).
        """
        layers = []
        for q_net in _q_networks(self.critic):
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
        self._packed.clear()

    def fused_linear(self, module: nn.Linear, x: th.Tensor, then_relu: bool) -> Optional[th.Tensor]:
        """
        One hidden layer of the copy as a fused oneDNN product: ``relu(x W^T + b)`` when ``then_relu``, else
        ``x W^T + b``, in the copy's precision.

        :param module: a hidden ``Linear`` of the critic (one of :attr:`layers`)
        :param x: its input ``[rows, in_features]``, contiguous, in the copy's dtype
        :param then_relu: apply the ReLU that follows the layer
        :return: the output (a new tensor), or None when oneDNN refused the product: the copy then warns once and
            stops fusing (the caller runs the layer the unfused way)
        """
        mkldnn = th.ops.mkldnn
        try:
            packed = self._packed.get(id(module))
            if packed is None:
                weight_t, _ = self.weights[id(module)]
                packed = self._packed[id(module)] = mkldnn._reorder_linear_weight(weight_t.t().contiguous(), x.shape[0])
            return mkldnn._linear_pointwise(x, packed, self.weights[id(module)][1], "relu" if then_relu else "none", [], "")
        except RuntimeError as error:
            warnings.warn(f"the fused {self.dtype} product failed ({error}); scoring goes on without fusing", stacklevel=2)
            self.fused = False
            self._packed.clear()
            return None

    def layer_norm_kernel(self) -> Optional[LazyCompiled]:
        """:return: the compiled LayerNorm-and-tanh kernel when :attr:`compile_layer_norm` asks for it (and it has not
        failed to compile), else None"""
        if not self.compile_layer_norm or self._layer_norm_tanh.failed:
            return None
        return self._layer_norm_tanh


def _reused_buffer(
    critic: nn.Module, key: tuple[int, int, int], shape: tuple[int, ...], like: th.Tensor, dtype: Optional[th.dtype] = None
) -> th.Tensor:
    """
    A tensor kept on the critic under ``key`` and reused across gradient steps (a fresh ``[num_samples * batch, 256]``
    tensor per call costs more in page faults than the work written into it); made again when the shape, dtype or
    device changes.

    :param critic: the module that keeps the buffers
    :param key: ``(q-network index, slot, rows)``, the slots as in this module's description
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
    mlp: nn.Sequential,
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
    for position, module in enumerate(mlp):
        if position < first:
            continue
        if isinstance(module, nn.Linear):
            if low_precision is not None and low_precision.fused and id(module) in low_precision.weights:
                then_relu = position + 1 < len(mlp) and isinstance(mlp[position + 1], nn.ReLU)
                fused = low_precision.fused_linear(module, x.contiguous(), then_relu)
                if fused is not None:
                    x, owned = fused, True
                    if then_relu:
                        first = position + 2  # the ReLU is applied
                    continue
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
            # the tanh that follows it in a LayerNorm torso, both in float32 on reused buffers, then one conversion (or
            # one compiled kernel for the three)
            after = mlp[position + 1] if position + 1 < len(mlp) else None
            followed_by_tanh = isinstance(after, nn.Tanh)
            kernel = low_precision.layer_norm_kernel()
            x, owned = _layer_norm_no_grad(critic, (index, position), module, x, followed_by_tanh, kernel), True
            if followed_by_tanh:
                first = position + 2  # the tanh is applied
        else:
            x, owned = module(x), False
    return x


def _layer_norm_no_grad(
    critic: nn.Module,
    key: tuple[int, int],
    module: nn.LayerNorm,
    x: th.Tensor,
    then_tanh: bool,
    kernel: Optional[LazyCompiled] = None,
) -> th.Tensor:
    """
    ``module(x)`` (and the tanh after it when ``then_tanh``) for a low-precision ``x``, returned in ``x``'s dtype in a
    reused buffer (a fresh ``[5120, 256]`` tensor per call cost more in page faults than the arithmetic): with a
    compiled ``kernel`` (:meth:`LowPrecisionCopy.layer_norm_kernel`), in one pass from ``x`` into that buffer; else
    normalised in float32 into reused buffers, then converted.
    """
    index, position = key
    rows, shape = x.shape[0], tuple(x.shape)
    stats = (rows, 1) if len(module.normalized_shape) == 1 and x.dim() == 2 else None
    affine = module.weight is not None and module.bias is not None
    if kernel is not None and then_tanh and stats is not None and affine:
        result = _reused_buffer(critic, (index, LAYER_NORM_RESULT - position, rows), shape, x)
        return kernel(True, x, module.weight, module.bias, module.eps, result)
    wide = _reused_buffer(critic, (index, LAYER_NORM_INPUT - position, rows), shape, x, th.float32).copy_(x)
    normed = _reused_buffer(critic, (index, LAYER_NORM_OUTPUT - position, rows), shape, x, th.float32)
    if stats is not None and affine:
        mean = _reused_buffer(critic, (index, LAYER_NORM_MEAN - position, rows), stats, x, th.float32)
        rstd = _reused_buffer(critic, (index, LAYER_NORM_RSTD - position, rows), stats, x, th.float32)
        th.ops.aten.native_layer_norm.out(
            wide, list(module.normalized_shape), module.weight, module.bias, module.eps, out0=normed, out1=mean, out2=rstd
        )
    else:
        normed.copy_(module(wide))
    if then_tanh:
        tanh_in_place(normed)
    return _reused_buffer(critic, (index, LAYER_NORM_RESULT - position, rows), shape, x).copy_(normed)


#: the first layer is split into a per-state and a per-sample product (:func:`_first_layer_split`) when the
#: features are at least this wide and at least twice the action: measured on this CPU, the first layer 3x faster
#: for OP3-sized inputs (68 + 20; the whole pass 1.18x, a retired probe,
#: ``git show 9cccda3:benchmarks/results/scoring_split.md``), and slower than one
#: product for Hopper-sized ones (11 + 3)
SPLIT_MIN_FEATURES = 32


def _first_layer_split(
    critic: nn.Module,
    index: int,
    q_net: nn.Sequential,
    features: th.Tensor,
    actions: th.Tensor,
    low_precision: LowPrecisionCopy,
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
    weight_t, bias = low_precision.weights[id(q_net[0])]
    width = features.shape[1]
    per_state = th.mm(features, weight_t[:width])
    if bias is not None:
        per_state.add_(bias)
    out = _reused_buffer(critic, (index, 0, actions.shape[0]), (actions.shape[0], weight_t.shape[1]), actions)
    th.mm(actions, weight_t[width:], out=out)
    out.view(-1, features.shape[0], out.shape[1]).add_(per_state)
    return out


def _splits_first_layer(
    q_net: nn.Sequential, features_dim: int, action_dim: int, low_precision: Optional[LowPrecisionCopy]
) -> bool:
    modules = list(q_net)
    return (
        low_precision is not None
        and features_dim >= max(SPLIT_MIN_FEATURES, 2 * action_dim)
        and len(modules) > 2
        and isinstance(modules[0], nn.Linear)
        and id(modules[0]) in low_precision.weights
    )


def network_outputs(
    critic: BaseModel,
    obs: PyTorchObs,
    flat_actions: th.Tensor,
    num_samples: int,
    low_precision: Optional[LowPrecisionCopy] = None,
) -> tuple[th.Tensor, list[th.Tensor]]:
    """
    The no-grad pass of a critic the engine runs (:func:`runs_no_grad_pass`) over ``num_samples`` actions per state:
    the features are extracted once per state, each Q-network runs on reused buffers (see ``_run_mlp_no_grad``), in
    the copy's precision with ``low_precision``. In float32 the outputs are, bit for bit, the Q-networks' outputs on
    ``[tile_obs(features), flat_actions]``.

    :param critic: the critic
    :param obs: observations ``[batch, ...]``
    :param flat_actions: ``[num_samples * batch, action_dim]``, sample-major (row ``n * batch + b``)
    :param num_samples: actions per state
    :param low_precision: a synchronised low-precision copy of ``critic``
    :return: the features ``[batch, features_dim]`` and each Q-network's output ``[num_samples * batch, ...]``, in
        float32 (the output layer runs in float32); the outputs are buffers that the next pass overwrites
    """
    assert critic.features_extractor is not None, "a critic scored by the engine has its features extractor"
    features = critic.extract_features(obs, critic.features_extractor)
    action_dim = flat_actions.shape[1]
    outputs = []
    q_input = split_inputs = None
    for index, q_net in enumerate(_q_networks(critic)):
        assert isinstance(q_net, nn.Sequential), "the no-grad pass runs Q-networks built as nn.Sequential (SB3's)"
        if _splits_first_layer(q_net, features.shape[1], action_dim, low_precision):
            assert low_precision is not None
            if split_inputs is None:  # converted once for all the Q-networks
                split_inputs = (features.to(low_precision.dtype), flat_actions.to(low_precision.dtype))
            hidden = _first_layer_split(critic, index, q_net, *split_inputs, low_precision)
            outputs.append(_run_mlp_no_grad(critic, index, q_net, hidden, low_precision, first=1, owned=True))
            continue
        if q_input is None:
            q_input = th.cat([features.repeat(num_samples, 1), flat_actions], dim=1)
            if low_precision is not None:
                q_input = q_input.to(low_precision.dtype)
        outputs.append(_run_mlp_no_grad(critic, index, q_net, q_input, low_precision))
    return features, outputs


def score_actions(
    critic: nn.Module, obs: PyTorchObs, actions: th.Tensor, low_precision: Optional[LowPrecisionCopy] = None
) -> th.Tensor:
    """
    Q-values of several actions per state, in a single critic call over ``num_samples * batch`` rows.
    Actions are clipped to the normalised bounds ``[-1, 1]`` first, as the environment would clip them.

    Without autograd (target computations) a critic the engine runs (:func:`runs_no_grad_pass`: SB3's
    ``ContinuousCritic``, the categorical critic) is scored by :func:`network_outputs`: features once per state,
    reused buffers, the low-precision copy (not while ``torch.compile`` traces: see :func:`uses_engine`).

    :param critic: the critic (minimum over its Q-networks is taken): any critic called as ``critic(obs, actions)``
        that returns one ``[batch, 1]`` tensor per Q-network
    :param obs: observations ``[batch, ...]``
    :param actions: ``[num_samples, batch, action_dim]``
    :param low_precision: a synchronised low-precision copy of ``critic``: without autograd the Q-networks run
        in its precision (the features and the result stay float32)
    :return: Q-values ``[num_samples, batch]``
    """
    num_samples, batch_size, action_dim = actions.shape
    flat_actions = actions.reshape(num_samples * batch_size, action_dim).clamp(-1.0, 1.0)
    if not uses_engine(critic, low_precision):
        return q_min(critic(tile_obs(obs, num_samples), flat_actions)).reshape(num_samples, batch_size)
    assert isinstance(critic, BaseModel)
    features, outputs = eager_network_outputs(critic, obs, flat_actions, num_samples, low_precision)
    if not isinstance(critic, ContinuousCritic):  # the outputs are not Q-values yet (a categorical critic's logits)
        q_values_of = cast(Callable[[th.Tensor], th.Tensor], critic.q_values_of)
        outputs = [q_values_of(output) for output in outputs]
    # copy out of the reused buffer (the result outlives the next call), in the critic's own precision
    return q_min(outputs).reshape(num_samples, batch_size).to(features.dtype, copy=True)


#: :func:`network_outputs`, run eagerly where ``torch.compile`` traces the code (a break in its graph)
eager_network_outputs = th.compiler.disable(network_outputs)
