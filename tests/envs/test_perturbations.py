"""Perturbations reach the physics on every robot; OP3 and dm_control walker envs pass the env checkers."""

import importlib.util
import os
import re
import subprocess
import sys

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from sb3_lifelong.envs import DMC_WALKER_ID, OP3_WALK_ID, PAPER_STAGES, PERTURBATIONS, DynamicsSchedule

#: the dm_control walker, where dm-control is installed (the mujoco extra); a skip says how to get it
NO_DM_CONTROL = pytest.mark.skipif(
    importlib.util.find_spec("dm_control") is None, reason='dm-control is not installed (pip install "sb3_lifelong[mujoco]")'
)
DMC = pytest.param(DMC_WALKER_ID, marks=NO_DM_CONTROL)
GYM_ROBOTS = ["Walker2d-v5", "Hopper-v5", "HalfCheetah-v5", "Humanoid-v5", DMC]
TEST_VALUES = dict(
    hip_deformation=0.3,
    foot_scale=1.5,
    ground_softness=0.1,
    friction=0.3,
    mass_scale=1.5,
    gravity=5.0,
    actuator_strength=0.5,
    joint_damping=10.0,
    leg_motor_scale=-1.0,
    joint_lock=1.0,
)


def op3_or_skip() -> None:
    try:
        from sb3_lifelong.envs.op3 import make_op3_spec

        make_op3_spec()
    except ImportError as e:  # no mujoco-menagerie, or no robot model in it; a bug after loading is a failure
        pytest.skip(f"mujoco-menagerie not installed: {e}")
    except RuntimeError as e:
        if "Could not load robotis_op3" not in str(e):
            raise
        pytest.skip(f"robotis_op3 not available from mujoco-menagerie (set MENAGERIE_ROOT to a local copy): {e}")


def fixed_policy(step: int, n: int) -> np.ndarray:
    return 0.8 * np.sin(2 * np.pi * step * 0.05 + np.arange(n))


def rollout_return(env: gym.Env, policy=fixed_policy, steps: int = 150) -> float:
    env.reset(seed=0)
    total = 0.0
    for i in range(steps):
        _, reward, terminated, truncated, _ = env.step(policy(i, env.action_space.shape[0]))
        total += float(reward)
        if terminated or truncated:
            break
    return total


@pytest.mark.parametrize("env_id", GYM_ROBOTS)
def test_every_perturbation_changes_zero_shot_return(env_id: str) -> None:
    env = DynamicsSchedule(gym.make(env_id))
    nominal = rollout_return(env)
    assert rollout_return(env) == nominal  # deterministic
    for name in env.supported_params:
        value = TEST_VALUES[name]
        _, high = env.editor.valid_range(name)
        value = min(value, high)
        env.set_params({name: value}, immediate=True)
        changed = rollout_return(env)
        assert abs(changed - nominal) > 1e-3 * max(1.0, abs(nominal)), (name, nominal, changed)
    env.set_params({}, immediate=True)
    assert rollout_return(env) == nominal  # back to the nominal robot, bit for bit


@pytest.mark.parametrize("env_id", ["Walker2d-v5", "Humanoid-v5", DMC])
def test_contact_changes_reach_the_contacts(env_id: str) -> None:
    env = DynamicsSchedule(gym.make(env_id), stages=[{"friction": 0.3, "ground_softness": 0.08}])
    env.reset(seed=0)
    model, data = env.unwrapped.model, env.unwrapped.data
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    feet = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, g) for g in env.editor.description.foot_geoms}
    found = 0
    for i in range(200):
        env.step(fixed_policy(i, env.action_space.shape[0]))
        for c in data.contact[: data.ncon]:
            if floor in (c.geom1, c.geom2) and (feet & {c.geom1, c.geom2}):
                assert c.friction[0] == pytest.approx(0.3) and c.solref[0] == pytest.approx(0.08)
                found += 1
        if found > 5:
            break
    assert found > 5, "no foot-floor contact seen"


def test_nominal_contact_is_what_mujoco_mixes() -> None:
    # Walker2d's feet have friction 1.9 > floor 0.7: MuJoCo takes the max, so the nominal friction is 1.9, and a
    # floor friction set without raising the floor's priority would change nothing
    env = DynamicsSchedule(gym.make("Walker2d-v5"))
    assert env.nominal_params["friction"] == pytest.approx(1.9)
    assert env.nominal_params["ground_softness"] == pytest.approx(0.02)
    env.set_params(friction=0.1, immediate=True)
    model = env.unwrapped.model
    assert model.geom_priority[0] > model.geom_priority[1:].max()


