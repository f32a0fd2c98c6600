"""
Where compiled and eager training differ on this machine: the setups of ``tests/test_compiled.py`` (a CRR student,
12 updates, with and without a gradient clip, float32 and bf16 scoring; MPO, 20 updates, defaults and with the action
penalty), each trained eagerly and with ``compile_losses=True``, and the parameters' absolute differences listed per
parameter tensor (those above the tests' 1e-4). First, one CRR update's gradients before any optimizer step: the
same batch and noise through the eager and the compiled forward pass, so that a difference there is the graphs'
arithmetic, not Adam's (whose first steps are +-lr whatever a gradient's size).

Both are also compared with the same update in float64, which tells which of the two is wrong; and, first, small
torsos' gradients, compiled against eager, per activation, which tells which operation the compiler gets wrong.

On an AMD EPYC with torch 2.13 they differ by at most 2e-7. On an AMX Xeon with torch 2.11 the compiled gradients
of the LayerNorm torsos' first layers were wrong by up to 30 %, from the package's tanh (an ``autograd.Function``),
and eager matched float64 (``benchmarks/results/amx/compiled_vs_eager_before_fix.txt``,
``tanh_compiled_gradients.txt``). Under ``torch.compile`` that tanh is now written out of place, and the two agree to
2e-7 there (``compiled_vs_eager_after_fix.txt``).

Usage (from the repository's root)::

    OMP_NUM_THREADS=1 python benchmarks/compiled_vs_eager.py
"""

import contextlib
import pathlib
import sys
from collections.abc import Iterator
from typing import Any

import torch as th
from stable_baselines3.common import policies as sb3_policies
from torch import nn

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # the tests' helpers

from sb3_lifelong.common.fast_ops import Tanh
from sb3_lifelong.crr.losses import actor_loss
from tests.test_compiled import flat_params, mpo, mpo_params, student
from tests.test_crr import pendulum_data

TOLERANCE = 1e-4  # the tests'
GRADIENT_TOLERANCE = 1e-5  # of the largest gradient component: rounding is far below it


def report(label: str, compiled_ran: bool, difference: th.Tensor, named: list[tuple[str, th.Tensor]]) -> None:
    """Print the largest difference and, per parameter tensor, the components above :data:`TOLERANCE`."""
    above = int((difference > TOLERANCE).sum())
    largest = float(difference.max())
    print(f"{label}: compiled {compiled_ran}, largest difference {largest:.2e}, {above} of {difference.numel()} > {TOLERANCE}")
    per_parameter(difference, named, TOLERANCE)


def per_parameter(difference: th.Tensor, named: list[tuple[str, th.Tensor]], tolerance: float) -> None:
    """Print, per parameter tensor, the largest difference and how many components are above ``tolerance``."""
    offset = 0
    for name, parameter in named:
        part = difference[offset : offset + parameter.numel()]
        offset += parameter.numel()
        if part.numel() and part.max() > tolerance:
            print(f"    {name} ({parameter.numel()}): largest {float(part.max()):.2e}, {int((part > tolerance).sum())} above")


def as_double(replay_data: Any) -> Any:
    """:return: the batch with its floating-point tensors in float64"""
    return type(replay_data)(*(t.double() if th.is_tensor(t) and t.is_floating_point() else t for t in replay_data))


@contextlib.contextmanager
def keeping_float64_observations() -> Iterator[None]:
    """SB3's policies cast Box observations to float32 (``preprocess_obs``); the float64 reference keeps them."""
    original = sb3_policies.preprocess_obs
    sb3_policies.preprocess_obs = lambda obs, *args, **kwargs: obs  # type: ignore[assignment]
    try:
        yield
    finally:
        sb3_policies.preprocess_obs = original


def update_gradients(
    model: Any, compiled: bool, replay_data: Any, heads: Any, target_noise: th.Tensor, sample_noise: th.Tensor
) -> th.Tensor:
    """:return: one CRR update's gradients (critic and actor losses), flattened in the policy's parameter order"""
    parameters = [p for p in model.policy.parameters() if p.requires_grad]
    fit, mean, std, sampled_q = model._forward(compiled, replay_data, heads, target_noise, sample_noise)
    advantage = model._advantage(fit.q_values, sampled_q)
    loss = fit.loss + actor_loss(replay_data.actions, mean, std, advantage.weights)
    grads = th.autograd.grad(loss, parameters, allow_unused=True)
    return th.cat([th.zeros_like(p).flatten() if g is None else g.flatten() for p, g in zip(parameters, grads)])


