"""
Every default of the shared policy classes (``sb3_lifelong/common/policies.py``), written out: the algorithms pass most
of them explicitly, so no training test sees a changed default, and the mutation benchmark's full run of the module
found each one free to change (issue 66). A change of one is a change of behaviour, with a CHANGELOG line and a change
here.
"""

import torch as th
from stable_baselines3.common.torch_layers import CombinedExtractor, FlattenExtractor, NatureCNN
from testkit import signature_defaults

from sb3_lifelong.common import policies


def test_the_actors_and_policys_defaults():
    actor = dict(squash_mean=True, init_std=0.7, min_std=1e-4, layer_norm=False, head_init_scale=None)
    assert signature_defaults(policies.GaussianActor.__init__) == dict(
        activation_fn=th.nn.ReLU, normalize_images=True, **actor
    )
    assert signature_defaults(policies.GaussianPolicy.__init__) == dict(
        net_arch=None,
        activation_fn=th.nn.ReLU,
        **actor,
        features_extractor_class=FlattenExtractor,
        features_extractor_kwargs=None,
        normalize_images=True,
        optimizer_class=th.optim.Adam,
        optimizer_kwargs=None,
    )


def test_the_critics_and_observation_mixins_defaults():
    assert signature_defaults(policies.QCritic.__init__) == dict(
        activation_fn=th.nn.ReLU, normalize_images=True, n_critics=2, share_features_extractor=True, layer_norm=False
    )
    assert signature_defaults(policies.GaussianActorCriticPolicy.__init__) == dict(n_critics=1, share_features_extractor=False)
    assert signature_defaults(policies.DictObservationsMixin.__init__) == dict(features_extractor_class=CombinedExtractor)
    assert signature_defaults(policies.ImageObservationsMixin.__init__) == dict(features_extractor_class=NatureCNN)
    assert signature_defaults(policies.mlp_layers) == dict(layer_norm=False)
    assert signature_defaults(policies.sample_gaussian) == dict(noise=None)


def test_adam_is_fused_unless_the_user_chose_an_implementation():
    assert policies.with_fast_optimizer(th.optim.Adam, None) == dict(fused=True)
    assert policies.with_fast_optimizer(th.optim.AdamW, dict(eps=1e-5)) == dict(eps=1e-5, fused=True)
    assert policies.with_fast_optimizer(th.optim.Adam, dict(foreach=False)) == dict(foreach=False)
    assert policies.with_fast_optimizer(th.optim.Adam, dict(fused=False)) == dict(fused=False)
    assert policies.with_fast_optimizer(th.optim.SGD, None) == {}


def test_the_target_networks_are_frozen_copies():
    from sb3_lifelong import MPO

    for share in (False, True):
        policy = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8], share_features_extractor=share)).policy
        for target in (policy.actor_target, policy.critic_target):
            assert not target.training and all(not p.requires_grad for p in target.parameters())
        for trained in (policy.actor, policy.critic):
            assert all(p.requires_grad for p in trained.parameters())
        critic_trains = {id(p) for group in policy.critic.optimizer.param_groups for p in group["params"]}
        assert critic_trains == {id(p) for p in policy.critic.parameters()}  # the critic's optimizer trains all of it
