"""
Golden model edits (issue 66): what each perturbation writes into a MuJoCo model, computed by hand on a toy robot.

The toy has a floor and two feet that mix their contact parameters (equal priorities, ``solmix`` 1 and 3), a torque
motor, a force-limited and an unlimited position servo on its leg, a servo and a motor elsewhere, a limited knee whose
reference angle lies inside its range and an unlimited ankle whose reference lies outside +-pi. Every expected number
below is written from the XML, not read back from the editor; every array the perturbation should not touch is checked
to be bit for bit the nominal one, and a return to the nominal values gives back the whole model.
"""

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from sb3_lifelong.envs.perturbations import MujocoHandle, PhysicsEditor, RobotDescription  # noqa: E402

TOY = """
<mujoco model="toy">
  <compiler angle="radian"/>
  <option timestep="0.01" gravity="0 0 -9.81"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" friction="0.8 0.005 0.0001" solref="0.02 1"
          solimp="0.9 0.95 0.001 0.5 2" condim="3"/>
    <body name="torso" pos="0 0 1">
      <geom name="chest" type="box" size="0.1 0.1 0.1" mass="2"/>
      <body name="thigh" pos="0 0 -0.2">
        <joint name="hip" type="hinge" axis="0 1 0" damping="0.5" range="-1 1" limited="true"/>
        <geom name="thigh_geom" type="capsule" size="0.03 0.1" mass="0.5"/>
        <body name="shin" pos="0 0 -0.25">
          <joint name="knee" type="hinge" axis="0 1 0" damping="0.2" range="-1.5 0.3" limited="true" ref="-0.2"/>
          <geom name="shin_geom" type="capsule" size="0.02 0.1" mass="0.3"/>
          <body name="foot" pos="0 0 -0.15">
            <joint name="ankle" type="hinge" axis="0 1 0" damping="0.1" limited="false" ref="4.0"/>
            <geom name="foot_box" type="box" size="0.05 0.04 0.01" mass="0.1" friction="1.2 0.01 0.0002"
                  solref="0.04 0.8" solimp="0.8 0.9 0.002 0.4 3" solmix="3" condim="4"/>
            <geom name="toe" type="capsule" size="0.01 0.03" pos="0.05 0 0" mass="0.05"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="hip_motor" joint="hip" gear="10"/>
    <position name="knee_servo" joint="knee" kp="20" kv="2" forcelimited="true" forcerange="-5 5"/>
    <position name="hip_servo" joint="hip" kp="6" kv="1" forcelimited="false"/>
    <position name="ankle_servo" joint="ankle" kp="8" kv="0.5" forcelimited="false"/>
    <motor name="ankle_motor" joint="ankle" gear="3"/>
  </actuator>
</mujoco>
"""
HIP_MOTOR, KNEE_SERVO, HIP_SERVO, ANKLE_SERVO, ANKLE_MOTOR = range(5)
KNEE, ANKLE = 1, 2
FLOOR, FOOT_BOX, TOE = 0, 4, 5
#: constants MuJoCo derives from the gears (mj_setConst), which change with them
DERIVED = ("actuator_length0", "actuator_acc0")


def toy(lock_joint="knee", **description) -> tuple:
    """The toy model and an editor on it: the leg is the hip and the knee; the ankle's motors are not the leg's."""
    model = mujoco.MjModel.from_xml_string(TOY)
    fields = dict(leg_joints=("hip", "knee"), lock_joint=lock_joint)
    fields.update(description)
    desc = RobotDescription("Toy", "floor", ("foot_box", "toe"), "thigh", (0.0, 1.0, 0.0), **fields)
    return model, PhysicsEditor(MujocoHandle(model, mujoco.MjData(model), desc))


def snapshot(model) -> dict:
    arrays = {n: getattr(model, n) for n in dir(model) if not n.startswith("_")}
    arrays = {n: a.copy() for n, a in arrays.items() if isinstance(a, np.ndarray)}
    arrays["opt.gravity"] = model.opt.gravity.copy()
    return arrays