def test_recompile_when_feet_have_mass() -> None:
    env = DynamicsSchedule(gym.make("Walker2d-v5"))
    model = env.unwrapped.model
    foot = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "foot")
    mass0, total0 = float(model.body_mass[foot]), float(model.body_subtreemass[0])
    env.set_params(foot_scale=1.5, immediate=True)
    assert env.editor.last_apply_recompiled
    assert model.body_mass[foot] > mass0 * 1.2  # longer capsule, same density
    assert model.body_subtreemass[0] == pytest.approx(total0 + 2 * (model.body_mass[foot] - mass0))  # both feet
    # identical to a model compiled from scratch with the longer feet
    spec = mujoco.MjSpec.from_file(env.unwrapped.fullpath)
    for name in ("foot_geom", "foot_left_geom"):
        spec.geom(name).size[1] *= 1.5
    fresh = spec.compile()
    for field in ("body_mass", "body_inertia", "body_ipos", "geom_size", "geom_rbound", "body_subtreemass", "dof_invweight0"):
        np.testing.assert_array_equal(getattr(model, field), getattr(fresh, field), err_msg=field)
    env.set_params({}, immediate=True)
    assert model.body_mass[foot] == mass0 and not env.editor.last_apply_recompiled


def test_field_edits_update_derived_constants() -> None:
    env = DynamicsSchedule(gym.make("Hopper-v5"), stages=[{"mass_scale": 2.0, "gravity": 3.0, "actuator_strength": 0.5}])
    model = env.unwrapped.model
    total = float(model.body_subtreemass[0])
    env2 = gym.make("Hopper-v5")
    assert total == pytest.approx(2.0 * float(env2.unwrapped.model.body_subtreemass[0]))  # mj_setConst ran
    np.testing.assert_allclose(model.opt.gravity, [0.0, 0.0, -3.0])
    np.testing.assert_allclose(model.actuator_gear[:, 0], 0.5 * env2.unwrapped.model.actuator_gear[:, 0])


@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Walker2d-v5", "Hopper-v5"])
def test_leg_motor_scale_scales_and_reverses_one_leg(env_id: str) -> None:
    env = DynamicsSchedule(gym.make(env_id))
    model = env.unwrapped.model
    nominal = model.actuator_gear[:, 0].copy()
    leg = env.editor._leg_actuators
    others = [a for a in range(model.nu) if a not in leg]
    assert leg and len(leg) == len(env.editor.description.leg_joints)
    for scale in (-1.0, 0.25, 2.0):
        env.set_params({"leg_motor_scale": scale}, immediate=True)
        np.testing.assert_allclose(model.actuator_gear[leg, 0], scale * nominal[leg])
        np.testing.assert_array_equal(model.actuator_gear[others, 0], nominal[others])  # the other leg is untouched
    env.set_params({}, immediate=True)
    np.testing.assert_array_equal(model.actuator_gear[:, 0], nominal)


def test_reversed_leg_pushes_the_other_way() -> None:
    """A torque on the reversed leg's joints has the opposite sign for the same control."""
    forces = {}
    for scale in (1.0, -1.0):
        env = DynamicsSchedule(gym.make("HalfCheetah-v5"), stages=[{"leg_motor_scale": scale}])
        env.reset(seed=0)
        env.unwrapped.data.ctrl[:] = 1.0
        mujoco.mj_forward(env.unwrapped.model, env.unwrapped.data)
        forces[scale] = env.unwrapped.data.qfrc_actuator[3:].copy()  # joint torques (after the root's three dofs)
    np.testing.assert_allclose(forces[-1.0][:3], -forces[1.0][:3])
    np.testing.assert_allclose(forces[-1.0][3:], forces[1.0][3:])
    assert np.all(np.abs(forces[1.0]) > 0)


