"""Categorical (distributional) Q-function critic, as in the CRR paper, with its TD target and loss."""

from typing import NamedTuple, Optional

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn
from torch.nn import functional as F

from sb3_lifelong.common.losses import sum_of
from sb3_lifelong.common.policies import mlp_layers
from sb3_lifelong.numerics.scoring import LowPrecisionCopy, eager_network_outputs, tile_obs, uses_engine

__all__ = ["CategoricalCritic", "CriticLoss", "categorical_projection"]


class CriticLoss(NamedTuple):
    """A critic's loss on a batch, and the Q-values of the batch's actions it saw on the way."""

    #: the loss (scalar, differentiable in the critic's parameters)
    loss: th.Tensor
    #: the lowest (expected) Q-value over the Q-networks of each of the batch's actions, ``[batch]`` (detached)
    q_values: th.Tensor


def categorical_projection(next_probs: th.Tensor, rewards: th.Tensor, discounts: th.Tensor, support: th.Tensor) -> th.Tensor:
    """
    Project the distribution of ``rewards + discounts * Z`` back onto the fixed ``support`` (C51 projection):
    each shifted atom's mass is split between its two neighbouring atoms, in proportion to closeness; values
    beyond the support are clipped to its ends.

    :param next_probs: probabilities of the next state's return, ``[batch, n_atoms]``
    :param rewards: ``[batch, 1]``
    :param discounts: ``gamma * (1 - done)`` (or n-step discount), ``[batch, 1]``
    :param support: atoms, evenly spaced and increasing, ``[n_atoms]``
    :return: projected target probabilities ``[batch, n_atoms]``
    """
    n_atoms = support.shape[0]
    v_min, v_max = support[0], support[-1]
    delta = (v_max - v_min) / (n_atoms - 1)
    shifted = (rewards + discounts * support.unsqueeze(0)).clamp(v_min, v_max)
    position = (shifted - v_min) / delta  # fractional atom index, [B, K]
    lower = position.floor().clamp(0, n_atoms - 1)
    upper = position.ceil().clamp(0, n_atoms - 1)
    upper_weight = position - lower
    lower_weight = 1.0 - upper_weight  # when lower == upper, all the mass goes to that atom
    target = th.zeros_like(next_probs)
    target.scatter_add_(1, lower.long(), next_probs * lower_weight)
    target.scatter_add_(1, upper.long(), next_probs * upper_weight)
    return target


