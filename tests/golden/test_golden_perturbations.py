"""
Golden values of the perturbation table (``sb3_lifelong.envs.perturbations.PERTURBATIONS``): the ranges, units and
observation scales users read in ``docs/modules/envs.md`` are the code's. First in the module's mutation set: most of
the table's mutants are module constants, which every test of the set would otherwise run for.
"""

import dataclasses
import pathlib
import re

import numpy as np
import pytest

from sb3_lifelong.envs import PERTURBATIONS

DOCS = pathlib.Path(__file__).resolve().parents[2] / "docs" / "modules" / "envs.md"


def test_the_docs_table_of_perturbations_is_the_codes() -> None:
    """``docs/modules/envs.md`` lists every perturbation with its unit, range and observation scale: each as in
    ``PERTURBATIONS`` (a range or scale changed in one place and not the other fails here)."""
    docs = DOCS.read_text()
    rows = re.findall(r"^\| `(\w+)` \| ([^|]+) \| [^|]+ \| \[([^,\]]+), ([^\]]+)\][^|]* \| ([^|]+) \|$", docs, re.M)
    number = {"pi": np.pi}
    table = {
        name: (unit.strip(), eval(low, {"__builtins__": {}}, number), eval(high, {"__builtins__": {}}, number), float(scale))
        for name, unit, low, high, scale in rows
    }
    assert list(table) == list(PERTURBATIONS)
    for name, p in PERTURBATIONS.items():
        assert table[name] == (p.unit, pytest.approx(p.low, rel=1e-12), pytest.approx(p.high, rel=1e-12), p.obs_scale), name
    with pytest.raises(dataclasses.FrozenInstanceError):
        PERTURBATIONS["friction"].low = -1.0  # type: ignore[misc]


def test_the_docs_table_of_robots_is_the_codes() -> None:
    """Each robot's row in ``docs/modules/envs.md`` (floor, feet, deformed hip and its axis, the weakened leg, the
    locked joint) is its ``RobotDescription``; Humanoid's damping range is the one the perturbation table gives."""
    from sb3_lifelong.envs.dmc import DMC_WALKER_DESCRIPTION
    from sb3_lifelong.envs.op3 import OP3_DESCRIPTION
    from sb3_lifelong.envs.perturbations import ROBOTS

    descriptions = {
        "`Walker2d-v5`": ROBOTS["Walker2dEnv"],
        "`Hopper-v5`": ROBOTS["HopperEnv"],
        "`HalfCheetah-v5`": ROBOTS["HalfCheetahEnv"],
        "`Humanoid-v5`": ROBOTS["HumanoidEnv"],
        "dm_control walker": DMC_WALKER_DESCRIPTION,
        "OP3 (": OP3_DESCRIPTION,
    }
    lines = DOCS.read_text().splitlines()
    axes = {(1.0, 0.0, 0.0): "x", (0.0, 1.0, 0.0): "y", (0.0, 0.0, 1.0): "z", (-1.0, 0.0, 0.0): "-x"}
    for start, robot in descriptions.items():
        (row,) = [line for line in lines if line.startswith(f"| {start}") and line.count("|") == 9]
        cells = [cell.strip() for cell in row.split("|")[1:-1]]
        names = [re.findall(r"`(\w+)`", cell) for cell in cells]
        assert names[1] == [robot.floor_geom], start
        assert names[2] in ([], list(robot.foot_geoms)), start  # OP3's four soles are described, not named
        assert names[3] == [robot.hip_body] and re.search(r"\((-?[xyz])\b", cells[3]).group(1) == axes[robot.hip_axis]
        assert names[6] == list(robot.leg_joints) and names[7] == [robot.lock_joint], start
        assert set(robot.perturbations) == set(PERTURBATIONS), start  # "all ten apply to each"
    assert ROBOTS["HumanoidEnv"].ranges == {"joint_damping": (0.0, 3.0)}
    assert "(Humanoid: [0, 3], RK4 diverges above)" in DOCS.read_text()
    assert all(not robot.ranges for name, robot in ROBOTS.items() if name != "HumanoidEnv")
