"""
Named physical changes of a MuJoCo robot ("perturbations") and the editor that applies them.

Every perturbation is one float in documented units. The :class:`PhysicsEditor` keeps a copy of the
nominal model fields it may touch; applying a set of values restores those fields, edits them, and calls
``mujoco.mj_setConst`` so that derived constants (sub-tree masses, inverse weights, actuator
accelerations) follow. Changes that alter masses or inertias derived from geometry (larger feet on a robot
whose feet have mass) are compiled again from an :class:`mujoco.MjSpec` and the compiled arrays are copied
into the live model, so the env, its ``MjData`` and its renderer keep working on the same objects.

Contact changes (``ground_softness``, ``friction``) raise the floor's ``geom_priority`` above every other
geom: MuJoCo then takes the contact parameters from the floor alone instead of mixing them with the robot's
(friction would otherwise be the maximum of the two geoms and solref their average, so a slipperier or softer
floor could have no effect at all).
"""

import os
import warnings
import zlib
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

try:  # MuJoCo is an optional dependency: ``pip install "sb3_lifelong[mujoco]"``
    import mujoco
except ImportError:  # pragma: no cover - exercised only without the extra
    mujoco = None
except Exception as error:  # MuJoCo loads the OpenGL backend named by MUJOCO_GL at import, and fails without it
    raise ImportError(
        f"importing mujoco failed with MUJOCO_GL={os.environ.get('MUJOCO_GL')!r} "
        f"({type(error).__name__}: {error}): that backend's library is missing. Unset MUJOCO_GL: nothing here needs "
        "OpenGL except rendering, which picks a working backend itself (sb3_lifelong.envs.rendering)"
    ) from error


@dataclass(frozen=True)
class Perturbation:
    """
    Description of one named physical change.

    :param name: name used in stages, schedules and ``info["dynamics_params"]``
    :param unit: unit of the value
    :param description: what the value means physically
    :param low: smallest value that makes physical sense
    :param high: largest value that makes physical sense
    :param obs_scale: when the value is appended to the observation it is given as
        ``(value - nominal) / obs_scale``
    """

    name: str
    unit: str
    description: str
    low: float
    high: float
    obs_scale: float


PERTURBATIONS: Dict[str, Perturbation] = {
    p.name: p
    for p in [
        Perturbation(
            "hip_deformation",
            "rad",
            "rotation of the right hip (thigh) body's frame about the robot's hip axis, relative to its parent; "
            "the joint readings do not see it",
            -np.pi / 2,
            np.pi / 2,
            0.5,
        ),
        Perturbation(
            "foot_scale",
            "x nominal",
            "scale of the feet's contact geometry along the sole (box length and width, capsule length, sphere "
            "radius); mass and inertia follow when the feet have mass",
            0.1,
            5.0,
            1.0,
        ),
        Perturbation(
            "ground_softness",
            "s",
            "time constant of the floor contact (solref[0], damping ratio kept): larger is softer and sinks more",
            1e-4,
            1.0,
            0.05,
        ),
        Perturbation("friction", "1", "sliding friction coefficient of the floor contact", 0.0, 10.0, 1.0),
        Perturbation("mass_scale", "x nominal", "scale of every body's mass and inertia", 0.05, 20.0, 1.0),
        Perturbation("gravity", "m/s^2", "magnitude of gravity, along the model's gravity direction", 0.0, 100.0, 9.81),
        Perturbation(
            "actuator_strength",
            "x nominal",
            "scale of actuator torque: gear of torque motors, force limit of position servos",
            0.0,
            10.0,
            1.0,
        ),
        Perturbation("joint_damping", "x nominal", "scale of every joint's viscous damping", 0.0, 100.0, 1.0),
        Perturbation(
            "leg_motor_scale",
            "x nominal",
            "scale of the motors of one leg (the robot description's leg_joints: the right leg, HalfCheetah's back "
            "leg): torque of torque motors, force limit of position servos; below 0 the motors are reversed (a torque "
            "motor pushes the other way, a servo is sent to the mirrored angle)",
            -2.0,
            5.0,
            1.0,
        ),
        Perturbation(
            "joint_lock",
            "1",
            "share of one joint's range of motion taken away (the robot description's lock_joint: the right knee, "
            "HalfCheetah's back knee), shrinking the range toward the joint's reference angle; 1 locks the joint",
            0.0,
            1.0,
            1.0,
        ),
    ]
}

