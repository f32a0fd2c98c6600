"""
Golden behaviour of the shared policy classes (``sb3_lifelong/common/policies.py``) beyond their defaults
(``test_golden_policy_defaults.py``): the training-flag cache, which layers run in a lower precision, the image
check of the policy alias, the actor's action scale, its head's initialisation bounds, uneven and split
architectures, the learning rate an optimizer starts at, the stochastic default of every call, and what the critic's
optimizer trains when it shares the actor's extractor. Each test was written against a survivor of the module's
mutation run (``benchmarks/mutation``).
"""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from sb3_lifelong.common import policies
from sb3_lifelong.numerics.fast_ops import HiddenLinear

OBS = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
ACTIONS = gym.spaces.Box(-2.0, 2.0, (2,), np.float32)


def policy(**kwargs) -> policies.GaussianActorCriticPolicy:
    return policies.GaussianActorCriticPolicy(OBS, ACTIONS, lambda _: 1e-3, **kwargs)


# ----------------------------------------------------------------------------------------------- training flags
def test_training_flags_reach_every_submodule_and_the_cache_follows_the_roots() -> None:
    owner = nn.Module()
    first, second = nn.Sequential(nn.Linear(2, 2), nn.Sequential(nn.Dropout())), nn.Sequential(nn.Dropout())
    policies.set_training_flags(owner, False, first, second)
    assert not owner.training and all(not m.training for root in (first, second) for m in root.modules())
    cache = owner.__dict__["_mode_modules"]
    policies.set_training_flags(owner, True, first, second)  # the same roots: the same list
    assert owner.__dict__["_mode_modules"] is cache and all(m.training for m in second.modules())
    policies.set_training_flags(owner, False, first)  # fewer roots: the one left out keeps its flag
    assert all(not m.training for m in first.modules()) and all(m.training for m in second.modules())
    other = nn.Sequential(nn.Dropout())
    policies.set_training_flags(owner, True, other)  # as many roots, another one: a new list
    assert all(m.training for m in other.modules()) and all(not m.training for m in first.modules())


# ---------------------------------------------------------------------------------------------------- layers
@pytest.mark.parametrize("layer_norm", [False, True])
def test_only_the_layers_between_two_hidden_layers_are_hidden_linears(layer_norm: bool) -> None:
    for output_dim in (1, 2):
        layers = policies.mlp_layers(4, output_dim, [8, 8, 8], nn.ReLU, layer_norm)
        linears = [layer for layer in layers if isinstance(layer, nn.Linear)]
        assert [isinstance(layer, HiddenLinear) for layer in linears] == [False, True, True, False]
        assert linears[-1].out_features == output_dim
    torso = [layer for layer in policies.mlp_layers(4, -1, [8, 8], nn.ReLU, layer_norm) if isinstance(layer, nn.Linear)]
    assert [isinstance(layer, HiddenLinear) for layer in torso] == [False, True]


def test_a_channel_first_image_of_any_channel_count_calls_for_the_cnn() -> None:
    for channels in (1, 2, 3, 5):
        image = gym.spaces.Box(0, 255, (channels, 36, 36), np.uint8)
        assert policies.policy_alias_for(image) == "CnnPolicy"
    assert policies.policy_alias_for(gym.spaces.Box(0, 255, (36, 36, 3), np.uint8)) == "MlpPolicy"  # channel-last
    assert policies.policy_alias_for(gym.spaces.Box(0.0, 1.0, (3, 36, 36), np.float32)) == "MlpPolicy"  # not uint8


# ----------------------------------------------------------------------------------------------------- actor
def test_the_actors_predict_scales_its_action_to_the_bounds() -> None:
    th.manual_seed(0)
    actor = policy(net_arch=[8]).actor
    assert actor.squash_output is True
    obs = np.array([[0.3, -0.2, 0.9]], np.float32)
    action, _ = actor.predict(obs, deterministic=True)
    with th.no_grad():
        unit = actor(th.as_tensor(obs), deterministic=True).numpy()
    np.testing.assert_allclose(action, 2.0 * unit, rtol=0, atol=1e-6)  # [-1, 1] -> [-2, 2] (float32 rounding)


