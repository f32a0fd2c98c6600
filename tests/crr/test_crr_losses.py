"""
CRR's loss terms one by one, against NumPy written from the formulas of the CRR paper (Wang et al. 2020, "Critic
Regularized Regression": ``f = 1[A > 0]`` and ``f = min(exp(A / beta), max_weight)``, ``A = Q(s, a) - mean_j Q(s,
a_j)`` or ``- max_j``), the C51 projection (Bellemare et al. 2017) and Kish's effective sample size, never by calling
the code under test; one whole CRR update's losses on a fixed batch (golden numbers, the networks evaluated in NumPy
from their weights); and CRR against BC on data where only the advantage's weights can tell the good actions from the
bad ones.
"""

import math

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_lifelong import BC, CRR
from sb3_lifelong.core.datasets import OfflineSamples
from sb3_lifelong.crr.distributional import categorical_projection
from sb3_lifelong.crr.losses import (
    actor_loss,
    advantage_weights,
    crr_weights,
    effective_sample_size,
    ess_temperature,
    sarsa_next_actions,
)
from sb3_lifelong.crr.targets import target_actions

# ---------------------------------------------------------------------------------------------------------------------
# NumPy references
# ---------------------------------------------------------------------------------------------------------------------


def np_exp_weights(advantages: np.ndarray, beta: float, max_weight: float) -> np.ndarray:
    return np.exp(np.minimum(advantages / beta, math.log(max_weight)))


def np_ess(weights: np.ndarray) -> float:
    return float(weights.sum() ** 2 / (len(weights) * (weights**2).sum()))


def np_log_normal(x, mean, std) -> np.ndarray:
    return (-0.5 * ((x - mean) / std) ** 2 - np.log(std) - 0.5 * math.log(2 * math.pi)).sum(axis=-1)


def np_projection(probs: np.ndarray, rewards: np.ndarray, discounts: np.ndarray, support: np.ndarray) -> np.ndarray:
    """C51, atom by atom: each atom ``z_j`` moves to ``r + d z_j`` (clipped), its mass split between the two nearest atoms"""
    v_min, v_max, n = support[0], support[-1], len(support)
    delta = (v_max - v_min) / (n - 1)
    out = np.zeros_like(probs)
    for row in range(probs.shape[0]):
        for j in range(n):
            moved = min(max(rewards[row] + discounts[row] * support[j], v_min), v_max)
            b = (moved - v_min) / delta
            low, high = math.floor(b), math.ceil(b)
            if low == high:
                out[row, low] += probs[row, j]
            else:
                out[row, low] += probs[row, j] * (high - b)
                out[row, high] += probs[row, j] * (b - low)
    return out


def t64(x) -> th.Tensor:
    return th.tensor(np.asarray(x), dtype=th.float64)


# ---------------------------------------------------------------------------------------------------------------------
# Advantages and their weights
# ---------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("beta,max_weight", [(1.0, 20.0), (0.3, 5.0), (4.0, 1.5), (0.05, 100.0)])
def test_exp_weights_against_numpy(beta, max_weight):
    advantages = np.random.default_rng(0).normal(size=64) * 2.0
    weights, clipped = crr_weights(t64(advantages), "exp", beta, max_weight)
    np.testing.assert_allclose(weights.numpy(), np_exp_weights(advantages, beta, max_weight), rtol=1e-12)
    assert clipped.numpy().tolist() == (np.exp(advantages / beta) >= max_weight).tolist()
    assert clipped.any() and not clipped.all()  # both sides of the clip are exercised
    # the same through a tensor temperature (the ESS search's)
    weights_t, _ = crr_weights(t64(advantages), "exp", t64(beta), max_weight)
    np.testing.assert_allclose(weights_t.numpy(), weights.numpy(), rtol=0)


def test_exp_weights_at_the_clip_and_the_indicator_at_zero():
    at_clip = math.log(20.0)
    weights, clipped = crr_weights(t64([at_clip - 1e-9, at_clip, at_clip + 1e-9]), "exp", 1.0, 20.0)
    np.testing.assert_allclose(weights.numpy(), [20.0, 20.0, 20.0], rtol=1e-8)
    assert clipped.tolist() == [False, True, True]
    weights, _ = crr_weights(t64([-1e-12, 0.0, 1e-12]), "indicator")
    assert weights.tolist() == [0.0, 0.0, 1.0]  # strictly positive advantages only


