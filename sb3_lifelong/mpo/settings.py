"""MPO's policy loss settings (its ``policy_loss`` argument), the counterpart of Acme's ``GaussianPolicyLossConfig``."""

import dataclasses
import numbers

from sb3_lifelong.core.settings import Settings

__all__ = ["PolicyLossConfig"]


@dataclasses.dataclass(frozen=True)
class PolicyLossConfig(Settings):
    """
    The KL bounds of MPO's policy improvement, its dual variables' initial values, and the action penalty: what
    Acme groups as ``GaussianPolicyLossConfig`` (MPO's ``policy_loss`` argument: this, or a dict of some of its
    fields, e.g. ``MPO("MlpPolicy", env, policy_loss=dict(epsilon_mean=0.01))``). The duals' learning rate is
    MPO's ``dual_learning_rate``, as in Acme's ``MPOConfig``.

    :param epsilon: KL bound of the E-step (temperature dual)
    :param epsilon_mean: per-dimension KL bound on the change of the policy's mean (the decoupled M-step)
    :param epsilon_stddev: per-dimension KL bound on the change of the policy's standard deviation
    :param init_temperature: initial value of the temperature dual (and of the action penalty's)
    :param init_alpha_mean: initial value of the mean's Lagrange multipliers
    :param init_alpha_stddev: initial value of the standard deviation's Lagrange multipliers
    :param action_penalty: add the Multi-Objective MPO action penalty, a second objective ``-||a - clip(a)||``
        with its own temperature, which pulls samples (and the mean when it is not squashed) into bounds
    :param epsilon_penalty: KL bound of the action penalty's E-step
    """

    epsilon: float = 0.1
    epsilon_mean: float = 2.5e-3
    epsilon_stddev: float = 1e-6
    init_temperature: float = 1.0
    init_alpha_mean: float = 1.0
    init_alpha_stddev: float = 10.0
    action_penalty: bool = False
    epsilon_penalty: float = 1e-3

    def invalid(self) -> dict[str, str]:
        positive = ["epsilon", "epsilon_mean", "epsilon_stddev", "epsilon_penalty"]
        positive += ["init_temperature", "init_alpha_mean", "init_alpha_stddev"]
        rule = "the bounds and the duals' initial values must be > 0"
        problems = {name: rule for name in positive if not _positive(self, name)}
        if not isinstance(self.action_penalty, bool):
            problems["action_penalty"] = "True or False"
        return problems


def _positive(settings: Settings, name: str) -> bool:
    value = getattr(settings, name)
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and float(value) > 0
