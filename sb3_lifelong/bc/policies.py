"""Policy of behaviour cloning: the shared Gaussian actor alone (no critic)."""

from typing import Any

from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule

from sb3_lifelong.common.policies import DictObservationsMixin, GaussianActor, GaussianPolicy, set_training_flags


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


MlpPolicy = BCPolicy