@pytest.mark.parametrize("baseline", ["mean", "max"])
@pytest.mark.parametrize("transform", ["exp", "indicator"])
@pytest.mark.parametrize("normalize", [False, True])
def test_advantage_weights_against_numpy(baseline, transform, normalize):
    rng = np.random.default_rng(1)
    data_q, sampled_q = rng.normal(size=16) * 3.0, rng.normal(size=(5, 16)) * 3.0
    got = advantage_weights(t64(data_q), t64(sampled_q), baseline, transform, beta=0.7, max_weight=8.0, normalize=normalize)
    advantages = data_q - (sampled_q.mean(axis=0) if baseline == "mean" else sampled_q.max(axis=0))
    np.testing.assert_allclose(got.advantages.numpy(), advantages, rtol=1e-12)
    spread = advantages.std(ddof=1) if normalize else 1.0
    if transform == "exp":
        want = np_exp_weights(advantages / spread, 0.7, 8.0)
        assert got.beta.item() == pytest.approx(0.7 * spread, rel=1e-12)  # in reward units
    else:
        want = (advantages > 0).astype(float)
        assert math.isnan(got.beta.item())
    np.testing.assert_allclose(got.weights.numpy(), want, rtol=1e-12)
    if baseline == "max":  # no action of the data beats the best of the policy's samples by much
        assert (advantages <= 0).sum() > (advantages > 0).sum()


def test_advantage_weights_with_a_target_ess():
    rng = np.random.default_rng(2)
    data_q, sampled_q = rng.normal(size=128), rng.normal(size=(4, 128))
    got = advantage_weights(t64(data_q), t64(sampled_q), "mean", "exp", beta=1.0, max_weight=20.0, target_ess=0.6)
    advantages = data_q - sampled_q.mean(axis=0)
    beta = got.beta.item()
    assert beta != 1.0
    np.testing.assert_allclose(got.weights.numpy(), np_exp_weights(advantages, beta, 20.0), rtol=1e-5)
    assert np_ess(np_exp_weights(advantages, beta, 20.0)) == pytest.approx(0.6, abs=1e-4)


def test_effective_sample_size_against_numpy():
    rng = np.random.default_rng(3)
    weights = rng.exponential(size=(3, 50))
    got = effective_sample_size(t64(weights)).numpy()
    np.testing.assert_allclose(got, [np_ess(row) for row in weights], rtol=1e-12)


@pytest.mark.parametrize("target", [0.3, 0.7, 0.95])
def test_ess_temperature_reaches_its_target_and_the_next_grid_point_does_not(target):
    """The temperature found gives the target's ESS in NumPy; 1 % colder gives less, 1 % warmer more, and every warmer
    one more. With clipped weights the ESS is not monotone in the temperature (at the coldest ones every weight is
    clipped or about 0: the fraction clipped, here ~0.44, again): the search takes the warmest crossing."""
    advantages = np.random.default_rng(4).standard_t(3, size=300)
    beta = ess_temperature(t64(advantages), target, max_weight=20.0).item()
    assert np_ess(np_exp_weights(advantages, beta, 20.0)) == pytest.approx(target, abs=1e-4)
    assert (
        np_ess(np_exp_weights(advantages, 0.99 * beta, 20.0)) < target < np_ess(np_exp_weights(advantages, 1.01 * beta, 20.0))
    )
    assert all(np_ess(np_exp_weights(advantages, b, 20.0)) > target for b in beta * np.geomspace(1.01, 1e3, 50))
    assert np_ess(np_exp_weights(advantages, 1e-3 * beta, 20.0)) > 0.4  # the cold end is above 0.3 again


# ---------------------------------------------------------------------------------------------------------------------
# The critic's target and the actor's loss
# ---------------------------------------------------------------------------------------------------------------------


def test_sarsa_next_actions_against_numpy_with_random_masks():
    rng = np.random.default_rng(5)
    sampled, data = rng.normal(size=(3, 10, 2)), rng.normal(size=(10, 2))
    mask = (rng.random((10, 1)) < 0.5).astype(float)
    mask[0], mask[1] = 1.0, 0.0
    got = sarsa_next_actions(t64(sampled), t64(data), t64(mask)).numpy()
    want = np.where(mask[None].astype(bool), data[None], sampled)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("v_min, v_max", [(-3.0, 5.0), (-12.0, 20.0), (-0.6, 1.0)])  # atoms 1, 4 and 0.2 apart
