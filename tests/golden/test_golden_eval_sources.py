"""
Golden per-source evaluations (issue "Tests that check values, not a path against itself"): with CRR's
``actor_per_source=True``, ``learn_offline(eval_env=..., eval_sources=...)`` and ``distill(..., eval_sources=...)``
evaluate each environment with the actor of its own source.

Each source's actor is set by hand to a constant action, ``tanh(b_k)`` (its output layer's weights zero, its bias
``b_k``), and the learning rate is zero so that no update moves it. The evaluation environments record every action
they receive and reward its first component, so the expected actions and mean returns are ``tanh`` of the biases,
computed here with NumPy. The sources are 1 and 4 (not 0 and 1: a source id used as an actor's index would not
exist), and env ``"a"`` is mapped to the *second* source, so that a routing which ignores ``eval_sources``, uses the
first actor everywhere, or follows the environments' order gives other numbers.
"""

from typing import Any, Optional

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback

from sb3_lifelong import CRR, LifelongReplayBuffer
from sb3_lifelong.crr.policies import PerSourceActor
from sb3_lifelong.distill import distill
from sb3_lifelong.evaluation.callbacks import MultiEnvEvalCallback

OBS = spaces.Box(-1.0, 1.0, (3,), np.float32)
ACT = spaces.Box(-1.0, 1.0, (2,), np.float32)
#: source id -> the bias of its actor's output layer (the actors' heads are in the order of the sorted source ids)
BIASES = {1: np.array([0.5, -0.2]), 4: np.array([-0.9, 0.3])}
#: evaluation env -> the source whose actor must act in it: "a" (listed first) gets the second source
EVAL_SOURCES = {"a": 4, "b": 1}
UPDATES, EVAL_FREQ, EPISODES = 4, 2, 2


class ActionRevealingEnv(gym.Env):
    """One-step episodes from a random observation, rewarded with the action's first component; records the actions."""

    observation_space = OBS
    action_space = ACT

    def __init__(self) -> None:
        self.actions: list[np.ndarray] = []

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return self.np_random.uniform(-1, 1, 3).astype(np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.actions.append(np.array(action, dtype=np.float64))
        return np.zeros(3, np.float32), float(action[0]), True, False, {}


def two_source_buffer(n: int = 40) -> LifelongReplayBuffer:
    rng = np.random.default_rng(0)
    buffer = LifelongReplayBuffer(10, OBS, ACT, device="cpu")
    for source in BIASES:
        buffer.set_source(source, name=f"source_{source}")
        for _ in range(n):
            obs = rng.uniform(-1, 1, (1, 3)).astype(np.float32)
            action = rng.uniform(-1, 1, (1, 2)).astype(np.float32)
            buffer.add(obs, obs, action, rng.normal(size=1), np.zeros(1), [{}])
    return buffer


class ConstantActors(BaseCallback):
    """At the start of training, sets each source's actor to the constant mean ``tanh(BIASES[source])``."""

    def _on_training_start(self) -> None:
        model: Any = self.model
        assert model.source_ids == sorted(BIASES)  # the actors' order: the sorted source ids (documented)
        assert isinstance(model.actor, PerSourceActor)
        for head, source in enumerate(sorted(BIASES)):
            actor = model.actor.head(head)
            with th.no_grad():
                actor.mu.weight.zero_()
                actor.mu.bias.copy_(th.as_tensor(BIASES[source], dtype=th.float32))

    def _on_step(self) -> bool:
        return True


@pytest.fixture
def evaluations(monkeypatch) -> list[dict[str, float]]:
    """The mean return per environment of every evaluation that a ``MultiEnvEvalCallback`` makes (its own result)."""
    seen: list[dict[str, float]] = []
    evaluate = MultiEnvEvalCallback.evaluate

    def recording_evaluate(self: MultiEnvEvalCallback) -> dict[str, float]:
        means = evaluate(self)
        seen.append(dict(means))
        return means

    monkeypatch.setattr(MultiEnvEvalCallback, "evaluate", recording_evaluate)
    return seen


def student_kwargs() -> dict[str, Any]:
    # learning_rate=0: the hand-set actors stay as they are through the updates between the evaluations (with one
    # actor per source the update is eager: no compilation to switch off)
    return dict(
        actor_per_source=True,
        policy_kwargs=dict(net_arch=[8]),
        batch_size=16,
        num_samples=2,
        learning_rate=0.0,
        seed=0,
        device="cpu",
    )


def check_evaluations(envs: dict[str, ActionRevealingEnv], evaluations: list[dict[str, float]]) -> None:
    """Every action env ``name`` received is ``tanh`` of its source's bias; every evaluation's mean return its first part."""
    expected = {name: np.tanh(BIASES[source]) for name, source in EVAL_SOURCES.items()}
    assert not np.allclose(expected["a"], expected["b"])  # the two actors are told apart
    n_evaluations = UPDATES // EVAL_FREQ
    for name, env in envs.items():
        assert len(env.actions) == n_evaluations * EPISODES
        np.testing.assert_allclose(np.stack(env.actions), np.tile(expected[name], (len(env.actions), 1)), atol=1e-6)
    assert len(evaluations) == n_evaluations
    for means in evaluations:
        assert set(means) == set(EVAL_SOURCES)
        for name, mean in means.items():
            assert mean == pytest.approx(expected[name][0], abs=1e-6)


def test_learn_offline_evaluates_each_env_with_its_sources_actor(evaluations: list[dict[str, float]]) -> None:
    """
    ``learn_offline(eval_env, eval_sources)``: env "a" is played by source 4's actor and env "b" by source 1's. Fails
    if eval_sources is not passed to the evaluation, or if every env is evaluated with the first (or the active)
    actor, or with the actor at the source id's position.
    """
    model = CRR.from_offline_data(two_source_buffer(), **student_kwargs())
    envs = {"a": ActionRevealingEnv(), "b": ActionRevealingEnv()}
    model.select_source(4)  # the model's own choice, not the last evaluated env's ("b": 1)
    model.learn_offline(
        UPDATES,
        callback=ConstantActors(),
        eval_env=envs,
        eval_freq=EVAL_FREQ,
        n_eval_episodes=EPISODES,
        log_interval=0,
        eval_sources=EVAL_SOURCES,
    )
    assert model.num_timesteps == UPDATES
    check_evaluations(envs, evaluations)
    assert model.active_source == 4  # the model's own choice of actor is restored after the evaluations
    # and predict then acts with source 4's actor
    action, _ = model.predict(np.zeros(3, np.float32), deterministic=True)
    np.testing.assert_allclose(action, np.tanh(BIASES[4]), atol=1e-6)


def test_distill_evaluates_each_env_with_its_sources_actor(evaluations: list[dict[str, float]]) -> None:
    """
    ``distill(buffer, CRR, eval_env, eval_sources, actor_per_source=True)``: the same per-source routing through the
    distillation pipeline. Fails if distill drops eval_sources on the way to learn_offline (every env then gets the
    default, first actor: source 1's in env "a" too).
    """
    envs = {"a": ActionRevealingEnv(), "b": ActionRevealingEnv()}
    student = distill(
        two_source_buffer(),
        CRR,
        total_updates=UPDATES,
        eval_env=envs,
        eval_freq=EVAL_FREQ,
        n_eval_episodes=EPISODES,
        callback=ConstantActors(),
        log_interval=0,
        eval_sources=EVAL_SOURCES,
        **student_kwargs(),
    )
    assert isinstance(student, CRR) and student.num_timesteps == UPDATES
    check_evaluations(envs, evaluations)
