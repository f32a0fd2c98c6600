"""
CRR's losses, as pure functions of tensors: the TD target's next actions with the data's where SARSA has them, the
advantage of the data's actions over the policy's and its weights (``exp`` or indicator, a fixed temperature or one
chosen from the weights' effective sample size), and the actor's weighted regression. What calls the networks (the
target policy's samples, the target critic's values, the critic's own loss) is :mod:`sb3_lifelong.crr.targets`;
``CRR.train`` calls both (:class:`sb3_lifelong.crr.crr.CRR`).
"""

import math
from typing import NamedTuple, Optional, Union

import torch as th

from sb3_lifelong.common.policies import gaussian_log_prob

ADVANTAGE_TRANSFORMS = ("exp", "indicator")
ADVANTAGE_BASELINES = ("mean", "max")


def advantage_baseline(sampled_q: th.Tensor, kind: str = "mean") -> th.Tensor:
    """
    Value estimate of each state from the Q-values of actions sampled from the policy.

    :param sampled_q: ``[num_samples, batch]``
    :param kind: ``"mean"`` (expected value, CRR's ``A_mean``) or ``"max"`` (CRR's ``A_max``)
    :return: ``[batch]``
    """
    if kind == "mean":
        return sampled_q.mean(dim=0)
    if kind == "max":
        return sampled_q.max(dim=0).values
    raise ValueError(f"advantage baseline must be one of {ADVANTAGE_BASELINES}, got {kind!r}")


def crr_weights(
    advantages: th.Tensor, transform: str = "exp", beta: Union[float, th.Tensor] = 1.0, max_weight: float = 20.0
) -> tuple[th.Tensor, th.Tensor]:
    """
    CRR's weights of the data's actions in the policy's regression.

    - ``"exp"``: ``min(exp(A / beta), max_weight)`` (computed without overflow);
    - ``"indicator"``: ``1[A > 0]`` (the limit of ``exp`` clipped to 1 when ``beta -> 0``).

    :param advantages: advantages of the data's actions, any shape
    :param transform: ``"exp"`` or ``"indicator"``
    :param beta: temperature of ``exp`` (> 0; a scalar tensor too; ``inf``: equal weights)
    :param max_weight: upper bound of ``exp``'s weights (>= 1)
    :return: the weights and a boolean mask of the weights clipped at ``max_weight``, shaped like ``advantages``
    """
    if transform == "exp":
        log_max = math.log(max_weight)
        scaled = advantages / beta
        clipped = scaled >= log_max
        return th.exp(scaled.clamp(max=log_max)), clipped
    if transform == "indicator":
        return (advantages > 0).to(advantages.dtype), th.zeros_like(advantages, dtype=th.bool)
    raise ValueError(f"advantage transform must be one of {ADVANTAGE_TRANSFORMS}, got {transform!r}")


class AdvantageWeights(NamedTuple):
    """The advantages of the data's actions and their weights in the policy's regression, ``[batch]`` each."""

    advantages: th.Tensor
    weights: th.Tensor
    #: the weights clipped at ``max_weight`` (bool)
    clipped: th.Tensor
    #: the temperature the ``exp`` weights used, in reward units (a scalar; NaN for the indicator)
    beta: th.Tensor


def effective_sample_size(weights: th.Tensor) -> th.Tensor:
    """
    Kish's effective sample size of a weighted regression, as a fraction of the batch:
    ``(sum w)^2 / (n sum w^2)``, 1 for equal weights, ``1 / n`` when one row has all the weight.

    :param weights: non-negative weights ``[..., batch]`` (the last dimension is the batch)
    :return: ``[...]``, in ``[1 / batch, 1]`` (1 where every weight is 0)
    """
    total = weights.sum(dim=-1)
    squares = (weights * weights).sum(dim=-1)
    fraction = total * total / (weights.shape[-1] * squares.clamp_min(th.finfo(weights.dtype).tiny))
    return th.where(squares > 0, fraction, th.ones_like(fraction))


#: the grid of :func:`ess_temperature`: candidate temperatures per pass, and the passes of a search from scratch
ESS_GRID_POINTS = 64
ESS_GRID_PASSES = 2
#: a search from scratch spans the Gaussian guess / e^7 ... x e^7 (about / 1100 ... x 1100); one warm-started from
#: the previous batch's temperature spans it / e^0.5 ... x e^0.5 in one pass (and starts from scratch if the
#: target is outside)
ESS_SEARCH_SPAN = 7.0
ESS_WARM_SPAN = 0.5
#: the search window moves (by its width) while every candidate reaches the target, or none does: far-from-Gaussian
#: advantages (two nearly tied best rows far above the rest) put the temperature outside the Gaussian guess's window;
#: it stops at the guess / e^40 (below that, every weight but the best rows' is 0 in float32) or x e^40
ESS_SHIFT_LIMIT = 40.0