def test_categorical_projection_against_numpy(v_min, v_max):
    rng = np.random.default_rng(6)
    support = np.linspace(v_min, v_max, 9)
    probs = rng.dirichlet(np.ones(9), size=12)
    rewards = rng.uniform(-4.0, 4.0, size=12) * (v_max - v_min) / 8.0
    discounts = rng.choice([0.0, 0.5, 0.9, 1.0], size=12)
    rewards[0], discounts[0] = support[1] - support[0], 1.0  # every atom lands exactly on an atom
    got = categorical_projection(t64(probs), t64(rewards[:, None]), t64(discounts[:, None]), t64(support)).numpy()
    np.testing.assert_allclose(got, np_projection(probs, rewards, discounts, support), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(got.sum(axis=1), 1.0, rtol=1e-12)  # no mass lost
    # the projected mean is the shifted mean where nothing is clipped
    inside = (rewards + discounts * support[0] >= support[0]) & (rewards + discounts * support[-1] <= support[-1])
    np.testing.assert_allclose((got @ support)[inside], (rewards + discounts * (probs @ support))[inside], rtol=1e-10)


def test_actor_loss_against_numpy_and_its_gradient():
    rng = np.random.default_rng(7)
    actions, mean_value = rng.uniform(-1, 1, size=(6, 2)), rng.uniform(-1, 1, size=(6, 2))
    std_value, weights = rng.uniform(0.2, 0.8, size=(6, 2)), rng.exponential(size=6)
    mean = t64(mean_value).requires_grad_()
    loss = actor_loss(t64(actions), mean, t64(std_value), t64(weights))
    assert loss.item() == pytest.approx(-(weights * np_log_normal(actions, mean_value, std_value)).mean(), rel=1e-12)
    loss.backward()  # pulled towards the data's actions, in proportion to their weights
    np.testing.assert_allclose(
        mean.grad.numpy(), -weights[:, None] * (actions - mean_value) / std_value**2 / len(weights), rtol=1e-12
    )


# ---------------------------------------------------------------------------------------------------------------------
# Golden numbers: one CRR update's losses on a fixed batch, the networks evaluated in NumPy
# ---------------------------------------------------------------------------------------------------------------------


def np_linear(x: np.ndarray, layer) -> np.ndarray:
    return x @ layer.weight.detach().double().numpy().T + layer.bias.detach().double().numpy()


def np_q(critic, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """the lowest over the Q-networks (Linear, ReLU, Linear) of ``[..., batch]`` states and actions"""
    inputs = np.concatenate([np.broadcast_to(obs, actions.shape[:-1] + obs.shape[-1:]), actions], axis=-1)
    values = [np_linear(np.maximum(np_linear(inputs, net[0]), 0.0), net[2])[..., 0] for net in critic.q_networks]
    return np.min(values, axis=0)


def np_actor(actor, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    latent = np.maximum(np_linear(obs, actor.latent_pi[0]), 0.0)
    std = np.log1p(np.exp(np_linear(latent, actor.std_head))) * actor.init_std / math.log(2.0) + actor.min_std
    return np.tanh(np_linear(latent, actor.mu)), std


def random_data(n: int = 40, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "observations": rng.uniform(-1, 1, size=(n, 3)).astype(np.float32),
        "actions": rng.uniform(-1, 1, size=(n, 2)).astype(np.float32),
        "rewards": rng.normal(size=n).astype(np.float32),
        "next_observations": rng.uniform(-1, 1, size=(n, 3)).astype(np.float32),
        "terminals": rng.random(n) < 0.2,
    }


@pytest.mark.parametrize(
    "critic_target,transform", [("policy", "exp"), ("sarsa", "exp"), ("sarsa", "indicator"), ("policy", "indicator")]
)
def test_crr_update_golden_numbers(critic_target, transform):
    """The TD target (the target policy's samples, or the data's next action where the mask says the data has it),
    the critic's loss, the advantages of the data's actions, their weights and the actor's loss of one update."""
    model = CRR.from_offline_data(
        random_data(),
        action_space=spaces.Box(-1, 1, (2,)),
        normalized_actions=True,
        policy_kwargs=dict(net_arch=[8], n_critics=2),
        critic_target=critic_target,
        advantage_transform=transform,
        beta=0.5,
        max_weight=3.0,
        num_samples=3,
        n_target_samples=2,
        gamma=0.9,
        compute=dict(scoring_dtype="float32", compile_losses=False),
        seed=3,
        device="cpu",
    )
    with th.no_grad():  # target networks that differ from the online ones
        for parameter in [*model.actor_target.parameters(), *model.critic_target.parameters()]:
            parameter.add_(0.2 * th.randn_like(parameter))
    rng = np.random.default_rng(8)
    batch = 6
    obs, next_obs = rng.uniform(-1, 1, size=(batch, 3)), rng.uniform(-1, 1, size=(batch, 3))
    actions, next_actions = rng.uniform(-1, 1, size=(batch, 2)), rng.uniform(-1, 1, size=(batch, 2))
    rewards, dones = rng.normal(size=(batch, 1)), np.array([[0.0], [1.0], [0.0], [0.0], [1.0], [0.0]])
    mask = np.array([[1.0], [1.0], [0.0], [1.0], [0.0], [0.0]])
    target_noise, sample_noise = rng.normal(size=(2, batch, 2)) * 2.0, rng.normal(size=(3, batch, 2))

    def f32(x):
        return th.tensor(x, dtype=th.float32)

    replay = OfflineSamples(
        f32(obs), f32(actions), f32(next_obs), f32(dones), f32(rewards), None, f32(next_actions), f32(mask)
    )
    fit, mean, std, sampled_q = model._forward_pass(replay, None, f32(target_noise), f32(sample_noise))
    advantage = model._advantage(fit.q_values, sampled_q)
    loss = actor_loss(replay.actions, mean, std, advantage.weights)

    # the TD target: r + gamma (1 - done) mean_k min_i Q'_i(s', a'_k)
    target_mean, target_std = np_actor(model.actor_target, next_obs)
    next_a = np.clip(target_mean[None] + target_std[None] * target_noise, -1, 1)
    if critic_target == "sarsa":
        next_a = np.where(mask[None].astype(bool), next_actions[None], next_a)
    td = rewards[:, 0] + 0.9 * (1 - dones[:, 0]) * np_q(model.critic_target, next_obs, next_a).mean(axis=0)
    online_q = [
        np_linear(np.maximum(np_linear(np.concatenate([obs, actions], 1), net[0]), 0), net[2])[:, 0]
        for net in model.critic.q_networks
    ]
    critic = 0.5 * sum(np.mean((q - td) ** 2) for q in online_q)
    assert fit.loss.item() == pytest.approx(critic, rel=1e-5)
    np.testing.assert_allclose(fit.q_values.numpy(), np.min(online_q, axis=0), rtol=1e-5)
    # the advantage of the data's action over the policy's samples (the online critic, not clipped samples' noise)
    policy_mean, policy_std = np_actor(model.actor, obs)
    np.testing.assert_allclose(mean.detach().numpy(), policy_mean, rtol=1e-5, atol=1e-7)
    samples = np.clip(policy_mean[None] + policy_std[None] * sample_noise, -1, 1)
    advantages = np.min(online_q, axis=0) - np_q(model.critic, obs, samples).mean(axis=0)
    np.testing.assert_allclose(advantage.advantages.numpy(), advantages, rtol=1e-4, atol=1e-6)
    assert (advantages > 0).any() and (advantages < 0).any()
    weights = np_exp_weights(advantages, 0.5, 3.0) if transform == "exp" else (advantages > 0).astype(float)
    np.testing.assert_allclose(advantage.weights.numpy(), weights, rtol=1e-4, atol=1e-6)
    assert loss.item() == pytest.approx(-(weights * np_log_normal(actions, policy_mean, policy_std)).mean(), rel=1e-4)


def test_target_actions_use_the_datas_next_action_only_where_the_mask_says():
    model = CRR.from_offline_data(
        random_data(), action_space=spaces.Box(-1, 1, (2,)), normalized_actions=True, policy_kwargs=dict(net_arch=[8]),
        seed=0, device="cpu",
    )  # fmt: skip
    replay = OfflineSamples(
        th.zeros(3, 3), th.zeros(3, 2), th.zeros(3, 3), th.zeros(3, 1), th.zeros(3, 1), None,
        th.tensor([[0.5, 0.5], [0.25, -0.25], [0.9, 0.9]]), th.tensor([[1.0], [0.0], [1.0]]),
    )  # fmt: skip
    noise = th.full((2, 3, 2), 100.0)  # the policy's samples clip to 1
    policy = target_actions(model.actor_target, replay, None, 2, data_next_actions=False, noise=noise)
    assert th.equal(policy, th.ones(2, 3, 2))
    sarsa = target_actions(model.actor_target, replay, None, 2, data_next_actions=True, noise=noise)
    assert th.equal(sarsa[:, 0], replay.next_actions[0].expand(2, 2)) and th.equal(
        sarsa[:, 2], replay.next_actions[2].expand(2, 2)
    )
    assert th.equal(sarsa[:, 1], th.ones(2, 2))
    with pytest.raises(ValueError, match="next actions"):
        target_actions(model.actor_target, replay._replace(next_actions=None), None, 2, data_next_actions=True)


# ---------------------------------------------------------------------------------------------------------------------
# CRR against BC where only the advantage can tell good actions from bad ones
# ---------------------------------------------------------------------------------------------------------------------


def bandit_data(n: int = 512, seed: int = 0) -> dict:
    """One-step episodes: half the data's actions are good (near +0.7, reward 1), half bad (near -0.7, reward 0)."""
    rng = np.random.default_rng(seed)
    good = rng.random(n) < 0.5
    actions = np.where(good, 0.7, -0.7) + 0.05 * rng.normal(size=n)
    obs = rng.uniform(-1, 1, size=(n, 2)).astype(np.float32)
    return {
        "observations": obs,
        "actions": actions.reshape(-1, 1).astype(np.float32),
        "rewards": good.astype(np.float32),
        "next_observations": obs,
        "terminals": np.ones(n, dtype=bool),
    }


@pytest.mark.parametrize("transform", ["exp", "indicator"])
def test_crr_picks_the_good_action_where_bc_averages(transform):
    data, space = bandit_data(), spaces.Box(-1, 1, (1,))
    kwargs = dict(policy_kwargs=dict(net_arch=[16]), batch_size=64, learning_rate=1e-2, seed=0, device="cpu")
    crr = CRR.from_offline_data(
        data, action_space=space, advantage_transform=transform, beta=0.1, compute=dict(compile_losses=False), **kwargs
    ).learn_offline(200, log_interval=0)
    bc = BC.from_offline_data(data, action_space=space, **kwargs).learn_offline(200, log_interval=0)
    obs = np.random.default_rng(1).uniform(-1, 1, size=(64, 2)).astype(np.float32)
    crr_actions, bc_actions = crr.predict(obs, deterministic=True)[0], bc.predict(obs, deterministic=True)[0]
    assert np.abs(bc_actions).mean() < 0.3, bc_actions.mean()  # the Gaussian's mean between the two modes
    assert crr_actions.min() > 0.45, crr_actions.min()  # every state: the good mode


def test_ess_temperature_of_equal_advantages_is_infinite_whatever_their_value():
    """Equal advantages give equal weights at every temperature: ``inf``, also where their float32 std is not 0."""
    assert th.full((8,), -3.3).std().item() > 0  # the float32 mean of equal values is not always the value
    for value in (0.932944, 0.01, -3.3, 1e6):
        assert ess_temperature(th.full((8,), value, dtype=th.float64), 0.5).item() == math.inf


def test_the_categorical_critic_needs_two_atoms_and_an_increasing_support():
    """The edges by hand: 2 atoms are a support; 1 atom, or v_min at or above v_max, is not."""
    import gymnasium as gym

    from sb3_lifelong import CRR

    def critic(**support):
        kwargs = dict(net_arch=[4], distributional_critic=True, **support)
        return CRR("MlpPolicy", gym.make("Pendulum-v1"), policy_kwargs=kwargs, device="cpu").critic

    np.testing.assert_array_equal(critic(n_atoms=2, v_min=-1.0, v_max=-0.5).support.numpy(), [-1.0, -0.5])
    for bad in (
        dict(n_atoms=1, v_min=-1.0, v_max=1.0),
        dict(n_atoms=5, v_min=1.0, v_max=1.0),
        dict(n_atoms=5, v_min=2.0, v_max=1.0),
    ):
        with pytest.raises(ValueError, match="need n_atoms >= 2 and v_min < v_max"):
            critic(**bad)
