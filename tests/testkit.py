"""
Helpers shared by the test files (imported as ``from testkit import ...``: pytest puts ``tests/`` on the path).

Test files never import from each other; what two of them need lives here or, as a fixture, in ``conftest.py``.
"""

import dataclasses
import importlib.util
import pathlib
import types

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_lifelong.buffers.manifest import FIELD_NAMES
from sb3_lifelong.core.datasets import record_transitions

ROOT = pathlib.Path(__file__).resolve().parents[1]

#: the claims files of the studies that test the paper's two-stage and three-stage claims (a study's claims are data
#: of its folder: ``sb3_lifelong.experiments.load_claims`` reads them)
PAPER_CLAIMS = ROOT / "benchmarks" / "studies" / "paper_cpu" / "claims.py"
THREE_STAGE_CLAIMS = ROOT / "benchmarks" / "studies" / "paper_cpu_three" / "claims.py"

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


def small_preset():
    """The tiny preset shortened to 60 + 60 steps: a whole collection in seconds (the ``small_collection`` fixture)."""
    import dataclasses

    from sb3_lifelong.experiments import PRESETS

    return dataclasses.replace(
        PRESETS["tiny"], stage_steps=(60, 60), learning_starts=30, eval_freq=60, distill_steps=20, distill_eval_freq=10
    )


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


def signature_defaults(function) -> dict:
    """:return: the parameters of ``function`` that have a default, with it"""
    import inspect

    return {n: p.default for n, p in inspect.signature(function).parameters.items() if p.default is not p.empty}


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


# the small buffer of the buffer tests: 3-dimensional observations, 2-dimensional actions
OBS = gym.spaces.Box(-10, 10, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)


def fill(buffer, steps, n_envs, seed=0, start=0, stage=None, rng=None):
    """Add `steps` add() calls of random transitions, with episode ends and timeouts."""
    rng = rng if rng is not None else np.random.default_rng(seed)
    for _ in range(steps):
        done = rng.random(n_envs) < 0.15
        trunc = done & (rng.random(n_envs) < 0.5)
        infos = [{"TimeLimit.truncated": bool(trunc[i])} for i in range(n_envs)]
        if stage is not None:
            for info in infos:
                info.update(stage=stage, dynamics_params={"mass": 1.0 + stage})
        buffer.add(
            rng.normal(size=(n_envs, 3)).astype(np.float32),
            rng.normal(size=(n_envs, 3)).astype(np.float32),
            rng.uniform(-1, 1, size=(n_envs, 2)).astype(np.float32),
            rng.normal(size=n_envs).astype(np.float32),
            done,
            infos,
        )


def all_rows(buffer):
    return {name: np.array(buffer.store.read_range(name, 0, buffer.size())) for name in FIELD_NAMES}


def shrink_screen(screen: types.ModuleType, monkeypatch, eval_freq: int) -> None:
    """
    The forgetting screen's script at seconds' scale, for the studies that build on it: one robot (HalfCheetah, 600
    steps of Env-A, every Env-A counted learnt), ``eval_freq``, one episode per evaluation, 400-step parts, tiny
    networks and 100-step episodes.
    """
    monkeypatch.setattr(screen, "ROBOTS", {"cheetah": screen.Robot("HalfCheetah-v5", 600, -1e9)})
    monkeypatch.setattr(screen, "EVAL_FREQ", eval_freq)
    monkeypatch.setattr(screen, "EVAL_EPISODES", 1)
    monkeypatch.setattr(screen, "SAME_EPISODES", 1)
    monkeypatch.setattr(screen, "PART", 400)
    full = screen.preset

    def small(candidate: str):
        return dataclasses.replace(full(candidate), net_arch=(16, 16), batch_size=32, num_samples=4, learning_starts=100,
                                   max_episode_steps=100)  # fmt: skip

    monkeypatch.setattr(screen, "preset", small)
