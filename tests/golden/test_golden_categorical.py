"""
Golden numbers for the categorical critic itself (issue 66), built directly at sizes that differ from each other
(3 next actions, 4 rows, 2 action dimensions, 7 atoms, 2 Q-networks with a hidden layer), so that a mixed-up
dimension changes a number instead of passing by coincidence (the CRR golden test has 2 next actions, 2 action
dimensions and as many rows as atoms). Every expected number is computed here in NumPy, in float64, from the
critic's weights:

- the TD target: per row and next action the distribution of the Q-network with the lowest expected value,
  averaged over the next actions, shifted by ``r + discount * z`` and projected onto the support, on both of the
  critic's paths (its own call under autograd, the scoring engine's no-grad pass);
- with a bfloat16 copy, the target is the copy's (close to the float32 target, but not it);
- the cross-entropy loss and the lowest expected Q-value, ``expected`` on logits with more than two dimensions, and
  ``q1_forward`` of the first network of two;
- a shared features extractor gets no gradient from the critic, an own one does;
- the critic's defaults, read from the critic it builds.
"""

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, FlattenExtractor
from torch import nn

from sb3_lifelong.crr.distributional import CategoricalCritic
from sb3_lifelong.numerics.scoring import LowPrecisionCopy

OBS_DIM, ACTION_DIM, HIDDEN = 3, 2, 6
N_NEXT, ROWS, N_ATOMS = 3, 4, 7
V_MIN, V_MAX = -3.0, 3.0
SUPPORT = np.linspace(V_MIN, V_MAX, N_ATOMS)


def critic(seed: int = 0, **kwargs) -> CategoricalCritic:
    th.manual_seed(seed)
    obs_space = spaces.Box(-1, 1, (OBS_DIM,))
    built = CategoricalCritic(
        obs_space,
        spaces.Box(-1, 1, (ACTION_DIM,)),
        net_arch=[HIDDEN],
        features_extractor=FlattenExtractor(obs_space),
        features_dim=OBS_DIM,
        n_critics=2,
        n_atoms=N_ATOMS,
        v_min=V_MIN,
        v_max=V_MAX,
        **kwargs,
    )
    with th.no_grad():  # sharper distributions than the default init, so that the networks' expected values differ
        for net in built.q_networks:
            net[-1].weight.mul_(4.0)
    return built


def weights_of(model: CategoricalCritic) -> list[tuple[np.ndarray, ...]]:
    """each Q-network's ``(W1, b1, W2, b2)`` in float64"""
    layers = [(net[0].weight, net[0].bias, net[2].weight, net[2].bias) for net in model.q_networks]
    return [tuple(p.detach().double().numpy() for p in params) for params in layers]


