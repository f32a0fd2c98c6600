"""The scale-free conservativeness of CRR: the exp transform's temperature set by the weights' effective sample size."""

import math

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from testkit import Recorder, flat_params, pendulum_data

from sb3_lifelong import CRR
from sb3_lifelong.crr.losses import advantage_weights, crr_weights, effective_sample_size, ess_temperature


@pytest.fixture(scope="module")
def data() -> dict:
    return pendulum_data()


def offline(data: dict, seed: int = 0, **kwargs) -> CRR:
    return CRR.from_offline_data(
        data, env=None, action_space=spaces.Box(-2, 2, (1,)), seed=seed, policy_kwargs=dict(net_arch=[32, 32]),
        batch_size=32, **kwargs,
    )  # fmt: skip


def test_effective_sample_size_hand_computed():
    assert effective_sample_size(th.ones(8)).item() == pytest.approx(1.0)
    assert effective_sample_size(th.tensor([1.0, 0.0, 0.0, 0.0])).item() == pytest.approx(0.25)
    assert effective_sample_size(th.tensor([1.0, 1.0, 0.0, 0.0])).item() == pytest.approx(0.5)
    assert effective_sample_size(th.tensor([3.0, 1.0])).item() == pytest.approx(16 / (2 * 10))
    assert effective_sample_size(th.zeros(4)).item() == 1.0  # no weight at all: defined, not NaN
    np.testing.assert_allclose(effective_sample_size(th.tensor([[1.0, 1.0], [1.0, 0.0]])).numpy(), [1.0, 0.5])


@pytest.mark.parametrize("target", [0.6, 0.8, 0.95])
def test_two_point_advantages_closed_form(target):
    # advantages +-a, half each: ESS = cosh(x)^2 / cosh(2x) with x = a / beta, so cosh(x)^2 = target / (2 target - 1)
    a = 2.0
    beta = ess_temperature(th.tensor([a, -a] * 64), target).item()
    assert beta == pytest.approx(a / math.acosh(math.sqrt(target / (2 * target - 1))), rel=1e-4)


def test_gaussian_advantages_match_the_closed_form():
    # ESS = exp(-s^2 / beta^2) for Gaussian advantages without clipping: beta = s / sqrt(-ln target)
    advantages = th.randn(200_000, generator=th.Generator().manual_seed(0)) * 0.7
    beta = ess_temperature(advantages, 0.9, max_weight=1e9).item()
    assert beta == pytest.approx(0.7 / math.sqrt(-math.log(0.9)), rel=0.02)


@pytest.mark.parametrize("scale", [1e-3, 0.1, 3.0, 250.0])
def test_weights_do_not_depend_on_the_reward_scale(scale):
    generator = th.Generator().manual_seed(1)
    data_q, sampled_q = th.randn(256, generator=generator) * 5, th.randn(4, 256, generator=generator) * 5
    reference = advantage_weights(data_q, sampled_q, "mean", "exp", 1.0, 20.0, target_ess=0.9)
    scaled = advantage_weights(scale * data_q, scale * sampled_q, "mean", "exp", 1.0, 20.0, target_ess=0.9)
    np.testing.assert_allclose(scaled.weights.numpy(), reference.weights.numpy(), rtol=2e-4)
    assert scaled.beta.item() == pytest.approx(scale * reference.beta.item(), rel=1e-4)
    assert effective_sample_size(scaled.weights).item() == pytest.approx(0.9, abs=1e-4)
    # a fixed beta is not scale-free: the same data at 100x the reward collapses onto a few transitions
    fixed = [advantage_weights(c * data_q, c * sampled_q, "mean", "exp", 1.0, 20.0).weights for c in (0.01, 1.0)]
    assert effective_sample_size(fixed[0]).item() > 0.99 and effective_sample_size(fixed[1]).item() < 0.5