class CategoricalCritic(BaseModel):
    """
    Q-function(s) with a categorical distribution over ``n_atoms`` evenly spaced returns in ``[v_min, v_max]``.

    Calling the critic returns the expected Q-values, one ``[batch, 1]`` tensor per Q-network, exactly like
    SB3's ``ContinuousCritic``: code that only needs Q-values (``score_actions``, ``q_min``) works with both.
    :meth:`logits` gives the distributions, for the cross-entropy loss.

    :param observation_space: Observation space
    :param action_space: Action space
    :param net_arch: Network architecture
    :param features_extractor: Network to extract features
    :param features_dim: Number of features
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param n_critics: Number of Q-networks
    :param share_features_extractor: Whether the features extractor is shared with the actor
    :param n_atoms: number of atoms of the distribution
    :param v_min: smallest return of the support
    :param v_max: largest return of the support
    :param layer_norm: LayerNorm and tanh after the first hidden layer (see :func:`sb3_lifelong.common.policies.mlp_layers`)
    """

    support: th.Tensor
    features_extractor: BaseFeaturesExtractor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        n_critics: int = 1,
        share_features_extractor: bool = True,
        n_atoms: int = 51,
        v_min: float = -150.0,
        v_max: float = 150.0,
        layer_norm: bool = False,
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        if n_atoms < 2 or not v_min < v_max:
            raise ValueError(f"need n_atoms >= 2 and v_min < v_max, got n_atoms={n_atoms}, v_min={v_min}, v_max={v_max}")
        action_dim = get_action_dim(self.action_space)
        self.share_features_extractor = share_features_extractor
        self.n_critics = n_critics
        self.n_atoms = n_atoms
        self.v_min = float(v_min)
        self.v_max = float(v_max)
        self.layer_norm = layer_norm
        self.q_networks: list[nn.Module] = []
        for idx in range(n_critics):
            q_net = nn.Sequential(*mlp_layers(features_dim + action_dim, n_atoms, net_arch, activation_fn, layer_norm))
            self.add_module(f"qf{idx}", q_net)
            self.q_networks.append(q_net)
        self.register_buffer("support", th.linspace(self.v_min, self.v_max, n_atoms))

    def logits(self, obs: PyTorchObs, actions: th.Tensor, features: Optional[th.Tensor] = None) -> tuple[th.Tensor, ...]:
        """
        :param obs: observations ``[batch, ...]``
        :param actions: normalised actions ``[batch, action_dim]``
        :param features: precomputed features of ``obs`` (optional)
        :return: one ``[batch, n_atoms]`` tensor of logits per Q-network
        """
        if features is None:
            with th.set_grad_enabled(not self.share_features_extractor):
                features = self.extract_features(obs, self.features_extractor)
        qvalue_input = th.cat([features, actions], dim=1)
        return tuple(q_net(qvalue_input) for q_net in self.q_networks)

    def td_target(
        self,
        next_obs: PyTorchObs,
        next_actions: th.Tensor,
        rewards: th.Tensor,
        discounts: th.Tensor,
        low_precision: Optional[LowPrecisionCopy] = None,
    ) -> th.Tensor:
        """
        The distributional TD target: per transition and next action, the distribution of the Q-network with the
        lowest expected value, averaged over the next actions, shifted by ``rewards + discounts * Z`` and projected
        back onto the support. Call it on the target critic, without autograd: the logits are then the scoring
        engine's (:func:`~sb3_lifelong.numerics.scoring.network_outputs`: bit for bit :meth:`logits` in float32;
        :func:`~sb3_lifelong.numerics.scoring.uses_engine`).

        :param next_obs: next observations ``[batch, ...]``
        :param next_actions: normalised next actions ``[n_next_actions, batch, action_dim]``
        :param rewards: ``[batch, 1]``
        :param discounts: ``gamma * (1 - done)`` (or the n-step discount), ``[batch, 1]``
        :param low_precision: a synchronised low-precision copy of this critic, to compute the logits with
        :return: target probabilities ``[batch, n_atoms]``
        """
        n_next_actions = next_actions.shape[0]
        flat_next_actions = next_actions.reshape(-1, next_actions.shape[-1])
        if not uses_engine(self, low_precision):
            logits = self.logits(tile_obs(next_obs, n_next_actions) if n_next_actions > 1 else next_obs, flat_next_actions)
        else:
            logits = tuple(eager_network_outputs(self, next_obs, flat_next_actions, n_next_actions, low_precision)[1])
        next_probs = th.softmax(th.stack(logits), dim=-1)  # [C, T*B, K]
        lowest = (next_probs * self.support).sum(-1).argmin(dim=0)  # [T*B]
        next_probs = next_probs.gather(0, lowest.view(1, -1, 1).expand(1, *next_probs.shape[1:]))[0]
        next_probs = next_probs.view(n_next_actions, -1, next_probs.shape[-1]).mean(dim=0)
        return categorical_projection(next_probs, rewards, discounts, self.support)

    def loss(self, obs: PyTorchObs, actions: th.Tensor, target_probs: th.Tensor) -> CriticLoss:
        """
        Cross-entropy of each Q-network's distribution of the data's actions with the target distribution, summed
        over the Q-networks.

        :param obs: observations ``[batch, ...]``
        :param actions: the data's normalised actions ``[batch, action_dim]``
        :param target_probs: the target distribution (:meth:`td_target`), ``[batch, n_atoms]``
        :return: the loss and the lowest expected Q-value of each action over the Q-networks
        """
        logits = self.logits(obs, actions)
        loss = sum_of(-(target_probs * F.log_softmax(lg, dim=-1)).sum(dim=-1).mean() for lg in logits)
        with th.no_grad():
            q_values = th.cat([self.expected(lg) for lg in logits], dim=1).min(dim=1).values
        return CriticLoss(loss, q_values)

    def expected(self, logits: th.Tensor) -> th.Tensor:
        """
        :param logits: ``[..., n_atoms]``
        :return: expected return ``[..., 1]``
        """
        return (th.softmax(logits, dim=-1) * self.support).sum(dim=-1, keepdim=True)

    def q_values_of(self, output: th.Tensor) -> th.Tensor:
        """
        What a Q-network's output means, for the scoring engine (:func:`~sb3_lifelong.numerics.scoring.runs_no_grad_pass`).

        :param output: a Q-network's logits ``[rows, n_atoms]``
        :return: the expected Q-values ``[rows, 1]``
        """
        return self.expected(output)

    def forward(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        return tuple(self.expected(logits) for logits in self.logits(obs, actions))

    def q1_forward(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """:return: the expected Q-value of the first network only, ``[batch, 1]``"""
        with th.no_grad():
            features = self.extract_features(obs, self.features_extractor)
        return self.expected(self.q_networks[0](th.cat([features, actions], dim=1)))
