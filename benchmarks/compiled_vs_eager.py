"""
Where compiled and eager training differ on this machine: the setups of ``tests/test_compiled.py`` (a CRR student,
12 updates, with and without a gradient clip, float32 and bf16 scoring; MPO, 20 updates, defaults and with the action
penalty), each trained eagerly and with ``compile_losses=True``, and the parameters' absolute differences listed per
parameter tensor (those above the tests' 1e-4). First, one CRR update's gradients before any optimizer step: the
same batch and noise through the eager and the compiled forward pass, so that a difference there is the graphs'
arithmetic, not Adam's (whose first steps are +-lr whatever a gradient's size).

On an AMD EPYC with torch 2.13 they differ by at most 2e-7. On an AMX Xeon with torch 2.11 they differ by up to one
learning-rate step per update (``benchmarks/results/amx/compiled_vs_eager.txt``).

Usage (from the repository's root)::

    OMP_NUM_THREADS=1 python benchmarks/compiled_vs_eager.py
"""

import pathlib
import sys

import torch as th

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # the tests' helpers

from sb3_lifelong.crr.losses import actor_loss
from tests.test_compiled import flat_params, mpo, mpo_params, student
from tests.test_crr import pendulum_data

TOLERANCE = 1e-4  # the tests'


def report(label: str, compiled_ran: bool, difference: th.Tensor, named: list[tuple[str, th.Tensor]]) -> None:
    """Print the largest difference and, per parameter tensor, the components above :data:`TOLERANCE`."""
    above = int((difference > TOLERANCE).sum())
    largest = float(difference.max())
    print(f"{label}: compiled {compiled_ran}, largest difference {largest:.2e}, {above} of {difference.numel()} > {TOLERANCE}")
    offset = 0
    for name, parameter in named:
        part = difference[offset : offset + parameter.numel()]
        offset += parameter.numel()
        if part.numel() and part.max() > TOLERANCE:
            print(f"    {name} ({parameter.numel()}): largest {float(part.max()):.2e}, {int((part > TOLERANCE).sum())} above")


def first_update_gradients(data: dict) -> None:
    """One CRR update's gradients (critic and actor losses), eager and compiled, on the same batch and noise."""
    model = student(data, compile_losses=True, max_grad_norm=1e-3)
    model.learn_offline(1, log_interval=0)  # set up (and compiled once)
    replay_data, heads = model._sample(model.batch_size)
    shape = tuple(replay_data.actions.shape)
    generator = th.Generator().manual_seed(0)
    target_noise = th.randn((model.n_target_samples, *shape), generator=generator)
    sample_noise = th.randn((model.num_samples, *shape), generator=generator)
    parameters = [p for p in model.policy.parameters() if p.requires_grad]
    gradients = {}
    for compiled in (False, True):
        fit, mean, std, sampled_q = model._forward(compiled, replay_data, heads, target_noise, sample_noise)
        advantage = model._advantage(fit.q_values, sampled_q)
        loss = fit.loss + actor_loss(replay_data.actions, mean, std, advantage.weights)
        grads = th.autograd.grad(loss, parameters, allow_unused=True)
        gradients[compiled] = th.cat(
            [th.zeros_like(p).flatten() if g is None else g.flatten() for p, g in zip(parameters, grads)]
        )
    eager, compiled_grads = gradients[False], gradients[True]
    difference = (compiled_grads - eager).abs()
    relative = float((difference / eager.abs().clamp_min(1e-12)).median())
    flips = int(((compiled_grads * eager) < 0).sum())
    print(
        f"CRR first update's gradients: largest |g| {float(eager.abs().max()):.2e}, largest difference "
        f"{float(difference.max()):.2e}, relative to each |g| (median) {relative:.1e}, "
        f"signs differing {flips} of {eager.numel()}"
    )


def main() -> None:
    th.set_num_threads(1)
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
