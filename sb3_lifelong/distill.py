"""
Offline distillation: train a fresh student (CRR by default, or BC) on everything a robot has collected.

The second half of the Offline Distillation Pipeline: any off-policy collector (MPO, SAC, TD3, CRR) explores
online and keeps every transition; the whole lifetime buffer, with no task boundaries, is then distilled into one
policy offline.

This module sits above the algorithms (it imports them; none of them imports it). The algorithms' ``distill``
method reaches it through :func:`sb3_lifelong.common.base.set_distill_pipeline`, which importing this module
calls (the package's ``__init__`` does). ``sb3_lifelong.common.distill`` re-exports it under its old path.
"""

import os
import pathlib
from typing import Any, Optional, Union

from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import configure
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import MaybeCallback

from sb3_lifelong.buffers import LifelongReplayBuffer
from sb3_lifelong.common.base import set_distill_pipeline
from sb3_lifelong.crr import CRR

__all__ = ["DistillSource", "distill"]

DistillSource = Union[OffPolicyAlgorithm, ReplayBuffer, str, os.PathLike, dict]


def _is_buffer_directory(source: Any) -> bool:
    return isinstance(source, (str, os.PathLike)) and (pathlib.Path(source) / "manifest.json").is_file()


def distill(
    source: DistillSource,
    student_class: Optional[type] = None,
    gradient_steps: int = 100_000,
    policy: Any = "MlpPolicy",
    eval_env: Optional[Any] = None,
    eval_freq: int = 10_000,
    n_eval_episodes: int = 5,
    callback: MaybeCallback = None,
    log_interval: int = 1_000,
    tb_log_name: str = "distill",
    progress_bar: bool = False,
    eval_sources: Optional[dict[str, int]] = None,
    **student_kwargs: Any,
) -> Any:
    """
    Train a new policy offline on a collector's whole replay buffer (or on a buffer or dataset alone).

    :param source: an SB3 off-policy model (its replay buffer is used, e.g. MPO / SAC / TD3 with a
        ``LifelongReplayBuffer``), a replay buffer, the directory of a ``LifelongReplayBuffer`` on disk (opened
        read-only, so collection may go on in another process), or a d4rl-style dict / ``.npz`` path
    :param student_class: the offline algorithm (default :class:`sb3_lifelong.CRR`; :class:`sb3_lifelong.BC`
        for behaviour cloning), any class with ``from_offline_data`` and ``learn_offline``
    :param gradient_steps: number of offline gradient updates
    :param policy: the student's policy
    :param eval_env: environment(s) to evaluate the student on every ``eval_freq`` updates (a dict name -> env
        gives the names of the ``eval/<name>/mean_reward`` curves: Env-A, Env-B, ...)
    :param eval_freq: evaluation period, in updates
    :param n_eval_episodes: episodes per environment and evaluation
    :param callback: extra callback(s), called after every update
    :param log_interval: dump the training logs every this many updates
    :param tb_log_name: the name of the student's log folder; when ``source`` is a model that logs to
        tensorboard, the student logs into ``<the model's run>/<tb_log_name>``, beside the collection curves
    :param progress_bar: show a progress bar
    :param eval_sources: with ``actor_per_source=True`` (a CRR diagnostic): the source whose actor is evaluated in
        each environment of ``eval_env``, by name
    :param student_kwargs: the student's hyperparameters (``advantage_transform="exp"``, ``beta=1.0``,
        ``batch_size``, ``seed``, ``tensorboard_log``, ``verbose``, ...)
    :return: the trained student, ready for ``predict`` and ``save``
    """
    if student_class is None:
        student_class = CRR
    teacher: Optional[OffPolicyAlgorithm] = source if isinstance(source, OffPolicyAlgorithm) else None
    if teacher is not None:
        if teacher.replay_buffer is None or teacher.replay_buffer.size() == 0:
            raise ValueError(f"{type(teacher).__name__} has no data in its replay buffer to distil")
        data: Any = teacher.replay_buffer
        student_kwargs.setdefault("tensorboard_log", teacher.tensorboard_log)
        student_kwargs.setdefault("verbose", teacher.verbose)
        student_kwargs.setdefault("observation_space", teacher.observation_space)
        student_kwargs.setdefault("action_space", teacher.action_space)
    elif _is_buffer_directory(source):
        data = LifelongReplayBuffer.open(source, read_only=True)  # type: ignore[arg-type]
    else:
        data = source

    student = student_class.from_offline_data(data, policy=policy, **student_kwargs)  # type: ignore[attr-defined]

    teacher_dir = teacher.logger.get_dir() if teacher is not None and teacher._logger is not None else None
    if teacher is not None and teacher_dir is not None and teacher.tensorboard_log is not None:
        formats = ["csv", "tensorboard"] + (["stdout"] if student.verbose >= 1 else [])
        student.set_logger(configure(os.path.join(teacher_dir, tb_log_name), formats))
    student.learn_offline(
        gradient_steps,
        callback=callback,
        eval_env=eval_env,
        eval_freq=eval_freq,
        n_eval_episodes=n_eval_episodes,
        log_interval=log_interval,
        tb_log_name=tb_log_name,
        progress_bar=progress_bar,
        eval_sources=eval_sources,
    )
    return student


set_distill_pipeline(distill)
