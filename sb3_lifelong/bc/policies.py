"""Policy of behaviour cloning: the shared Gaussian actor alone (no critic)."""

from typing import Any, Optional

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, FlattenExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_lifelong.common.policies import GaussianActor, set_training_flags
from sb3_lifelong.common.utils import with_fast_optimizer


class BCPolicy(BasePolicy):
    """
    Gaussian policy for behaviour cloning: a :class:`~sb3_lifelong.common.policies.GaussianActor` (the same actor
    as MPO's and CRR's, so that weights can be compared or transferred) and its optimizer.

    :param observation_space: Observation space
    :param action_space: Action space (Box)
    :param lr_schedule: Learning rate schedule (could be constant)
    :param net_arch: Hidden layers of the actor
    :param activation_fn: Activation function
    :param squash_mean: Whether the mean is squashed by ``tanh``
    :param init_std: Standard deviation of the initial policy (normalised action units)
    :param min_std: Lower bound of the policy's standard deviation
    :param features_extractor_class: Features extractor to use
    :param features_extractor_kwargs: Keyword arguments to pass to the features extractor
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param optimizer_class: The optimizer to use, ``th.optim.Adam`` by default
    :param optimizer_kwargs: Additional keyword arguments, excluding the learning rate, to pass to the optimizer
    """

    actor: GaussianActor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: Optional[list[int]] = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        squash_mean: bool = True,
        init_std: float = 0.7,
        min_std: float = 1e-4,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: Optional[dict[str, Any]] = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: Optional[dict[str, Any]] = None,
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=optimizer_class,
            optimizer_kwargs=with_fast_optimizer(optimizer_class, optimizer_kwargs),
            squash_output=True,
            normalize_images=normalize_images,
        )
        if not isinstance(action_space, spaces.Box):
            raise TypeError(f"{type(self).__name__} supports only gymnasium.spaces.Box actions, got {action_space}")
        self.net_arch = [256, 256] if net_arch is None else net_arch
        self.activation_fn = activation_fn
        self.squash_mean = squash_mean
        self.init_std = init_std
        self.min_std = min_std
        features_extractor = self.make_features_extractor()
        self.actor = GaussianActor(
            observation_space,
            action_space,
            net_arch=self.net_arch,
            features_extractor=features_extractor,
            features_dim=features_extractor.features_dim,
            activation_fn=activation_fn,
            normalize_images=normalize_images,
            squash_mean=squash_mean,
            init_std=init_std,
            min_std=min_std,
        )
        self.actor.optimizer = self.optimizer_class(
            self.actor.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs  # type: ignore[call-arg]
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                net_arch=self.net_arch,
                activation_fn=self.activation_fn,
                squash_mean=self.squash_mean,
                init_std=self.init_std,
                min_std=self.min_std,
                lr_schedule=self._dummy_schedule,
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
                features_extractor_class=self.features_extractor_class,
                features_extractor_kwargs=self.features_extractor_kwargs,
            )
        )
        return data

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self.actor(observation, deterministic)

    def set_training_mode(self, mode: bool) -> None:
        set_training_flags(self, mode, self.actor)


class MultiInputPolicy(BCPolicy):
    """
    BC policy for Dict observation spaces (``CombinedExtractor`` by default). See :class:`BCPolicy`.
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


MlpPolicy = BCPolicy
