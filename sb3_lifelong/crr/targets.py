"""
The critic's side of a CRR update, which calls the networks: the TD target's next actions (the target policy's
samples, or the data's with SARSA), the target critic's value of them (a regression or a categorical critic), and the
critic's loss. The arithmetic on the resulting tensors is :mod:`sb3_lifelong.crr.losses`.
"""

from typing import Any, Optional, Union

import torch as th
from stable_baselines3.common.policies import ContinuousCritic

from sb3_lifelong.common.losses import q_regression_loss, td_target
from sb3_lifelong.common.policies import sample_gaussian
from sb3_lifelong.crr.distributional import CategoricalCritic, CriticLoss
from sb3_lifelong.crr.losses import sarsa_next_actions
from sb3_lifelong.crr.policies import GaussianActor, PerSourceActor, actor_distribution
from sb3_lifelong.numerics.scoring import LowPrecisionCopy, score_actions


def target_actions(
    actor_target: Union[GaussianActor, PerSourceActor],
    replay_data: Any,
    heads: Optional[th.Tensor],
    n_target_samples: int,
    data_next_actions: bool = False,
    noise: Optional[th.Tensor] = None,
) -> th.Tensor:
    """
    The next actions of the TD target: samples of the target policy, or (``data_next_actions``, SARSA) the data's
    next action where the data shows it.

    :param actor_target: the target actor
    :param replay_data: the batch (with ``next_actions`` and ``next_action_mask`` for ``data_next_actions``)
    :param heads: with one actor per source, the actor of each row ``[batch]``
    :param n_target_samples: number of target-policy actions per transition
    :param data_next_actions: use the data's next actions (``critic_target="sarsa"``)
    :param noise: the standard normal draws of the samples (:func:`sample_gaussian`; None: drawn here)
    :return: ``[n_target_samples, batch, action_dim]``, in ``[-1, 1]``
    """
    mean, std = actor_distribution(actor_target, replay_data.next_observations, heads)
    actions = sample_gaussian(mean, std, n_target_samples, noise).clamp(-1.0, 1.0)
    if data_next_actions:
        next_actions = getattr(replay_data, "next_actions", None)
        if next_actions is None:
            raise ValueError(
                "critic_target='sarsa' needs the data's next actions: train offline (learn_offline) on offline data"
            )
        actions = sarsa_next_actions(actions, next_actions, replay_data.next_action_mask)
    return actions


def critic_td_target(
    critic_target: Union[ContinuousCritic, CategoricalCritic],
    next_obs: Any,
    next_actions: th.Tensor,
    rewards: th.Tensor,
    bootstrap: th.Tensor,
    scoring_copy: Optional[LowPrecisionCopy] = None,
) -> th.Tensor:
    """
    The critic's TD target, averaged over the next actions: ``rewards + bootstrap * Q'(s', a')`` (the lowest over
    the Q-networks) for a regression critic, the projected distribution (:meth:`CategoricalCritic.td_target`) for
    a categorical one. Without autograd.

    :param critic_target: the target critic
    :param next_obs: next observations ``[batch, ...]``
    :param next_actions: ``[n_next_actions, batch, action_dim]``
    :param rewards: ``[batch, 1]``
    :param bootstrap: ``(1 - done) * discount``, ``[batch, 1]``
    :param scoring_copy: a low-precision copy of ``critic_target`` to score the actions with
    :return: ``[batch, 1]`` (regression) or ``[batch, n_atoms]`` (categorical)
    """
    if isinstance(critic_target, CategoricalCritic):
        return critic_target.td_target(next_obs, next_actions, rewards, bootstrap, scoring_copy)
    return td_target(rewards, bootstrap, score_actions(critic_target, next_obs, next_actions, scoring_copy).mean(0))


def critic_loss(
    critic: Union[ContinuousCritic, CategoricalCritic], obs: Any, actions: th.Tensor, target: th.Tensor
) -> CriticLoss:
    """
    :param critic: the online critic
    :param obs: observations ``[batch, ...]``
    :param actions: the data's normalised actions ``[batch, action_dim]``
    :param target: :func:`critic_td_target`'s target
    :return: the loss (half the squared error of each Q-network, summed; a categorical critic's cross-entropy, see
        :meth:`CategoricalCritic.loss`) and the lowest Q-value of each action over the Q-networks
    """
    if isinstance(critic, CategoricalCritic):
        return critic.loss(obs, actions, target)
    current_q_values = critic(obs, actions)
    loss = q_regression_loss(current_q_values, target)
    return CriticLoss(loss, th.cat(current_q_values, dim=1).detach().min(dim=1).values)
