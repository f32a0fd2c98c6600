"""
The Offline Distillation Pipeline, given the student's class: train a fresh student on everything a robot has
collected, offline.

Any off-policy collector (MPO, SAC, TD3, CRR) explores online and keeps every transition; the whole lifetime buffer,
with no task boundaries, is then distilled into one policy. :meth:`LifelongOffPolicyAlgorithm.distill
<sb3_lifelong.common.base.LifelongOffPolicyAlgorithm.distill>` calls it with the model as the source;
:func:`sb3_lifelong.distill.distill` (above the algorithms) is the same with CRR as the default student. It needs no
algorithm of the package: the student class is given.
"""

import inspect
import os
from typing import Any, Optional, Union

import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import (
    CSVOutputFormat,
    HumanOutputFormat,
    JSONOutputFormat,
    Logger,
    TensorBoardOutputFormat,
    make_output_format,
)
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import MaybeCallback, Schedule

__all__ = ["DistillSource", "distill"]

DistillSource = Union[OffPolicyAlgorithm, ReplayBuffer, str, os.PathLike, dict]


def _format_names(logger: Logger) -> set[str]:
    """:return: the names (as ``configure`` takes them) of the output formats of ``logger``"""
    names = set()
    for output in logger.output_formats:
        if isinstance(output, HumanOutputFormat):
            names.add("log" if getattr(output, "own_file", False) else "stdout")
        elif isinstance(output, CSVOutputFormat):
            names.add("csv")
        elif isinstance(output, JSONOutputFormat):
            names.add("json")
        elif isinstance(output, TensorBoardOutputFormat):
            names.add("tensorboard")
    return names


def _logger_beside(teacher: OffPolicyAlgorithm, tb_log_name: str, verbose: int) -> Optional[Logger]:
    """
    The student's logger in ``<the teacher's log folder>/<tb_log_name>``, with the teacher's output formats (CSV
    too, and stdout when ``verbose >= 2``), when the teacher logs somewhere: to ``tensorboard_log``, or to a logger
    the user gave it with ``set_logger``. None when the teacher has no logger of its own to follow.
    """
    if teacher._logger is None or (teacher.tensorboard_log is None and not teacher._custom_logger):
        return None
    formats = _format_names(teacher.logger)
    if teacher.tensorboard_log is not None:
        formats |= {"csv", "tensorboard"}
    if verbose >= 2:  # SB3's tables of the training values (verbose=1 prints the evaluations, one line each)
        formats.add("stdout")
    teacher_dir = teacher.logger.get_dir()
    if teacher_dir is None:  # a logger with no folder (stdout only): the student prints, as the teacher does
        return Logger(None, [make_output_format("stdout", "")] if "stdout" in formats else [])
    folder = os.path.join(teacher_dir, tb_log_name)
    os.makedirs(folder, exist_ok=True)
    return Logger(folder, [make_output_format(name, folder) for name in sorted(formats)])


def _describe(buffer: Any) -> str:
    """:return: the size of ``buffer``, per source when it knows its sources"""
    counts = buffer.source_counts() if hasattr(buffer, "source_counts") else None
    if not counts:
        return f"{buffer.size():,} transitions"
    sources = getattr(buffer, "sources", {})
    per_source = ", ".join(
        f"{sources.get(source, {}).get('name', f'source {source}')}: {count:,}" for source, count in sorted(counts.items())
    )
    return f"{sum(counts.values()):,} transitions ({per_source})"


# what from_offline_data takes besides the constructor's arguments
_FROM_OFFLINE_DATA = {"observation_space", "action_space", "normalized_actions", "env"}


def _check_student_arguments(student_class: type, student_kwargs: dict[str, Any]) -> None:
    """Refuse, naming it, an argument that the student's constructor does not take (``beta`` for BC)."""
    parameters = inspect.signature(student_class).parameters  # the constructor's
    if any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters.values()):
        return
    unknown = sorted(set(student_kwargs) - set(parameters) - _FROM_OFFLINE_DATA)
    if unknown:
        raise TypeError(
            f"{student_class.__name__} takes no argument {', '.join(map(repr, unknown))}: "
            f"see help({student_class.__name__}) for its arguments"
        )