def test_servo_reversal_mirrors_the_target_and_keeps_feedback_negative() -> None:
    op3_or_skip()
    env = DynamicsSchedule(gym.make(OP3_WALK_ID))
    model = env.unwrapped.model
    gain, bias, limit = model.actuator_gainprm[:, 0].copy(), model.actuator_biasprm.copy(), model.actuator_forcerange.copy()
    leg = env.editor._leg_actuators
    assert len(leg) == 6
    env.set_params({"leg_motor_scale": -0.5}, immediate=True)
    np.testing.assert_allclose(model.actuator_gainprm[leg, 0], -gain[leg])
    np.testing.assert_array_equal(model.actuator_biasprm, bias)  # feedback (-kp q) keeps its sign
    np.testing.assert_allclose(model.actuator_forcerange[leg], 0.5 * limit[leg])


@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Walker2d-v5", "Hopper-v5"])
def test_joint_lock_holds_the_joint_near_its_reference(env_id: str) -> None:
    moved = {}
    for share in (0.0, 1.0):
        env = DynamicsSchedule(gym.make(env_id), stages=[{"joint_lock": share}])
        model, data = env.unwrapped.model, env.unwrapped.data
        joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, env.editor.description.lock_joint)
        address = model.jnt_qposadr[joint]
        env.reset(seed=0)
        env.action_space.seed(0)
        angles = []
        for _ in range(300):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            angles.append(float(data.qpos[address]))
            if terminated or truncated:
                env.reset()
        moved[share] = np.ptp(angles)
    assert moved[1.0] < 0.2 < moved[0.0], moved  # locked: a soft limit's give of a few degrees, free: a wide swing
    env.set_params({"joint_lock": 0.5}, immediate=True)
    low, high = env.editor._nominal["jnt_range"][joint]
    np.testing.assert_allclose(model.jnt_range[joint], [low / 2, high / 2])  # reference 0: half the range either side


def test_limb_perturbations_need_their_parts() -> None:
    import dataclasses

    from sb3_lifelong.envs.perturbations import ROBOTS, PhysicsEditor, find_mujoco

    handle = find_mujoco(gym.make("Hopper-v5"))
    handle.description = dataclasses.replace(ROBOTS["HopperEnv"], leg_joints=(), lock_joint=None)
    editor = PhysicsEditor(handle)
    assert "leg_motor_scale" not in editor.supported and "joint_lock" not in editor.supported
    with pytest.raises(ValueError, match="unknown dynamics parameter 'joint_lock'"):
        editor.validate({"joint_lock": 1.0})
    handle.description = dataclasses.replace(ROBOTS["HopperEnv"], lock_joint="no_such_joint")
    with pytest.raises(ValueError, match="no joint named 'no_such_joint'"):
        PhysicsEditor(handle)
    with pytest.raises(ValueError, match="outside its physical range"):
        DynamicsSchedule(gym.make("Hopper-v5"), stages=[{"joint_lock": 1.5}])


def test_an_unvaried_schedule_observes_the_whole_robot_parameters_only() -> None:
    """The observation of a schedule whose stages vary nothing kept its size when the limb perturbations came."""
    env = DynamicsSchedule(gym.make("Hopper-v5"), append_params=True)
    assert env.observed_params == ["hip_deformation", "foot_scale", "ground_softness", "friction", "mass_scale", "gravity",
                                   "actuator_strength", "joint_damping"]  # fmt: skip
    assert env.observation_space.shape == (11 + 8,)


def test_perturbations_are_documented() -> None:
    for p in PERTURBATIONS.values():
        assert p.unit and p.description and p.low < p.high and p.obs_scale > 0


# ---------------------------------------------------------------------------------------------- OP3 and dm_control


def test_op3_env_checkers() -> None:
    op3_or_skip()
    env = gym.make(OP3_WALK_ID)
    gym_check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(gym.make(OP3_WALK_ID).unwrapped)
    wrapped = DynamicsSchedule(gym.make(OP3_WALK_ID), stages=[{}, "hip_0.3"], switch_at=[5], append_params=True)
    gym_check_env(wrapped, skip_render_check=True)
    wrapped = DynamicsSchedule(gym.make(OP3_WALK_ID), stages=[{}, "hip_0.3"], switch_at=[5], append_params=True)
    obs, info = wrapped.reset(seed=0)
    assert obs.shape == (69,) and info["stage"] == 0 and info["dynamics_params"]["ground_softness"] == pytest.approx(0.004)


@NO_DM_CONTROL
def test_dmc_walker_env_checkers() -> None:
    gym_check_env(gym.make(DMC_WALKER_ID).unwrapped, skip_render_check=True)
    sb3_check_env(DynamicsSchedule(gym.make(DMC_WALKER_ID), stages=["foot_1.2"], append_params=True))