def changed(model, before: dict) -> set:
    return {n for n, a in snapshot(model).items() if not np.array_equal(a, before[n], equal_nan=True)}


def test_the_toy_is_what_its_xml_says():
    model, _ = toy()
    assert model.body_quat.shape[0] == 5 and model.nu == 5
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "foot_box") == FOOT_BOX
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "toe") == TOE
    np.testing.assert_array_equal(model.actuator_biasprm[KNEE_SERVO, :3], [0.0, -20.0, -2.0])
    np.testing.assert_array_equal(model.actuator_forcelimited, [0, 1, 0, 0, 0])
    np.testing.assert_array_equal(model.qpos0, [0.0, -0.2, 4.0])


def test_the_nominal_contact_and_parameters_are_the_floor_and_first_foot_mixed():
    """Equal priorities: friction is the larger of the two, solref and solimp mix by solmix (1 and 3: weight 1/4)."""
    _, editor = toy()
    contact = editor.contact_nominal
    np.testing.assert_allclose(contact["friction"], [1.2, 0.01, 0.0002], rtol=1e-12)
    np.testing.assert_allclose(contact["solref"], [0.25 * 0.02 + 0.75 * 0.04, 0.25 * 1.0 + 0.75 * 0.8], rtol=1e-12)
    np.testing.assert_allclose(
        contact["solimp"], 0.25 * np.array([0.9, 0.95, 0.001, 0.5, 2]) + 0.75 * np.array([0.8, 0.9, 0.002, 0.4, 3]), rtol=1e-12
    )
    assert int(contact["condim"]) == 4
    assert editor.nominal_params == pytest.approx(
        {
            "hip_deformation": 0.0,
            "foot_scale": 1.0,
            "ground_softness": 0.035,
            "friction": 1.2,
            "mass_scale": 1.0,
            "gravity": 9.81,
            "actuator_strength": 1.0,
            "joint_damping": 1.0,
            "leg_motor_scale": 1.0,
            "joint_lock": 0.0,
        },
        rel=1e-12,
    )
    assert list(editor.nominal_params) == list(editor.supported)


def test_a_floor_of_higher_priority_gives_its_own_contact():
    model = mujoco.MjModel.from_xml_string(TOY.replace('condim="3"/>', 'condim="3" priority="2"/>'))
    desc = RobotDescription("Toy", "floor", ("foot_box",), "thigh")
    contact = PhysicsEditor(MujocoHandle(model, mujoco.MjData(model), desc)).contact_nominal
    np.testing.assert_array_equal(contact["friction"], [0.8, 0.005, 0.0001])
    np.testing.assert_array_equal(contact["solref"], [0.02, 1.0])
    np.testing.assert_array_equal(contact["solimp"], [0.9, 0.95, 0.001, 0.5, 2])
    assert int(contact["condim"]) == 3
    model = mujoco.MjModel.from_xml_string(TOY.replace('solmix="3"', 'solmix="3" priority="1"'))
    contact = PhysicsEditor(MujocoHandle(model, mujoco.MjData(model), desc)).contact_nominal
    np.testing.assert_array_equal(contact["friction"], [1.2, 0.01, 0.0002])  # the foot's, not the larger of the two
    np.testing.assert_array_equal(contact["solref"], [0.04, 0.8])
    assert int(contact["condim"]) == 4


