"""The policies' building blocks: the LayerNorm torso's layers, and the Gaussian actor's samples against their law."""

import math

import numpy as np
import torch as th
from torch import nn

from sb3_lifelong import MPO
from sb3_lifelong.common.policies import mlp_layers
from sb3_lifelong.numerics.fast_ops import HiddenLinear


def test_layer_norm_torso_with_unequal_widths():
    layers = mlp_layers(5, 3, [32, 16], nn.ReLU, layer_norm=True)
    linears = [layer for layer in layers if isinstance(layer, nn.Linear)]
    assert [(layer.in_features, layer.out_features) for layer in linears] == [(5, 32), (32, 16), (16, 3)]
    norms = [layer for layer in layers if isinstance(layer, nn.LayerNorm)]
    assert len(norms) == 1 and norms[0].normalized_shape == (32,) and layers.index(norms[0]) == 1
    # only the Linear from one hidden layer to the next is the fast hidden kind: not the input's, not the output's
    assert [isinstance(layer, HiddenLinear) for layer in linears] == [False, True, False]
    assert nn.Sequential(*layers)(th.zeros(4, 5)).shape == (4, 3)
    # without an output layer, every Linear after the first is between hidden layers
    linears = [layer for layer in mlp_layers(5, 0, [32, 16, 8], nn.ReLU, layer_norm=True) if isinstance(layer, nn.Linear)]
    assert [isinstance(layer, HiddenLinear) for layer in linears] == [False, True, True]


def test_actor_samples_follow_its_gaussian():
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, device="cpu")
    actor = model.policy.actor
    obs = th.zeros(20_000, 3)
    with th.no_grad():
        mean, std = actor.distribution_params(obs[:1])
        samples = actor(obs).numpy()[:, 0]
    mean, std = float(mean[0, 0]), float(std[0, 0])
    assert samples.min() >= -1.0 and samples.max() <= 1.0
    # the law inside the clip: P(a <= x) = Phi((x - mean) / std) where -1 < x < 1
    for z in (-0.5, 0.0, 0.5):
        x = mean + z * std
        if -1.0 < x < 1.0:
            expected = 0.5 * (1 + math.erf(z / math.sqrt(2)))
            assert abs(np.mean(samples <= x) - expected) < 0.015, (z, np.mean(samples <= x), expected)
    with th.no_grad():  # deterministic: the mean, clipped to the action box
        np.testing.assert_allclose(actor(obs[:3], deterministic=True).numpy(), np.clip(mean, -1.0, 1.0), rtol=1e-6)
