"""The sampler's checks, each at its boundary: what a user gets for an impossible request, and what still works."""

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)


def filled(rows: int = 6, **kwargs) -> LifelongReplayBuffer:
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", **kwargs)
    for k in range(rows):
        obs = np.full((1, 3), k, np.float32)
        buffer.add(obs, obs + 1, np.zeros((1, 2), np.float32), np.array([k], np.float32), np.zeros(1), [{}])
    return buffer


def test_n_steps_is_at_least_one() -> None:
    with pytest.raises(ValueError, match=r"n_steps must be >= 1, got 0"):
        LifelongReplayBuffer(0, OBS, ACT, device="cpu", n_steps=0)
    one_step = filled(n_steps=1).sample(4)
    assert len(one_step.rewards) == 4 and one_step.discounts is None  # one step: SB3's samples, gamma applied by the loss


def test_an_empty_buffer_and_weights_of_zero_cannot_be_sampled() -> None:
    with pytest.raises(ValueError, match="cannot sample from an empty buffer"):
        LifelongReplayBuffer(0, OBS, ACT, device="cpu").sample(4)
    buffer = filled()
    buffer.set_sampling_weights({0: 0.0})
    with pytest.raises(ValueError, match="the sampling weights give zero probability to every stored transition"):
        buffer.sample(4)
    with pytest.raises(ValueError, match=r"sampling weight of source 0 must be finite and >= 0, got -1.0"):
        buffer.set_sampling_weights({0: -1.0})
    buffer.set_sampling_weights({0: 1e-12})  # tiny but positive: samples
    assert len(buffer.sample(4).rewards) == 4


@pytest.mark.parametrize("scale", [float("inf"), float("-inf"), float("nan")])
def test_a_reward_scale_is_finite(scale) -> None:
    buffer = filled()
    with pytest.raises(ValueError, match=r"reward scale of source 0 must be finite, got"):
        buffer.set_reward_scale({0: scale})
    buffer.set_reward_scale({0: -2.0})  # negative is allowed: the rewards are multiplied
    rows = np.arange(6)
    np.testing.assert_allclose(buffer._get_samples(rows).rewards.numpy().ravel(), -2.0 * rows)


def test_pos_and_full_follow_from_the_rows() -> None:
    buffer = filled()
    assert buffer.pos == 6 and buffer.full is False
    with pytest.raises(AttributeError, match="the position of a lifelong buffer is its size and cannot be set"):
        buffer.pos = 0
    buffer.full = False  # what it is: allowed (SB3 assigns it)
    with pytest.raises(AttributeError, match="whether a lifelong buffer is full follows from its size and capacity"):
        buffer.full = True
    capped = filled(rows=6, capacity=6)
    assert capped.full is True and capped.pos == 6
    capped.full = True
    with pytest.raises(AttributeError, match="cannot be set"):
        capped.full = False