@pytest.mark.parametrize(
    "params, friction, solref",
    [
        ({"friction": 0.3}, [0.3, 0.01, 0.0002], [0.035, 0.85]),
        ({"ground_softness": 0.1}, [1.2, 0.01, 0.0002], [0.1, 0.85]),
        ({"ground_softness": 0.1, "friction": 0.0}, [0.0, 0.01, 0.0002], [0.1, 0.85]),
    ],
)
def test_contact_changes_give_the_floor_priority_and_the_mixed_contact(params, friction, solref):
    """The floor takes priority over every geom and carries the mixed contact with the changed number in it."""
    model, editor = toy()
    before = snapshot(model)
    editor.apply(params)
    assert int(model.geom_priority[FLOOR]) == 1  # the highest priority in the model (0) plus one
    np.testing.assert_allclose(model.geom_friction[FLOOR], friction, rtol=1e-12)
    np.testing.assert_allclose(model.geom_solref[FLOOR], solref, rtol=1e-12)
    np.testing.assert_allclose(model.geom_solimp[FLOOR], editor.contact_nominal["solimp"], rtol=0)
    assert int(model.geom_condim[FLOOR]) == 4
    for name in ("geom_priority", "geom_friction", "geom_solref", "geom_solimp", "geom_condim"):
        np.testing.assert_array_equal(getattr(model, name)[1:], before[name][1:])  # the floor alone
    assert changed(model, before) == {"geom_priority", "geom_friction", "geom_solref", "geom_solimp", "geom_condim"}


def test_nominal_contact_values_leave_the_floor_alone():
    model, editor = toy()
    before = snapshot(model)
    nominal = editor.nominal_params
    editor.apply({"friction": nominal["friction"], "ground_softness": nominal["ground_softness"]})
    assert changed(model, before) == set()
    editor.apply({"friction": nominal["friction"], "ground_softness": 0.03})
    assert int(model.geom_priority[FLOOR]) == 1


def test_foot_scale_scales_each_foot_along_its_sole():
    """A box foot: its length and width (not its thickness); a capsule: its length. Sizes, bounding boxes and spheres
    are those of the robot compiled with the scaled feet."""
    model, editor = toy()
    before = snapshot(model)
    editor.apply({"foot_scale": 1.5})
    np.testing.assert_allclose(model.geom_size[FOOT_BOX], [0.075, 0.06, 0.01], rtol=1e-12)
    np.testing.assert_allclose(model.geom_size[TOE], [0.01, 0.045, 0.0], rtol=1e-12)
    scaled = TOY.replace('size="0.01 0.03"', 'size="0.01 0.045"').replace('size="0.05 0.04 0.01"', 'size="0.075 0.06 0.01"')
    compiled = mujoco.MjModel.from_xml_string(scaled)
    for name in ("geom_size", "geom_rbound", "geom_aabb"):
        np.testing.assert_allclose(getattr(model, name), getattr(compiled, name), rtol=1e-12, atol=1e-15, err_msg=name)
    assert model.geom_rbound[FOOT_BOX] == pytest.approx(np.sqrt(0.075**2 + 0.06**2 + 0.01**2), rel=1e-12)
    assert model.geom_rbound[TOE] == pytest.approx(0.01 + 0.045, rel=1e-12)
    others = [g for g in range(model.ngeom) if g not in (FOOT_BOX, TOE)]
    for name in ("geom_size", "geom_rbound", "geom_aabb"):
        np.testing.assert_array_equal(getattr(model, name)[others], before[name][others])
    # and what MuJoCo derives from the geometry (mj_setConst): the bounding volumes and the dofs' length scales
    assert {"geom_size", "geom_rbound", "geom_aabb"} <= changed(model, before) <= {
        "geom_size", "geom_rbound", "geom_aabb", "bvh_aabb", "dof_length"
    }  # fmt: skip


def test_a_foot_of_a_shape_that_has_no_sole_is_refused_by_name():
    model = mujoco.MjModel.from_xml_string(TOY)
    desc = RobotDescription("Toy", "floor", ("floor",), "thigh")
    editor = PhysicsEditor(MujocoHandle(model, mujoco.MjData(model), desc))
    with pytest.raises(ValueError, match="foot_scale cannot scale geoms of type mjGEOM_PLANE"):
        editor.apply({"foot_scale": 2.0})


