"""
The Robotis OP3 walking task (``sb3_lifelong/OP3Walk-v0``).

The robot comes from ``mujoco-menagerie`` (``robotis_op3``), loaded the normal way: the package downloads it
once for users with network; set ``MENAGERIE_ROOT`` to a local copy of the menagerie to work offline.

Task: walk forward (+x of the world) as fast as possible without falling.

* Action: 20 values in [-1, 1]; joint position targets ``q_target = q_stand + action_scale * action`` for the
  position servos, held for ``frame_skip`` physics steps (default 10 x 2 ms: a 50 Hz control rate).
* Observation (68 floats): joint positions relative to the standing pose (20), joint velocities x 0.1 (20),
  gravity direction in the torso frame (3), heading as (cos yaw, sin yaw) (2), torso angular velocity in the
  torso frame (3), previous action (20). Everything an IMU and the joint encoders of the real robot give.
* Reward per step: ``forward_weight * clip(v_x, -max_speed, max_speed) + alive_bonus
  - smoothness_weight * mean((a_t - a_{t-1})^2)``.
  ``v_x`` (m/s) is the torso's forward speed over the control step: it is the objective. The alive bonus pays for
  staying up. The weights make diving forward never pay: with the speed capped at 0.5 m/s (above what the OP3
  walks) a dive earns at most 2 per step for the ~25 steps a fall takes (~50), while standing earns 1 per step
  (discounted value ~100 at gamma 0.99) and walking at 0.25 m/s 1.5 per step. A first version (5 x speed, 0.5
  alive, cap 1 m/s) taught PPO to throw itself forward. The smoothness term discourages the bang-bang jitter
  that position targets invite, which wears real servos; it is small enough not to stop walking.
* Termination: the torso is lower than ``fall_height`` x its standing height, or tilts more than 60 degrees.
  Truncation: 1000 steps (20 s) through the registration's ``max_episode_steps``.
"""

import copy
import os
from typing import Any, Dict, Optional, Tuple

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from sb3_lifelong.envs.perturbations import RobotDescription
from sb3_lifelong.envs.rendering import make_renderer

#: right/left foot contact boxes (named by this env; the menagerie model leaves them unnamed)
OP3_FOOT_GEOMS = ("r_foot_sole", "r_foot_front", "l_foot_sole", "l_foot_front")

OP3_DESCRIPTION = RobotDescription(
    name="OP3",
    floor_geom="floor",
    foot_geoms=OP3_FOOT_GEOMS,
    hip_body="r_hip_pitch_link",
    hip_axis=(-1.0, 0.0, 0.0),  # roll: the right leg splays outwards for positive values
    leg_joints=("r_hip_yaw", "r_hip_roll", "r_hip_pitch", "r_knee", "r_ank_pitch", "r_ank_roll"),
    lock_joint="r_knee",
)

# knee bend of the standing pose (rad); hip and ankle pitch take half of it each, so the soles stay flat
_CROUCH = 0.35
#: joint angles of the standing pose (rad), by joint name; joints not listed are at 0
OP3_STAND_POSE: Dict[str, float] = {
    "l_sho_roll": 1.2,
    "r_sho_roll": -1.2,
    "l_hip_pitch": -_CROUCH,
    "l_knee": 2 * _CROUCH,
    "l_ank_pitch": _CROUCH,
    "r_hip_pitch": _CROUCH,
    "r_knee": -2 * _CROUCH,
    "r_ank_pitch": -_CROUCH,
}

_MODEL_CACHE: Dict[str, Any] = {}


def make_op3_spec() -> Any:
    """
    The OP3 scene from mujoco-menagerie as an editable ``mujoco.MjSpec``, with this task's additions: named and
    visible foot contact boxes and a camera that follows the robot.

    :return: the spec
    """
    try:
        import mujoco_menagerie
    except ImportError as e:  # pragma: no cover
        raise ImportError('The OP3 task needs mujoco-menagerie: pip install "sb3_lifelong[mujoco]"') from e
    try:
        spec = mujoco_menagerie.get("robotis_op3").spec("scene")
    except Exception as e:
        root = os.environ.get("MENAGERIE_ROOT")
        hint = (
            f" (MENAGERIE_ROOT={root})" if root else " (set MENAGERIE_ROOT to a local mujoco_menagerie copy to work offline)"
        )
        raise RuntimeError(f"Could not load robotis_op3 from mujoco-menagerie{hint}: {e}") from e
    counts = {"r": 0, "l": 0}
    for geom in spec.geoms:
        if geom.classname.name == "foot":
            side = geom.parent.name[0]
            geom.name = f"{side}_foot_{('sole', 'front')[counts[side]]}"
            counts[side] += 1
            geom.group = 2  # visible in renders, so foot changes show; physics unchanged
            geom.rgba = [0.85, 0.45, 0.1, 1.0]
    spec.worldbody.add_camera(
        name="track",
        mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM,
        pos=[0.45, -0.75, 0.45],
        xyaxes=[0.857, 0.514, 0.0, -0.14, 0.233, 0.963],
    )
    return spec