def test_the_heads_initialisation_is_a_normal_cut_at_two_standard_deviations() -> None:
    th.manual_seed(0)
    actor = policies.GaussianActorCriticPolicy(
        OBS, gym.spaces.Box(-1, 1, (64,), np.float32), lambda _: 1e-3, net_arch=[256], head_init_scale=0.5
    ).actor
    std = math.sqrt(0.5 / 256)
    for head in (actor.mu, actor.std_head):
        weight = head.weight.detach().abs()
        assert float(weight.max()) <= 2.0 * std and float(weight.max()) > 1.9 * std  # 16,384 draws reach the cut
        assert float(head.weight.detach().std()) == pytest.approx(0.88 * std, rel=0.03)  # a normal cut at 2 sd: 0.880 sd
        assert float(head.bias.abs().max()) == 0.0
    for scale in (0, 0.0, -1.0, "1"):
        with pytest.raises(ValueError, match="head_init_scale must be None or a number > 0"):
            policy(head_init_scale=scale)


def test_uneven_empty_and_split_architectures() -> None:
    uneven = policy(net_arch=[8, 16])
    assert uneven.actor.mu.in_features == 16 and uneven.actor.std_head.in_features == 16
    empty = policy(net_arch=[])
    assert empty.actor.mu.in_features == 3 and not list(empty.actor.latent_pi)
    split = policy(net_arch=dict(pi=[8], qf=[16, 4]))
    assert [m.out_features for m in split.actor.latent_pi if isinstance(m, nn.Linear)] == [8]
    assert [m.out_features for m in split.critic.q_networks[0] if isinstance(m, nn.Linear)] == [16, 4, 1]
    default = policy()
    assert default.net_arch == [256, 256]
    assert [m.out_features for m in default.actor.latent_pi if isinstance(m, nn.Linear)] == [256, 256]


def test_an_optimizer_starts_at_the_schedules_first_value() -> None:
    built = policies.GaussianActorCriticPolicy(OBS, ACTIONS, lambda progress: 1e-3 * progress + 1e-5, net_arch=[8])
    for optimizer in (built.actor.optimizer, built.critic.optimizer):
        assert optimizer.param_groups[0]["lr"] == pytest.approx(1e-3 + 1e-5, rel=1e-12)  # progress 1 at the start


def test_every_call_is_stochastic_unless_asked_otherwise() -> None:
    built = policy(net_arch=[8])
    obs = th.tensor([[0.1, 0.2, 0.3]])
    for call in (built, built._predict, built.actor, built.actor._predict):
        with th.no_grad():
            assert not th.equal(call(obs), call(obs))
            assert th.equal(call(obs, deterministic=True), call(obs, deterministic=True))


class LinearExtractor(BaseFeaturesExtractor):
    def __init__(self, observation_space: gym.spaces.Box) -> None:
        super().__init__(observation_space, features_dim=4)
        self.linear = nn.Linear(3, 4)

    def forward(self, obs: th.Tensor) -> th.Tensor:
        return self.linear(obs)


def test_a_shared_extractor_is_trained_by_the_actor_alone() -> None:
    built = policy(net_arch=[8], share_features_extractor=True, features_extractor_class=LinearExtractor)
    extractor = {id(p) for p in built.actor.features_extractor.parameters()}
    assert built.critic.features_extractor is built.actor.features_extractor and len(extractor) == 2
    critic_trains = {id(p) for group in built.critic.optimizer.param_groups for p in group["params"]}
    actor_trains = {id(p) for group in built.actor.optimizer.param_groups for p in group["params"]}
    assert critic_trains == {id(p) for p in built.critic.parameters()} - extractor and extractor <= actor_trains