def softmax(x: np.ndarray) -> np.ndarray:
    e = np.exp(x - x.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


def hand_logits(model: CategoricalCritic, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """``[2 nets, ..., n_atoms]``: relu(x W1' + b1) W2' + b2 of x = [s, a]"""
    x = np.concatenate([np.broadcast_to(obs, (*actions.shape[:-1], OBS_DIM)), actions], axis=-1)
    return np.stack([np.maximum(x @ w1.T + b1, 0.0) @ w2.T + b2 for w1, b1, w2, b2 in weights_of(model)])


def hand_projection(probs: np.ndarray, rewards: np.ndarray, discounts: np.ndarray) -> np.ndarray:
    """C51's projection, atom by atom: each shifted atom's mass split between its two neighbours on the support"""
    delta = SUPPORT[1] - SUPPORT[0]
    out = np.zeros_like(probs)
    for row in range(probs.shape[0]):
        for j, z in enumerate(SUPPORT):
            shifted = min(max(rewards[row, 0] + discounts[row, 0] * z, V_MIN), V_MAX)
            position = (shifted - V_MIN) / delta
            low, high = int(np.floor(position)), int(np.ceil(position))
            if low == high:
                out[row, low] += probs[row, j]
            else:
                out[row, low] += probs[row, j] * (high - position)
                out[row, high] += probs[row, j] * (position - low)
    return out


def inputs(seed: int = 1) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    next_obs = rng.uniform(-1, 1, (ROWS, OBS_DIM))
    next_actions = rng.uniform(-1, 1, (N_NEXT, ROWS, ACTION_DIM))
    rewards = np.array([[0.5], [-1.25], [2.0], [0.1]])
    discounts = np.array([[0.9], [0.9], [0.0], [0.45]])  # a terminal row, and an n-step discount
    return next_obs, next_actions, rewards, discounts


def tensors(*arrays: np.ndarray) -> list[th.Tensor]:
    return [th.tensor(a, dtype=th.float32) for a in arrays]


def hand_target(model: CategoricalCritic) -> np.ndarray:
    next_obs, next_actions, rewards, discounts = inputs()
    probs = softmax(hand_logits(model, next_obs, next_actions))  # [2 nets, 3 actions, 4 rows, 7 atoms]
    lowest = (probs @ SUPPORT).argmin(axis=0)  # [3 actions, 4 rows]
    assert 0 < lowest.sum() < lowest.size, "both networks must be the lowest somewhere"
    picked = np.where((lowest == 0)[..., None], probs[0], probs[1])
    return hand_projection(picked.mean(axis=0), rewards, discounts)


def test_td_target_at_uneven_sizes_by_hand_on_both_paths():
    model = critic()
    next_obs, next_actions, rewards, discounts = tensors(*inputs())
    want = hand_target(model)
    with th.no_grad():  # the scoring engine's pass, as in the update
        engine = model.td_target(next_obs, next_actions, rewards, discounts).double().numpy()
    eager = model.td_target(next_obs, next_actions, rewards, discounts).detach().double().numpy()  # the critic's call
    for got in (engine, eager):
        assert got.shape == (ROWS, N_ATOMS)
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(got.sum(axis=1), 1.0, rtol=1e-6)


def test_td_target_with_a_bfloat16_copy_is_the_copys():
    model = critic()
    next_obs, next_actions, rewards, discounts = tensors(*inputs())
    copy = LowPrecisionCopy(model, th.bfloat16)
    with th.no_grad():
        low = model.td_target(next_obs, next_actions, rewards, discounts, low_precision=copy).double().numpy()
    want = hand_target(model)
    # bf16 products: close to the float32 target, and not it (a pass that ignored the copy gives the float32 one)
    np.testing.assert_allclose(low, want, atol=0.05)
    assert np.abs(low - want).max() > 1e-4
    np.testing.assert_allclose(low.sum(axis=1), 1.0, rtol=1e-5)


def test_loss_expected_and_q1_forward_by_hand():
    model = critic()
    rng = np.random.default_rng(2)
    obs, actions = rng.uniform(-1, 1, (ROWS, OBS_DIM)), rng.uniform(-1, 1, (ROWS, ACTION_DIM))
    target = softmax(rng.normal(size=(ROWS, N_ATOMS)))
    logits = hand_logits(model, obs, actions)  # [2 nets, 4 rows, 7 atoms]
    fit = model.loss(*tensors(obs, actions, target))
    log_probs = logits - np.log(np.exp(logits).sum(axis=-1, keepdims=True))
    # the cross-entropy, summed over atoms, averaged over rows, summed over the networks (4 rows, 7 atoms: a mixed-up
    # axis gives another number)
    assert fit.loss.item() == pytest.approx(sum(-(target * lp).sum(axis=1).mean() for lp in log_probs), rel=1e-5)
    q = softmax(logits) @ SUPPORT  # [2 nets, 4 rows]
    assert np.abs(q[0] - q[1]).min() > 1e-3
    np.testing.assert_allclose(fit.q_values.numpy(), q.min(axis=0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(model.q1_forward(*tensors(obs, actions)).detach().numpy(), q[0][:, None], rtol=1e-5, atol=1e-6)
    # ``expected`` reads the last axis of logits of any rank
    many = rng.normal(size=(2, ROWS, N_ATOMS))
    got = model.expected(th.tensor(many, dtype=th.float32)).detach().numpy()
    assert got.shape == (2, ROWS, 1)
    np.testing.assert_allclose(got[..., 0], softmax(many) @ SUPPORT, rtol=1e-5, atol=1e-6)


class LinearExtractor(BaseFeaturesExtractor):
    def __init__(self, observation_space: spaces.Box) -> None:
        super().__init__(observation_space, features_dim=4)
        self.linear = nn.Linear(OBS_DIM, 4)

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.linear(observations)


@pytest.mark.parametrize("share", [True, False])
def test_a_shared_features_extractor_gets_no_gradient_from_the_critic(share):
    obs_space = spaces.Box(-1, 1, (OBS_DIM,))
    model = CategoricalCritic(
        obs_space,
        spaces.Box(-1, 1, (ACTION_DIM,)),
        net_arch=[HIDDEN],
        features_extractor=LinearExtractor(obs_space),
        features_dim=4,
        share_features_extractor=share,
    )
    obs, actions = th.rand(ROWS, OBS_DIM), th.rand(ROWS, ACTION_DIM)
    model.loss(obs, actions, th.full((ROWS, 51), 1 / 51)).loss.backward()
    grad = model.features_extractor.linear.weight.grad
    if share:  # the actor trains a shared extractor; the critic's loss leaves it alone
        assert grad is None
    else:
        assert grad is not None and grad.abs().sum() > 0
    assert all(p.grad is not None for net in model.q_networks for p in net.parameters())


def test_the_critics_defaults_in_what_it_builds():
    obs_space = spaces.Box(-1, 1, (OBS_DIM,))
    model = CategoricalCritic(
        obs_space, spaces.Box(-1, 1, (ACTION_DIM,)), [HIDDEN], FlattenExtractor(obs_space), features_dim=OBS_DIM
    )
    np.testing.assert_array_equal(model.support.numpy(), np.linspace(-150.0, 150.0, 51).astype(np.float32))
    assert (model.n_atoms, model.v_min, model.v_max, model.n_critics) == (51, -150.0, 150.0, 1)
    assert len(model.q_networks) == 1 and model.share_features_extractor and model.normalize_images
    kinds = [type(layer) for layer in model.q_networks[0]]
    assert kinds == [nn.Linear, nn.ReLU, nn.Linear] and not model.layer_norm
    assert model.q_networks[0][-1].out_features == 51
