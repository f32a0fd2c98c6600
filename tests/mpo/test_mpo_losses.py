"""
MPO's loss terms and duals one by one, against NumPy written from the formulas of the MPO paper (Abdolmaleki et al.
2018, "Relative Entropy Regularized Policy Iteration": the E-step's temperature dual, the decoupled M-step and its
per-dimension trust region) and of Acme's ``MPO`` loss, never by calling the code under test; then one whole policy
improvement of an ``MPO`` model on a fixed batch (golden numbers, every intermediate).

Acme's conventions, which ``sb3_lifelong.mpo.losses`` follows:

- temperature: ``loss = eta * epsilon + eta * mean_B[logsumexp_N(Q / eta) - log N]``, weights ``softmax_N(Q / eta)``;
- trust region: ``KL(pi_target || pi_online)`` per action dimension, the mean's with the target's std and the std's
  with the target's mean, averaged over the batch; the policy pays ``sg(alpha) * KL``, the duals
  ``alpha * (epsilon - sg(KL))`` (so that a gradient *descent* step raises ``alpha`` when ``KL > epsilon``);
- Multi-Objective MPO's action penalty: a second objective ``-||a - clip(a, -1, 1)||`` with its own temperature.
"""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_lifelong import MPO
from sb3_lifelong.mpo.losses import (
    DUAL_RAW_FLOOR,
    action_penalty_q,
    dual_value,
    e_step,
    inverse_softplus,
    m_step_loss,
    temperature_loss_and_weights,
    trust_region,
)
from sb3_lifelong.mpo.mpo import TargetSamples

# ---------------------------------------------------------------------------------------------------------------------
# NumPy references, from the formulas
# ---------------------------------------------------------------------------------------------------------------------


def np_logsumexp(x: np.ndarray, axis: int = 0) -> np.ndarray:
    top = x.max(axis=axis, keepdims=True)
    return (top + np.log(np.exp(x - top).sum(axis=axis, keepdims=True))).squeeze(axis)


def np_softplus(x: np.ndarray) -> np.ndarray:
    return np.log1p(np.exp(x))


def np_sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def np_temperature(q: np.ndarray, eta: float, epsilon: float) -> tuple[float, np.ndarray, float]:
    """:return: the temperature's loss, the weights and d loss / d eta (the weights held fixed: they are detached)"""
    n = q.shape[0]
    lse = np_logsumexp(q / eta, axis=0)
    weights = np.exp(q / eta - lse)
    loss = eta * (epsilon + np.mean(lse - math.log(n)))
    # d/d eta [eta * lse(Q / eta)] = lse - sum_i w_i Q_i / eta
    grad = epsilon + np.mean(lse - math.log(n)) - np.mean((weights * q).sum(axis=0) / eta)
    return float(loss), weights, float(grad)


def np_gaussian_kl(mean_p, std_p, mean_q, std_q) -> np.ndarray:
    """KL(N(m_p, s_p^2) || N(m_q, s_q^2)) per dimension: log(s_q / s_p) + (s_p^2 + (m_p - m_q)^2) / (2 s_q^2) - 1/2"""
    return np.log(std_q / std_p) + (std_p**2 + (mean_p - mean_q) ** 2) / (2 * std_q**2) - 0.5


def np_log_normal(x, mean, std) -> np.ndarray:
    """log N(x; mean, std^2), summed over the last axis"""
    return (-0.5 * ((x - mean) / std) ** 2 - np.log(std) - 0.5 * math.log(2 * math.pi)).sum(axis=-1)


def np_m_step(actions, weights, online_mean, online_std, target_mean, target_std) -> float:
    """-mean_B sum_N w (log N(a; mu, sigma_target) + log N(a; mu_target, sigma)), straight from the samples"""
    total = sum(weights)
    fit = np_log_normal(actions, online_mean[None], target_std[None]) + np_log_normal(
        actions, target_mean[None], online_std[None]
    )
    return float(-(total * fit).sum(axis=0).mean())


def np_action_penalty(actions: np.ndarray) -> np.ndarray:
    return -np.linalg.norm(actions - np.clip(actions, -1.0, 1.0), axis=-1)


def t64(x) -> th.Tensor:
    return th.tensor(np.asarray(x), dtype=th.float64)


