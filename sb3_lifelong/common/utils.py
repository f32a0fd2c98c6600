"""Tensor helpers shared by the algorithms: sample many actions per state and score them in one critic call."""

from typing import Union

import torch as th
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.type_aliases import PyTorchObs


def tile_obs(obs: PyTorchObs, num_samples: int) -> PyTorchObs:
    """
    Repeat a batch of observations ``num_samples`` times along the batch dimension, sample-major:
    row ``n * batch + b`` holds observation ``b``.

    :param obs: observations ``[batch, ...]`` (or a dict of them)
    :param num_samples: number of copies
    :return: observations ``[num_samples * batch, ...]``
    """
    if isinstance(obs, dict):
        return {key: tile_obs(value, num_samples) for key, value in obs.items()}  # type: ignore[misc]
    return obs.repeat(num_samples, *([1] * (obs.dim() - 1)))


def sample_gaussian(mean: th.Tensor, std: th.Tensor, num_samples: int) -> th.Tensor:
    """
    :param mean: ``[batch, action_dim]``
    :param std: ``[batch, action_dim]``
    :param num_samples: number of samples per state
    :return: samples ``[num_samples, batch, action_dim]`` (not clipped)
    """
    noise = th.randn((num_samples, *mean.shape), dtype=mean.dtype, device=mean.device)
    return mean.unsqueeze(0) + std.unsqueeze(0) * noise


def q_min(q_values: Union[tuple[th.Tensor, ...], list[th.Tensor]]) -> th.Tensor:
    """
    :param q_values: one ``[batch, 1]`` tensor per critic
    :return: the element-wise minimum over critics, ``[batch, 1]``
    """
    if len(q_values) == 1:
        return q_values[0]
    return th.min(th.cat(list(q_values), dim=1), dim=1, keepdim=True)[0]


def score_actions(critic: ContinuousCritic, obs: PyTorchObs, actions: th.Tensor, tiled_obs: bool = False) -> th.Tensor:
    """
    Q-values of several actions per state, in a single critic call over ``num_samples * batch`` rows.
    Actions are clipped to the normalised bounds ``[-1, 1]`` first, as the environment would clip them.

    :param critic: the critic (minimum over its Q-networks is taken)
    :param obs: observations ``[batch, ...]`` (or already tiled to ``[num_samples * batch, ...]`` if ``tiled_obs``)
    :param actions: ``[num_samples, batch, action_dim]``
    :param tiled_obs: whether ``obs`` is already tiled
    :return: Q-values ``[num_samples, batch]``
    """
    num_samples, batch_size, action_dim = actions.shape
    if not tiled_obs:
        obs = tile_obs(obs, num_samples)
    flat_actions = actions.reshape(num_samples * batch_size, action_dim).clamp(-1.0, 1.0)
    return q_min(critic(obs, flat_actions)).reshape(num_samples, batch_size)