def _nominal_model() -> Any:
    key = os.environ.get("MENAGERIE_ROOT", "")
    if key not in _MODEL_CACHE:
        _MODEL_CACHE[key] = make_op3_spec().compile()
    return copy.deepcopy(_MODEL_CACHE[key])


class OP3WalkEnv(gym.Env):
    """
    Robotis OP3 walking forward, 20 joint position targets at 50 Hz.

    :param render_mode: ``None`` or ``"rgb_array"`` (needs OpenGL: chosen when the first frame is rendered, see
        :func:`sb3_lifelong.envs.rendering.make_renderer`)
    :param frame_skip: physics steps (2 ms) per control step
    :param action_scale: joint target offset (rad) for an action of 1
    :param forward_weight: reward per m/s of forward speed
    :param alive_bonus: reward per control step while not fallen
    :param smoothness_weight: weight of the action-change penalty
    :param max_speed: speed (m/s) beyond which the forward reward is capped
    :param fall_height: termination when the torso is below this fraction of its standing height
    :param reset_noise_scale: half-width (rad) of the uniform noise added to the standing pose at reset
    :param width: width of rendered frames
    :param height: height of rendered frames
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(
        self,
        render_mode: Optional[str] = None,
        frame_skip: int = 10,
        action_scale: float = 0.5,
        forward_weight: float = 2.0,
        alive_bonus: float = 1.0,
        smoothness_weight: float = 0.1,
        max_speed: float = 0.5,
        fall_height: float = 0.6,
        reset_noise_scale: float = 0.02,
        width: int = 480,
        height: int = 480,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        if frame_skip < 1:
            raise ValueError(f"frame_skip must be >= 1, got {frame_skip}")
        self.render_mode = render_mode
        self.frame_skip = int(frame_skip)
        self.action_scale = float(action_scale)
        self.forward_weight = float(forward_weight)
        self.alive_bonus = float(alive_bonus)
        self.smoothness_weight = float(smoothness_weight)
        self.max_speed = float(max_speed)
        self.fall_height = float(fall_height)
        self.reset_noise_scale = float(reset_noise_scale)
        self.width, self.height = int(width), int(height)
        self.robot_description = OP3_DESCRIPTION

        self.model = _nominal_model()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._torso = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "body_link")
        self._joint_qpos = np.array([m.jnt_qposadr[m.actuator_trnid[a, 0]] for a in range(m.nu)])
        self._joint_qvel = np.array([m.jnt_dofadr[m.actuator_trnid[a, 0]] for a in range(m.nu)])
        names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, m.actuator_trnid[a, 0]) for a in range(m.nu)]
        self.joint_names = tuple(names)
        self.stand_pose = np.array([OP3_STAND_POSE.get(n, 0.0) for n in names])
        self._ctrl_low, self._ctrl_high = m.actuator_ctrlrange[:, 0].copy(), m.actuator_ctrlrange[:, 1].copy()
        self._feet = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in OP3_FOOT_GEOMS]
        self.dt = m.opt.timestep * self.frame_skip

        self.action_space = spaces.Box(-1.0, 1.0, shape=(m.nu,), dtype=np.float32)
        n_obs = 3 * m.nu + 8
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(n_obs,), dtype=np.float64)
        self._prev_action = np.zeros(m.nu)
        self.stand_height = self._place_standing(self.stand_pose)
        self._renderer: Any = None

    # ------------------------------------------------------------------ model helpers
    def make_spec(self) -> Any:
        """A fresh spec of the nominal model (used by perturbations that recompile)."""
        return make_op3_spec()

    def _place_standing(self, pose: np.ndarray) -> float:
        """Put the robot in ``pose`` with its lowest sole corner on the floor; return the torso height."""
        d = self.data
        mujoco.mj_resetData(self.model, d)
        d.qpos[self._joint_qpos] = pose
        d.qpos[2] = 0.0
        mujoco.mj_kinematics(self.model, d)
        corners = np.array([[sx, sy, -1.0] for sx in (-1, 1) for sy in (-1, 1)])
        lowest = np.inf
        for g in self._feet:
            points = d.geom_xpos[g] + (corners * self.model.geom_size[g]) @ d.geom_xmat[g].reshape(3, 3).T
            lowest = min(lowest, float(points[:, 2].min()))
        d.qpos[2] = -lowest + 1e-4
        mujoco.mj_forward(self.model, d)
        return float(d.qpos[2])

    # ------------------------------------------------------------------ gym API
    def _obs(self) -> np.ndarray:
        d = self.data
        rot = d.xmat[self._torso].reshape(3, 3)
        gravity = -rot[2, :]  # world -z in the torso frame
        heading = rot[:2, 0] / max(float(np.linalg.norm(rot[:2, 0])), 1e-8)
        return np.concatenate(
            [
                d.qpos[self._joint_qpos] - self.stand_pose,
                0.1 * d.qvel[self._joint_qvel],
                gravity,
                heading,
                d.qvel[3:6],  # free joint angular velocity is expressed in the torso frame
                self._prev_action,
            ]
        )

    def reset(self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None) -> Tuple[np.ndarray, Dict]:
        super().reset(seed=seed)
        noise = self.np_random.uniform(-self.reset_noise_scale, self.reset_noise_scale, size=self.model.nu)
        # the model may have been changed (deformed hip...): put the soles back on the floor
        self._place_standing(self.stand_pose + noise)
        self.data.ctrl[:] = self.stand_pose
        self._prev_action = np.zeros(self.model.nu)
        return self._obs(), {"x_position": float(self.data.qpos[0])}

    def step(self, action: np.ndarray) -> Tuple[np.ndarray, float, bool, bool, Dict[str, Any]]:
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        d = self.data
        d.ctrl[:] = np.clip(self.stand_pose + self.action_scale * a, self._ctrl_low, self._ctrl_high)
        x_before = float(d.qpos[0])
        mujoco.mj_step(self.model, d, nstep=self.frame_skip)
        velocity = (float(d.qpos[0]) - x_before) / self.dt
        forward = self.forward_weight * float(np.clip(velocity, -self.max_speed, self.max_speed))
        smooth = self.smoothness_weight * float(np.mean((a - self._prev_action) ** 2))
        self._prev_action = a
        height, upright = float(d.qpos[2]), float(d.xmat[self._torso][8])
        finite = bool(np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel)))
        terminated = (not finite) or height < self.fall_height * self.stand_height or upright < 0.5
        reward = forward + self.alive_bonus - smooth
        info = {
            "x_position": float(d.qpos[0]),
            "x_velocity": velocity,
            "reward_forward": forward,
            "reward_alive": self.alive_bonus,
            "reward_smoothness": -smooth,
        }
        obs = self._obs() if finite else np.zeros(self.model.nu * 3 + 8)
        return obs, reward, bool(terminated), False, info

    def render(self) -> Optional[np.ndarray]:  # type: ignore[override]
        if self.render_mode is None:
            gym.logger.warn('render() called without render_mode; create the env with render_mode="rgb_array"')
            return None
        if self._renderer is None:
            self._renderer = make_renderer(self.model, self.height, self.width)
        self._renderer.update_scene(self.data, camera="track")
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class OP3OpenLoopGait:
    """
    A hand-designed open-loop stepping gait for :class:`OP3WalkEnv` (no feedback): it walks the nominal robot
    forward at about 0.09 m/s and is fragile to changes of the robot, which makes it a cheap fixed policy for
    measuring what a perturbation does.

    :param period: step cycle (s)
    :param hip_amplitude: hip pitch swing (rad)
    :param knee_amplitude: knee bend of the swing leg (rad)
    :param lean: constant forward hip pitch (rad)
    :param sway: hip/ankle roll amplitude for the lateral weight shift (rad)
    :param action_scale: the env's ``action_scale`` (rad per unit action)
    :param dt: the env's control period (s)
    """

    def __init__(
        self,
        period: float = 0.4,
        hip_amplitude: float = 0.25,
        knee_amplitude: float = 0.4,
        lean: float = 0.1,
        sway: float = 0.08,
        action_scale: float = 0.5,
        dt: float = 0.02,
    ) -> None:
        self.period, self.hip, self.knee, self.lean, self.sway = period, hip_amplitude, knee_amplitude, lean, sway
        self.action_scale, self.dt = action_scale, dt

    def __call__(self, step: int) -> np.ndarray:
        """
        Action at a control step of the episode.

        :param step: control step index since reset
        :return: action in [-1, 1]
        """
        phase = 2 * np.pi * step * self.dt / self.period
        s = np.sin(phase)
        left, right = max(s, 0.0), max(-s, 0.0)  # which leg swings
        q = np.zeros(20)
        # joint order: head (0, 1), arms (2-7), left leg (8-13), right leg (14-19);
        # each leg: hip yaw, hip roll, hip pitch, knee, ankle pitch, ankle roll
        q[10], q[11], q[12] = -self.hip * left - self.lean, self.knee * left, 0.5 * (self.knee - self.hip) * left
        q[16], q[17], q[18] = self.hip * right + self.lean, -self.knee * right, -0.5 * (self.knee - self.hip) * right
        q[9] = q[15] = self.sway * np.cos(phase)
        q[13] = q[19] = -self.sway * np.cos(phase)
        return np.clip(q / self.action_scale, -1.0, 1.0)
