"""
Robots whose dynamics change: the :class:`DynamicsSchedule` wrapper, its schedulers, the perturbations, named stages
and the OP3 walking task.

Importing this module registers ``sb3_lifelong/OP3Walk-v0`` and ``sb3_lifelong/DMCWalker-v0`` with Gymnasium
(by entry-point string: MuJoCo, the menagerie and dm_control load only when an env is made).
"""

import gymnasium as gym

from sb3_lifelong.envs.perturbations import (
    PERTURBATIONS,
    ROBOTS,
    Perturbation,
    PhysicsEditor,
    RobotDescription,
    find_mujoco,
)
from sb3_lifelong.envs.schedule import (
    Constant,
    Cyclic,
    Drift,
    DynamicsSchedule,
    LinearRamp,
    RandomWalk,
    SawWave,
    Scheduler,
    UniformPerEpisode,
    stage_envs,
)
from sb3_lifelong.envs.stages import NAMED_STAGES, PAPER_STAGES

OP3_WALK_ID = "sb3_lifelong/OP3Walk-v0"
DMC_WALKER_ID = "sb3_lifelong/DMCWalker-v0"


def register_envs() -> None:
    """Register this package's envs with Gymnasium (done on import; safe to call again)."""
    if OP3_WALK_ID not in gym.registry:
        gym.register(id=OP3_WALK_ID, entry_point="sb3_lifelong.envs.op3:OP3WalkEnv", max_episode_steps=1000)
    if DMC_WALKER_ID not in gym.registry:
        # the suite ends its episodes itself (1000 control steps)
        gym.register(id=DMC_WALKER_ID, entry_point="sb3_lifelong.envs.dmc:DMCWalkerEnv")


register_envs()

__all__ = [
    "DMC_WALKER_ID",
    "NAMED_STAGES",
    "OP3_WALK_ID",
    "PAPER_STAGES",
    "PERTURBATIONS",
    "ROBOTS",
    "Constant",
    "Cyclic",
    "Drift",
    "DynamicsSchedule",
    "LinearRamp",
    "Perturbation",
    "PhysicsEditor",
    "RandomWalk",
    "RobotDescription",
    "SawWave",
    "Scheduler",
    "UniformPerEpisode",
    "find_mujoco",
    "register_envs",
    "stage_envs",
]
