from sb3_lifelong.common.policies import GaussianActorCriticMultiInputPolicy, GaussianActorCriticPolicy


class MPOPolicy(GaussianActorCriticPolicy):
    """
    Policy class (Gaussian actor and Q-critic, each with a target copy) for MPO.
    See :class:`sb3_lifelong.common.policies.GaussianActorCriticPolicy` for the parameters.
    """


class MultiInputPolicy(GaussianActorCriticMultiInputPolicy):
    """
    MPO policy for Dict observation spaces.
    See :class:`sb3_lifelong.common.policies.GaussianActorCriticPolicy` for the parameters.
    """


MlpPolicy = MPOPolicy