def test_clipped_weights_reach_the_target_and_warm_start_agrees():
    # a few outliers that clip at small temperatures (seeded: drawn from the global generator, the result depended on
    # the tests run before; seed 0 is one of the draws whose warm start lands 1e-3 away)
    advantages = th.cat([th.randn(250, generator=th.Generator().manual_seed(0)), th.tensor([40.0] * 6)])
    beta = ess_temperature(advantages, 0.7, max_weight=5.0)
    weights, _ = crr_weights(advantages, "exp", beta, 5.0)
    assert effective_sample_size(weights).item() == pytest.approx(0.7, abs=1e-4)
    for start in (beta.item() * 0.8, beta.item() * 1.3, beta.item() * 50):  # inside and outside the warm window
        # a warm start searches one grid pass (64 points over e^-0.5 ... e^0.5): about 1e-3 of the temperature
        assert ess_temperature(advantages, 0.7, 5.0, start=start).item() == pytest.approx(beta.item(), rel=2e-3)


def test_degenerate_and_bad_input():
    assert ess_temperature(th.full((16,), 3.0), 0.9).item() == math.inf  # equal advantages: equal weights
    weights, _ = crr_weights(th.full((16,), 3.0), "exp", th.tensor(math.inf))
    assert weights.tolist() == [1.0] * 16
    for bad in (0.0, 1.0, -0.5, 1.5):
        with pytest.raises(ValueError, match="target_ess"):
            ess_temperature(th.randn(8), bad)


def test_crr_with_target_ess_logs_it_and_resumes_exactly(data, tmp_path):
    model = offline(data, seed=2, target_ess=0.8)
    recorder = Recorder()
    model.learn_offline(60, callback=recorder, log_interval=1)
    assert recorder.values["train/weight_ess"] == pytest.approx(0.8, abs=1e-3)
    assert recorder.values["train/beta"] > 0 and model._ess_beta == pytest.approx(recorder.values["train/beta"], rel=0.5)
    model.save(tmp_path / "model.zip")
    uninterrupted = offline(data, seed=2, target_ess=0.8)
    uninterrupted.learn_offline(60, log_interval=0)
    uninterrupted.learn_offline(30, reset_num_timesteps=False, log_interval=0)
    resumed = CRR.load(tmp_path / "model.zip")
    assert resumed.target_ess == 0.8 and resumed._ess_beta == model._ess_beta
    resumed.set_offline_data(data)
    resumed.learn_offline(30, reset_num_timesteps=False, log_interval=0)
    th.testing.assert_close(flat_params(resumed), flat_params(uninterrupted), rtol=0, atol=0)


def test_indicator_and_fixed_beta_log_their_ess(data):
    for kwargs, beta_logged in ((dict(advantage_transform="indicator"), False), (dict(beta=2.0), True)):
        recorder = Recorder()
        offline(data, **kwargs).learn_offline(20, callback=recorder, log_interval=1)
        assert 0.0 < recorder.values["train/weight_ess"] <= 1.0
        beta = recorder.values["train/beta"]
        assert beta == pytest.approx(2.0) if beta_logged else math.isnan(beta)


def test_target_ess_needs_the_exp_transform():
    for kwargs, match in (
        (dict(target_ess=1.0), "target_ess"),
        (dict(target_ess=0.9, advantage_transform="indicator"), "indicator"),
        (dict(target_ess=0.9, normalize_advantages=True), "normalize_advantages"),
    ):
        with pytest.raises(ValueError, match=match):
            CRR("MlpPolicy", "Pendulum-v1", **kwargs)


def test_ess_temperature_found_outside_the_gaussian_guess_window():
    # two nearly tied best rows far above a third: the size reaches 0.5 at a temperature about e^-7.6 below the
    # Gaussian guess, outside its first window (the search returned the window's edge, at a size of 0.545)
    advantages = th.tensor([1.953125e-03, -3.0, 0.0])
    beta = ess_temperature(advantages, 0.5, max_weight=1e30).item()
    weights, _ = crr_weights(advantages, "exp", beta, max_weight=1e30)
    assert abs(effective_sample_size(weights).item() - 0.5) < 1e-3
    assert 1e-3 < beta < 2e-3