ALL_PERTURBATIONS: Tuple[str, ...] = tuple(PERTURBATIONS)
#: perturbations of one part of the robot, supported where its description names that part (``leg_joints``,
#: ``lock_joint``); the others act on the whole robot, its feet or the one deformed hip
LIMB_PERTURBATIONS: Tuple[str, ...] = ("leg_motor_scale", "joint_lock")


@dataclass(frozen=True)
class RobotDescription:
    """
    Which parts of a MuJoCo model the perturbations act on.

    :param name: robot name used in messages
    :param floor_geom: name of the floor geom
    :param foot_geoms: names of the feet's contact geoms
    :param hip_body: name of the body rotated by ``hip_deformation`` (the right thigh)
    :param hip_axis: axis of that rotation in the body's own frame
    :param perturbations: names of the perturbations that make sense for this robot
    :param leg_joints: the joints of one leg, whose motors ``leg_motor_scale`` scales (empty: not supported)
    :param lock_joint: the joint ``joint_lock`` locks (None: not supported)
    :param ranges: robot-specific physical ranges that replace the generic ones (``name -> (low, high)``)
    """

    name: str
    floor_geom: str
    foot_geoms: Tuple[str, ...]
    hip_body: str
    hip_axis: Tuple[float, float, float] = (1.0, 0.0, 0.0)
    perturbations: Tuple[str, ...] = ALL_PERTURBATIONS
    leg_joints: Tuple[str, ...] = ()
    lock_joint: Optional[str] = None
    ranges: Mapping[str, Tuple[float, float]] = field(default_factory=dict)


#: Robot descriptions, keyed by the class name of the unwrapped env. An env may instead carry its own
#: description as the attribute ``robot_description``.
ROBOTS: Dict[str, RobotDescription] = {
    "Walker2dEnv": RobotDescription(
        "Walker2d",
        "floor",
        ("foot_geom", "foot_left_geom"),
        "thigh",
        (0.0, 1.0, 0.0),
        leg_joints=("thigh_joint", "leg_joint", "foot_joint"),
        lock_joint="leg_joint",
    ),
    # one leg: leg_motor_scale acts on all three motors
    "HopperEnv": RobotDescription(
        "Hopper",
        "floor",
        ("foot_geom",),
        "thigh",
        (0.0, 1.0, 0.0),
        leg_joints=("thigh_joint", "leg_joint", "foot_joint"),
        lock_joint="leg_joint",
    ),
    # no left/right: the back leg plays the deformed hip, the weak or reversed leg and the locked knee
    "HalfCheetahEnv": RobotDescription(
        "HalfCheetah",
        "floor",
        ("bfoot", "ffoot"),
        "bthigh",
        (0.0, 1.0, 0.0),
        leg_joints=("bthigh", "bshin", "bfoot"),
        lock_joint="bshin",
    ),
    # Humanoid integrates with RK4 (damping is explicit): above ~3x nominal damping the simulation diverges
    "HumanoidEnv": RobotDescription(
        "Humanoid",
        "floor",
        ("right_foot", "left_foot"),
        "right_thigh",
        (1.0, 0.0, 0.0),
        leg_joints=("right_hip_x", "right_hip_z", "right_hip_y", "right_knee"),
        lock_joint="right_knee",
        ranges={"joint_damping": (0.0, 3.0)},
    ),
}

# model fields that field-edit perturbations write (restored from the nominal copy before every application)
_EDITED_FIELDS = (
    "geom_friction",
    "geom_solref",
    "geom_solimp",
    "geom_priority",
    "geom_condim",
    "geom_size",
    "geom_rbound",
    "geom_aabb",
    "body_quat",
    "body_mass",
    "body_inertia",
    "actuator_gear",
    "actuator_forcerange",
    "actuator_gainprm",
    "actuator_biasprm",
    "dof_damping",
    "jnt_range",
    "jnt_limited",
)


def _require_mujoco() -> None:
    if mujoco is None:  # pragma: no cover
        raise ImportError('Perturbations need MuJoCo: pip install "sb3_lifelong[mujoco]"')


def stable_seed(*parts: Any) -> int:
    """
    A seed that depends only on its arguments (not on Python's per-process hash salt).

    :param parts: values turned into text and hashed
    :return: a 32-bit seed
    """
    return zlib.crc32("/".join(str(p) for p in parts).encode())


def _model_arrays(model: Any) -> List[str]:
    return [n for n in dir(model) if not n.startswith("_") and isinstance(getattr(model, n), np.ndarray)]