def first_update_gradients(data: dict) -> None:
    """
    One CRR update's gradients, eager and compiled, on the same batch and noise, and both against the same update in
    float64 (eager, float64 scoring): the one far from float64 is the one whose arithmetic is wrong.
    """
    model = student(data, compile_losses=True, max_grad_norm=1e-3)
    model.learn_offline(1, log_interval=0)  # set up (and compiled once)
    replay_data, heads = model._sample(model.batch_size)
    shape = tuple(replay_data.actions.shape)
    generator = th.Generator().manual_seed(0)
    target_noise = th.randn((model.n_target_samples, *shape), generator=generator)
    sample_noise = th.randn((model.num_samples, *shape), generator=generator)
    eager = update_gradients(model, False, replay_data, heads, target_noise, sample_noise)
    compiled_grads = update_gradients(model, True, replay_data, heads, target_noise, sample_noise)
    reference_model = student(data, compile_losses=False, max_grad_norm=1e-3, scoring_dtype="float32")
    reference_model.learn_offline(1, log_interval=0)
    reference_model.policy.load_state_dict(model.policy.state_dict())
    reference_model.policy.double()
    with keeping_float64_observations():
        reference = update_gradients(
            reference_model, False, as_double(replay_data), heads, target_noise.double(), sample_noise.double()
        ).float()
    named = [(n, p) for n, p in model.policy.named_parameters() if p.requires_grad]
    scale = float(reference.abs().max())
    for label, grads, against in (
        ("compiled - eager", compiled_grads, eager),
        ("eager - float64", eager, reference),
        ("compiled - float64", compiled_grads, reference),
    ):
        difference = (grads - against).abs()
        relative = float((difference / against.abs().clamp_min(1e-12)).median())
        flips = int(((grads * against) < 0).sum())
        print(
            f"CRR first update's gradients, {label}: largest |g| {scale:.2e}, largest difference "
            f"{float(difference.max()):.2e}, relative to each |g| (median) {relative:.1e}, "
            f"signs differing {flips} of {grads.numel()}"
        )
        per_parameter(difference, named, GRADIENT_TOLERANCE * scale)


def torso_gradients() -> None:
    """
    Small torsos, ``Linear(4, h) -> [LayerNorm] -> activation -> Linear(h, 1)``, their gradients compiled against eager
    (relative to the largest): which operation a compiler gets wrong. "fast" is the package's ``Tanh``.
    """
    activations = {"fast": Tanh, "torch": nn.Tanh, "relu": nn.ReLU}
    for layer_norm in (True, False):
        for activation, make in activations.items():
            for rows, hidden in ((32, 32), (256, 256)):
                th.manual_seed(0)
                middle = [nn.LayerNorm(hidden)] if layer_norm else []
                net = nn.Sequential(nn.Linear(4, hidden), *middle, make(), nn.Linear(hidden, 1))
                x = th.randn(rows, 4)

                def loss(x: th.Tensor, net: nn.Module = net) -> th.Tensor:
                    return (net(x) ** 2).mean()

                th._dynamo.reset()  # a fresh compilation for each torso
                compiled = th.compile(loss, dynamic=False)
                eager_grads = th.autograd.grad(loss(x), list(net.parameters()))
                compiled_grads = th.autograd.grad(compiled(x), list(net.parameters()))
                scale = max(float(g.abs().max()) for g in eager_grads)
                worst = [
                    (name, float((a - b).abs().max()) / scale)
                    for (name, _), a, b in zip(net.named_parameters(), eager_grads, compiled_grads)
                ]
                print(
                    f"torso {'LayerNorm + ' if layer_norm else ''}{activation}, {rows} x {hidden}: largest difference "
                    f"{max(w for _, w in worst):.1e} of the largest gradient; "
                    + " ".join(f"{name} {w:.0e}" for name, w in worst)
                )


def main() -> None:
    th.set_num_threads(1)
    torso_gradients()
    data = pendulum_data(300)
    first_update_gradients(data)
    settings = (dict(max_grad_norm=1e-3), dict(max_grad_norm=1e-3, scoring_dtype="float32"), dict(scoring_dtype="bfloat16"))
    for kwargs in settings:
        eager = student(data, compile_losses=False, **kwargs).learn_offline(12, log_interval=0)
        compiled = student(data, compile_losses=True, **kwargs).learn_offline(12, log_interval=0)
        ran = compiled._forward.compiled is not None and not compiled._forward.failed
        difference = (flat_params(compiled) - flat_params(eager)).abs()
        report(f"CRR {kwargs}", ran, difference, list(compiled.policy.named_parameters()))
    for kwargs in ({}, dict(policy_on_next_obs=False, action_penalty=True, max_grad_norm=1e-3)):
        eager, compiled = mpo(False, **kwargs).learn(60), mpo(True, **kwargs).learn(60)
        ran = compiled._forward.compiled is not None and not compiled._forward.failed
        difference = (mpo_params(compiled) - mpo_params(eager)).abs()
        report(f"MPO {kwargs}", ran, difference, list(compiled.policy.named_parameters()))


if __name__ == "__main__":
    main()
