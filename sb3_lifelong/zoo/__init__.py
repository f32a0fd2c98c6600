"""
Use this package's algorithms from `rl-zoo3 <https://github.com/DLR-RM/rl-baselines3-zoo>`_, the training framework
of SB3 users: :func:`register` adds them to the zoo's algorithm table, and ``python -m sb3_lifelong.zoo`` runs the
zoo's own ``train`` / ``enjoy`` commands with them and with this package's hyperparameter files::

    python -m sb3_lifelong.zoo train --algo mpo --env Hopper-v5 -f logs/
    python -m sb3_lifelong.zoo enjoy --algo mpo --env Hopper-v5 -f logs/

Needs ``pip install "sb3_lifelong[extra]"`` (or ``pip install rl_zoo3``).
"""

import pathlib

from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_lifelong.crr import CRR
from sb3_lifelong.mpo import MPO

#: the zoo's names of this package's algorithms (online use: CRR learns online too, from its own replay buffer)
ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"mpo": MPO, "crr": CRR}
HYPERPARAMS = pathlib.Path(__file__).parent / "hyperparams"


def hyperparams_file(algo: str) -> pathlib.Path:
    """:return: this package's hyperparameter file for ``algo`` (``mpo`` or ``crr``)"""
    if algo not in ALGORITHMS:
        raise ValueError(f"no hyperparameters for {algo!r} here: this package adds {sorted(ALGORITHMS)} to the zoo")
    return HYPERPARAMS / f"{algo}.yml"


def register() -> None:
    """Add MPO and CRR to rl-zoo3's algorithm table (``rl_zoo3.ALGOS``), so that its commands accept them."""
    try:
        from rl_zoo3 import ALGOS
    except ImportError as error:
        raise ImportError("rl-zoo3 is not installed: pip install rl_zoo3 (or sb3_lifelong[extra])") from error
    ALGOS.update(ALGORITHMS)