def test_actuator_strength_scales_each_kind_of_actuator_by_its_own_field():
    """Torque motors: the gear; force-limited servos: the force range; unlimited servos: kp in the gain and the bias
    (and the velocity gain kv with it), every actuator."""
    model, editor = toy()
    before = snapshot(model)
    editor.apply({"actuator_strength": 2.0})
    np.testing.assert_array_equal(model.actuator_gear[[HIP_MOTOR, ANKLE_MOTOR], 0], [20.0, 6.0])
    np.testing.assert_array_equal(
        model.actuator_gear[[KNEE_SERVO, HIP_SERVO, ANKLE_SERVO]], before["actuator_gear"][[1, 2, 3]]
    )
    np.testing.assert_array_equal(model.actuator_forcerange[KNEE_SERVO], [-10.0, 10.0])
    np.testing.assert_array_equal(model.actuator_gainprm[KNEE_SERVO], before["actuator_gainprm"][KNEE_SERVO])
    np.testing.assert_array_equal(model.actuator_gainprm[[HIP_SERVO, ANKLE_SERVO], 0], [12.0, 16.0])
    np.testing.assert_array_equal(model.actuator_biasprm[HIP_SERVO, :3], [0.0, -12.0, -2.0])
    np.testing.assert_array_equal(model.actuator_biasprm[ANKLE_SERVO, :3], [0.0, -16.0, -1.0])
    np.testing.assert_array_equal(model.actuator_biasprm[KNEE_SERVO], before["actuator_biasprm"][KNEE_SERVO])
    assert changed(model, before) == {"actuator_gear", "actuator_forcerange", "actuator_gainprm", "actuator_biasprm", *DERIVED}


@pytest.mark.parametrize("scale", [-0.5, 2.0])
def test_leg_motor_scale_scales_the_legs_actuators_and_reverses_their_commands(scale):
    """The leg's torque motor: gear times the scale (its sign too); its servos: |scale| on the force range or on kp
    in both terms, and below 0 the commanded angle's gain negated, the feedback kept. The ankle's actuators stay."""
    model, editor = toy()
    before = snapshot(model)
    editor.apply({"leg_motor_scale": scale})
    sign, size = np.sign(scale), abs(scale)
    assert model.actuator_gear[HIP_MOTOR, 0] == 10.0 * scale
    np.testing.assert_array_equal(model.actuator_forcerange[KNEE_SERVO], [-5.0 * size, 5.0 * size])
    assert model.actuator_gainprm[KNEE_SERVO, 0] == 20.0 * sign
    np.testing.assert_array_equal(model.actuator_biasprm[KNEE_SERVO, :3], [0.0, -20.0, -2.0])
    assert model.actuator_gainprm[HIP_SERVO, 0] == 6.0 * scale
    np.testing.assert_array_equal(model.actuator_biasprm[HIP_SERVO, :3], [0.0, -6.0 * size, -1.0 * size])
    for name in ("actuator_gear", "actuator_forcerange", "actuator_gainprm", "actuator_biasprm"):
        np.testing.assert_array_equal(getattr(model, name)[[ANKLE_SERVO, ANKLE_MOTOR]], before[name][[3, 4]])


def test_strength_and_a_legs_scale_multiply():
    model, editor = toy()
    editor.apply({"actuator_strength": 2.0, "leg_motor_scale": -0.5})
    np.testing.assert_array_equal(model.actuator_gear[[HIP_MOTOR, ANKLE_MOTOR], 0], [-10.0, 6.0])
    np.testing.assert_array_equal(model.actuator_forcerange[KNEE_SERVO], [-5.0, 5.0])
    np.testing.assert_array_equal(model.actuator_gainprm[[KNEE_SERVO, HIP_SERVO, ANKLE_SERVO], 0], [-20.0, -6.0, 16.0])


def test_joint_damping_scales_every_dof():
    model, editor = toy()
    before = snapshot(model)
    editor.apply({"joint_damping": 3.0})
    np.testing.assert_allclose(model.dof_damping, [1.5, 0.6, 0.3], rtol=1e-12)
    assert changed(model, before) == {"dof_damping"}