def _ess_of_temperatures(advantages: th.Tensor, log_betas: th.Tensor, log_max: float) -> th.Tensor:
    """:return: the effective sample size of the clipped ``exp`` weights at each temperature ``exp(log_betas)``"""
    log_weights = (advantages.unsqueeze(0) * th.exp(-log_betas).unsqueeze(1)).clamp(max=log_max)  # [G, B]
    return effective_sample_size(th.exp(log_weights - log_weights.max(dim=1, keepdim=True).values))


def ess_temperature(
    advantages: th.Tensor, target_ess: float, max_weight: float = 20.0, start: Optional[float] = None
) -> th.Tensor:
    """
    The temperature of the ``exp`` transform at which the (clipped) weights' effective sample size is
    ``target_ess`` of the batch (to a relative precision of about 1e-5).

    A temperature in reward units has no fixed meaning: ``beta = 1`` keeps a student close to the data when the
    advantages spread over a tenth of a reward unit and makes it nearly greedy when they spread over five. The
    effective sample size does not depend on the reward's scale: multiplying every advantage by ``c`` multiplies this
    temperature by ``c`` and leaves the weights unchanged. For Gaussian advantages of standard deviation ``s`` and no
    clipping, ``ESS = exp(-s^2 / beta^2)``, so ``beta = s / sqrt(-ln target_ess)``: the centre of the search.

    The size grows with the temperature, so the search is a grid of candidates (vectorised) refined around the
    first one that reaches the target, then interpolated linearly between the two that bracket it. With clipped
    weights the size is not monotone: at the coldest temperatures every weight is clipped or about 0 and the size
    rises again (to the fraction of clipped weights); the search then takes the warmest temperature at which the
    size falls to the target (every warmer one is above it). The first window is centred on the Gaussian guess; while
    every candidate in it reaches the target (or none does) the window moves down (up) by its width, to at most
    ``e^40`` from the guess. So a target below every size the clipped weights reach (the share of clipped weights
    keeps it up at the coldest temperatures) gives the coldest temperature of that range: the greediest weights.

    :param advantages: ``[batch]``
    :param target_ess: the weights' effective sample size as a fraction of the batch, in ``(0, 1)``; larger is
        closer to behaviour cloning (1: equal weights), smaller is greedier
    :param max_weight: the clip of the ``exp`` weights (the size is that of the clipped weights)
    :param start: a temperature to search around first (the previous batch's): one grid pass instead of two
    :return: a scalar tensor (``inf`` when the advantages are all equal: every temperature gives equal weights)
    """
    if not 0.0 < target_ess < 1.0:
        raise ValueError(f"target_ess must be in (0, 1), got {target_ess}")
    values = advantages.detach().flatten().float()
    # equal advantages have a float32 std of ~1e-11 rather than 0 (8 x 0.932944): compare them, not their std
    spread = float(values.std()) if values.numel() > 1 and bool(values.max() > values.min()) else 0.0
    if not spread > 0:
        return advantages.new_tensor(math.inf)
    log_max = math.log(max_weight)

    def grid(lo: float, hi: float) -> tuple[th.Tensor, th.Tensor]:
        log_betas = th.linspace(lo, hi, ESS_GRID_POINTS, device=values.device)
        return log_betas, _ess_of_temperatures(values, log_betas, log_max)

    warm = start is not None and math.isfinite(start) and start > 0
    if warm:
        assert start is not None
        low, high, passes = math.log(start) - ESS_WARM_SPAN, math.log(start) + ESS_WARM_SPAN, 1
        log_betas, ess = grid(low, high)
    else:
        centre = math.log(spread / math.sqrt(-math.log(target_ess)))
        low, high, passes = centre - ESS_SEARCH_SPAN, centre + ESS_SEARCH_SPAN, ESS_GRID_PASSES
        log_betas, ess = grid(low, high)
        width = high - low
        while True:  # the crossing outside the window: move it (the passes below then refine inside it)
            reached = ess >= target_ess
            if bool(reached.all()) and low > centre - ESS_SHIFT_LIMIT:
                low, high = low - width, low
            elif not bool(reached.any()) and high < centre + ESS_SHIFT_LIMIT:
                low, high = high, high + width
            else:
                break
            log_betas, ess = grid(low, high)
    for done in range(passes):
        if done > 0:  # the first pass's grid is the window's, evaluated above
            log_betas, ess = grid(low, high)
        reached = ess >= target_ess
        if warm and not (bool(reached[-1]) and not bool(reached[0])):  # the target is outside the window
            return ess_temperature(advantages, target_ess, max_weight)
        # the warmest crossing: the first candidate from which every warmer one reaches the target (clipped weights'
        # size is not monotone in the temperature: the coldest ones, every weight clipped or ~0, can reach it again)
        missed = (~reached).nonzero()
        first = 0 if len(missed) == 0 else min(int(missed[-1]) + 1, ESS_GRID_POINTS - 1)
        low, high = float(log_betas[max(first - 1, 0)]), float(log_betas[first])
    below, above = float(ess[max(first - 1, 0)]), float(ess[first])
    share = (target_ess - below) / (above - below) if above > below else 1.0
    return advantages.new_tensor(math.exp(low + min(max(share, 0.0), 1.0) * (high - low)))