# ---------------------------------------------------------------------------------------------------------------------
# The E-step
# ---------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("eta", [0.3, 1.0, 4.0])
def test_temperature_loss_weights_and_gradient_against_numpy(eta):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(6, 5)) * 3.0
    temperature = t64(eta).requires_grad_()
    loss, weights = temperature_loss_and_weights(t64(q), temperature, epsilon=0.05)
    want_loss, want_weights, want_grad = np_temperature(q, eta, 0.05)
    assert loss.item() == pytest.approx(want_loss, rel=1e-12)
    np.testing.assert_allclose(weights.numpy(), want_weights, rtol=1e-12)
    np.testing.assert_allclose(weights.sum(dim=0).numpy(), 1.0, rtol=1e-12)
    loss.backward()
    assert temperature.grad.item() == pytest.approx(want_grad, rel=1e-10)


def test_temperature_dual_moves_towards_its_kl_bound():
    """The dual's gradient is ``epsilon - KL(q || uniform over the samples)``: a descent step lowers the temperature
    (greedier weights) while the improved policy is closer to the old one than ``epsilon``, raises it past it."""
    q = t64([[0.0, 0.0], [1.0, 2.0], [2.0, 4.0]])
    for eta, epsilon, sign in ((10.0, 0.5, +1), (0.05, 0.01, -1)):
        temperature = t64(eta).requires_grad_()
        loss, weights = temperature_loss_and_weights(q, temperature, epsilon)
        loss.backward()
        kl = (weights * th.log(weights * q.shape[0])).sum(dim=0).mean().item()  # KL(q || pi_old) over the samples
        assert temperature.grad.item() == pytest.approx(epsilon - kl, rel=1e-9, abs=1e-12)
        assert np.sign(temperature.grad.item()) == sign


def test_action_penalty_is_minus_the_distance_outside_the_box():
    actions = np.array([[[0.5, -0.5], [2.0, 0.0], [-3.0, 4.0]], [[1.0, -1.0], [0.0, -1.5], [1.2, 1.2]]])
    got = action_penalty_q(t64(actions)).numpy()
    np.testing.assert_allclose(got, np_action_penalty(actions), rtol=1e-12)
    np.testing.assert_allclose(got, [[0.0, -1.0, -math.hypot(2.0, 3.0)], [0.0, -0.5, -math.hypot(0.2, 0.2)]], rtol=1e-12)


def test_e_step_without_the_penalty_is_the_task_objective_alone():
    rng = np.random.default_rng(1)
    q, actions = rng.normal(size=(5, 4)), 2.5 * rng.normal(size=(5, 4, 2))  # many samples outside [-1, 1]
    temperature = t64(0.7).requires_grad_()
    improved = e_step(t64(q), t64(actions), temperature, epsilon=0.1)
    want_loss, want_weights, want_grad = np_temperature(q, 0.7, 0.1)
    assert len(improved.weights) == 1
    np.testing.assert_allclose(improved.weights[0].numpy(), want_weights, rtol=1e-12)
    assert improved.dual_loss.item() == pytest.approx(want_loss, rel=1e-12)
    improved.dual_loss.backward()
    assert temperature.grad.item() == pytest.approx(want_grad, rel=1e-10)


def test_e_step_with_the_penalty_adds_its_objective_and_its_dual():
    rng = np.random.default_rng(2)
    q, actions = rng.normal(size=(5, 4)), 2.0 * rng.normal(size=(5, 4, 2))
    temperature, penalty_temperature = t64(0.7).requires_grad_(), t64(0.2).requires_grad_()
    improved = e_step(t64(q), t64(actions), temperature, 0.1, penalty_temperature, epsilon_penalty=0.01)
    task_loss, task_weights, task_grad = np_temperature(q, 0.7, 0.1)
    penalty_loss, penalty_weights, penalty_grad = np_temperature(np_action_penalty(actions), 0.2, 0.01)
    assert len(improved.weights) == 2
    np.testing.assert_allclose(improved.weights[0].numpy(), task_weights, rtol=1e-12)
    np.testing.assert_allclose(improved.weights[1].numpy(), penalty_weights, rtol=1e-12)
    # the penalty's weights prefer the samples inside the box
    inside = np.linalg.norm(actions - np.clip(actions, -1, 1), axis=-1) == 0
    assert penalty_weights[inside].min() > penalty_weights[~inside].max()
    assert improved.dual_loss.item() == pytest.approx(task_loss + penalty_loss, rel=1e-12)
    improved.dual_loss.backward()
    assert temperature.grad.item() == pytest.approx(task_grad, rel=1e-10)
    assert penalty_temperature.grad.item() == pytest.approx(penalty_grad, rel=1e-10)
    assert penalty_temperature.grad.item() != 0.0


