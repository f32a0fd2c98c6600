"""Policies of CRR: the shared Gaussian actor-critic, with an optional categorical (distributional) critic."""

import copy
from typing import Any, Optional, Union

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy, ContinuousCritic
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_lifelong.common.policies import (
    DictObservationsMixin,
    GaussianActor,
    GaussianActorCriticPolicy,
    ImageObservationsMixin,
    QCritic,
)
from sb3_lifelong.crr.distributional import CategoricalCritic


def _select_rows(obs: PyTorchObs, rows: th.Tensor) -> PyTorchObs:
    if isinstance(obs, dict):
        return {key: value[rows] for key, value in obs.items()}
    return obs[rows]


class PerSourceActor(BasePolicy):
    """
    Several independent Gaussian actors ("heads", each with its own networks) behind the interface of one
    :class:`GaussianActor`: CRR's diagnostic of one actor per data source with a shared critic.

    ``distribution_params(obs, heads)`` evaluates each row with the actor of its head; without ``heads``, and in
    ``forward`` / ``predict``, the active head (:attr:`active_head`, set with ``CRR.select_source``) acts.

    :param actors: the actors, one per head (same spaces)
    """

    def __init__(self, actors: list[GaussianActor]):
        if len(actors) < 1:
            raise ValueError("PerSourceActor needs at least one actor")
        super().__init__(
            actors[0].observation_space,
            actors[0].action_space,
            normalize_images=actors[0].normalize_images,
            squash_output=True,
        )
        self.heads = nn.ModuleList(actors)
        self.active_head = 0

    @property
    def n_heads(self) -> int:
        return len(self.heads)

    def head(self, index: int) -> GaussianActor:
        """:return: the actor of head ``index``"""
        actor = self.heads[index]
        assert isinstance(actor, GaussianActor)
        return actor

    def distribution_params(self, obs: PyTorchObs, heads: Optional[th.Tensor] = None) -> tuple[th.Tensor, th.Tensor]:
        """
        :param obs: Observation
        :param heads: index of the actor of each row (``[batch]``, long); None: the active head for every row
        :return: mean and standard deviation of each row's action distribution, each ``[batch, action_dim]``
        """
        if heads is None:
            return self.head(self.active_head).distribution_params(obs)
        used = th.unique(heads).tolist()
        if len(used) == 1:
            return self.head(used[0]).distribution_params(obs)
        mean = std = None
        for head in used:
            rows = th.nonzero(heads == head, as_tuple=True)[0]
            head_mean, head_std = self.head(head).distribution_params(_select_rows(obs, rows))
            if mean is None or std is None:
                mean = head_mean.new_empty((heads.shape[0], head_mean.shape[1]))
                std = head_std.new_empty((heads.shape[0], head_std.shape[1]))
            mean = mean.index_copy(0, rows, head_mean)
            std = std.index_copy(0, rows, head_std)
        assert mean is not None and std is not None
        return mean, std

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self.heads[self.active_head](obs, deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self(observation, deterministic)

    def set_training_mode(self, mode: bool) -> None:
        for index in range(self.n_heads):
            self.head(index).set_training_mode(mode)
        self.training = mode


def actor_distribution(
    actor: Union[GaussianActor, PerSourceActor], obs: PyTorchObs, heads: Optional[th.Tensor] = None
) -> tuple[th.Tensor, th.Tensor]:
    """
    :param actor: the actor (one per source: ``heads`` picks each row's)
    :param obs: observations ``[batch, ...]``
    :param heads: with one actor per source, the actor of each row ``[batch]``
    :return: the mean and std of the policy's Gaussian, ``[batch, action_dim]`` each
    """
    if isinstance(actor, PerSourceActor):
        return actor.distribution_params(obs, heads)
    return actor.distribution_params(obs)


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
    :param n_actors: number of independent actors (:class:`PerSourceActor` when > 1, sharing the one critic):
        CRR sets it from its data's sources with ``actor_per_source=True``
    :param averaged_actor: keep a copy of the actor, ``actor_average``, that CRR updates as a moving average of the
        actor's weights (``actor_averaging``); ``predict`` uses it. CRR sets it
    :param kwargs: the actor-critic's other settings, see
        :class:`sb3_lifelong.common.policies.GaussianActorCriticPolicy`
    """

    critic: Union[ContinuousCritic, CategoricalCritic]
    critic_target: Union[ContinuousCritic, CategoricalCritic]
    actor: Union[GaussianActor, PerSourceActor]
    actor_target: Union[GaussianActor, PerSourceActor]
    actor_average: Optional[Union[GaussianActor, PerSourceActor]]

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        distributional_critic: bool = False,
        n_atoms: int = 51,
        v_min: float = -150.0,
        v_max: float = 150.0,
        n_actors: int = 1,
        averaged_actor: bool = False,
        **kwargs: Any,
    ):
        if n_actors < 1:
            raise ValueError(f"n_actors must be >= 1, got {n_actors}")
        if n_actors > 1 and kwargs.get("share_features_extractor", False):
            raise ValueError("n_actors > 1 (one actor per source) cannot share a features extractor with the critic")
        # read by make_trained_actor and make_critic, which the parent's constructor calls
        self.n_actors = n_actors
        self.distributional_critic = distributional_critic
        self.n_atoms = n_atoms
        self.v_min = v_min
        self.v_max = v_max
        self.averaged_actor = averaged_actor
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)
        # like the target actor: never trained by gradient, always in evaluation mode
        self.actor_average = copy.deepcopy(self.actor_target) if self.averaged_actor else None

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        actor = self.actor if self.actor_average is None else self.actor_average
        return actor(observation, deterministic)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                distributional_critic=self.distributional_critic,
                n_atoms=self.n_atoms,
                v_min=self.v_min,
                v_max=self.v_max,
                n_actors=self.n_actors,
                averaged_actor=self.averaged_actor,
            )
        )
        return data

    def make_trained_actor(self) -> Union[GaussianActor, PerSourceActor]:
        if self.n_actors == 1:
            return self.make_actor()
        return PerSourceActor([self.make_actor() for _ in range(self.n_actors)]).to(self.device)

    def make_critic(
        self, features_extractor: Optional[BaseFeaturesExtractor] = None
    ) -> Union[ContinuousCritic, CategoricalCritic]:
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        if not self.distributional_critic:
            return QCritic(**critic_kwargs).to(self.device)
        return CategoricalCritic(**critic_kwargs, n_atoms=self.n_atoms, v_min=self.v_min, v_max=self.v_max).to(self.device)


class MultiInputPolicy(DictObservationsMixin, CRRPolicy):
    """
    CRR policy for Dict observation spaces (``CombinedExtractor`` by default).
    See :class:`CRRPolicy` for the parameters.
    """


class CnnPolicy(ImageObservationsMixin, CRRPolicy):
    """
    CRR policy for image observation spaces, as SB3's SAC ``CnnPolicy``: ``NatureCNN`` features (a CNN for each
    actor, one per source with ``actor_per_source``, and one for the critic, regression or categorical, unless
    ``share_features_extractor=True``; each target copy has its own), then :class:`CRRPolicy`'s networks.

    :param observation_space: an image space: a ``uint8`` Box ``(C, H, W)`` of bounds 0 and 255 (SB3 transposes an
        environment's ``(H, W, C)`` images to it), at least 36x36 for ``NatureCNN``
    :param action_space: Action space (Box)
    :param lr_schedule: Learning rate schedule (could be constant)
    :param features_extractor_class: Features extractor to use (``NatureCNN`` by default)
    :param kwargs: :class:`CRRPolicy`'s other parameters: ``net_arch``, ``features_extractor_kwargs`` (e.g.
        ``features_dim``), ``normalize_images`` (True by default: the pixels are divided by 255.0; False feeds them as
        they are), ...
    """


MlpPolicy = CRRPolicy