@dataclass
class MujocoHandle:
    """
    The live MuJoCo objects of an env and how to rebuild its model.

    :param model: the ``mujoco.MjModel`` stepped by the env
    :param data: the matching ``mujoco.MjData``
    :param description: what the perturbations act on
    :param make_spec: returns a fresh ``mujoco.MjSpec`` of the nominal model (for recompiles); ``None`` if the
        model cannot be rebuilt
    """

    model: Any
    data: Any
    description: RobotDescription
    make_spec: Optional[Callable[[], Any]] = None
    extra: Dict[str, Any] = field(default_factory=dict)


def find_mujoco(env: Any) -> MujocoHandle:
    """
    Find the MuJoCo model, data and robot description behind a (wrapped) Gymnasium env.

    Works with Gymnasium's MuJoCo envs listed in :data:`ROBOTS` and with envs that expose ``model``,
    ``data`` and ``robot_description`` (optionally ``make_spec()``), like the OP3 and dm_control walker envs of
    this package.

    :param env: the env
    :return: the handle
    """
    _require_mujoco()
    base = getattr(env, "unwrapped", env)
    model, data = getattr(base, "model", None), getattr(base, "data", None)
    if not isinstance(model, mujoco.MjModel) or not isinstance(data, mujoco.MjData):
        raise TypeError(
            f"{type(base).__name__} is not a MuJoCo env (no `model`/`data` attributes of type mujoco.MjModel/MjData): "
            "dynamics perturbations need one"
        )
    description = getattr(base, "robot_description", None) or ROBOTS.get(type(base).__name__)
    if description is None:
        known = ", ".join(sorted(ROBOTS)) + ", OP3WalkEnv, DMCWalkerEnv"
        raise ValueError(
            f"No robot description for {type(base).__name__}: known envs are {known}. Give the env an attribute "
            "`robot_description` (sb3_lifelong.envs.RobotDescription) or add one to sb3_lifelong.envs.perturbations.ROBOTS"
        )
    make_spec = getattr(base, "make_spec", None)
    fullpath = getattr(base, "fullpath", None)
    if make_spec is None and isinstance(fullpath, str):

        def make_spec() -> Any:
            return mujoco.MjSpec.from_file(fullpath)

    return MujocoHandle(model, data, description, make_spec)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, a, b)
    return out


def _axis_angle_quat(axis: Sequence[float], angle: float) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_axisAngle2Quat(out, np.asarray(axis, dtype=np.float64), float(angle))
    return out


def _scaled_size(geom_type: int, size: np.ndarray, scale: float) -> np.ndarray:
    """Sole-wise scaling of a geom's size (length dimensions, not thickness)."""
    size = np.array(size, dtype=np.float64)
    if geom_type in (mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_ELLIPSOID):
        size[:2] *= scale
    elif geom_type in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
        size[1] *= scale
    elif geom_type == mujoco.mjtGeom.mjGEOM_SPHERE:
        size[0] *= scale
    else:
        raise ValueError(f"foot_scale cannot scale geoms of type {mujoco.mjtGeom(geom_type).name}")
    return size