@pytest.mark.parametrize(
    "lock_joint, share, expected",
    [
        ("knee", 0.5, [-0.2 + 0.5 * (-1.5 + 0.2), -0.2 + 0.5 * (0.3 + 0.2)]),  # toward its reference -0.2
        ("knee", 1.0, [-0.2, -0.2]),
        ("ankle", 0.25, [np.pi - 0.75 * 2 * np.pi, np.pi]),  # unlimited: from +-pi, toward its reference clipped to pi
    ],
)
def test_joint_lock_shrinks_the_range_toward_the_reference(lock_joint, share, expected):
    model, editor = toy(lock_joint=lock_joint)
    joint = {"knee": KNEE, "ankle": ANKLE}[lock_joint]
    before = snapshot(model)
    editor.apply({"joint_lock": share})
    np.testing.assert_allclose(model.jnt_range[joint], expected, rtol=1e-12, atol=1e-15)
    assert model.jnt_limited[joint] == 1
    others = [j for j in range(model.njnt) if j != joint]
    np.testing.assert_array_equal(model.jnt_range[others], before["jnt_range"][others])
    np.testing.assert_array_equal(model.jnt_limited[others], before["jnt_limited"][others])
    assert changed(model, before) <= {"jnt_range", "jnt_limited"}


def test_gravity_is_a_magnitude_along_the_nominal_direction():
    model, editor = toy()
    before = snapshot(model)
    editor.apply({"gravity": 3.0})
    np.testing.assert_allclose(model.opt.gravity, [0.0, 0.0, -3.0], rtol=1e-12)
    assert changed(model, before) == {"opt.gravity"}


def test_everything_at_once_and_back_to_nominal_bit_for_bit():
    model, editor = toy()
    before = snapshot(model)
    values = {
        "hip_deformation": 0.3,
        "foot_scale": 0.7,
        "ground_softness": 0.2,
        "friction": 0.5,
        "mass_scale": 1.7,
        "gravity": 4.0,
        "actuator_strength": 0.6,
        "joint_damping": 4.0,
        "leg_motor_scale": -1.5,
        "joint_lock": 0.9,
    }
    assert editor.apply(values) == values
    assert editor.params == values and not editor.last_apply_recompiled
    assert len(changed(model, before)) > 10
    assert editor.apply({}) == editor.nominal_params
    assert changed(model, before) == set()


def test_ranges_values_and_the_allowed_text():
    """ground_softness's lowest value is two time steps (MuJoCo clamps below); a description's range replaces the
    generic one; bools, strings and values outside the range are refused with the range in the message."""
    _, editor = toy(ranges={"joint_damping": (0.0, 3.0)})
    assert editor.valid_range("ground_softness") == (0.02, 1.0)
    assert editor.valid_range("joint_damping") == (0.0, 3.0)
    assert editor.valid_range("friction") == (0.0, 10.0)
    assert editor.validate({"joint_damping": np.float32(3.0), "friction": 0}) == {"joint_damping": 3.0, "friction": 0.0}
    assert type(editor.validate({"friction": np.int64(2)})["friction"]) is float
    with pytest.raises(ValueError, match=r"stage 2: joint_damping=3\.5 x nominal is outside its physical range \[0, 3\]"):
        editor.validate({"joint_damping": 3.5}, where="stage 2")
    with pytest.raises(ValueError, match=r"ground_softness=0\.01 s is outside its physical range \[0\.02, 1\]"):
        editor.validate({"ground_softness": 0.01})
    for bad in (True, np.bool_(False), "1", None):
        with pytest.raises(ValueError, match="friction must be a real number"):
            editor.validate({"friction": bad})
    with pytest.raises(ValueError, match="outside its physical range"):
        editor.validate({"friction": float("nan")})
    with pytest.raises(ValueError, match="unknown dynamics parameter 'Friction' for Toy"):
        editor.validate({"Friction": 1.0})
    text = editor.allowed_text()
    assert text.startswith("hip_deformation [rad] in [-1.571, 1.571] (nominal 0); foot_scale [x nominal] in [0.1, 5]")
    assert "ground_softness [s] in [0.02, 1] (nominal 0.035)" in text and "joint_damping [x nominal] in [0, 3]" in text
    assert text.endswith("joint_lock [1] in [0, 1] (nominal 0)")


