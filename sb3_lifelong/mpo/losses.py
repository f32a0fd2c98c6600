"""
MPO's losses, as pure functions of tensors: the duals' parametrisation, the E-step (weights of the sampled actions
and the temperatures' loss), the decoupled M-step and its per-dimension trust region. ``MPO.train`` calls them in
that order (:class:`sb3_lifelong.mpo.mpo.MPO`).
"""

import math
from typing import NamedTuple, Optional

import torch as th
from torch.nn import functional as F

from sb3_lifelong.common.policies import LOG_SQRT_2PI, gaussian_kl_per_dim

# Lowest raw (pre-softplus) value of a dual variable: softplus(-18) ~ 1.5e-8
DUAL_RAW_FLOOR = -18.0
DUAL_EPSILON = 1e-8


def inverse_softplus(value: float) -> float:
    """:return: ``x`` such that ``softplus(x) == value`` (``value > 0``)"""
    if value <= 0:
        raise ValueError(f"Dual variables must be initialised > 0, got {value}")
    return float(value + math.log(-math.expm1(-value)))


def dual_value(raw: th.Tensor) -> th.Tensor:
    """:return: the positive dual variable parametrised by ``raw``: ``softplus(raw) + 1e-8``"""
    return F.softplus(raw) + DUAL_EPSILON


def temperature_loss_and_weights(q_values: th.Tensor, temperature: th.Tensor, epsilon: float) -> tuple[th.Tensor, th.Tensor]:
    """
    E-step of MPO: non-parametric improved policy over sampled actions, and the loss of the temperature dual.

    ``weights = softmax_N(Q / eta)`` and
    ``loss = eta * (epsilon + mean_B[logsumexp_N(Q / eta) - log N])`` (the gradient flows into ``eta`` only).

    :param q_values: Q-values of the sampled actions, ``[num_samples, batch]`` (no gradient needed)
    :param temperature: the temperature ``eta`` (scalar tensor, > 0)
    :param epsilon: bound on ``KL(q || pi_old)`` per state
    :return: the temperature loss (scalar) and the normalised weights ``[num_samples, batch]`` (detached)
    """
    q_values = q_values.detach()
    num_samples = q_values.shape[0]
    weights = th.softmax(q_values / temperature.detach(), dim=0)
    log_normaliser = th.logsumexp(q_values / temperature, dim=0) - math.log(num_samples)
    loss = temperature * (epsilon + log_normaliser.mean())
    return loss, weights


def action_penalty_q(sampled_actions: th.Tensor) -> th.Tensor:
    """
    The Multi-Objective MPO action penalty as a second "Q-function": ``-||a - clip(a, -1, 1)||``.

    :param sampled_actions: ``[num_samples, batch, action_dim]``
    :return: ``[num_samples, batch]``
    """
    # the norm written out: torch 2.11's compiler gave vector_norm over a last dimension of size 1 the wrong shape
    return -(sampled_actions - sampled_actions.clamp(-1.0, 1.0)).square().sum(dim=-1).sqrt()


class EStep(NamedTuple):
    """The E-step: the non-parametric improved policy, as weights of the sampled actions, and the temperatures' loss."""

    #: the normalised weights ``[num_samples, batch]`` of each objective (the task's first, then the action penalty's)
    weights: list[th.Tensor]
    #: the temperature duals' loss, summed over the objectives
    dual_loss: th.Tensor


def e_step(
    q_values: th.Tensor,
    sampled_actions: th.Tensor,
    temperature: th.Tensor,
    epsilon: float,
    penalty_temperature: Optional[th.Tensor] = None,
    epsilon_penalty: float = 0.0,
) -> EStep:
    """
    :param q_values: the target critic's Q-values of the sampled actions, ``[num_samples, batch]``
    :param sampled_actions: the target policy's samples ``[num_samples, batch, action_dim]``
    :param temperature: the task's temperature dual (> 0)
    :param epsilon: the task's KL bound
    :param penalty_temperature: the action penalty's temperature dual, None without the penalty
        (:func:`action_penalty_q`, Multi-Objective MPO)
    :param epsilon_penalty: the action penalty's KL bound
    :return: the weights of each objective and the duals' loss
    """
    dual_loss, weights = temperature_loss_and_weights(q_values, temperature, epsilon)
    all_weights = [weights]
    if penalty_temperature is not None:
        penalty_q = action_penalty_q(sampled_actions)
        penalty_loss, penalty_weights = temperature_loss_and_weights(penalty_q, penalty_temperature, epsilon_penalty)
        dual_loss = dual_loss + penalty_loss
        all_weights.append(penalty_weights)
    return EStep(all_weights, dual_loss)


