"""
Offline distillation: train a fresh student (CRR by default, or BC) on everything a robot has collected.

The second half of the Offline Distillation Pipeline (:mod:`sb3_lifelong.common.distillation`), with CRR as the
default student. A model reaches the same pipeline with ``model.distill(CRR, ...)``.
"""

from typing import Any, Optional

from sb3_lifelong.common.distillation import DistillSource
from sb3_lifelong.common.distillation import distill as distill_into
from sb3_lifelong.crr import CRR

__all__ = ["DistillSource", "distill"]


def distill(source: DistillSource, student_class: Optional[type] = None, gradient_steps: int = 100_000, **kwargs: Any) -> Any:
    """
    Train a new policy offline on a collector's whole replay buffer (or on a buffer or dataset alone).

    :param source: an SB3 off-policy model (its replay buffer is used), a replay buffer, the directory of a
        ``LifelongReplayBuffer`` on disk (opened read-only), or a d4rl-style dict / ``.npz`` path
    :param student_class: the offline algorithm (default :class:`sb3_lifelong.CRR`; :class:`sb3_lifelong.BC` for
        behaviour cloning)
    :param gradient_steps: number of offline gradient updates
    :param kwargs: the pipeline's settings (``eval_env``, ``eval_freq``, ``tb_log_name``, ...: see
        :func:`sb3_lifelong.common.distillation.distill`) and the student's hyperparameters
    :return: the trained student, ready for ``predict`` and ``save``
    """
    return distill_into(source, CRR if student_class is None else student_class, gradient_steps, **kwargs)
