"""
Sizes an algorithm cannot run with are refused when it is built, each named with its value. Before, SB3 stored them
unchecked: ``batch_size=-1`` failed later inside numpy, ``batch_size=0`` as a torch reduction error or a NaN hint.
"""

import re

import numpy as np
import pytest
from gymnasium import spaces
from testkit import pendulum_data

from sb3_lifelong import BC, CRR, MPO
from sb3_lifelong.common.arguments import check_off_policy_sizes

ALGORITHMS = [MPO, CRR, BC]
#: Pendulum's action space
ACTIONS = spaces.Box(-2.0, 2.0, (1,), np.float32)
BATCH = "must be an integer >= 1: the transitions of one gradient update"
BUFFER = "must be an integer >= 1: the transitions the replay buffer holds"
STARTS = "must be >= 0: the environment steps before learning starts"
STEPS = "must be an integer >= 1, or -1 for as many as the rollout's environment steps"


def message(algorithm: type, *clauses: str) -> str:
    """:return: the exact message for these clauses, as a regular expression matching it whole"""
    return "^" + re.escape(f"Invalid {algorithm.__name__} hyperparameters: {'; '.join(clauses)}") + "$"


@pytest.mark.parametrize("algorithm", ALGORITHMS, ids=lambda algorithm: algorithm.__name__)
@pytest.mark.parametrize(
    "kwargs, clause",
    [
        ({"batch_size": 0}, f"batch_size=0 ({BATCH})"),
        ({"batch_size": -1}, f"batch_size=-1 ({BATCH})"),
        ({"batch_size": 32.0}, f"batch_size=32.0 ({BATCH})"),
        ({"buffer_size": 0}, f"buffer_size=0 ({BUFFER})"),
        ({"buffer_size": -5}, f"buffer_size=-5 ({BUFFER})"),
        ({"learning_starts": -1}, f"learning_starts=-1 ({STARTS})"),
        ({"gradient_steps": 0}, f"gradient_steps=0 ({STEPS})"),
        ({"gradient_steps": -2}, f"gradient_steps=-2 ({STEPS})"),
    ],
    ids=lambda value: str(value) if isinstance(value, dict) else "",
)
def test_a_wrong_size_is_refused_at_construction(algorithm, kwargs, clause):
    with pytest.raises(ValueError, match=message(algorithm, clause)):
        algorithm("MlpPolicy", "Pendulum-v1", **kwargs)


@pytest.mark.parametrize("algorithm", ALGORITHMS, ids=lambda algorithm: algorithm.__name__)
def test_every_wrong_size_is_named_at_once(algorithm):
    clauses = [f"batch_size=0 ({BATCH})", f"learning_starts=-3 ({STARTS})", f"gradient_steps=0 ({STEPS})"]
    with pytest.raises(ValueError, match=message(algorithm, *clauses)):
        algorithm("MlpPolicy", "Pendulum-v1", batch_size=0, learning_starts=-3, gradient_steps=0)


@pytest.mark.parametrize("algorithm", [CRR, BC], ids=lambda algorithm: algorithm.__name__)
def test_offline_construction_checks_the_batch_size_too(algorithm):
    with pytest.raises(ValueError, match=message(algorithm, f"batch_size=-1 ({BATCH})")):
        algorithm.from_offline_data(pendulum_data(50), action_space=ACTIONS, batch_size=-1)


@pytest.mark.parametrize("algorithm", ALGORITHMS, ids=lambda algorithm: algorithm.__name__)
def test_the_limits_themselves_are_accepted(algorithm):
    """batch_size and buffer_size 1, learning_starts 0 (a float too), gradient_steps -1 and numpy integers run."""
    env = "Pendulum-v1"
    model = algorithm("MlpPolicy", env, batch_size=np.int64(1), buffer_size=1, learning_starts=0.0, gradient_steps=-1)
    assert model.batch_size == 1 and model.gradient_steps == -1
    model = algorithm("MlpPolicy", env, batch_size=2, buffer_size=100, learning_starts=0, gradient_steps=1)
    model.learn(4)
    assert model.num_timesteps == 4


def test_the_check_refuses_arguments_it_does_not_know():
    with pytest.raises(TypeError, match=re.escape("check_off_policy_sizes checks ['batch_size', 'buffer_size', ")):
        check_off_policy_sizes("MPO", tau=2.0)
    check_off_policy_sizes("MPO", batch_size=1, buffer_size=1, learning_starts=0, gradient_steps=-1)  # no error
    with pytest.raises(ValueError, match=message(MPO, f"batch_size=True ({BATCH})")):
        check_off_policy_sizes("MPO", batch_size=True)  # a bool is not a size


def test_the_algorithms_own_checks_still_apply():
    with pytest.raises(ValueError, match=r"^Invalid MPO hyperparameters: num_samples=0 \("):
        MPO("MlpPolicy", "Pendulum-v1", num_samples=0)
    with pytest.raises(ValueError, match=r"^Invalid BC hyperparameters: loss='mse2' \(must be one of "):
        BC("MlpPolicy", "Pendulum-v1", loss="mse2")
