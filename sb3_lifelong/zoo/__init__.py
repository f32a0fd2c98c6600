"""
Use this package's algorithms from `rl-zoo3 <https://github.com/DLR-RM/rl-baselines3-zoo>`_, the training framework
of SB3 users: :func:`register` adds them to the zoo's algorithm table, and ``python -m sb3_lifelong.zoo`` runs the
zoo's own ``train`` / ``enjoy`` / ``record-video`` / plot commands with them and with this package's hyperparameter
files::

    python -m sb3_lifelong.zoo train --algo mpo --env Hopper-v5 -f logs/
    python -m sb3_lifelong.zoo enjoy --algo mpo --env Hopper-v5 -f logs/

A hyperparameter file may name this package's classes, as the zoo's files name SB3's
(``replay_buffer_class: sb3_lifelong.LifelongReplayBuffer``, ``env_wrapper: sb3_lifelong.envs.DynamicsSchedule``,
``callback: sb3_lifelong.zoo.StageEvalCallback``); ``-optimize`` searches MPO's and CRR's spaces
(:mod:`sb3_lifelong.zoo.optimize`).

Needs ``pip install "sb3_lifelong[extra]"`` (or ``pip install rl_zoo3``).
"""

import pathlib
from collections.abc import Mapping, Sequence
from typing import Any, Optional

from stable_baselines3.common.base_class import BaseAlgorithm

import sb3_lifelong
from sb3_lifelong.buffers import LifelongReplayBuffer
from sb3_lifelong.crr import CRR
from sb3_lifelong.envs import stage_envs
from sb3_lifelong.evaluation.callbacks import MultiEnvEvalCallback
from sb3_lifelong.mpo import MPO
from sb3_lifelong.zoo.optimize import CONVERTERS, SAMPLERS

__all__ = ["ALGORITHMS", "HYPERPARAMS", "StageEvalCallback", "hyperparams_file", "register"]

#: the zoo's names of this package's algorithms (online use: CRR learns online too, from its own replay buffer)
ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"mpo": MPO, "crr": CRR}
HYPERPARAMS = pathlib.Path(__file__).parent / "hyperparams"
#: the names a hyperparameter file's Python strings (``replay_buffer_class``, ``replay_buffer_kwargs``,
#: ``policy_kwargs``) may use besides the zoo's own: the zoo evaluates them in its module ``rl_zoo3.exp_manager``
ZOO_NAMES: dict[str, Any] = {"sb3_lifelong": sb3_lifelong, "LifelongReplayBuffer": LifelongReplayBuffer}


def hyperparams_file(algo: str) -> pathlib.Path:
    """:return: this package's hyperparameter file for ``algo`` (``mpo`` or ``crr``)"""
    if algo not in ALGORITHMS:
        raise ValueError(f"no hyperparameters for {algo!r} here: this package adds {sorted(ALGORITHMS)} to the zoo")
    return HYPERPARAMS / f"{algo}.yml"


def register() -> None:
    """
    Make rl-zoo3 accept this package: MPO and CRR in its algorithm table (``rl_zoo3.ALGOS``), their samplers for
    ``-optimize`` (``HYPERPARAMS_SAMPLER`` and ``HYPERPARAMS_CONVERTER``), and the names of :data:`ZOO_NAMES` in the
    namespace where the zoo evaluates a hyperparameter file's strings, so that
    ``replay_buffer_class: sb3_lifelong.LifelongReplayBuffer`` works as ``replay_buffer_class: HerReplayBuffer`` does.
    Safe to call again.
    """
    try:
        from rl_zoo3 import ALGOS, exp_manager, hyperparams_opt
    except ImportError as error:
        raise ImportError("rl-zoo3 is not installed: pip install rl_zoo3 (or sb3_lifelong[extra])") from error
    ALGOS.update(ALGORITHMS)
    hyperparams_opt.HYPERPARAMS_SAMPLER.update(SAMPLERS)
    hyperparams_opt.HYPERPARAMS_CONVERTER.update(CONVERTERS)
    for name, value in ZOO_NAMES.items():
        vars(exp_manager).setdefault(name, value)


class StageEvalCallback(MultiEnvEvalCallback):
    """
    For hyperparameter files: evaluate on every stage of a :class:`~sb3_lifelong.envs.DynamicsSchedule` run, one
    pinned copy of the robot per stage (:func:`~sb3_lifelong.envs.stage_envs`), logging ``eval/<name>/mean_reward``.
    The zoo's own evaluation env counts its own steps, so it never leaves the first stage: run with
    ``--eval-freq -1`` and this callback instead::

        callback:
          - sb3_lifelong.zoo.StageEvalCallback:
              env_id: Walker2d-v5
              stages: [{}, {hip_deformation: 0.3}]
              append_params: true
              eval_freq: 20000

    :param env_id: the robot's gym id (the training env's)
    :param stages: the ``DynamicsSchedule`` wrapper's stages
    :param names: the name of each stage in the logs (default ``Env-A``, ``Env-B``, ...)
    :param append_params: the wrapper's ``append_params``
    :param observed_params: the wrapper's ``observed_params``
    :param env_kwargs: keyword arguments of ``gym.make``
    :param kwargs: :class:`~sb3_lifelong.evaluation.callbacks.MultiEnvEvalCallback`'s (``eval_freq``,
        ``n_eval_episodes``, ``log_path``, ``best_model_save_path``, ``seed``, ``verbose``, ...)
    """

    def __init__(
        self,
        env_id: str,
        stages: Sequence[Any],
        names: Optional[Sequence[str]] = None,
        append_params: bool = False,
        observed_params: Optional[Sequence[str]] = None,
        env_kwargs: Optional[Mapping[str, Any]] = None,
        **kwargs: Any,
    ):
        envs = stage_envs(
            env_id, stages, names, env_kwargs=env_kwargs, append_params=append_params, observed_params=observed_params
        )
        super().__init__(envs, **kwargs)