# ---------------------------------------------------------------------------------------------------------------------
# The M-step and its trust region
# ---------------------------------------------------------------------------------------------------------------------


def fixed_policies(seed: int = 3, batch: int = 4, action_dim: int = 2):
    rng = np.random.default_rng(seed)
    target_mean = rng.uniform(-0.5, 0.5, size=(batch, action_dim))
    target_std = rng.uniform(0.2, 0.6, size=(batch, action_dim))
    online_mean = target_mean + rng.normal(size=(batch, action_dim)) * 0.3
    online_std = target_std * rng.uniform(0.5, 1.8, size=(batch, action_dim))
    return target_mean, target_std, online_mean, online_std


@pytest.mark.parametrize("objectives", [1, 2])
def test_m_step_against_numpy_and_its_gradients(objectives):
    rng = np.random.default_rng(4)
    target_mean, target_std, online_mean, online_std = fixed_policies()
    actions = target_mean[None] + target_std[None] * rng.normal(size=(7, 4, 2))
    weights = [np.exp(logits) / np.exp(logits).sum(axis=0) for logits in rng.normal(size=(objectives, 7, 4))]
    mean, std = t64(online_mean).requires_grad_(), t64(online_std).requires_grad_()
    loss = m_step_loss(t64(actions), [t64(w) for w in weights], mean, std, t64(target_mean), t64(target_std))
    assert loss.item() == pytest.approx(
        np_m_step(actions, weights, online_mean, online_std, target_mean, target_std), rel=1e-12
    )
    loss.backward()
    w = sum(weights)[..., None]  # [N, B, 1]
    batch = actions.shape[1]
    # d/d mu: -sum_N w (a - mu) / sigma_target^2 / B; d/d sigma: -sum_N w ((a - mu_target)^2 / sigma^3 - 1 / sigma) / B
    grad_mean = -(w * (actions - online_mean[None])).sum(axis=0) / target_std**2 / batch
    grad_std = -(w * ((actions - target_mean[None]) ** 2 / online_std[None] ** 3 - 1 / online_std[None])).sum(axis=0) / batch
    np.testing.assert_allclose(mean.grad.numpy(), grad_mean, rtol=1e-10)
    np.testing.assert_allclose(std.grad.numpy(), grad_std, rtol=1e-10)


def test_m_step_mean_and_std_are_decoupled():
    """The mean is fitted with the target's std and the std with the target's mean: moving the online std does not
    change the mean's gradient, and moving the online mean does not change the std's."""
    rng = np.random.default_rng(5)
    target_mean, target_std, online_mean, online_std = fixed_policies()
    actions = t64(target_mean[None] + target_std[None] * rng.normal(size=(7, 4, 2)))
    weights = [t64(np.full((7, 4), 1 / 7))]

    def grads(mean_value, std_value):
        mean, std = t64(mean_value).requires_grad_(), t64(std_value).requires_grad_()
        m_step_loss(actions, weights, mean, std, t64(target_mean), t64(target_std)).backward()
        return mean.grad.numpy(), std.grad.numpy()

    base_mean_grad, base_std_grad = grads(online_mean, online_std)
    np.testing.assert_allclose(grads(online_mean, 2 * online_std)[0], base_mean_grad, rtol=1e-12)
    np.testing.assert_allclose(grads(online_mean + 0.4, online_std)[1], base_std_grad, rtol=1e-12)