def test_documented_defaults_of_the_weights_and_the_search():
    # crr_weights: exp at beta = 1 clipped at 20; ess_temperature: the clip at 20 too
    advantages = th.tensor([-1.0, 0.0, 0.5, 4.0])
    weights, clipped = crr_weights(advantages)
    np.testing.assert_allclose(weights.numpy(), np.minimum(np.exp([-1.0, 0.0, 0.5, 4.0]), 20.0), rtol=1e-6)
    assert clipped.tolist() == [False, False, False, True]
    normal = th.tensor(np.random.default_rng(0).normal(size=64), dtype=th.float32)  # at 0.3 the clip matters
    assert ess_temperature(normal, 0.3).item() == ess_temperature(normal, 0.3, max_weight=20.0).item()
    assert ess_temperature(normal, 0.3).item() != ess_temperature(normal, 0.3, max_weight=21.0).item()


def test_warm_start_is_one_grid_pass_and_a_useless_start_is_ignored(monkeypatch):
    import sb3_lifelong.crr.losses as losses

    advantages = th.tensor(np.random.default_rng(0).normal(size=256), dtype=th.float32)
    cold = ess_temperature(advantages, 0.7).item()
    calls = []
    real = losses._ess_of_temperatures
    monkeypatch.setattr(losses, "_ess_of_temperatures", lambda *a: calls.append(1) or real(*a))
    warm = ess_temperature(advantages, 0.7, start=cold * 1.2).item()  # the target within the warm window
    assert len(calls) == 1 and math.isclose(warm, cold, rel_tol=1e-3)
    calls.clear()
    far = ess_temperature(advantages, 0.7, start=cold * 100).item()  # outside it: the search starts again
    assert len(calls) > 1 and math.isclose(far, cold, rel_tol=1e-3)
    for useless in (0.0, -1.0, math.inf, math.nan):  # no warm start: the search from scratch
        assert math.isclose(ess_temperature(advantages, 0.7, start=useless).item(), cold, rel_tol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("target", [0.05, 0.3, 0.7, 0.95])
@pytest.mark.parametrize("max_weight", [20.0, 1e30])
def test_search_hits_its_target_to_the_documented_precision(seed, target, max_weight):
    # two grid passes and a linear interpolation between the candidates that bracket the crossing: the size at the
    # returned temperature is the target to about 1e-5 (a bracket one candidate off is worse than 1e-4)
    generator = th.Generator().manual_seed(seed)
    advantages = th.cat([th.randn(192, generator=generator), 3 * th.rand(64, generator=generator) - 4])  # skewed
    beta = ess_temperature(advantages, target, max_weight=max_weight)
    weights, _ = crr_weights(advantages, "exp", beta, max_weight)
    size = effective_sample_size(weights).item()
    reachable = effective_sample_size(crr_weights(advantages, "exp", 1e-9, max_weight)[0]).item() < target
    if max_weight > 1e6 or reachable:
        assert size == pytest.approx(target, abs=1e-4)
        # warm-started from a temperature within its window: one pass, about 1e-3 of the temperature
        warm = ess_temperature(advantages, target, max_weight=max_weight, start=beta.item() * 1.1)
        assert warm.item() == pytest.approx(beta.item(), rel=2e-3)


def reference_search(advantages: np.ndarray, target: float, max_weight: float, start=None, windows=None):
    """
    The search of ``ess_temperature``'s docstring, in float64 NumPy: a grid of 64 log-temperatures over the Gaussian
    guess +- 7 (or a warm start +- 0.5, one pass), moved by its width while every candidate reaches the target (or
    none does) up to +-40 from the guess, refined once around the warmest crossing, then interpolated linearly.

    :return: the temperature; ``windows`` collects the (low, high) of every grid evaluated, in order
    """
    windows = [] if windows is None else windows
    a = np.asarray(advantages, dtype=np.float64)
    if a.max() == a.min():
        return math.inf

    def grid(lo, hi):
        windows.append((lo, hi))
        log_betas = np.linspace(lo, hi, 64)
        log_w = np.minimum(a[None, :] / np.exp(log_betas)[:, None], math.log(max_weight))
        w = np.exp(log_w - log_w.max(axis=1, keepdims=True))
        return log_betas, w.sum(axis=1) ** 2 / (len(a) * (w * w).sum(axis=1))

    warm = start is not None and math.isfinite(start) and start > 0
    if warm:
        low, high, passes = math.log(start) - 0.5, math.log(start) + 0.5, 1
        log_betas, ess = grid(low, high)
        if not (ess[-1] >= target and not ess[0] >= target):  # the target is outside the warm window
            return reference_search(a, target, max_weight, None, windows)
    else:
        centre = math.log(a.std(ddof=1) / math.sqrt(-math.log(target)))
        low, high, passes = centre - 7.0, centre + 7.0, 2
        log_betas, ess = grid(low, high)
        while True:
            if (ess >= target).all() and low > centre - 40.0:
                low, high = low - 14.0, low
            elif not (ess >= target).any() and high < centre + 40.0:
                low, high = high, high + 14.0
            else:
                break
            log_betas, ess = grid(low, high)
    for done in range(passes):
        if done:
            log_betas, ess = grid(low, high)
        missed = np.flatnonzero(ess < target)
        first = 0 if len(missed) == 0 else min(int(missed[-1]) + 1, 63)
        low, high = log_betas[max(first - 1, 0)], log_betas[first]
    below, above = ess[max(first - 1, 0)], ess[first]
    share = (target - below) / (above - below) if above > below else 1.0
    return math.exp(low + min(max(share, 0.0), 1.0) * (high - low))


SEARCH_CASES = [
    *[(seed, target, max_weight, None) for seed in (0, 1) for target in (0.05, 0.5, 0.9) for max_weight in (20.0, 1e30)],
    (2, 0.7, 20.0, 1.2),  # warm, the target inside the window (the start is a factor of the cold answer)
    (2, 0.7, 20.0, 100.0),  # warm, outside it: the search starts again from scratch
    (2, 0.7, 20.0, math.exp(0.495)),  # warm, the crossing in the window's first cell: still inside, one pass
    (3, 0.3, 1e30, 0.9),
    ("tied", 0.5, 1e30, None),  # the window moves down past the Gaussian guess's (two nearly tied best rows)
    ("clipped", 0.02, 20.0, None),  # below every size the clipped weights reach: the window moves to its limit
    ("clipped_x1e6", 0.02, 20.0, None),  # the limit is relative to the guess: at another scale, another window
    ("clipped_x1e-6", 0.02, 20.0, None),
]


@pytest.mark.parametrize("case, target, max_weight, start", SEARCH_CASES)
def test_search_follows_its_documented_algorithm_window_by_window(monkeypatch, case, target, max_weight, start):
    """Every grid the search evaluates (its cost) and its answer, against the float64 reference above."""
    import sb3_lifelong.crr.losses as losses

    if case == "tied":
        advantages = th.tensor([1.953125e-03, -3.0, 0.0])
    elif isinstance(case, str):  # "clipped", at a scale
        scale = float(case.partition("_x")[2] or 1.0)
        advantages = th.cat([th.full((8,), 30.0 * scale), th.zeros(248)])  # 8 rows far above: clipped when cold
    else:
        generator = th.Generator().manual_seed(case)
        advantages = th.cat([th.randn(192, generator=generator), 3 * th.rand(64, generator=generator) - 4])
    if start is not None:
        start = start * reference_search(advantages.numpy(), target, max_weight)
    expected_windows: list = []
    expected = reference_search(advantages.numpy(), target, max_weight, start, expected_windows)
    windows = []
    real = losses._ess_of_temperatures

    def recording(values, log_betas, log_max):
        windows.append((float(log_betas[0]), float(log_betas[-1])))
        return real(values, log_betas, log_max)

    monkeypatch.setattr(losses, "_ess_of_temperatures", recording)
    found = ess_temperature(advantages, target, max_weight=max_weight, start=start).item()
    assert len(windows) == len(expected_windows), (windows, expected_windows)
    np.testing.assert_allclose(np.array(windows), np.array(expected_windows), rtol=0, atol=2e-5)
    assert found == pytest.approx(expected, rel=2e-5)