class PhysicsEditor:
    """
    Applies a full set of perturbation values to a live MuJoCo model.

    Each call of :meth:`apply` starts again from the nominal model, so perturbations compose and a return to the
    nominal values gives back the nominal physics bit for bit.

    :param handle: the model, data and description (see :func:`find_mujoco`)
    """

    def __init__(self, handle: MujocoHandle) -> None:
        _require_mujoco()
        self.handle = handle
        self.model = handle.model
        self.data = handle.data
        self.description = desc = handle.description
        m = self.model
        # mj_setConst runs kinematics at qpos0 in the MjData it gets (it overwrites qpos): give it a scratch one so
        # that a change in the middle of an episode leaves the robot's state alone
        self._scratch = mujoco.MjData(m)
        self._floor = self._id(mujoco.mjtObj.mjOBJ_GEOM, desc.floor_geom)
        self._feet = [self._id(mujoco.mjtObj.mjOBJ_GEOM, name) for name in desc.foot_geoms]
        self._hip = self._id(mujoco.mjtObj.mjOBJ_BODY, desc.hip_body)
        leg = [self._id(mujoco.mjtObj.mjOBJ_JOINT, name) for name in desc.leg_joints]
        driven = [a for a in range(m.nu) if m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT]
        self._leg_actuators = [a for a in driven if int(m.actuator_trnid[a, 0]) in leg]
        if leg and not self._leg_actuators:
            raise ValueError(f"{desc.name}: no actuator drives the leg joints {desc.leg_joints}")
        self._lock = None if desc.lock_joint is None else self._id(mujoco.mjtObj.mjOBJ_JOINT, desc.lock_joint)
        if self._lock is not None and int(m.jnt_type[self._lock]) != int(mujoco.mjtJoint.mjJNT_HINGE):
            raise ValueError(f"{desc.name}: joint_lock needs a hinge joint, {desc.lock_joint!r} is not one")
        self._nominal = {name: getattr(m, name).copy() for name in _EDITED_FIELDS}
        self._nominal_gravity = m.opt.gravity.copy()
        # feet whose mass comes from their geometry need a recompile when they change size
        self._feet_have_mass = self._feet_have_geometric_mass()
        self._dirty: set = set()  # fields a recompile changed, restored with the edited fields
        self._compiled: Dict[float, Dict[str, np.ndarray]] = {}
        self._nominal_all: Optional[Dict[str, np.ndarray]] = None
        self.contact_nominal = self._effective_contact()
        self.nominal_params: Dict[str, float] = {
            "hip_deformation": 0.0,
            "foot_scale": 1.0,
            "ground_softness": float(self.contact_nominal["solref"][0]),
            "friction": float(self.contact_nominal["friction"][0]),
            "mass_scale": 1.0,
            "gravity": float(np.linalg.norm(self._nominal_gravity)),
            "actuator_strength": 1.0,
            "joint_damping": 1.0,
            "leg_motor_scale": 1.0,
            "joint_lock": 0.0,
        }
        parts = {"leg_motor_scale": bool(self._leg_actuators), "joint_lock": self._lock is not None}
        self.nominal_params = {k: v for k, v in self.nominal_params.items() if k in desc.perturbations and parts.get(k, True)}
        self.params: Dict[str, float] = dict(self.nominal_params)
        self.last_apply_recompiled = False

    # ------------------------------------------------------------------ helpers
    def _id(self, obj: Any, name: str) -> int:
        idx = mujoco.mj_name2id(self.model, obj, name)
        if idx < 0:
            raise ValueError(f"{self.description.name}: no {obj.name[6:].lower()} named {name!r} in the model")
        return int(idx)

    def _feet_have_geometric_mass(self) -> bool:
        """Whether a foot geom contributes mass (then resizing it must recompile)."""
        if self.handle.make_spec is None:
            return False
        spec = self.handle.make_spec()
        names = set(self.description.foot_geoms)
        for geom in spec.geoms:
            if geom.name in names:
                mass = geom.mass
                if not (np.isfinite(mass) and mass == 0.0):
                    return True
        return False

    def _effective_contact(self) -> Dict[str, np.ndarray]:
        """Contact parameters MuJoCo uses today between the floor and the first foot geom."""
        m, f, g = self.model, self._floor, self._feet[0]
        if m.geom_priority[f] != m.geom_priority[g]:
            win = f if m.geom_priority[f] > m.geom_priority[g] else g
            return {
                "friction": m.geom_friction[win].copy(),
                "solref": m.geom_solref[win].copy(),
                "solimp": m.geom_solimp[win].copy(),
                "condim": np.array(m.geom_condim[win]),
            }
        mix_f, mix_g = float(m.geom_solmix[f]), float(m.geom_solmix[g])
        w = 0.5 if mix_f + mix_g < mujoco.mjMINVAL else mix_f / (mix_f + mix_g)
        return {
            "friction": np.maximum(m.geom_friction[f], m.geom_friction[g]),
            "solref": w * m.geom_solref[f] + (1 - w) * m.geom_solref[g],
            "solimp": w * m.geom_solimp[f] + (1 - w) * m.geom_solimp[g],
            "condim": np.array(max(m.geom_condim[f], m.geom_condim[g])),
        }

    # ------------------------------------------------------------------ validation
    @property
    def supported(self) -> Tuple[str, ...]:
        """Names of the perturbations this robot supports."""
        return tuple(self.nominal_params)

    def valid_range(self, name: str) -> Tuple[float, float]:
        """
        Physically sensible range of one perturbation for this robot.

        :param name: perturbation name
        :return: ``(low, high)``
        """
        p = PERTURBATIONS[name]
        low, high = self.description.ranges.get(name, (p.low, p.high))
        if name == "ground_softness":
            # MuJoCo silently clamps time constants below two time steps
            low = max(low, 2 * float(self.model.opt.timestep))
        return low, high

    def allowed_text(self) -> str:
        """Human-readable list of the allowed perturbations, units and ranges."""
        items = []
        for name in self.supported:
            low, high = self.valid_range(name)
            unit = PERTURBATIONS[name].unit
            items.append(f"{name} [{unit}] in [{low:.4g}, {high:.4g}] (nominal {self.nominal_params[name]:.4g})")
        return "; ".join(items)

    def validate(self, params: Mapping[str, float], where: str = "") -> Dict[str, float]:
        """
        Check names and values; return them as floats.

        :param params: perturbation values
        :param where: context for error messages
        :return: the checked values
        """
        out = {}
        prefix = f"{where}: " if where else ""
        for name, value in params.items():
            if name not in self.nominal_params:
                raise ValueError(
                    f"{prefix}unknown dynamics parameter {name!r} for {self.description.name}. Allowed: {self.allowed_text()}"
                )
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise ValueError(f"{prefix}{name} must be a real number (not a bool or a string), got {value!r}")
            value = float(value)
            low, high = self.valid_range(name)
            if not (np.isfinite(value) and low <= value <= high):
                raise ValueError(
                    f"{prefix}{name}={value!r} {PERTURBATIONS[name].unit} is outside its physical range "
                    f"[{low:.4g}, {high:.4g}] for {self.description.name}. Allowed: {self.allowed_text()}"
                )
            out[name] = value
        return out

    # ------------------------------------------------------------------ application
    def apply(self, params: Mapping[str, float]) -> Dict[str, float]:
        """
        Set the model to the nominal robot changed by ``params`` (missing names take their nominal value).

        :param params: perturbation values
        :return: the full set of values now in effect
        """
        full = dict(self.nominal_params)
        full.update(self.validate(params))
        m, nom = self.model, self._nominal
        foot = full.get("foot_scale", 1.0)
        recompile = self._feet_have_mass and foot != 1.0
        # 1. back to the nominal model (or to a recompiled variant of it)
        if self._nominal_all is not None:
            for name in self._dirty:
                np.copyto(getattr(m, name), self._nominal_all[name])
        for name, value in nom.items():
            np.copyto(getattr(m, name), value)
        m.opt.gravity[:] = self._nominal_gravity
        if recompile:
            for name, value in self._compiled_arrays(foot).items():
                np.copyto(getattr(m, name), value)
        # 2. field edits
        if "foot_scale" in full and foot != 1.0 and not recompile:
            for g in self._feet:
                size = _scaled_size(int(m.geom_type[g]), nom["geom_size"][g], foot)
                m.geom_size[g] = size
                if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
                    m.geom_aabb[g, 3:] = size
                    m.geom_rbound[g] = float(np.linalg.norm(size))
                else:
                    m.geom_rbound[g] = nom["geom_rbound"][g] * foot
                    m.geom_aabb[g, 3:] = nom["geom_aabb"][g, 3:] * foot
        if full.get("hip_deformation", 0.0) != 0.0:
            turn = _axis_angle_quat(self.description.hip_axis, full["hip_deformation"])
            m.body_quat[self._hip] = _quat_mul(nom["body_quat"][self._hip], turn)
        soft, fric = full.get("ground_softness"), full.get("friction")
        if (soft is not None and soft != self.nominal_params["ground_softness"]) or (
            fric is not None and fric != self.nominal_params["friction"]
        ):
            f, c = self._floor, self.contact_nominal
            m.geom_priority[f] = int(nom["geom_priority"].max()) + 1
            m.geom_friction[f] = c["friction"]
            m.geom_solref[f] = c["solref"]
            m.geom_solimp[f] = c["solimp"]
            m.geom_condim[f] = int(c["condim"])
            if soft is not None:
                m.geom_solref[f, 0] = soft
            if fric is not None:
                m.geom_friction[f, 0] = fric
        if full.get("mass_scale", 1.0) != 1.0:
            m.body_mass[1:] *= full["mass_scale"]
            m.body_inertia[1:] *= full["mass_scale"]
        if "gravity" in full:
            g0 = self._nominal_gravity
            norm = float(np.linalg.norm(g0))
            direction = g0 / norm if norm > 0 else np.array([0.0, 0.0, -1.0])
            m.opt.gravity[:] = direction * full["gravity"]
        self._scale_motors_and_joints(full)
        mujoco.mj_setConst(m, self._scratch)
        self.params = full
        self.last_apply_recompiled = recompile
        return dict(full)

    def _scale_motors_and_joints(self, full: Mapping[str, float]) -> None:
        """The actuator and joint perturbations: strength of every motor, damping, one leg's motors, one joint's lock."""
        m = self.model
        if full.get("actuator_strength", 1.0) != 1.0:
            s = full["actuator_strength"]
            for a in range(m.nu):
                if m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE:
                    m.actuator_gear[a] *= s  # torque motor: torque per unit of control
                elif m.actuator_forcelimited[a]:
                    m.actuator_forcerange[a] *= s  # servo: maximum torque
                else:
                    m.actuator_gainprm[a, 0] *= s  # unlimited servo: stiffness
                    m.actuator_biasprm[a, 1:3] *= s
        if full.get("joint_damping", 1.0) != 1.0:
            m.dof_damping[:] *= full["joint_damping"]
        if full.get("leg_motor_scale", 1.0) != 1.0:
            self._scale_leg_motors(full["leg_motor_scale"])
        if full.get("joint_lock", 0.0) != 0.0:
            self._lock_joint(full["joint_lock"])

    def _scale_leg_motors(self, scale: float) -> None:
        """Scale one leg's motors by ``abs(scale)``; a negative ``scale`` also reverses them."""
        m = self.model
        for a in self._leg_actuators:
            if m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE:
                m.actuator_gear[a] *= scale  # torque motor: torque per unit of control, its sign reversed below 0
                continue
            # position servo (force = kp * ctrl - kp * q): reversing negates the commanded angle only; negating the
            # bias too would turn its feedback positive
            if scale < 0:
                m.actuator_gainprm[a, 0] *= -1
            if m.actuator_forcelimited[a]:
                m.actuator_forcerange[a] *= abs(scale)
            else:
                m.actuator_gainprm[a, 0] *= abs(scale)
                m.actuator_biasprm[a, 1:3] *= abs(scale)

    def _lock_joint(self, share: float) -> None:
        """Shrink the locked joint's range by ``share`` toward its reference angle (``qpos0``, clipped to the range)."""
        m, j = self.model, self._lock
        low, high = (float(x) for x in self._nominal["jnt_range"][j])
        if not self._nominal["jnt_limited"][j]:  # an unlimited hinge: its range is shrunk from +-pi
            low, high = -np.pi, np.pi
        reference = float(np.clip(m.qpos0[m.jnt_qposadr[j]], low, high))
        m.jnt_limited[j] = 1
        m.jnt_range[j] = [reference + (1 - share) * (low - reference), reference + (1 - share) * (high - reference)]

    def _compiled_arrays(self, foot: float) -> Dict[str, np.ndarray]:
        """Arrays of the model recompiled with scaled feet (cached per scale)."""
        if foot in self._compiled:
            return self._compiled[foot]
        if self.handle.make_spec is None:
            raise ValueError(f"{self.description.name}: foot_scale needs a recompile but the env has no model source")
        spec = self.handle.make_spec()
        names = set(self.description.foot_geoms)
        for geom in spec.geoms:
            if geom.name not in names:
                continue
            fromto = np.array(geom.fromto, dtype=np.float64)
            if np.all(np.isfinite(fromto)):
                a, b = fromto[:3], fromto[3:]
                c = (a + b) / 2
                geom.fromto = np.concatenate([c + foot * (a - c), c + foot * (b - c)])
            else:
                geom.size = _scaled_size(int(geom.type), np.array(geom.size), foot)
        with warnings.catch_warnings():  # e.g. deprecation notes about the env's own XML
            warnings.simplefilter("ignore")
            new = spec.compile()
        if self._nominal_all is None:
            # called right after apply() restored the nominal model: every array is nominal here
            self._nominal_all = {n: getattr(self.model, n).copy() for n in _model_arrays(self.model)}
        changed = {}
        for name, base in self._nominal_all.items():
            fresh = getattr(new, name)
            if base.shape != fresh.shape:
                raise RuntimeError(f"{self.description.name}: recompiled model changed the size of {name}")
            if not np.array_equal(base, fresh):
                changed[name] = np.array(fresh)
        self._dirty.update(n for n in changed if n not in self._nominal)
        self._compiled[foot] = changed
        return changed
