"""
Property-based tests (``hypothesis``) of the losses' arithmetic: what must hold for every input, not only the hand
computed ones. ``max_examples`` stays modest: each test runs in about a second.
"""

import math

import numpy as np
import torch as th
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from sb3_lifelong.common.policies import gaussian_kl_per_dim, gaussian_log_prob
from sb3_lifelong.crr.distributional import categorical_projection
from sb3_lifelong.crr.losses import crr_weights, effective_sample_size, ess_temperature
from sb3_lifelong.mpo.losses import temperature_loss_and_weights

FAST = settings(max_examples=40, deadline=None, database=None)
means = st.floats(-5.0, 5.0, allow_nan=False)
stds = st.floats(0.05, 5.0, allow_nan=False)


@FAST
@given(mean_p=means, std_p=stds, mean_q=means, std_q=stds)
def test_gaussian_kl_is_non_negative_and_zero_only_at_equality(mean_p, std_p, mean_q, std_q):
    kl = gaussian_kl_per_dim(*(th.tensor([x], dtype=th.float64) for x in (mean_p, std_p, mean_q, std_q))).item()
    assert kl >= -1e-12
    assert gaussian_kl_per_dim(*(th.tensor([x], dtype=th.float64) for x in (mean_p, std_p, mean_p, std_p))).item() == 0.0
    if abs(mean_p - mean_q) > 1e-3 or abs(math.log(std_p / std_q)) > 1e-3:
        assert kl > 0
    # the closed form, written independently
    expected = math.log(std_q / std_p) + (std_p**2 + (mean_p - mean_q) ** 2) / (2 * std_q**2) - 0.5
    assert math.isclose(kl, expected, rel_tol=1e-9, abs_tol=1e-12)


@FAST
@given(
    x=arrays(np.float64, (3,), elements=means),
    mean=arrays(np.float64, (3,), elements=means),
    std=arrays(np.float64, (3,), elements=stds),
)
def test_gaussian_log_prob_is_torch_distributions(x, mean, std):
    got = gaussian_log_prob(th.tensor(x), th.tensor(mean), th.tensor(std)).item()
    want = th.distributions.Normal(th.tensor(mean), th.tensor(std)).log_prob(th.tensor(x)).sum().item()
    assert math.isclose(got, want, rel_tol=1e-10, abs_tol=1e-10)


# no weight below 1e-100: their squares would underflow to 0 in float64
weights_arrays = arrays(np.float64, st.integers(1, 40), elements=st.one_of(st.just(0.0), st.floats(1e-100, 1e3)))


@FAST
@given(weights=weights_arrays)
def test_effective_sample_size_is_in_its_range(weights):
    ess = effective_sample_size(th.tensor(weights)).item()
    n = len(weights)
    if weights.sum() == 0:
        assert ess == 1.0
    else:
        assert 1.0 / n - 1e-12 <= ess <= 1.0 + 1e-12
        assert math.isclose(ess, weights.sum() ** 2 / (n * (weights**2).sum()), rel_tol=1e-9)
        positive = (weights > 0).sum()
        assert ess <= positive / n + 1e-9  # never more than the share of rows with any weight


advantages_arrays = arrays(np.float64, st.integers(2, 64), elements=st.floats(-10.0, 10.0, allow_nan=False))


@FAST
@given(advantages=advantages_arrays, betas=st.lists(st.floats(0.01, 100.0), min_size=2, max_size=6))
def test_ess_of_unclipped_exp_weights_grows_with_the_temperature(advantages, betas):
    betas = sorted(betas)
    # the weights relative to the largest (as the ESS search computes them): exp(A / beta) alone overflows at 6 / 0.015
    sizes = [effective_sample_size(th.exp(th.tensor(advantages - advantages.max()) / beta)).item() for beta in betas]
    assert all(0.0 < size <= 1.0 + 1e-12 for size in sizes)
    assert all(later >= earlier - 1e-9 for earlier, later in zip(sizes, sizes[1:]))


@FAST
@given(advantages=advantages_arrays, target=st.floats(0.05, 0.95), scale=st.floats(0.01, 100.0))
def test_ess_temperature_hits_its_target_and_scales_with_the_advantages(advantages, target, scale):
    values = th.tensor(advantages)
    beta = ess_temperature(values, target, max_weight=1e30).item()
    single = advantages.astype(np.float32)  # the search runs in float32: differences below its range are ties there
    if not single.max() > single.min():
        assert beta == math.inf
        return
    # differences of float32's subnormals (below 1e-38) leave no temperature float32 can divide by
    assume(float(single.max()) - float(single.min()) > 1e-30)
    weights, _ = crr_weights(values, "exp", beta, max_weight=1e30)
    reachable = effective_sample_size(crr_weights(values, "exp", 1e-6 * np.std(advantages), max_weight=1e30)[0]).item()
    if reachable < target:  # the target is above the coldest ESS (a single best row has 1 / n of it): reached
        assert math.isclose(effective_sample_size(weights).item(), target, abs_tol=2e-3)
        scaled = ess_temperature(scale * values, target, max_weight=1e30).item()
        assert math.isclose(scaled, scale * beta, rel_tol=1e-3)


@FAST
@given(
    probs=arrays(np.float64, (3, 7), elements=st.floats(0.0, 1.0)),
    rewards=arrays(np.float64, (3, 1), elements=st.floats(-20.0, 20.0)),
    discounts=arrays(np.float64, (3, 1), elements=st.floats(0.0, 1.0)),
)
def test_categorical_projection_keeps_the_mass_on_the_support(probs, rewards, discounts):
    probs = probs + 1e-3
    probs = probs / probs.sum(axis=1, keepdims=True)
    support = th.linspace(-6.0, 6.0, 7, dtype=th.float64)
    target = categorical_projection(th.tensor(probs), th.tensor(rewards), th.tensor(discounts), support).numpy()
    assert (target >= 0).all()
    np.testing.assert_allclose(target.sum(axis=1), 1.0, rtol=1e-10)
    # the projected mean is the shifted mean, clipped atom by atom to the support
    shifted = np.clip(rewards + discounts * support.numpy()[None], -6.0, 6.0)
    np.testing.assert_allclose(target @ support.numpy(), (probs * shifted).sum(axis=1), rtol=1e-9, atol=1e-9)


@FAST
@given(q=arrays(np.float64, (5, 3), elements=st.floats(-50.0, 50.0)), eta=st.floats(0.05, 20.0), epsilon=st.floats(0.0, 1.0))
def test_mpo_weights_are_a_distribution_and_the_dual_loss_is_bounded(q, eta, epsilon):
    """The E-step's weights sum to 1 per state; ``eta (epsilon + lse(Q / eta) - log N)`` lies between
    ``eta epsilon + mean(Q)`` (Jensen) and ``eta epsilon + max(Q)``."""
    loss, weights = temperature_loss_and_weights(th.tensor(q), th.tensor(eta, dtype=th.float64), epsilon)
    np.testing.assert_allclose(weights.sum(dim=0).numpy(), 1.0, rtol=1e-10)
    lower = eta * epsilon + q.mean(axis=0).mean()
    upper = eta * epsilon + q.max(axis=0).mean()
    assert lower - 1e-9 <= loss.item() <= upper + 1e-9
