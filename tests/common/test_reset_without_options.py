"""
The package's wrappers call ``reset`` as SB3 does: ``options`` only when it is given, so that an environment whose
``reset`` accepts only ``seed`` (SB3 runs it) trains too. Before, the resume wrapper always passed ``options=None``:
``TypeError: reset() got an unexpected keyword argument 'options'``.
"""

from typing import Any, Optional

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_lifelong import MPO
from sb3_lifelong.common.resume import EpisodeRngRecorder
from sb3_lifelong.core.contract import reset_options
from sb3_lifelong.envs import DynamicsSchedule


class SeedOnlyResetEnv(gym.Env):
    """A point to move towards the origin, whose ``reset`` accepts ``seed`` and no ``options`` (an older style)."""

    observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

    def __init__(self) -> None:
        self.resets: list[Optional[int]] = []
        self._state = np.zeros(2, np.float32)
        self._steps = 0

    def reset(self, seed: Optional[int] = None) -> tuple[np.ndarray, dict[str, Any]]:  # type: ignore[override]
        super().reset(seed=seed)
        self.resets.append(seed)
        self._state = self.np_random.uniform(-1.0, 1.0, 2).astype(np.float32)
        self._steps = 0
        return self._state.copy(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self._state = np.clip(self._state + 0.1 * action, -1.0, 1.0).astype(np.float32)
        self._steps += 1
        return self._state.copy(), -float(np.linalg.norm(self._state)), False, self._steps >= 50, {}


class SeedOnlyReset(gym.Wrapper):
    """A wrapper whose ``reset`` accepts only ``seed``, around any env."""

    def reset(self, seed: Optional[int] = None) -> tuple[Any, dict[str, Any]]:  # type: ignore[override]
        return self.env.reset(seed=seed)


def test_reset_options_passes_options_only_when_given():
    assert reset_options(None) == {}
    assert reset_options({}) == {"options": {}}
    assert reset_options({"init": 1}) == {"options": {"init": 1}}


def test_mpo_trains_on_an_env_whose_reset_takes_only_seed():
    env = SeedOnlyResetEnv()
    model = MPO("MlpPolicy", env, learning_starts=50, batch_size=32, num_samples=4, policy_kwargs={"net_arch": [16]}, seed=0)
    model.learn(300)
    assert model.num_timesteps == 300
    assert model._n_updates == 250  # one update per step after learning_starts: training ran
    # the seeded first reset, then one after each of the six 50-step episodes (the VecEnv resets at an episode's end)
    assert env.resets == [0] + [None] * 6
    assert np.isfinite(model.temperature)


def test_the_resume_wrapper_still_passes_given_options():
    class OptionsEnv(SeedOnlyResetEnv):
        def reset(self, seed=None, options=None):  # type: ignore[override]
            self.resets.append(options["start"] if options else None)
            return super().reset(seed=seed)

    env = OptionsEnv()
    wrapped = EpisodeRngRecorder(env)
    wrapped.reset(seed=1, options={"start": 7})
    wrapped.reset(seed=2)
    assert env.resets == [7, 1, None, 2]  # OptionsEnv's record, then SeedOnlyResetEnv's, for each reset


def test_dynamics_schedule_resets_an_env_whose_reset_takes_only_seed():
    schedule = DynamicsSchedule(SeedOnlyReset(gym.make("Hopper-v5")), stages=[{}, {"gravity": 1.5}], switch_at=[5])
    obs, info = schedule.reset(seed=0)
    assert obs.shape == schedule.observation_space.shape and info["stage"] == 0
    for _ in range(5):
        schedule.step(schedule.action_space.sample())
    _, info = schedule.reset()
    assert info["stage"] == 1 and info["dynamics_params"]["gravity"] > 0
