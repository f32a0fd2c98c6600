"""Policy of behaviour cloning: the shared Gaussian actor alone (no critic)."""

from typing import Any

from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule

from sb3_lifelong.common.policies import (
    DictObservationsMixin,
    GaussianActor,
    GaussianPolicy,
    ImageObservationsMixin,
    set_training_flags,
)


class BCPolicy(GaussianPolicy):
    """
    Gaussian policy for behaviour cloning: a :class:`~sb3_lifelong.common.policies.GaussianActor` (the same actor
    as MPO's and CRR's, so that weights can be compared or transferred) and its optimizer.
    See :class:`~sb3_lifelong.common.policies.GaussianPolicy` for the parameters.
    """

    actor: GaussianActor

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Box, lr_schedule: Schedule, **kwargs: Any):
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
        self.actor = self.make_actor()
        self.actor.optimizer = self.make_optimizer(self.actor.parameters(), lr_schedule)

    def set_training_mode(self, mode: bool) -> None:
        set_training_flags(self, mode, self.actor)


class MultiInputPolicy(DictObservationsMixin, BCPolicy):
    """
    BC policy for Dict observation spaces (``CombinedExtractor`` by default). See :class:`BCPolicy`.
    """


class CnnPolicy(ImageObservationsMixin, BCPolicy):
    """
    BC policy for image observation spaces, as SB3's SAC ``CnnPolicy``: ``NatureCNN`` features, then
    :class:`BCPolicy`'s Gaussian actor.

    :param observation_space: an image space: a ``uint8`` Box ``(C, H, W)`` of bounds 0 and 255 (SB3 transposes an
        environment's ``(H, W, C)`` images to it), at least 36x36 for ``NatureCNN``
    :param action_space: Action space (Box)
    :param lr_schedule: Learning rate schedule (could be constant)
    :param features_extractor_class: Features extractor to use (``NatureCNN`` by default)
    :param kwargs: :class:`BCPolicy`'s other parameters: ``net_arch``, ``features_extractor_kwargs`` (e.g.
        ``features_dim``), ``normalize_images`` (True by default: the pixels are divided by 255.0; False feeds them as
        they are), ...
    """


MlpPolicy = BCPolicy
