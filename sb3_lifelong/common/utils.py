"""Tensor helpers shared by the algorithms: sample many actions per state and score them in one critic call."""

from typing import Union

import torch as th
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn


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


def _run_mlp_no_grad(critic: nn.Module, index: int, mlp: nn.Module, inputs: th.Tensor) -> th.Tensor:
    """
    Evaluate a ``Linear``/activation stack without autograd, writing every ``Linear`` output into a buffer kept
    on the critic (reused across gradient steps) and applying ReLUs in place. Same result, bit for bit, as
    ``mlp(inputs)``, without allocating (and page-faulting in) several ``[num_samples * batch, 256]``
    temporaries per call.
    """
    buffers: dict[tuple[int, int, int], th.Tensor] = critic.__dict__.setdefault("_no_grad_buffers", {})
    x = inputs
    owned = False
    module: nn.Module
    for position, module in enumerate(mlp):  # type: ignore[arg-type]
        if isinstance(module, nn.Linear):
            key = (index, position, x.shape[0])
            out = buffers.get(key)
            if out is None or out.dtype != x.dtype or out.device != x.device:
                out = buffers[key] = x.new_empty((x.shape[0], module.out_features))
            if module.bias is not None:
                th.addmm(module.bias, x, module.weight.t(), out=out)
            else:
                th.mm(x, module.weight.t(), out=out)
            x, owned = out, True
        elif isinstance(module, nn.ReLU) and owned:
            x.relu_()
        else:
            x, owned = module(x), False
    return x


def score_actions(critic: ContinuousCritic, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
    """
    Q-values of several actions per state, in a single critic call over ``num_samples * batch`` rows.
    Actions are clipped to the normalised bounds ``[-1, 1]`` first, as the environment would clip them.

    Without autograd (target computations) the features are extracted once per state rather than once per
    sample, and the critic's MLPs run on reused buffers (see ``_run_mlp_no_grad``).

    :param critic: the critic (minimum over its Q-networks is taken)
    :param obs: observations ``[batch, ...]``
    :param actions: ``[num_samples, batch, action_dim]``
    :return: Q-values ``[num_samples, batch]``
    """
    num_samples, batch_size, action_dim = actions.shape
    flat_actions = actions.reshape(num_samples * batch_size, action_dim).clamp(-1.0, 1.0)
    if th.is_grad_enabled() or not isinstance(critic, ContinuousCritic):
        return q_min(critic(tile_obs(obs, num_samples), flat_actions)).reshape(num_samples, batch_size)
    features = critic.extract_features(obs, critic.features_extractor)
    q_input = th.cat([features.repeat(num_samples, 1), flat_actions], dim=1)
    q_values = [_run_mlp_no_grad(critic, index, q_net, q_input) for index, q_net in enumerate(critic.q_networks)]
    # copy out of the reused buffer: the result outlives the next call
    return q_min(q_values).reshape(num_samples, batch_size).clone()
