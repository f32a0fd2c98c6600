"""
Named settings of MPO from published configurations, as keyword arguments of :class:`~sb3_lifelong.mpo.MPO`::

    from sb3_lifelong import MPO
    from sb3_lifelong.mpo.presets import acme_mujoco

    model = MPO("MlpPolicy", "HalfCheetah-v5", **acme_mujoco())
    model = MPO("MlpPolicy", "HalfCheetah-v5", **acme_mujoco(learning_starts=5_000))  # one setting changed

:func:`acme_mujoco` is Acme's MPO MuJoCo baseline (the library of the paper's group): one update per four
environment steps, 4-step returns, 256x256x256 networks. At a quarter of SB3's update ratio it makes a collection of
a million steps cost a quarter of the updates. :data:`ACME_MUJOCO_SOURCES` names the source of every setting.
"""

import copy
import inspect
from typing import Any

from torch import nn

from sb3_lifelong.mpo.mpo import MPO

__all__ = ["ACME_MUJOCO", "ACME_MUJOCO_SOURCES", "acme_mujoco"]

#: Acme's MPO MuJoCo baseline as MPO's keyword arguments (see :data:`ACME_MUJOCO_SOURCES` for each one's source)
ACME_MUJOCO: dict[str, Any] = {
    "train_freq": 4,
    "gradient_steps": 1,
    "batch_size": 256,
    "n_steps": 4,
    "learning_rate": 3e-4,
    "gamma": 0.99,
    "learning_starts": 1_000,
    "num_samples": 20,
    "policy_loss": {
        "epsilon": 0.1,
        "epsilon_mean": 0.01,
        "epsilon_stddev": 1e-6,
        "init_temperature": 10.0,
        "init_alpha_mean": 10.0,
        "init_alpha_stddev": 1000.0,
        "action_penalty": True,
        "epsilon_penalty": 1e-3,
    },
    "dual_learning_rate": 1e-2,
    "tau": 1.0,
    "target_update_interval": 100,
    "max_grad_norm": 40.0,
    "policy_kwargs": {
        "net_arch": [256, 256, 256],
        "layer_norm": True,
        "activation_fn": nn.ELU,
        "init_std": 0.5,
        "min_std": 1e-6,
        "head_init_scale": 1e-4,
        "squash_mean": False,
    },
}

_RUN_MPO = "acme examples/baselines/rl_continuous/run_mpo.py"
_CONFIG = "acme agents/jax/mpo/config.py MPOConfig default"
_LOSS = "acme agents/jax/mpo/types.py GaussianPolicyLossConfig default"
_NETWORKS = "acme agents/jax/mpo/networks.py make_control_networks"

#: where each setting of :data:`ACME_MUJOCO` comes from
ACME_MUJOCO_SOURCES: dict[str, str] = {
    "train_freq": f"{_RUN_MPO}: samples_per_insert=64 at batch 256 is one update per 4 inserted steps",
    "gradient_steps": f"{_RUN_MPO}: sgd_steps_per_learner_step=1",
    "batch_size": f"{_CONFIG} (batch_size=256)",
    "n_steps": f"{_RUN_MPO}: FromTransitions(n_step=4)",
    "learning_rate": f"{_RUN_MPO}: learning_rate=3e-4",
    "gamma": f"{_CONFIG} (discount=0.99)",
    "learning_starts": f"{_CONFIG} (min_replay_size=1000)",
    "num_samples": f"{_CONFIG} (num_samples=20)",
    "policy_loss.epsilon": f"{_LOSS} (epsilon=0.1)",
    "policy_loss.epsilon_mean": f"{_RUN_MPO}: GaussianPolicyLossConfig(epsilon_mean=0.01)",
    "policy_loss.epsilon_stddev": f"{_LOSS} (epsilon_stddev=1e-6)",
    "policy_loss.init_temperature": f"{_LOSS} (init_log_temperature=10, a raw value through softplus: 10.00005)",
    "policy_loss.init_alpha_mean": f"{_LOSS} (init_log_alpha_mean=10, through softplus)",
    "policy_loss.init_alpha_stddev": f"{_LOSS} (init_log_alpha_stddev=1000, through softplus)",
    "dual_learning_rate": f"{_CONFIG} (dual_learning_rate=1e-2)",
    "policy_loss.action_penalty": f"{_LOSS} (action_penalization=True)",
    "policy_loss.epsilon_penalty": f"{_LOSS} (epsilon_penalty=0.001)",
    "tau": f"{_CONFIG} (target_update_period=100: hard copies)",
    "target_update_interval": f"{_CONFIG} (target_update_period=100)",
    "max_grad_norm": f"{_CONFIG} (grad_norm_clip=40)",
    "policy_kwargs.net_arch": f"{_RUN_MPO}: policy_layer_sizes and critic_layer_sizes (256, 256, 256)",
    "policy_kwargs.layer_norm": f"{_NETWORKS}: LayerNormMLP torso (Linear, LayerNorm, tanh first) for both networks",
    "policy_kwargs.activation_fn": f"{_NETWORKS}: LayerNormMLP's later layers use elu",
    "policy_kwargs.init_std": f"{_RUN_MPO}: policy_init_scale=0.5 (MultivariateNormalDiagHead's init_scale)",
    "policy_kwargs.min_std": f"{_NETWORKS}: MultivariateNormalDiagHead's min_scale=1e-6",
    "policy_kwargs.head_init_scale": f"{_NETWORKS}: MultivariateNormalDiagHead's w_init=VarianceScaling(1e-4), zero biases",
    "policy_kwargs.squash_mean": f"{_NETWORKS}: MultivariateNormalDiagHead's mean is not squashed",
}


def acme_mujoco(**overrides: Any) -> dict[str, Any]:
    """
    Acme's MPO MuJoCo baseline as keyword arguments of :class:`~sb3_lifelong.mpo.MPO` (a fresh copy each call).

    What differs from Acme and cannot be set here: Acme runs 4 actors beside one learner and rate-limits the learner
    to the samples-per-insert ratio on average; here one process alternates 4 steps and one update. Acme's
    critic starts its output layer at a truncated normal of scale 0.01; ours uses torch's default initialisation (both
    give Q-values near 0 at the start). Acme's critic clips the sampled actions to the bounds before scoring them, as
    ours does.

    :param overrides: settings to change (a ``policy_kwargs`` or ``policy_loss`` dict given here is merged into the
        preset's)
    :return: the keyword arguments
    """
    kwargs = copy.deepcopy(ACME_MUJOCO)
    merged = {name: overrides.pop(name) for name in ("policy_kwargs", "policy_loss") if name in overrides}
    unknown = sorted(set(overrides) - set(inspect.signature(MPO).parameters))
    if unknown:
        raise TypeError(f"acme_mujoco() got settings MPO does not take: {unknown}")
    kwargs.update(overrides)
    for name, settings in merged.items():
        if not isinstance(settings, dict):
            raise TypeError(f"acme_mujoco() merges {name} into the preset's: pass a dict, got {settings!r}")
        kwargs[name].update(settings)
    return kwargs
