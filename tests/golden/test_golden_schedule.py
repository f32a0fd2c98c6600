"""
Golden schedules and model edits (issue 66):

- the target networks' schedule with several environments and several gradient steps per rollout: the targets move
  exactly after the updates whose count is a multiple of ``target_update_interval`` (counted in updates, not in
  environment steps or rollouts), by ``tau`` of the way to the online networks, and at no other time;
- what a perturbation changes in a MuJoCo model: ``mass_scale`` multiplies exactly every body's mass and inertia (not
  the world's) and the constants derived from them, ``hip_deformation`` turns exactly the named body's frame about its
  axis by the angle; every other array of the model stays as it was.
"""

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env

from sb3_lifelong import CRR, MPO
from sb3_lifelong.envs import DynamicsSchedule

N_ENVS, GRADIENT_STEPS, INTERVAL, LEARNING_STARTS, STEPS = 2, 3, 4, 10, 40


class BoxEnv(gym.Env):
    observation_space = spaces.Box(-5.0, 5.0, (3,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self.np_random.normal(size=3).astype(np.float32), {}

    def step(self, action):
        self.t += 1
        obs = self.np_random.normal(size=3).astype(np.float32)
        return obs, float(np.sum(action) - obs[0]), False, self.t >= 15, {}


def flat(module: th.nn.Module) -> th.Tensor:
    return th.cat([p.detach().flatten() for p in module.parameters()]).clone()


@pytest.mark.parametrize("algorithm,tau", [(MPO, 1.0), (MPO, 0.25), (CRR, 1.0), (CRR, 0.25)])
def test_targets_move_exactly_every_interval_of_updates(algorithm, tau):
    model = algorithm(
        "MlpPolicy",
        make_vec_env(BoxEnv, n_envs=N_ENVS, seed=0),
        policy_kwargs=dict(net_arch=[8]),
        batch_size=8,
        num_samples=2,
        learning_starts=LEARNING_STARTS,
        train_freq=1,
        gradient_steps=GRADIENT_STEPS,
        target_update_interval=INTERVAL,
        tau=tau,
        compute=dict(compile_losses=False, scoring_dtype="float32"),
        seed=0,
        device="cpu",
    )
    states = []  # after update u (u = 0: before the first): the targets and the online networks

    def record():
        networks = (model.critic_target, model.actor_target, model.critic, model.actor)
        states.append(tuple(flat(network) for network in networks))

    sample = model.replay_buffer.sample

    def recording_sample(*args, **kwargs):  # at the start of update u + 1: the state after update u
        record()
        return sample(*args, **kwargs)

    model.replay_buffer.sample = recording_sample
    model.learn(STEPS)
    record()
    # one rollout is one step of each env; every rollout after learning_starts env steps has GRADIENT_STEPS updates
    rollouts = sum(1 for t in range(N_ENVS, STEPS + 1, N_ENVS) if t > LEARNING_STARTS)
    assert model._n_updates == len(states) - 1 == rollouts * GRADIENT_STEPS == 45
    moved = []
    for update in range(1, len(states)):
        (critic_t, actor_t, critic, actor), (old_critic_t, old_actor_t, _, _) = states[update], states[update - 1]
        if update % INTERVAL == 0:  # Polyak towards the online networks after this update's step
            th.testing.assert_close(critic_t, tau * critic + (1 - tau) * old_critic_t, rtol=1e-6, atol=1e-7)
            th.testing.assert_close(actor_t, tau * actor + (1 - tau) * old_actor_t, rtol=1e-6, atol=1e-7)
            assert not th.equal(critic_t, old_critic_t) and not th.equal(actor_t, old_actor_t)
        if not (th.equal(critic_t, old_critic_t) and th.equal(actor_t, old_actor_t)):
            moved.append(update)
    assert moved == list(range(INTERVAL, 46, INTERVAL))  # 4, 8, ..., 44: and after no other update


# ---------------------------------------------------------------------------------------------------------------------
# What a perturbation changes in the model
# ---------------------------------------------------------------------------------------------------------------------

#: the arrays ``mj_setConst`` derives from the masses and the kinematics at ``qpos0`` (they follow any such edit)
DERIVED = {
    "body_subtreemass",
    "body_invweight0",
    "dof_invweight0",
    "dof_M0",
    "tendon_invweight0",
    "actuator_acc0",
    "cam_poscom0",
    "light_poscom0",
}


def model_arrays(model) -> dict:
    return {name: np.array(getattr(model, name)) for name in dir(model) if isinstance(getattr(model, name), np.ndarray)}


def changed_arrays(before: dict, model) -> set:
    return {name for name, value in before.items() if not np.array_equal(value, getattr(model, name))}


def assert_same_model(model, reference) -> None:
    for name, value in model_arrays(reference).items():
        np.testing.assert_allclose(getattr(model, name), value, rtol=1e-12, atol=1e-12, err_msg=name)


def hamilton(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """the quaternion product ``q r`` (``w, x, y, z``): the rotation ``r`` in the frame that ``q`` rotates to"""
    w1, v1, w2, v2 = q[0], q[1:], r[0], r[1:]
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


def test_mass_scale_multiplies_exactly_every_bodys_mass_and_inertia():
    env, nominal = DynamicsSchedule(gym.make("Hopper-v5")), gym.make("Hopper-v5").unwrapped.model
    model = env.unwrapped.model
    before = model_arrays(model)
    env.set_params(mass_scale=1.5, immediate=True)
    # the world body (0) has no mass to scale; every other body's mass and inertia are 1.5 times theirs
    assert model.body_mass[0] == 0.0 and (nominal.body_mass[1:] > 0).all()
    np.testing.assert_allclose(model.body_mass, np.concatenate([[0.0], 1.5 * nominal.body_mass[1:]]), rtol=1e-15)
    np.testing.assert_allclose(model.body_inertia[1:], 1.5 * nominal.body_inertia[1:], rtol=1e-15)
    np.testing.assert_array_equal(model.body_inertia[0], nominal.body_inertia[0])
    # what follows from them: the sub-tree masses, and the joint-space inertia at qpos0 (the bodies' part scaled,
    # the rotors' armature, which is not a body's, not)
    np.testing.assert_allclose(model.body_subtreemass, 1.5 * nominal.body_subtreemass, rtol=1e-12)
    armature = nominal.dof_armature
    assert (armature > 0).any() and (armature == 0).any()
    np.testing.assert_allclose(model.dof_M0 - armature, 1.5 * (nominal.dof_M0 - armature), rtol=1e-12)
    np.testing.assert_allclose(model.cam_poscom0, nominal.cam_poscom0, rtol=1e-12, atol=1e-12)  # the com stays put
    np.testing.assert_array_equal(model.opt.gravity, nominal.opt.gravity)
    # and nothing else: the same model as the nominal one with its masses and inertias edited by hand
    assert changed_arrays(before, model) - DERIVED == {"body_mass", "body_inertia"}
    nominal.body_mass[1:] *= 1.5
    nominal.body_inertia[1:] *= 1.5
    mujoco.mj_setConst(nominal, mujoco.MjData(nominal))
    assert_same_model(model, nominal)
    env.set_params({}, immediate=True)  # and back, bit for bit
    assert changed_arrays(before, model) == set()


def test_hip_deformation_turns_exactly_the_named_body_by_the_angle():
    env, nominal = DynamicsSchedule(gym.make("Hopper-v5")), gym.make("Hopper-v5").unwrapped.model
    model = env.unwrapped.model
    before = model_arrays(model)
    thigh = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "thigh")
    env.set_params(hip_deformation=0.3, immediate=True)
    # Hopper's thigh frame is the identity in its parent's: the turn itself, 0.3 rad about its own y axis
    np.testing.assert_array_equal(nominal.body_quat[thigh], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(model.body_quat[thigh], [np.cos(0.15), 0.0, np.sin(0.15), 0.0], rtol=1e-12, atol=1e-15)
    others = np.arange(model.nbody) != thigh
    np.testing.assert_array_equal(model.body_quat[others], nominal.body_quat[others])
    assert changed_arrays(before, model) - DERIVED == {"body_quat"}
    nominal.body_quat[thigh] = [np.cos(0.15), 0.0, np.sin(0.15), 0.0]
    mujoco.mj_setConst(nominal, mujoco.MjData(nominal))
    assert_same_model(model, nominal)


TOY = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="torso" pos="0 0 1">
      <freejoint/>
      <geom type="box" size="0.1 0.1 0.1" mass="1"/>
      <body name="thigh" pos="0 0 -0.2" quat="0.9238795 0 0.3826834 0">
        <joint name="hip" type="hinge" axis="1 0 0"/>
        <geom name="foot" type="box" size="0.05 0.05 0.2" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="hip" gear="10"/></actuator>
</mujoco>
"""


def test_hip_deformation_turns_about_the_bodys_own_axis():
    """A thigh frame already turned 45 degrees about y, deformed about its own x axis: ``q_nominal * q(x, angle)``."""
    from sb3_lifelong.envs.perturbations import MujocoHandle, PhysicsEditor, RobotDescription

    model = mujoco.MjModel.from_xml_string(TOY)
    description = RobotDescription("Toy", "floor", ("foot",), "thigh", (1.0, 0.0, 0.0), perturbations=("hip_deformation",))
    editor = PhysicsEditor(MujocoHandle(model, mujoco.MjData(model), description))
    nominal = model.body_quat[2].copy()
    np.testing.assert_allclose(nominal, [np.cos(np.pi / 8), 0.0, np.sin(np.pi / 8), 0.0], rtol=1e-6)
    editor.apply({"hip_deformation": -0.5})
    turn = np.array([np.cos(-0.25), np.sin(-0.25), 0.0, 0.0])
    np.testing.assert_allclose(model.body_quat[2], hamilton(nominal, turn), rtol=1e-12, atol=1e-15)
    assert np.abs(hamilton(turn, nominal) - hamilton(nominal, turn)).max() > 0.05  # the other order is another turn
    np.testing.assert_array_equal(model.body_quat[:2], [[1.0, 0.0, 0.0, 0.0]] * 2)


def test_a_description_without_an_axis_deforms_about_x_and_descriptions_cannot_change():
    """``hip_axis`` left out is the body's own x axis (roll), as the docs say; a description is frozen, because the
    registry's descriptions are shared by every env of that robot."""
    import dataclasses

    from sb3_lifelong.envs.perturbations import ROBOTS, MujocoHandle, PhysicsEditor, RobotDescription

    description = RobotDescription("Toy", "floor", ("foot",), "thigh", perturbations=("hip_deformation",))
    assert description.hip_axis == (1.0, 0.0, 0.0)
    model = mujoco.MjModel.from_xml_string(TOY)
    nominal = model.body_quat[2].copy()
    PhysicsEditor(MujocoHandle(model, mujoco.MjData(model), description)).apply({"hip_deformation": 0.3})
    turn = np.array([np.cos(0.15), np.sin(0.15), 0.0, 0.0])
    np.testing.assert_allclose(model.body_quat[2], hamilton(nominal, turn), rtol=1e-12, atol=1e-15)
    with pytest.raises(dataclasses.FrozenInstanceError):
        ROBOTS["HopperEnv"].hip_axis = (1.0, 0.0, 0.0)  # type: ignore[misc]
    assert ROBOTS["HopperEnv"].hip_axis == (0.0, 1.0, 0.0)
