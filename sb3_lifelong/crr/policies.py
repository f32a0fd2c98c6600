"""Policies of CRR: the shared Gaussian actor-critic, with an optional categorical (distributional) critic."""

from typing import Any, Optional, Union

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, FlattenExtractor
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_lifelong.common.distributional import CategoricalCritic
from sb3_lifelong.common.policies import GaussianActorCriticPolicy


class CRRPolicy(GaussianActorCriticPolicy):
    """
    Gaussian actor and Q-critic (each with a target copy) for CRR. The critic is SB3's ``ContinuousCritic``
    (regression on the TD target) or, with ``distributional_critic=True``, a :class:`CategoricalCritic` over
    ``n_atoms`` returns in ``[v_min, v_max]`` (cross-entropy on the projected TD target), as in the CRR paper.

    :param distributional_critic: use a categorical critic
    :param n_atoms: atoms of the categorical critic
    :param v_min: smallest return of the categorical critic's support (choose it from the reward scale:
        about ``min_reward / (1 - gamma)``)
    :param v_max: largest return of the categorical critic's support
    See :class:`sb3_lifelong.common.policies.GaussianActorCriticPolicy` for the other parameters.
    """

    critic: Union[ContinuousCritic, CategoricalCritic]  # type: ignore[assignment]
    critic_target: Union[ContinuousCritic, CategoricalCritic]  # type: ignore[assignment]

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: Optional[Union[list[int], dict[str, list[int]]]] = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        squash_mean: bool = True,
        init_std: float = 0.7,
        min_std: float = 1e-4,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: Optional[dict[str, Any]] = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: Optional[dict[str, Any]] = None,
        n_critics: int = 1,
        share_features_extractor: bool = False,
        distributional_critic: bool = False,
        n_atoms: int = 51,
        v_min: float = -150.0,
        v_max: float = 150.0,
    ):
        # read by make_critic, which the parent's constructor calls
        self.distributional_critic = distributional_critic
        self.n_atoms = n_atoms
        self.v_min = v_min
        self.v_max = v_max
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch,
            activation_fn,
            squash_mean,
            init_std,
            min_std,
            features_extractor_class,
            features_extractor_kwargs,
            normalize_images,
            optimizer_class,
            optimizer_kwargs,
            n_critics,
            share_features_extractor,
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(distributional_critic=self.distributional_critic, n_atoms=self.n_atoms, v_min=self.v_min, v_max=self.v_max)
        )
        return data

    def make_critic(  # type: ignore[override]
        self, features_extractor: Optional[BaseFeaturesExtractor] = None
    ) -> Union[ContinuousCritic, CategoricalCritic]:
        if not self.distributional_critic:
            return super().make_critic(features_extractor)
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return CategoricalCritic(**critic_kwargs, n_atoms=self.n_atoms, v_min=self.v_min, v_max=self.v_max).to(self.device)


class MultiInputPolicy(CRRPolicy):
    """
    CRR policy for Dict observation spaces (``CombinedExtractor`` by default).
    See :class:`CRRPolicy` for the parameters.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor,
        **kwargs: Any,
    ):
        super().__init__(
            observation_space, action_space, lr_schedule, features_extractor_class=features_extractor_class, **kwargs
        )


MlpPolicy = CRRPolicy
