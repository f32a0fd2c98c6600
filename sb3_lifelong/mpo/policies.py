"""Policies of MPO: the shared Gaussian actor-critic."""

from typing import Any

from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor
from stable_baselines3.common.type_aliases import Schedule

from sb3_lifelong.common.policies import GaussianActorCriticPolicy


class MPOPolicy(GaussianActorCriticPolicy):
    """
    Policy class (Gaussian actor and Q-critic, each with a target copy) for MPO.
    See :class:`sb3_lifelong.common.policies.GaussianActorCriticPolicy` for the parameters.
    """


class MultiInputPolicy(MPOPolicy):
    """
    MPO policy for Dict observation spaces (``CombinedExtractor`` by default). See :class:`MPOPolicy`.
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


MlpPolicy = MPOPolicy
