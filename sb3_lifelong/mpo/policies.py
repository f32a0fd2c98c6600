"""Policies of MPO: the shared Gaussian actor-critic."""

from typing import Any

from stable_baselines3.common.policies import ContinuousCritic

from sb3_lifelong.common.policies import (
    DictObservationsMixin,
    GaussianActor,
    GaussianActorCriticPolicy,
    ImageObservationsMixin,
)


class MPOPolicy(GaussianActorCriticPolicy):
    """
    Policy class (Gaussian actor and Q-critic, each with a target copy) for MPO.
    See :class:`sb3_lifelong.common.policies.GaussianActorCriticPolicy` for the parameters; MPO's differ in one
    default:

    :param layer_norm: Acme's LayerNorm torso (LayerNorm and tanh after the first hidden layer of the actor and
        critics), on by default for MPO: at 100k steps, three seeds each, it took Walker2d-v5 from 305 to 927 (mean of
        the last three evaluations) and kept Hopper-v5 where it was (852 -> 1102), both above SAC
        (``benchmarks/studies/mpo_quality/mpo_quality.md``). ``False`` gives SB3's plain MLPs (MPO's default before
        2026-11-25).
    """

    actor: GaussianActor
    actor_target: GaussianActor
    critic: ContinuousCritic
    critic_target: ContinuousCritic

    def __init__(self, *args: Any, layer_norm: bool = True, **kwargs: Any):
        super().__init__(*args, layer_norm=layer_norm, **kwargs)


class MultiInputPolicy(DictObservationsMixin, MPOPolicy):
    """
    MPO policy for Dict observation spaces (``CombinedExtractor`` by default). See :class:`MPOPolicy`.
    """


class CnnPolicy(ImageObservationsMixin, MPOPolicy):
    """
    MPO policy for image observation spaces, as SB3's SAC ``CnnPolicy``: ``NatureCNN`` features (a CNN for the
    actor and one for the critics, unless ``share_features_extractor=True``; each target copy has its own), then
    :class:`MPOPolicy`'s networks (with its LayerNorm torso by default).

    :param observation_space: an image space: a ``uint8`` Box ``(C, H, W)`` of bounds 0 and 255 (SB3 transposes an
        environment's ``(H, W, C)`` images to it), at least 36x36 for ``NatureCNN``
    :param action_space: Action space (Box)
    :param lr_schedule: Learning rate schedule (could be constant)
    :param features_extractor_class: Features extractor to use (``NatureCNN`` by default)
    :param kwargs: :class:`MPOPolicy`'s other parameters: ``net_arch``, ``features_extractor_kwargs`` (e.g.
        ``features_dim``), ``normalize_images`` (True by default: the pixels are divided by 255.0; False feeds them as
        they are), ...
    """


MlpPolicy = MPOPolicy