def test_limb_parts_that_the_model_lacks_are_refused_by_name():
    with pytest.raises(ValueError, match=r"Toy: no actuator drives the leg joints \('foot_joint',\)"):
        model = mujoco.MjModel.from_xml_string(
            TOY.replace('name="ankle"', 'name="foot_joint"').replace('joint="ankle"', 'joint="hip"')
        )
        desc = RobotDescription("Toy", "floor", ("foot_box",), "thigh", leg_joints=("foot_joint",))
        PhysicsEditor(MujocoHandle(model, mujoco.MjData(model), desc))
    model = mujoco.MjModel.from_xml_string(
        TOY.replace('type="hinge" axis="0 1 0" damping="0.1"', 'type="slide" axis="0 0 1" damping="0.1"')
    )
    desc = RobotDescription("Toy", "floor", ("foot_box",), "thigh", lock_joint="ankle")
    with pytest.raises(ValueError, match="Toy: joint_lock needs a hinge joint, 'ankle' is not one"):
        PhysicsEditor(MujocoHandle(model, mujoco.MjData(model), desc))
    _, editor = toy(leg_joints=(), lock_joint=None)
    assert "leg_motor_scale" not in editor.supported and "joint_lock" not in editor.supported
    _, editor = toy(perturbations=("friction", "joint_lock"))
    assert editor.supported == ("friction", "joint_lock")


def test_feet_with_mass_are_recompiled_to_the_robot_built_with_scaled_feet():
    """Feet that carry mass change the bodies' inertia when they grow: the model is recompiled, and every array of it
    is then that of the robot written with the scaled feet (a capsule given by ``fromto`` scaled about its centre);
    back at the nominal value the model is the nominal one bit for bit, and the scaled one again comes from the cache."""
    xml = TOY.replace('size="0.01 0.03" pos="0.05 0 0"', 'size="0.01" fromto="0.02 0 0 0.08 0 0"')
    xml = xml.replace('size="0.05 0.04 0.01" mass="0.1"', 'size="0.05 0.04 0.01"')  # its mass from its volume: the foot's
    # centre of mass moves toward the box as it grows (body_ipos, which only a compile computes)
    scaled = xml.replace('fromto="0.02 0 0 0.08 0 0"', 'fromto="0.005 0 0 0.095 0 0"')
    scaled = scaled.replace('size="0.05 0.04 0.01"', 'size="0.075 0.06 0.01"')
    model = mujoco.MjModel.from_xml_string(xml)
    desc = RobotDescription("Toy", "floor", ("foot_box", "toe"), "thigh")
    editor = PhysicsEditor(MujocoHandle(model, mujoco.MjData(model), desc, make_spec=lambda: mujoco.MjSpec.from_string(xml)))
    before = snapshot(model)
    editor.apply({"foot_scale": 1.5})
    assert editor.last_apply_recompiled
    want = snapshot(mujoco.MjModel.from_xml_string(scaled))
    differ = [name for name, value in snapshot(model).items() if not np.allclose(value, want[name], rtol=1e-9, atol=1e-12)]
    assert differ == []
    assert {"body_mass", "body_inertia", "body_ipos", "geom_size"} <= changed(model, before)  # geom_pos stays
    editor.apply({})
    assert changed(model, before) == set() and not editor.last_apply_recompiled
    editor.apply({"foot_scale": 1.5})
    assert list(editor._compiled) == [1.5]
    assert [name for name, value in snapshot(model).items() if not np.allclose(value, want[name], rtol=1e-9, atol=1e-12)] == []
