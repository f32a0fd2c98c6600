"""
Helpers shared by the test files (imported as ``from testkit import ...``: pytest puts ``tests/`` on the path).

Test files never import from each other; what two of them need lives here or, as a fixture, in ``conftest.py``.
"""

import importlib.util
import pathlib
import types

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_lifelong.core.datasets import record_transitions

ROOT = pathlib.Path(__file__).resolve().parents[1]

#: the jobs of the tiny study every experiments test reads (the ``study`` fixture)
JOBS = [
    "collect",
    "distill_CRR_exp_beta1",
    "distill_CRR_indicator",
    "distill_CRR_indicator_A_only",
    "distill_BC",
    "distill_CRR_indicator_two_actors",
    "distill_CRR_indicator_ratio_1to10",
    "online_CRR_exp_beta1",
]


def benchmark_module(name: str) -> types.ModuleType:
    """:return: the benchmark or study script ``<name>.py`` found under ``benchmarks/``, imported"""
    found = sorted((ROOT / "benchmarks").rglob(f"{name}.py"))
    assert len(found) == 1, f"expected one benchmarks/**/{name}.py, found {found}"
    spec = importlib.util.spec_from_file_location(name, found[0])
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def pendulum_data(n: int = 400, seed: int = 0) -> dict:
    """Random-action Pendulum transitions (d4rl dict, actions in env units)."""
    rng = np.random.default_rng(seed)
    return record_transitions(gym.make("Pendulum-v1"), lambda obs: rng.uniform(-2, 2, size=1).astype(np.float32), n, seed)


def flat_params(model) -> th.Tensor:
    """:return: every parameter of the model's policy, and MPO's dual variables when it has them, in one vector"""
    tensors = [p.detach().flatten() for p in model.policy.parameters()]
    for name in ("log_temperature", "log_alpha_mean", "log_alpha_stddev"):
        if hasattr(model, name):
            tensors.append(getattr(model, name).detach().flatten())
    return th.cat(tensors)


class Recorder(BaseCallback):
    """Keeps the logger's values after every step."""

    def __init__(self):
        super().__init__()
        self.values: dict = {}

    def _on_step(self) -> bool:
        self.values.update(self.logger.name_to_value)
        return True
