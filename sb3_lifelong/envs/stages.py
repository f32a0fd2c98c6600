"""
Named stages: settings of the dynamics parameters under a name, usable wherever
:class:`~sb3_lifelong.envs.DynamicsSchedule` takes a stage (``stages=["default", "hip_0.3"]``). The paper's OP3
environment changes are here: a right hip deformed by 0.2 or 0.3 rad, feet 1.2 or 1.6 times larger, and a softer
"ground texture 0.1", which we express as a floor contact time constant of 0.1 s (``ground_softness``; the nominal
OP3 floor contact has 0.004 s). Combine named stages by merging dicts, e.g.
``{**NAMED_STAGES["hip_0.3"], **NAMED_STAGES["foot_1.6"]}`` (the paper's Env-C of its second combination).
"""

from typing import Dict

NAMED_STAGES: Dict[str, Dict[str, float]] = {
    "default": {},
    "hip_0.2": {"hip_deformation": 0.2},
    "hip_0.3": {"hip_deformation": 0.3},
    "foot_1.2": {"foot_scale": 1.2},
    "foot_1.6": {"foot_scale": 1.6},
    "ground_0.1": {"ground_softness": 0.1},
    # the paper's three-environment combinations (Env-C of each)
    "hip_0.2+foot_1.6": {"hip_deformation": 0.2, "foot_scale": 1.6},
    "hip_0.3+foot_1.6": {"hip_deformation": 0.3, "foot_scale": 1.6},
    "foot_1.2+ground_0.1": {"foot_scale": 1.2, "ground_softness": 0.1},
}

#: the names of the paper's single changes, in the order of its figures
PAPER_STAGES = ("hip_0.2", "hip_0.3", "foot_1.2", "foot_1.6", "ground_0.1")