def test_op3_task_basics() -> None:
    op3_or_skip()
    env = gym.make(OP3_WALK_ID)
    assert env.spec.max_episode_steps == 1000
    u = env.unwrapped
    assert env.action_space.shape == (20,) and env.observation_space.shape == (68,)
    assert u.dt == pytest.approx(0.02)  # 50 Hz control
    env.reset(seed=0)
    total = 0.0
    for _ in range(50):  # the standing pose holds
        _, reward, terminated, _, _ = env.step(np.zeros(20))
        total += reward
        assert not terminated
    assert total == pytest.approx(50 * 1.0, abs=2.0)  # alive bonus, little speed, little jitter
    # a fall terminates: lay the torso on its side
    u.data.qpos[3:7] = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0]
    assert env.step(np.zeros(20))[2]


def test_op3_paper_stages_hurt_a_fixed_gait() -> None:
    op3_or_skip()
    from sb3_lifelong.envs.op3 import OP3OpenLoopGait

    gait = OP3OpenLoopGait()
    env = DynamicsSchedule(gym.make(OP3_WALK_ID), stages=["default", *PAPER_STAGES])
    returns, distances = {}, {}
    for i, name in enumerate(["default", *PAPER_STAGES]):
        env.set_stage(i, immediate=True)
        returns[name] = rollout_return(env, lambda step, n: gait(step), steps=300)
        distances[name] = float(env.unwrapped.data.qpos[0])
    assert distances["default"] > 0.4  # the gait walks the nominal robot forward
    for name in PAPER_STAGES:
        assert returns[name] < returns["default"], returns
        assert distances[name] < 0.8 * distances["default"], distances


def test_op3_foot_scale_is_a_field_edit_equal_to_recompiling() -> None:
    op3_or_skip()
    from sb3_lifelong.envs.op3 import OP3_FOOT_GEOMS, OP3OpenLoopGait, make_op3_spec

    env = DynamicsSchedule(gym.make(OP3_WALK_ID), stages=["foot_1.6"])
    assert not env.editor.last_apply_recompiled  # massless feet: geometry only
    spec = make_op3_spec()
    for name in OP3_FOOT_GEOMS:
        spec.geom(name).size[:2] *= 1.6
    fresh = spec.compile()
    model = env.unwrapped.model
    for field in ("geom_size", "geom_rbound", "geom_aabb", "body_mass", "body_subtreemass"):
        np.testing.assert_allclose(getattr(model, field), getattr(fresh, field), rtol=1e-12, atol=1e-15, err_msg=field)
    gait = OP3OpenLoopGait()
    a = rollout_return(env, lambda step, n: gait(step), steps=100)
    env.unwrapped.model = fresh  # same trajectory on the recompiled model
    env.unwrapped.data = mujoco.MjData(fresh)
    b = rollout_return(env.env, lambda step, n: gait(step), steps=100)
    assert a == pytest.approx(b, rel=1e-9)