def distill(
    source: DistillSource,
    student_class: type,
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
    *,
    learning_rate: Optional[Union[float, Schedule]] = None,
    batch_size: Optional[int] = None,
    gamma: Optional[float] = None,
    advantage_transform: Optional[str] = None,
    beta: Optional[float] = None,
    max_weight: Optional[float] = None,
    num_samples: Optional[int] = None,
    critic_target: Optional[str] = None,
    actor_averaging: Optional[float] = None,
    loss: Optional[str] = None,
    policy_kwargs: Optional[dict[str, Any]] = None,
    seed: Optional[int] = None,
    device: Optional[Union[th.device, str]] = None,
    verbose: Optional[int] = None,
    **student_kwargs: Any,
) -> Any:
    """
    Train a new policy offline on a collector's whole replay buffer (or on a buffer or dataset alone).

    :param source: an SB3 off-policy model (its replay buffer is used, e.g. MPO / SAC / TD3 with a
        ``LifelongReplayBuffer``), a replay buffer, the directory of a ``LifelongReplayBuffer`` on disk (opened
        read-only, so collection may go on in another process), or a d4rl-style dict / ``.npz`` path
    :param student_class: the offline algorithm (:class:`sb3_lifelong.CRR`; :class:`sb3_lifelong.BC` for
        behaviour cloning), any class with ``from_offline_data`` and ``learn_offline``
    :param gradient_steps: number of offline gradient updates
    :param policy: the student's policy
    :param eval_env: environment(s) to evaluate the student on every ``eval_freq`` updates (a dict name -> env
        gives the names of the ``eval/<name>/mean_reward`` curves: Env-A, Env-B, ...)
    :param eval_freq: evaluation period, in updates
    :param n_eval_episodes: episodes per environment and evaluation
    :param callback: extra callback(s), called after every update
    :param log_interval: dump the training logs every this many updates
    :param tb_log_name: the name of the student's log folder; when ``source`` is a model that logs (to its
        ``tensorboard_log``, or to a logger given with ``set_logger``), the student logs into ``<the model's log
        folder>/<tb_log_name>`` with the model's output formats (and CSV), beside the collection curves, unless
        ``tensorboard_log`` is given here
    :param progress_bar: show a progress bar
    :param eval_sources: with ``actor_per_source=True`` (a CRR diagnostic): the source whose actor is evaluated in
        each environment of ``eval_env``, by name
    :param learning_rate: the student's learning rate (CRR and BC: 3e-4)
    :param batch_size: transitions per update (CRR and BC: 256)
    :param gamma: discount factor of CRR's critic (0.99)
    :param advantage_transform: CRR's weight of an action from its advantage ``A``: ``"exp"`` (default,
        ``min(exp(A / beta), max_weight)``) or ``"indicator"`` (``1[A > 0]``)
    :param beta: CRR's temperature of ``"exp"``, in the critic's return units (1.0); higher is closer to behaviour
        cloning
    :param max_weight: CRR's clip of the ``"exp"`` weights (20.0)
    :param num_samples: CRR's policy samples per state for the advantage's baseline (4)
    :param critic_target: CRR's TD target: ``"policy"`` (default, an action of the target policy) or ``"sarsa"``
        (the next action recorded in the data)
    :param actor_averaging: CRR's exponential moving average of the actor's weights, used by ``predict``
        (default None: off; e.g. 1e-3)
    :param loss: BC's loss: ``"nll"`` (default) or ``"mse"``
    :param policy_kwargs: the student's network settings (``net_arch``, ``layer_norm``, ...)
    :param seed: the student's seed
    :param device: the student's device (default: the model's when ``source`` is a model, else ``"auto"``)
    :param verbose: 1 prints what is distilled and one line per evaluation, 2 also SB3's tables of the training
        values (default: the model's when ``source`` is a model, else 0)
    :param student_kwargs: any other argument of the student's constructor (``tensorboard_log``,
        ``target_update_interval``, ``tau``, ``advantage_baseline``, ``actor_per_source``, ...: see
        :class:`~sb3_lifelong.CRR` and :class:`~sb3_lifelong.BC`) or of ``from_offline_data``
        (``observation_space``, ``action_space``, ``normalized_actions``). Arguments left at None take the student's
        defaults; an argument the student does not take (``beta`` for BC) raises a ``TypeError`` naming it.
    :return: the trained student, ready for ``predict`` and ``save``
    """
    if not isinstance(student_class, type) or not hasattr(student_class, "from_offline_data"):
        raise TypeError(
            f"the student must be an offline algorithm class (CRR, BC, ...), got {student_class!r}: model.distill(CRR, ...)"
        )
    named = dict(
        learning_rate=learning_rate,
        batch_size=batch_size,
        gamma=gamma,
        advantage_transform=advantage_transform,
        beta=beta,
        max_weight=max_weight,
        num_samples=num_samples,
        critic_target=critic_target,
        actor_averaging=actor_averaging,
        loss=loss,
        policy_kwargs=policy_kwargs,
        seed=seed,
        device=device,
        verbose=verbose,
    )
    student_kwargs.update({name: value for name, value in named.items() if value is not None})
    _check_student_arguments(student_class, student_kwargs)
    teacher: Optional[OffPolicyAlgorithm] = source if isinstance(source, OffPolicyAlgorithm) else None
    own_tensorboard_log = "tensorboard_log" in student_kwargs
    if teacher is not None:
        if teacher.replay_buffer is None or teacher.replay_buffer.size() == 0:
            raise ValueError(f"{type(teacher).__name__} has no data in its replay buffer to distil")
        data: Any = teacher.replay_buffer
        student_kwargs.setdefault("tensorboard_log", teacher.tensorboard_log)
        student_kwargs.setdefault("verbose", teacher.verbose)
        student_kwargs.setdefault("observation_space", teacher.observation_space)
        student_kwargs.setdefault("action_space", teacher.action_space)
        student_kwargs.setdefault("device", teacher.device)
    else:
        data = source  # a buffer directory is opened read-only by from_offline_data

    student = student_class.from_offline_data(data, policy=policy, **student_kwargs)

    logger = _logger_beside(teacher, tb_log_name, student.verbose) if teacher is not None and not own_tensorboard_log else None
    if logger is not None:
        student.set_logger(logger)
    if student.verbose >= 1:
        where = logger.get_dir() if logger is not None else student.tensorboard_log
        print(
            f"Distilling {_describe(student.replay_buffer)} into {type(student).__name__}: {gradient_steps:,} gradient "
            f"updates" + (f", logging to {where}" if where else "")
        )
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
