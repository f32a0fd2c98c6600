"""
The checks of the arguments every off-policy algorithm of the package shares (SB3's ``OffPolicyAlgorithm`` stores
them unchecked, so that ``batch_size=-1`` failed later inside numpy and ``batch_size=0`` as a torch reduction error).
"""

from typing import Any, Callable

import numpy as np

__all__ = ["RULES", "check_off_policy_sizes", "check_sizes_of"]


def _is_integer(value: Any) -> bool:
    """:return: whether ``value`` is an integer (``int`` or numpy's; not a ``bool``)"""
    return not isinstance(value, bool) and hasattr(value, "__index__")


def _is_number(value: Any) -> bool:
    """:return: whether ``value`` is a real number (an integer or a float, numpy's too; not a ``bool``)"""
    return _is_integer(value) or isinstance(value, (float, np.floating))


#: each argument: whether it must be an integer (else any real number), the test of its value, and the rule in words
RULES: dict[str, tuple[bool, Callable[[Any], bool], str]] = {
    "batch_size": (True, lambda n: n >= 1, "must be an integer >= 1: the transitions of one gradient update"),
    "buffer_size": (True, lambda n: n >= 1, "must be an integer >= 1: the transitions the replay buffer holds"),
    "learning_starts": (False, lambda n: n >= 0, "must be >= 0: the environment steps before learning starts"),
    "gradient_steps": (
        True,
        lambda n: n >= 1 or n == -1,
        "must be an integer >= 1, or -1 for as many as the rollout's environment steps",
    ),
}


def check_off_policy_sizes(algorithm: str, **sizes: Any) -> None:
    """
    Refuse sizes an off-policy algorithm cannot run with, naming each argument and its value.

    :param algorithm: the algorithm's name, for the message (``"MPO"``, ...)
    :param sizes: any of ``batch_size`` (an integer >= 1), ``buffer_size`` (an integer >= 1), ``learning_starts``
        (>= 0) and ``gradient_steps`` (an integer >= 1, or -1: as many as the rollout's environment steps)
    :raises ValueError: ``Invalid MPO hyperparameters: batch_size=0 (must be an integer >= 1: ...)``, one clause per
        argument that is wrong
    :raises TypeError: for an argument this function does not check
    """
    unknown = sorted(set(sizes) - set(RULES))
    if unknown:
        raise TypeError(f"check_off_policy_sizes checks {sorted(RULES)}, not {unknown}")
    bad = []
    for name, value in sizes.items():
        integer, valid, rule = RULES[name]
        if not ((_is_integer(value) if integer else _is_number(value)) and valid(value)):
            bad.append(f"{name}={value!r} ({rule})")
    if bad:
        raise ValueError(f"Invalid {algorithm} hyperparameters: {'; '.join(bad)}")


def check_sizes_of(model: Any) -> None:
    """
    :func:`check_off_policy_sizes` of a model's ``batch_size``, ``buffer_size``, ``learning_starts`` and
    ``gradient_steps``, named by the model's class (called by MPO, CRR and BC at construction).

    :param model: an off-policy algorithm
    :raises ValueError: naming each argument that is wrong and its value
    """
    check_off_policy_sizes(type(model).__name__, **{name: getattr(model, name) for name in RULES})
