"""
The Offline Distillation Pipeline, given the student's class: train a fresh student on everything a robot has
collected, offline.

Any off-policy collector (MPO, SAC, TD3, CRR) explores online and keeps every transition; the whole lifetime buffer,
with no task boundaries, is then distilled into one policy. :func:`sb3_lifelong.distill.distill` (above the
algorithms, with CRR as the default student) documents its arguments and calls it;
:meth:`LifelongOffPolicyAlgorithm.distill <sb3_lifelong.common.base.LifelongOffPolicyAlgorithm.distill>` calls it with
the model as the source. It needs no algorithm of the package: the student class is given.
"""

import inspect
import os
import sys
from typing import Any, Optional, Union

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
from stable_baselines3.common.type_aliases import MaybeCallback

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
    # a teacher that never learnt (a loaded model and buffer, a buffer filled by hand) has no logger yet
    if getattr(teacher, "_logger", None) is None or (teacher.tensorboard_log is None and not teacher._custom_logger):
        return None
    formats = _format_names(teacher.logger)
    if teacher.tensorboard_log is not None:
        formats |= {"csv", "tensorboard"}
    if verbose >= 2:  # SB3's tables of the training values (verbose=1 prints the evaluations, one line each)
        formats.add("stdout")
    teacher_dir = teacher.logger.get_dir()
    if teacher_dir is None:  # a logger with no folder (stdout only): the student prints, as the teacher does
        return Logger(None, [HumanOutputFormat(sys.stdout)] if "stdout" in formats else [])
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


def teacher_policy_alias(teacher: OffPolicyAlgorithm, student_class: type) -> Optional[str]:
    """
    :param teacher: the model whose buffer is distilled
    :param student_class: the student's algorithm
    :return: the name under which the teacher's algorithm lists its policy class (``"CnnPolicy"`` for MPO's or SAC's
        ``CnnPolicy``, ...) when the student's algorithm has a policy of that name; None otherwise (a policy class
        of the teacher's own, a name the student lacks)
    """
    teacher_aliases = getattr(teacher, "policy_aliases", {}) or {}
    names = [name for name, policy in teacher_aliases.items() if policy is type(teacher.policy)]
    student_aliases = getattr(student_class, "policy_aliases", {}) or {}
    return next((name for name in names if name in student_aliases), None)


# what from_offline_data takes besides the constructor's arguments
_FROM_OFFLINE_DATA = {"observation_space", "action_space", "normalized_actions", "env"}


def _check_student_arguments(student_class: type, student_kwargs: dict[str, Any]) -> None:
    """
    Refuse, naming it, an argument that the student's constructor does not take (``beta`` for BC), and
    ``gradient_steps``: the constructors' updates after each rollout, which an offline student never makes; the
    distillation's number of updates is ``total_updates``.
    """
    if "gradient_steps" in student_kwargs:
        raise TypeError(
            f"distill() trains for total_updates gradient updates (got gradient_steps={student_kwargs['gradient_steps']!r}, "
            "the constructors' updates after each rollout, which an offline student never makes): pass "
            "total_updates=... instead"
        )
    parameters = inspect.signature(student_class).parameters  # the constructor's
    if any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters.values()):
        return
    unknown = sorted(set(student_kwargs) - set(parameters) - _FROM_OFFLINE_DATA)
    if unknown:
        raise TypeError(
            f"{student_class.__name__} takes no argument {', '.join(map(repr, unknown))}: "
            f"see help({student_class.__name__}) for its arguments"
        )


#: The student's arguments that :func:`sb3_lifelong.distill.distill` names (keyword-only there): left at None, they take
#: the student's defaults (they are not passed, so a student that does not take one is not refused for it)
NAMED_STUDENT_ARGUMENTS = (
    "learning_rate",
    "batch_size",
    "gamma",
    "advantage_transform",
    "beta",
    "max_weight",
    "num_samples",
    "critic_target",
    "actor_averaging",
    "loss",
    "policy_kwargs",
    "seed",
    "device",
    "verbose",
)


def distill(
    source: DistillSource,
    student_class: type,
    *,
    total_updates: int = 100_000,
    policy: Any = None,
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
    The Offline Distillation Pipeline, given the student's class. :func:`sb3_lifelong.distill.distill` (CRR by
    default) and ``model.distill(student_class, ...)`` call it; the first documents every argument, with the same
    defaults. The arguments of ``NAMED_STUDENT_ARGUMENTS`` left at None are not passed to the student: it takes
    its defaults.

    :return: the trained student
    """
    if not isinstance(student_class, type) or not hasattr(student_class, "from_offline_data"):
        raise TypeError(
            f"the student must be an offline algorithm class (CRR, BC, ...), got {student_class!r}: model.distill(CRR, ...)"
        )
    for name in NAMED_STUDENT_ARGUMENTS:
        if name in student_kwargs and student_kwargs[name] is None:
            del student_kwargs[name]
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
        if policy is None:  # the student sees what the teacher saw: a CNN for a teacher's CnnPolicy, ...
            policy = teacher_policy_alias(teacher, student_class)
    else:
        data = source  # a buffer directory is opened read-only by from_offline_data
    # still None: from_offline_data picks the policy that the data's observation space calls for

    student = student_class.from_offline_data(data, policy=policy, **student_kwargs)

    logger = _logger_beside(teacher, tb_log_name, student.verbose) if teacher is not None and not own_tensorboard_log else None
    if logger is not None:
        student.set_logger(logger)
    if student.verbose >= 1:
        where = logger.get_dir() if logger is not None else student.tensorboard_log
        print(
            f"Distilling {_describe(student.replay_buffer)} into {type(student).__name__}: {total_updates:,} gradient "
            f"updates" + (f", logging to {where}" if where else "")
        )
    student.learn_offline(
        total_updates,
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
