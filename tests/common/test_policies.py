"""The policies' building blocks: the LayerNorm torso's layers, and the Gaussian actor's samples against their law."""

import math

import numpy as np
import torch as th
from torch import nn

from sb3_lifelong import MPO
from sb3_lifelong.common.policies import mlp_layers
from sb3_lifelong.numerics.fast_ops import HiddenLinear


def test_layer_norm_torso_with_unequal_widths():
    layers = mlp_layers(5, 3, [32, 16], nn.ReLU, layer_norm=True)
    linears = [layer for layer in layers if isinstance(layer, nn.Linear)]
    assert [(layer.in_features, layer.out_features) for layer in linears] == [(5, 32), (32, 16), (16, 3)]
    norms = [layer for layer in layers if isinstance(layer, nn.LayerNorm)]
    assert len(norms) == 1 and norms[0].normalized_shape == (32,) and layers.index(norms[0]) == 1
    # only the Linear from one hidden layer to the next is the fast hidden kind: not the input's, not the output's
    assert [isinstance(layer, HiddenLinear) for layer in linears] == [False, True, False]
    assert nn.Sequential(*layers)(th.zeros(4, 5)).shape == (4, 3)
    # without an output layer, every Linear after the first is between hidden layers
    linears = [layer for layer in mlp_layers(5, 0, [32, 16, 8], nn.ReLU, layer_norm=True) if isinstance(layer, nn.Linear)]
    assert [isinstance(layer, HiddenLinear) for layer in linears] == [False, True, True]


def test_actor_samples_follow_its_gaussian():
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, device="cpu")
    actor = model.policy.actor
    obs = th.zeros(20_000, 3)
    with th.no_grad():
        mean, std = actor.distribution_params(obs[:1])
        samples = actor(obs).numpy()[:, 0]
    mean, std = float(mean[0, 0]), float(std[0, 0])
    assert samples.min() >= -1.0 and samples.max() <= 1.0
    # the law inside the clip: P(a <= x) = Phi((x - mean) / std) where -1 < x < 1
    for z in (-0.5, 0.0, 0.5):
        x = mean + z * std
        if -1.0 < x < 1.0:
            expected = 0.5 * (1 + math.erf(z / math.sqrt(2)))
            assert abs(np.mean(samples <= x) - expected) < 0.015, (z, np.mean(samples <= x), expected)
    with th.no_grad():  # deterministic: the mean, clipped to the action box
        np.testing.assert_allclose(actor(obs[:3], deterministic=True).numpy(), np.clip(mean, -1.0, 1.0), rtol=1e-6)


# ------------------------------------------------------------------------------------- each check at its boundary
def test_the_policy_alias_an_observation_space_calls_for():
    import gymnasium as gym

    from sb3_lifelong.common.policies import policy_alias_for

    box = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
    assert policy_alias_for(gym.spaces.Dict({"pos": box})) == "MultiInputPolicy"
    assert policy_alias_for(gym.spaces.Box(0, 255, (3, 36, 36), np.uint8)) == "CnnPolicy"  # channel-first image
    assert policy_alias_for(gym.spaces.Box(0, 255, (36, 36, 3), np.uint8)) == "MlpPolicy"  # channel-last: not for a CNN
    assert policy_alias_for(gym.spaces.Box(0.0, 1.0, (3, 36, 36), np.float32)) == "MlpPolicy"  # floats: not SB3's image
    assert policy_alias_for(box) == "MlpPolicy"


def test_the_actors_std_bounds_and_action_space_are_checked():
    import gymnasium as gym
    import pytest

    from sb3_lifelong.common.policies import GaussianPolicy

    for bad in (dict(init_std=0.0), dict(min_std=-1e-6)):
        with pytest.raises(ValueError, match=r"init_std must be > 0 and min_std >= 0"):
            MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8], **bad))
    model = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8], min_std=0.0))  # the boundary: allowed
    assert model.actor.min_std == 0.0
    box = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
    with pytest.raises(TypeError, match=r"GaussianPolicy supports only gymnasium.spaces.Box actions, got Discrete\(2\)"):
        GaussianPolicy(box, gym.spaces.Discrete(2), lambda _: 1e-3)


def test_the_actor_acts_by_its_mean_or_a_clipped_sample_and_is_rebuilt_from_its_parameters():
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, policy_kwargs=dict(net_arch=[8], init_std=3.0, head_init_scale=0.5))
    actor = model.actor
    obs = th.randn(256, 3)
    mean, std = actor.distribution_params(obs)
    th.testing.assert_close(actor(obs, deterministic=True), mean.clamp(-1.0, 1.0))
    th.manual_seed(0)
    sampled = actor(obs)
    th.manual_seed(0)
    th.testing.assert_close(sampled, (mean + std * th.randn_like(mean)).clamp(-1.0, 1.0))
    assert sampled.abs().max() <= 1.0 and (sampled.abs() == 1.0).any()  # a std of about 3 clips some actions
    parameters = actor._get_constructor_parameters()
    assert {k: parameters[k] for k in ("net_arch", "init_std", "head_init_scale")} == dict(
        net_arch=[8], init_std=3.0, head_init_scale=0.5
    )
    rebuilt = type(actor)(**parameters)
    assert {k: v.shape for k, v in rebuilt.state_dict().items()} == {k: v.shape for k, v in actor.state_dict().items()}
    critic_parameters = model.policy._get_constructor_parameters()
    assert critic_parameters["n_critics"] == model.policy.n_critics and "share_features_extractor" in critic_parameters