def m_step_loss(
    sampled_actions: th.Tensor,
    all_weights: list[th.Tensor],
    online_mean: th.Tensor,
    online_std: th.Tensor,
    target_mean: th.Tensor,
    target_std: th.Tensor,
) -> th.Tensor:
    """
    Decoupled M-step: weighted maximum likelihood of the sampled actions, the mean fitted with the target's std
    and the std with the target's mean.

    ``-mean_B sum_N w * (log N(a; mu, sigma_target) + log N(a; mu_target, sigma))``, computed exactly from the
    weighted moments of the samples around the target mean (the log-density is quadratic in the action), so that
    the graph autograd differentiates holds ``[batch, action_dim]`` tensors, not ``[num_samples, batch,
    action_dim]`` ones.

    :param sampled_actions: ``[num_samples, batch, action_dim]``
    :param all_weights: the E-step weights of each objective, ``[num_samples, batch]`` each (no gradient)
    :param online_mean: the online policy's mean ``[batch, action_dim]`` (with gradient)
    :param online_std: the online policy's std ``[batch, action_dim]`` (with gradient)
    :param target_mean: the target policy's mean ``[batch, action_dim]``
    :param target_std: the target policy's std ``[batch, action_dim]``
    :return: the policy loss (scalar), summed over the objectives
    """
    with th.no_grad():  # the loss is linear in the weights: the objectives' weights add up
        weights = all_weights[0] if len(all_weights) == 1 else th.stack(all_weights).sum(dim=0)
        offsets = sampled_actions - target_mean.unsqueeze(0)  # [N, B, A]
        weighted = weights.unsqueeze(-1) * offsets
        total = weights.sum(dim=0).unsqueeze(-1)  # [B, 1]: sum_N w (1 per objective)
        first = weighted.sum(dim=0)  # [B, A]: sum_N w (a - mu_target)
        second = (weighted * offsets).sum(dim=0)  # [B, A]: sum_N w (a - mu_target)^2
    shift = online_mean - target_mean  # sum_N w (a - mu)^2 = second - 2 shift first + total shift^2
    fit_mean = -0.5 * (second - 2.0 * shift * first + total * shift.square()) / target_std.square()
    fit_mean = fit_mean - total * (th.log(target_std) + LOG_SQRT_2PI)
    fit_std = -0.5 * second / online_std.square() - total * (th.log(online_std) + LOG_SQRT_2PI)
    return -(fit_mean + fit_std).sum(dim=-1).mean()


class TrustRegion(NamedTuple):
    """The per-dimension KL constraints of the M-step, as penalties on the policy and losses of their duals."""

    #: ``sum(alpha * KL)`` for the mean and the std (gradient into the policy only)
    kl_loss: th.Tensor
    #: ``sum(alpha * (epsilon - KL))`` for the mean and the std (gradient into the duals only)
    dual_loss: th.Tensor
    #: ``KL(pi_target || pi_online)`` of the mean and of the std, averaged over the batch, ``[action_dim]`` each
    kl_mean: th.Tensor
    kl_stddev: th.Tensor


def trust_region(
    target_mean: th.Tensor,
    target_std: th.Tensor,
    online_mean: th.Tensor,
    online_std: th.Tensor,
    alpha_mean: th.Tensor,
    alpha_stddev: th.Tensor,
    epsilon_mean: float,
    epsilon_stddev: float,
) -> TrustRegion:
    """
    :param target_mean: ``[batch, action_dim]``
    :param target_std: ``[batch, action_dim]``
    :param online_mean: ``[batch, action_dim]`` (with gradient)
    :param online_std: ``[batch, action_dim]`` (with gradient)
    :param alpha_mean: the mean's Lagrange multipliers ``[action_dim]`` (with gradient)
    :param alpha_stddev: the std's Lagrange multipliers ``[action_dim]`` (with gradient)
    :param epsilon_mean: per-dimension KL bound of the mean
    :param epsilon_stddev: per-dimension KL bound of the std
    :return: the penalties, the duals' losses and the KLs
    """
    kl_mean = gaussian_kl_per_dim(target_mean, target_std, online_mean, target_std).mean(dim=0)
    kl_stddev = gaussian_kl_per_dim(target_mean, target_std, target_mean, online_std).mean(dim=0)
    kl_loss = (alpha_mean.detach() * kl_mean).sum() + (alpha_stddev.detach() * kl_stddev).sum()
    dual_loss = (alpha_mean * (epsilon_mean - kl_mean.detach())).sum() + (
        alpha_stddev * (epsilon_stddev - kl_stddev.detach())
    ).sum()
    return TrustRegion(kl_loss, dual_loss, kl_mean, kl_stddev)