@pytest.mark.parametrize("backend", ["auto", "egl", "osmesa"])
def test_op3_render_rgb_array(backend: str) -> None:
    op3_or_skip()
    # in a fresh process: MuJoCo binds a backend named by MUJOCO_GL when it is first imported
    script = (
        "import gymnasium as gym, sb3_lifelong.envs\n"
        "env = gym.make('sb3_lifelong/OP3Walk-v0', render_mode='rgb_array', width=64, height=48)\n"
        "env.reset(seed=0)\n"
        "frame = env.render()\n"
        "assert frame.shape == (48, 64, 3) and frame.std() > 0, frame.shape\n"
        "env.close()\n"
        "print('RENDER_OK')\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY")}
    if backend != "auto":  # "auto": the package picks a headless backend itself when the frame is asked for
        env.update(MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
    result = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    if "RENDER_OK" not in result.stdout:
        if re.search(r"OpenGL|osmesa|EGL|glfw|gladLoadGL", result.stderr, re.IGNORECASE):
            pytest.skip(f"no working {backend} OpenGL backend here: {result.stderr.strip().splitlines()[-1]}")
        raise AssertionError(result.stderr)


def test_import_without_a_gl_backend_needs_none() -> None:
    """Nothing but rendering needs OpenGL: a broken backend named by the user gives an error that says what to do."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY")}
    plain = subprocess.run(
        [sys.executable, "-c", "import sb3_lifelong, sb3_lifelong.envs"], env=env, capture_output=True, text=True
    )
    assert plain.returncode == 0, plain.stderr
    env.update(MUJOCO_GL="osmesa", PYOPENGL_PLATFORM="osmesa")
    named = subprocess.run([sys.executable, "-c", "import sb3_lifelong.envs"], env=env, capture_output=True, text=True)
    assert named.returncode == 0 or "Unset MUJOCO_GL" in named.stderr, named.stderr  # osmesa may be installed


@pytest.mark.parametrize("nominal, expected", [([0.3, 0.0, -0.4], [1.2, 0.0, -1.6]), ([0.0, 0.0, 0.0], [0.0, 0.0, -2.0])])
def test_gravity_keeps_the_nominal_direction_of_any_magnitude(nominal, expected):
    """A gravity of 2 points where the robot's own gravity points (a weak, tilted one too; straight down if it has none)."""
    base = gym.make("Hopper-v5")
    base.unwrapped.model.opt.gravity[:] = nominal
    env = DynamicsSchedule(base)
    env.set_params({"gravity": 2.0}, immediate=True)
    np.testing.assert_allclose(env.unwrapped.model.opt.gravity, expected)
    env.set_params({}, immediate=True)
    np.testing.assert_allclose(env.unwrapped.model.opt.gravity, nominal)


def test_unlimited_position_servos_scale_their_stiffness():
    """A position servo of no force limit (force = kp ctrl - kp q): strength and a leg's scale multiply kp in both terms;
    reversing the leg negates only the commanded angle."""
    base = gym.make("Walker2d-v5")
    model = base.unwrapped.model
    kp = 50.0
    model.actuator_biastype[:] = mujoco.mjtBias.mjBIAS_AFFINE
    model.actuator_gainprm[:, 0] = kp
    model.actuator_biasprm[:, :3] = [0.0, -kp, 0.0]
    model.actuator_forcelimited[:] = 0
    env = DynamicsSchedule(base)
    leg = env.editor._leg_actuators
    others = [a for a in range(model.nu) if a not in leg]
    assert leg and others
    env.set_params({"leg_motor_scale": -0.5}, immediate=True)
    np.testing.assert_allclose(model.actuator_gainprm[leg, 0], -0.5 * kp)
    np.testing.assert_allclose(model.actuator_biasprm[leg, 1], -0.5 * kp)
    np.testing.assert_allclose(model.actuator_gainprm[others, 0], kp)
    np.testing.assert_allclose(model.actuator_biasprm[others, 1], -kp)
    env.set_params({"actuator_strength": 0.5}, immediate=True)
    np.testing.assert_allclose(model.actuator_gainprm[:, 0], 0.5 * kp)
    np.testing.assert_allclose(model.actuator_biasprm[:, 1], -0.5 * kp)


def test_a_mujoco_env_without_a_robot_description_is_refused_with_the_way_out() -> None:
    with pytest.raises(
        ValueError,
        match=r"No robot description for InvertedPendulumEnv: known envs are HalfCheetahEnv, "
        r"HopperEnv, HumanoidEnv, Walker2dEnv, OP3WalkEnv, DMCWalkerEnv\. Give the env an attribute "
        r"`robot_description`",
    ):
        DynamicsSchedule(gym.make("InvertedPendulum-v5"))


def test_a_recompiled_foot_scale_is_cached_and_the_same_again() -> None:
    """foot_scale recompiles the model once per value; the second time the cached arrays give the same model."""
    env = DynamicsSchedule(gym.make("Hopper-v5"))
    model = env.unwrapped.model
    env.set_params({"foot_scale": 1.4}, immediate=True)
    first = {name: np.array(getattr(model, name)) for name in ("geom_size", "geom_rbound", "body_mass")}
    assert len(env.editor._compiled) == 1
    env.set_params({}, immediate=True)
    assert not np.array_equal(model.geom_size, first["geom_size"])  # back to the nominal feet
    env.set_params({"foot_scale": 1.4}, immediate=True)
    assert len(env.editor._compiled) == 1  # the cached recompile, not a second one
    for name, values in first.items():
        np.testing.assert_array_equal(getattr(model, name), values, err_msg=name)
    env.close()
