"""
The losses more than one algorithm uses, written once (each algorithm's own are in its ``losses.py``): the TD target
of a critic that regresses Q-values and the regression's loss, MPO's critic and CRR's (unless it is categorical).
"""

from collections.abc import Iterable, Sequence
from typing import Any, Union

import torch as th
from torch.nn import functional as F


def sum_of(losses: Iterable[th.Tensor]) -> th.Tensor:
    """:return: the sum of the losses (a typed ``sum``: the same additions, in the same order; one loss is itself)"""
    total: Union[th.Tensor, None] = None
    for loss in losses:
        total = loss if total is None else total + loss
    if total is None:
        raise ValueError("no losses to sum")
    return total


def bootstrap_discount(replay_data: Any, gamma: float) -> th.Tensor:
    """
    :param replay_data: a batch (SB3's ``ReplayBufferSamples`` or a lifelong buffer's)
    :param gamma: the discount, where the buffer gives none of its own
    :return: ``(1 - done) * discount`` of each transition, ``[batch, 1]``: the weight of the next state's value in
        the TD target, with the buffer's (n-step) discount when it gives one
    """
    discounts = replay_data.discounts if replay_data.discounts is not None else gamma
    return (1 - replay_data.dones) * discounts


def td_target(rewards: th.Tensor, bootstrap: th.Tensor, next_q: th.Tensor) -> th.Tensor:
    """
    :param rewards: ``[batch, 1]``
    :param bootstrap: :func:`bootstrap_discount`, ``[batch, 1]``
    :param next_q: the next state's value, ``[batch]`` (e.g. the mean of Q over sampled next actions)
    :return: the regression critic's TD target ``rewards + bootstrap * next_q``, ``[batch, 1]``
    """
    return rewards + bootstrap * next_q.unsqueeze(1)


def q_regression_loss(q_values: Sequence[th.Tensor], target: th.Tensor) -> th.Tensor:
    """
    :param q_values: each Q-network's values of the batch's actions, ``[batch, 1]`` each
    :param target: the TD target, ``[batch, 1]`` (no gradient)
    :return: half the mean squared error of each Q-network, summed over the Q-networks
    """
    return 0.5 * sum_of(F.mse_loss(current_q, target) for current_q in q_values)
