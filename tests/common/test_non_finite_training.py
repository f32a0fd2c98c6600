"""MPO and CRR stop with an error naming the update as soon as a loss or a dual is not finite, whatever the buffer."""

import re
from typing import Optional

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_lifelong import CRR, MPO

SMALL = dict(policy_kwargs=dict(net_arch=[16]), batch_size=32, learning_starts=40, seed=0)


class NanRewardEnv(gym.Env):
    """A 1-D point task whose reward is NaN at one step (the kind of bug SB3's ReplayBuffer stores silently)."""

    def __init__(self, nan_at: int = 45):
        self.observation_space = spaces.Box(-10.0, 10.0, shape=(2,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        self.nan_at = nan_at
        self.steps = 0
        self.x = 0.0

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        super().reset(seed=seed)
        self.x = 1.0
        return np.array([self.x, 0.0], dtype=np.float32), {}

    def step(self, action):
        self.steps += 1
        self.x = float(np.clip(self.x + 0.1 * float(action[0]), -10, 10))
        reward = float("nan") if self.steps == self.nan_at else -abs(self.x)
        return np.array([self.x, 0.0], dtype=np.float32), reward, False, self.steps % 20 == 0, {}


def all_finite(module: th.nn.Module) -> bool:
    return all(bool(th.isfinite(p).all()) for p in module.parameters())


STOPPED = r"critic_loss = nan at update (\d+) \(num_timesteps (\d+)\): not finite, training stopped"


@pytest.mark.parametrize("algorithm", [MPO, CRR])
def test_nan_reward_in_sb3s_buffer_stops_training_at_once(algorithm):
    """SB3's default buffer stores the NaN reward: the first update whose batch holds it raises, naming the update,
    before the target networks (and the actor, whose loss does not see the reward) take any NaN."""
    kwargs = dict(SMALL, num_samples=4) if algorithm is MPO else dict(SMALL)
    model = algorithm("MlpPolicy", NanRewardEnv(nan_at=45), **kwargs)
    with pytest.raises(FloatingPointError, match=STOPPED) as raised:
        model.learn(400)
    update, timestep = map(int, re.search(STOPPED, str(raised.value)).groups())
    assert update == model._n_updates and timestep == model.num_timesteps
    assert 45 <= timestep < 400  # it did not train on until the end
    assert "SB3's ReplayBuffer stores them" in str(raised.value)
    assert all_finite(model.critic_target) and all_finite(model.actor_target) and all_finite(model.actor)


def test_a_non_finite_mpo_dual_is_named():
    model = MPO("MlpPolicy", NanRewardEnv(nan_at=10**9), num_samples=4, **SMALL)
    model.learn(50)  # 10 updates
    with th.no_grad():
        model.log_alpha_stddev[0] = float("inf")
    with pytest.raises(FloatingPointError, match=r"log_alpha_stddev = inf at update 11 \(num_timesteps 50\)"):
        model.train(gradient_steps=3, batch_size=8)


def test_finite_training_is_unchanged():
    model = MPO("MlpPolicy", NanRewardEnv(nan_at=10**9), num_samples=4, **SMALL)
    model.learn(60)  # no error
    assert model._n_updates == 20 and all_finite(model.policy)
