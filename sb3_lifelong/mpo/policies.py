"""Policies of MPO: the shared Gaussian actor-critic."""

from typing import Any

from stable_baselines3.common.policies import ContinuousCritic

from sb3_lifelong.common.policies import DictObservationsMixin, GaussianActor, GaussianActorCriticPolicy


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


MlpPolicy = MPOPolicy