def sarsa_next_actions(sampled: th.Tensor, data_next_actions: th.Tensor, mask: th.Tensor) -> th.Tensor:
    """
    The next actions of a SARSA target: the data's next action where the data shows it, the policy's samples elsewhere.

    :param sampled: the target policy's samples ``[n_samples, batch, action_dim]``
    :param data_next_actions: the data's next actions ``[batch, action_dim]`` (any value where ``mask`` is 0)
    :param mask: 1 where the data holds the next action, 0 where it does not (the episode's last stored step) ``[batch, 1]``
    :return: ``[n_samples, batch, action_dim]``
    """
    mask = mask.unsqueeze(0)  # [1, B, 1]
    return mask * data_next_actions.unsqueeze(0) + (1.0 - mask) * sampled


def advantage_weights(
    data_q: th.Tensor,
    sampled_q: th.Tensor,
    baseline: str,
    transform: str,
    beta: float,
    max_weight: float,
    normalize: bool = False,
    target_ess: Optional[float] = None,
    ess_start: Optional[float] = None,
) -> AdvantageWeights:
    """
    :param data_q: Q-values of the data's actions ``[batch]``
    :param sampled_q: Q-values of actions sampled from the policy ``[num_samples, batch]``
    :param baseline: ``"mean"`` or ``"max"`` (:func:`advantage_baseline`)
    :param transform: ``"exp"`` or ``"indicator"`` (:func:`crr_weights`)
    :param beta: temperature of ``exp`` (unused with ``target_ess``)
    :param max_weight: upper bound of ``exp``'s weights
    :param normalize: divide the advantages by their standard deviation over the batch before the transform, so
        that ``beta`` is in units of that spread rather than of the reward
    :param target_ess: ``exp`` only: choose the temperature of this batch so that the weights' effective sample
        size is this fraction of the batch (:func:`ess_temperature`); None: ``beta``
    :param ess_start: with ``target_ess``, the temperature to search around first (the previous batch's)
    :return: the advantages of the data's actions (not normalised), their weights and the temperature used
    """
    advantages = data_q - advantage_baseline(sampled_q, baseline)
    if transform == "exp" and target_ess is not None:
        used = ess_temperature(advantages, target_ess, max_weight, start=ess_start)
        weights, clipped = crr_weights(advantages, transform, used, max_weight)
        return AdvantageWeights(advantages, weights, clipped, used)
    spread = advantages.std().clamp_min(1e-6) if normalize and advantages.numel() > 1 else None
    weights, clipped = crr_weights(advantages if spread is None else advantages / spread, transform, beta, max_weight)
    if transform != "exp":
        used = advantages.new_tensor(math.nan)
    else:
        used = advantages.new_tensor(beta) if spread is None else beta * spread
    return AdvantageWeights(advantages, weights, clipped, used)


def actor_loss(actions: th.Tensor, mean: th.Tensor, std: th.Tensor, weights: th.Tensor) -> th.Tensor:
    """
    :return: CRR's policy loss, the weighted negative log-likelihood of the data's ``actions`` ``[batch, action_dim]``
        under the policy's Gaussian (``mean``, ``std``), averaged over the batch
    """
    return -(weights * gaussian_log_prob(actions, mean, std)).mean()
