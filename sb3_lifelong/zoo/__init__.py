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

Each run gets its own lifetime buffer: the ``path`` of a ``LifelongReplayBuffer``'s ``replay_buffer_kwargs`` may hold
``{seed}``, ``{run}`` (the run's folder name, e.g. ``Hopper-v5_2``), ``{env}`` and ``{algo}``, and a relative path
is a folder of the run's log folder (``logs/mpo/Hopper-v5_2/lifetime``): see :func:`run_buffer_path`. Continuing
a run (``-i logs/.../Hopper-v5.zip``) reattaches the buffer the model was saved with; each ``-optimize`` trial gets
a folder of its own under the path (``trial_<number>``).

Needs ``pip install "sb3_lifelong[extra]"`` (or ``pip install rl_zoo3``).
"""

import functools
import os
import pathlib
import string
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

__all__ = ["ALGORITHMS", "HYPERPARAMS", "PRESETS", "StageEvalCallback", "hyperparams_file", "register", "run_buffer_path"]

#: the zoo's names of this package's algorithms (online use: CRR learns online too, from its own replay buffer)
ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"mpo": MPO, "crr": CRR}
HYPERPARAMS = pathlib.Path(__file__).parent / "hyperparams"
#: the names a hyperparameter file's Python strings (``replay_buffer_class``, ``replay_buffer_kwargs``,
#: ``policy_kwargs``) may use besides the zoo's own: the zoo evaluates them in its module ``rl_zoo3.exp_manager``
ZOO_NAMES: dict[str, Any] = {"sb3_lifelong": sb3_lifelong, "LifelongReplayBuffer": LifelongReplayBuffer}


#: the named presets of each algorithm that have a hyperparameter file of their own (``--conf-file`` / ``-conf``)
PRESETS: dict[str, tuple[str, ...]] = {"mpo": ("acme",), "crr": ()}


def hyperparams_file(algo: str, preset: Optional[str] = None) -> pathlib.Path:
    """
    :param algo: ``mpo`` or ``crr``
    :param preset: None for the package's defaults (the file ``train`` uses without ``-conf``), or a named preset
        (:data:`PRESETS`: ``"acme"`` is MPO at Acme's MuJoCo baseline, :func:`sb3_lifelong.mpo.presets.acme_mujoco`)
    :return: this package's hyperparameter file for ``algo``
    """
    if algo not in ALGORITHMS:
        raise ValueError(f"no hyperparameters for {algo!r} here: this package adds {sorted(ALGORITHMS)} to the zoo")
    if preset is None:
        return HYPERPARAMS / f"{algo}.yml"
    if preset not in PRESETS[algo]:
        raise ValueError(f"no preset {preset!r} for {algo}: the presets are {list(PRESETS[algo])}")
    return HYPERPARAMS / f"{algo}_{preset}.yml"


#: the names a hyperparameter file's buffer ``path`` may use (:func:`run_buffer_path`)
PATH_FIELDS = ("seed", "run", "env", "algo")


def run_buffer_path(path: Any, save_path: str, seed: Any, algo: str, env: str) -> str:
    """
    The directory of a run's lifetime buffer, from the ``path`` of a hyperparameter file's ``replay_buffer_kwargs``:
    ``{seed}``, ``{run}`` (the name of the run's folder, e.g. ``Hopper-v5_2``), ``{env}`` and ``{algo}`` are filled
    in, and a relative path is taken in the run's folder, so that two runs of one file never share a buffer (the second
    would refuse to add to the first's). An absolute path without ``{seed}`` or ``{run}`` is the same for every run.

    :param path: The ``path`` in the file
    :param save_path: The run's folder (``logs/mpo/Hopper-v5_2``)
    :param seed: The run's ``--seed``
    :param algo: The run's ``--algo``
    :param env: The run's ``--env``
    :return: The directory
    :raises ValueError: for a ``{name}`` that is not one of :data:`PATH_FIELDS`
    """
    text = os.fspath(path)
    values = {"seed": seed, "run": os.path.basename(os.path.normpath(save_path)), "env": env, "algo": algo}
    for _, name, _, _ in string.Formatter().parse(text):
        if name is not None and name not in PATH_FIELDS:
            allowed = ", ".join(f"{{{field}}}" for field in PATH_FIELDS)
            raise ValueError(f"replay_buffer_kwargs path {text!r} names {{{name}}}: a buffer path may use {allowed}")
    text = text.format(**values)
    return text if os.path.isabs(text) else os.path.join(save_path, text)


def _buffer_kwargs(hyperparams: Mapping[str, Any]) -> Optional[dict[str, Any]]:
    """The ``replay_buffer_kwargs`` of a ``LifelongReplayBuffer`` directory in processed hyperparameters, or None."""
    buffer_class, kwargs = hyperparams.get("replay_buffer_class"), hyperparams.get("replay_buffer_kwargs")
    if isinstance(buffer_class, type) and issubclass(buffer_class, LifelongReplayBuffer) and isinstance(kwargs, dict):
        if kwargs.get("path") is not None:
            return kwargs
    return None


def _preprocess_hyperparams(original: Any, manager: Any, hyperparams: dict[str, Any]) -> Any:
    """rl-zoo3's ``ExperimentManager._preprocess_hyperparams``, then the run's own buffer path (or, for ``-i``, the
    saved model's buffer: its kwargs are left to the zip, so that learn() reattaches it)."""
    processed = original(manager, hyperparams)
    kwargs = _buffer_kwargs(processed[0])
    if kwargs is not None:
        if manager.continue_training:
            del processed[0]["replay_buffer_kwargs"]
        else:
            name = manager.env_name.gym_id
            kwargs["path"] = run_buffer_path(kwargs["path"], manager.save_path, manager.seed, manager.algo, name)
    return processed


def _objective(original: Any, manager: Any, trial: Any) -> Any:
    """rl-zoo3's ``ExperimentManager.objective``, each trial with a buffer folder of its own (``trial_<number>``)."""
    kwargs = _buffer_kwargs(manager._hyperparams)
    if kwargs is None:
        return original(manager, trial)
    hyperparams = manager._hyperparams
    own = dict(kwargs, path=os.path.join(kwargs["path"], f"trial_{trial.number}"))
    manager._hyperparams = {**hyperparams, "replay_buffer_kwargs": own}
    try:
        return original(manager, trial)
    finally:
        manager._hyperparams = hyperparams


def _patch(cls: type, name: str, wrapper: Any) -> None:
    """Wrap a method of rl-zoo3's ``ExperimentManager`` once (register() may be called again)."""
    original = getattr(cls, name)
    if getattr(original, "_sb3_lifelong", False):
        return

    @functools.wraps(original)
    def patched(self: Any, *args: Any) -> Any:
        return wrapper(original, self, *args)

    patched._sb3_lifelong = True  # type: ignore[attr-defined]
    setattr(cls, name, patched)


def register() -> None:
    """
    Make rl-zoo3 accept this package: MPO and CRR in its algorithm table (``rl_zoo3.ALGOS``), their samplers for
    ``-optimize`` (``HYPERPARAMS_SAMPLER`` and ``HYPERPARAMS_CONVERTER``), and the names of :data:`ZOO_NAMES` in the
    namespace where the zoo evaluates a hyperparameter file's strings, so that
    ``replay_buffer_class: sb3_lifelong.LifelongReplayBuffer`` works as ``replay_buffer_class: HerReplayBuffer`` does;
    and each run its own lifetime buffer (:func:`run_buffer_path`; ``-i`` reattaches the saved model's buffer, and each
    ``-optimize`` trial gets a folder of its own). Safe to call again.
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
    _patch(exp_manager.ExperimentManager, "_preprocess_hyperparams", _preprocess_hyperparams)
    _patch(exp_manager.ExperimentManager, "objective", _objective)


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
