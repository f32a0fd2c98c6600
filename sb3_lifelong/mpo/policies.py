"""Policies of MPO: the shared Gaussian actor-critic."""

from sb3_lifelong.common.policies import DictObservationsMixin, GaussianActorCriticPolicy


class MPOPolicy(GaussianActorCriticPolicy):
    """
    Policy class (Gaussian actor and Q-critic, each with a target copy) for MPO.
    See :class:`sb3_lifelong.common.policies.GaussianActorCriticPolicy` for the parameters.
    """


class MultiInputPolicy(DictObservationsMixin, MPOPolicy):
    """
    MPO policy for Dict observation spaces (``CombinedExtractor`` by default). See :class:`MPOPolicy`.
    """


MlpPolicy = MPOPolicy