def test_trust_region_kls_penalties_and_duals_against_numpy():
    target_mean, target_std, online_mean, online_std = fixed_policies(batch=5, action_dim=3)
    alpha_mean_value, alpha_std_value = np.array([0.5, 2.0, 7.0]), np.array([3.0, 0.1, 1.0])
    mean, std = t64(online_mean).requires_grad_(), t64(online_std).requires_grad_()
    alpha_mean, alpha_std = t64(alpha_mean_value).requires_grad_(), t64(alpha_std_value).requires_grad_()
    epsilon_mean, epsilon_std = 0.05, 0.01
    region = trust_region(t64(target_mean), t64(target_std), mean, std, alpha_mean, alpha_std, epsilon_mean, epsilon_std)
    # decoupled: the mean's KL with the target's std, the std's with the target's mean; per dimension, batch mean
    kl_mean = np_gaussian_kl(target_mean, target_std, online_mean, target_std).mean(axis=0)
    kl_std = np_gaussian_kl(target_mean, target_std, target_mean, online_std).mean(axis=0)
    np.testing.assert_allclose(kl_mean, (0.5 * ((target_mean - online_mean) / target_std) ** 2).mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(region.kl_mean.detach().numpy(), kl_mean, rtol=1e-12)
    np.testing.assert_allclose(region.kl_stddev.detach().numpy(), kl_std, rtol=1e-12)
    assert region.kl_loss.item() == pytest.approx((alpha_mean_value * kl_mean).sum() + (alpha_std_value * kl_std).sum())
    assert region.dual_loss.item() == pytest.approx(
        (alpha_mean_value * (epsilon_mean - kl_mean)).sum() + (alpha_std_value * (epsilon_std - kl_std)).sum()
    )
    # the penalty's gradient goes into the policy only, the duals' into the duals only
    th.autograd.backward([region.kl_loss])
    assert alpha_mean.grad is None and alpha_std.grad is None
    batch = target_mean.shape[0]
    np.testing.assert_allclose(
        mean.grad.numpy(), alpha_mean_value * (online_mean - target_mean) / target_std**2 / batch, rtol=1e-10
    )
    # d/d sigma KL(N(mu_t, s_t) || N(mu_t, sigma)) = 1 / sigma - s_t^2 / sigma^3
    np.testing.assert_allclose(
        std.grad.numpy(), alpha_std_value * (1 / online_std - target_std**2 / online_std**3) / batch, rtol=1e-10
    )
    mean.grad, std.grad = None, None
    region.dual_loss.backward()
    assert mean.grad is None and std.grad is None
    np.testing.assert_allclose(alpha_mean.grad.numpy(), epsilon_mean - kl_mean, rtol=1e-12)
    np.testing.assert_allclose(alpha_std.grad.numpy(), epsilon_std - kl_std, rtol=1e-12)


@pytest.mark.parametrize("which", ["mean", "stddev"])
def test_trust_region_dual_rises_when_the_kl_exceeds_its_bound_and_falls_below(which):
    """A gradient descent step on the duals' loss raises ``alpha`` of a dimension whose KL exceeds its bound and lowers
    it where the KL is below (the constraint is then slack), through the softplus parametrisation too."""
    target_mean, target_std = np.zeros((3, 2)), np.ones((3, 2))
    online_mean, online_std = target_mean.copy(), target_std.copy()
    if which == "mean":
        online_mean[:, 0] = 0.5  # KL = 0.125 on the first dimension, 0 on the second
    else:
        online_std[:, 0] = 2.0  # KL = log 2 + 1/8 - 1/2 = 0.318
    raw = t64([inverse_softplus(1.0)] * 2).requires_grad_()
    other = t64([1.0, 1.0])
    alphas = (dual_value(raw), other) if which == "mean" else (other, dual_value(raw))
    region = trust_region(t64(target_mean), t64(target_std), t64(online_mean), t64(online_std), *alphas, 0.01, 0.01)
    kl = (region.kl_mean if which == "mean" else region.kl_stddev).detach().numpy()
    assert kl[0] > 0.01 and kl[1] == 0.0
    region.dual_loss.backward()
    np.testing.assert_allclose(raw.grad.numpy(), (0.01 - kl) * np_sigmoid(raw.detach().numpy()), rtol=1e-9)
    optimizer = th.optim.SGD([raw], lr=0.1)
    before = dual_value(raw).detach().clone()
    optimizer.step()
    after = dual_value(raw).detach()
    assert after[0] > before[0]  # the violated constraint's multiplier grows
    assert after[1] < before[1]  # the slack one's shrinks


def test_dual_parametrisation_is_a_shifted_softplus():
    raw = np.array([-20.0, -1.0, 0.0, 2.5, 30.0])
    np.testing.assert_allclose(dual_value(t64(raw)).numpy(), np_softplus(raw) + 1e-8, rtol=1e-12)
    for value in (1e-4, 0.5, 1.0, 10.0, 100.0):
        assert np_softplus(inverse_softplus(value)) == pytest.approx(value, rel=1e-9)
    with pytest.raises(ValueError, match="> 0"):
        inverse_softplus(-1.0)


def test_dual_floor_keeps_a_dual_positive_at_its_documented_size():
    # the floor of a raw dual (mpo.py clamps to it after each step): softplus(-18) ~ 1.5e-8, a dual that can still rise
    assert np_softplus(np.array(DUAL_RAW_FLOOR)) == pytest.approx(1.523e-8, rel=0.01)
    assert float(dual_value(t64(np.array(DUAL_RAW_FLOOR)))) == pytest.approx(2.523e-8, rel=0.01)


def test_temperature_loss_sends_no_gradient_into_the_q_values():
    q_values = th.randn(5, 4, dtype=th.float64, requires_grad=True)
    temperature = th.tensor(0.7, dtype=th.float64, requires_grad=True)
    loss, weights = temperature_loss_and_weights(q_values, temperature, 0.1)
    loss.backward()
    assert q_values.grad is None and temperature.grad is not None and not weights.requires_grad


def test_the_action_penalty_bound_defaults_to_zero():
    rng = np.random.default_rng(3)
    q_values, actions = t64(rng.normal(size=(6, 4))), t64(rng.uniform(-1.5, 1.5, size=(6, 4, 2)))
    eta, penalty = th.tensor(0.8, dtype=th.float64), th.tensor(0.3, dtype=th.float64)
    default = e_step(q_values, actions, eta, 0.1, penalty_temperature=penalty)
    explicit = e_step(q_values, actions, eta, 0.1, penalty_temperature=penalty, epsilon_penalty=0.0)
    assert float(default.dual_loss) == float(explicit.dual_loss)


# ---------------------------------------------------------------------------------------------------------------------
# Golden numbers: a whole policy improvement of an MPO model on a fixed batch
# ---------------------------------------------------------------------------------------------------------------------


def tiny_mpo(action_penalty: bool) -> MPO:
    env_space = spaces.Box(-1.0, 1.0, (3,), np.float32)

    class Tiny(gym.Env):
        observation_space = env_space
        action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros(3, np.float32), {}

        def step(self, action):
            return np.zeros(3, np.float32), 0.0, False, False, {}

    policy_kwargs = dict(net_arch=[8], layer_norm=False, squash_mean=not action_penalty)
    return MPO(
        "MlpPolicy",
        Tiny(),
        seed=11,
        policy_kwargs=policy_kwargs,
        policy_loss=dict(
            epsilon=0.1,
            epsilon_mean=0.01,
            epsilon_stddev=1e-4,
            epsilon_penalty=0.02,
            init_temperature=0.8,
            init_alpha_mean=2.0,
            init_alpha_stddev=5.0,
            action_penalty=action_penalty,
        ),
        num_samples=5,
        compute=dict(compile_losses=False),
        device="cpu",
    )


@pytest.mark.parametrize("action_penalty", [False, True])
def test_policy_improvement_golden_numbers(action_penalty):
    """MPO's policy improvement on a fixed batch and fixed networks: the E-step's weights and temperatures, the
    M-step, both KLs, the duals' losses and the gradient of the whole loss into each dual, against NumPy."""
    model = tiny_mpo(action_penalty)
    rng = np.random.default_rng(7)
    num_samples, batch = model.num_samples, 4
    obs = th.tensor(rng.uniform(-1, 1, size=(batch, 3)), dtype=th.float32)
    with th.no_grad():  # a target policy a little away from the online one: the trust region has work to do
        for parameter in model.actor_target.parameters():
            parameter.add_(0.3 * th.tensor(rng.normal(size=tuple(parameter.shape)), dtype=th.float32))
        target_mean, target_std = model.actor_target.distribution_params(obs)
        online_mean, online_std = model.actor.distribution_params(obs)
    actions = target_mean.unsqueeze(0) + 1.5 * target_std.unsqueeze(0) * th.randn(num_samples, batch, 2)
    actions[0, 0] = th.tensor([1.7, -2.2])  # outside the box: the action penalty sees it
    q_values = th.tensor(rng.normal(size=(num_samples, batch)) * 2.0, dtype=th.float32)
    targets = TargetSamples(th.zeros(batch, 1), target_mean, target_std, actions, q_values)
    with th.no_grad():  # raw duals away from their initial values, a different one per dimension
        model.log_alpha_mean.copy_(th.tensor([0.3, -0.4]))
        model.log_alpha_stddev.copy_(th.tensor([1.5, 0.2]))
    improvement, loss = model._policy_improvement(obs, targets)
    loss.backward()

    a, q = actions.double().numpy(), q_values.double().numpy()
    mu_t, sd_t, mu, sd = (x.double().numpy() for x in (target_mean, target_std, online_mean, online_std))
    raw_eta, raw_am, raw_as = (
        x.detach().double().numpy() for x in (model.log_temperature, model.log_alpha_mean, model.log_alpha_stddev)
    )
    eta, alpha_mean, alpha_std = (np_softplus(x) + 1e-8 for x in (raw_eta, raw_am, raw_as))
    eta_loss, weights, eta_grad = np_temperature(q, float(eta[0]), 0.1)
    all_weights, dual_loss = [weights], eta_loss
    if action_penalty:
        raw_pen = model.log_penalty_temperature.detach().double().numpy()
        pen_eta = np_softplus(raw_pen) + 1e-8
        pen_loss, pen_weights, pen_grad = np_temperature(np_action_penalty(a), float(pen_eta[0]), 0.02)
        all_weights.append(pen_weights)
        dual_loss += pen_loss
    m_step = np_m_step(a, all_weights, mu, sd, mu_t, sd_t)
    kl_mean = np_gaussian_kl(mu_t, sd_t, mu, sd_t).mean(axis=0)
    kl_std = np_gaussian_kl(mu_t, sd_t, mu_t, sd).mean(axis=0)
    assert kl_mean.max() > 0.01 and kl_std.max() > 1e-4  # at least one constraint violated of each kind
    kl_loss = (alpha_mean * kl_mean).sum() + (alpha_std * kl_std).sum()
    dual_loss += (alpha_mean * (0.01 - kl_mean)).sum() + (alpha_std * (1e-4 - kl_std)).sum()

    assert loss.item() == pytest.approx(m_step + kl_loss + dual_loss, rel=1e-5)
    assert improvement.actor_loss.item() == pytest.approx(m_step, rel=1e-5)
    assert improvement.temperature.item() == pytest.approx(float(eta[0]), rel=1e-6)
    assert improvement.alpha_mean.item() == pytest.approx(alpha_mean.mean(), rel=1e-6)
    assert improvement.alpha_stddev.item() == pytest.approx(alpha_std.mean(), rel=1e-6)
    assert improvement.kl_mean.item() == pytest.approx(kl_mean.mean(), rel=1e-4)
    assert improvement.kl_stddev.item() == pytest.approx(kl_std.mean(), rel=1e-4)
    assert improvement.ess.item() == pytest.approx((1 / (weights**2).sum(axis=0)).mean() / num_samples, rel=1e-5)
    assert improvement.std_min.item() == pytest.approx(sd.min(), rel=1e-6)
    assert improvement.std_max.item() == pytest.approx(sd.max(), rel=1e-6)
    # every dual's gradient: d loss / d raw = d loss / d dual * sigmoid(raw)
    np.testing.assert_allclose(model.log_temperature.grad.numpy(), eta_grad * np_sigmoid(raw_eta), rtol=1e-4)
    np.testing.assert_allclose(model.log_alpha_mean.grad.numpy(), (0.01 - kl_mean) * np_sigmoid(raw_am), rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(model.log_alpha_stddev.grad.numpy(), (1e-4 - kl_std) * np_sigmoid(raw_as), rtol=1e-4, atol=1e-9)
    if action_penalty:
        assert improvement.penalty_temperature.item() == pytest.approx(float(pen_eta[0]), rel=1e-6)
        np.testing.assert_allclose(model.log_penalty_temperature.grad.numpy(), pen_grad * np_sigmoid(raw_pen), rtol=1e-4)
    else:
        assert improvement.penalty_temperature is None and model.log_penalty_temperature.grad is None
