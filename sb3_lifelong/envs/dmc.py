"""
The dm_control suite walker as a Gymnasium env (``sb3_lifelong/DMCWalker-v0``), so that the same
:class:`~sb3_lifelong.envs.DynamicsSchedule` and perturbations apply to it.

Observations are the suite's ``orientations`` (14), ``height`` (1) and ``velocity`` (9) flattened to 24 floats;
actions are the suite's 6 torques in [-1, 1]; rewards are the suite's (in [0, 1] per step). The suite's episodes
last 1000 control steps (25 ms each); they end by truncation only.
"""

from typing import Any, Dict, Optional, Tuple

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_lifelong.envs.perturbations import RobotDescription

DMC_WALKER_DESCRIPTION = RobotDescription(
    name="dm_control walker",
    floor_geom="floor",
    foot_geoms=("right_foot", "left_foot"),
    hip_body="right_thigh",
    hip_axis=(0.0, 1.0, 0.0),
    leg_joints=("right_hip", "right_knee", "right_ankle"),
    lock_joint="right_knee",
)


class DMCWalkerEnv(gym.Env):
    """
    dm_control's ``walker`` domain (tasks ``stand``, ``walk``, ``run``) behind the Gymnasium API.

    :param task: suite task name
    :param render_mode: ``None`` or ``"rgb_array"``
    :param width: width of rendered frames
    :param height: height of rendered frames
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 40}

    def __init__(self, task: str = "walk", render_mode: Optional[str] = None, width: int = 320, height: int = 240) -> None:
        from dm_control import suite

        if task not in ("stand", "walk", "run"):
            raise ValueError(f"task must be 'stand', 'walk' or 'run', got {task!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.task = task
        self.render_mode = render_mode
        self.width, self.height = int(width), int(height)
        self._env = suite.load("walker", task, task_kwargs={"random": 0})
        self.robot_description = DMC_WALKER_DESCRIPTION
        spec = self._env.action_spec()
        self.action_space: spaces.Box = spaces.Box(
            spec.minimum.astype(np.float32), spec.maximum.astype(np.float32), dtype=np.float32
        )
        n_obs = sum(int(np.prod(s.shape)) for s in self._env.observation_spec().values())
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(n_obs,), dtype=np.float64)

    @property
    def model(self) -> Any:
        """The ``mujoco.MjModel`` simulated by the suite."""
        return self._env.physics.model.ptr

    @property
    def data(self) -> Any:
        """The ``mujoco.MjData`` simulated by the suite."""
        return self._env.physics.data.ptr

    def make_spec(self) -> Any:
        """A fresh spec of the nominal walker model (used by perturbations that recompile)."""
        import mujoco
        from dm_control.suite import walker

        xml, assets = walker.get_model_and_assets()
        text = xml.decode() if isinstance(xml, bytes) else xml
        return mujoco.MjSpec.from_string(text, include=assets)

    @staticmethod
    def _flat(observation: Dict[str, Any]) -> np.ndarray:
        return np.concatenate([np.asarray(v, dtype=np.float64).ravel() for v in observation.values()])

    def reset(self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None) -> Tuple[np.ndarray, Dict]:
        super().reset(seed=seed)
        # the suite draws its initial state from its own RandomState: seed it from Gymnasium's generator
        self._env.task._random = np.random.RandomState(int(self.np_random.integers(2**31)))
        time_step = self._env.reset()
        return self._flat(time_step.observation), {}

    def step(self, action: np.ndarray) -> Tuple[np.ndarray, float, bool, bool, Dict[str, Any]]:
        time_step = self._env.step(np.clip(action, self.action_space.low, self.action_space.high))
        truncated = time_step.last()
        return self._flat(time_step.observation), float(time_step.reward or 0.0), False, bool(truncated), {}

    def render(self) -> Optional[np.ndarray]:  # type: ignore[override]
        if self.render_mode is None:
            return None
        return self._env.physics.render(height=self.height, width=self.width, camera_id=0)

    def close(self) -> None:
        self._env.close()
