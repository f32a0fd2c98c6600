"""
What every job of a study shares: the robot through its stages (:func:`make_env`), what every model is built with
(:func:`model_kwargs`: the preset's network and ``device``), a job's callbacks and logs (:func:`job_callbacks`,
:func:`tensorboard_dir`), and the value support of a bounded critic (:func:`value_support`). The jobs themselves:
:mod:`~sb3_lifelong.experiments.collection` (MPO through the stages) and :mod:`~sb3_lifelong.experiments.protocol` (the
students, the online baselines, one seed).
"""

import pathlib
from collections.abc import Sequence
from typing import Any, Optional

import gymnasium as gym

from sb3_lifelong.envs import DynamicsSchedule, stage_envs
from sb3_lifelong.evaluation.callbacks import EVAL_SEED_OFFSET, MultiEnvEvalCallback, SourceQCallback, TrainLogCallback
from sb3_lifelong.experiments.presets import (
    Preset,
)


# ------------------------------------------------------------------------------------------------- environments
def make_env(preset: Preset, switch_at: Optional[Sequence[int]] = None, start_timestep: int = 0) -> DynamicsSchedule:
    """The robot through its stages, with the true physical parameters appended to the observation (as the paper)."""
    return DynamicsSchedule(
        gym.make(preset.env_id, **preset.env_kwargs),
        stages=list(preset.stages),
        switch_at=switch_at,
        append_params=True,
        start_timestep=start_timestep,
    )


# ------------------------------------------------------------------------------------------------- the jobs
def tensorboard_dir(directory: pathlib.Path) -> Optional[str]:
    """
    :param directory: a job's directory
    :return: the ``tensorboard_log`` of the job's model, ``<directory>/tb`` (SB3 writes each run into a folder
        ``<tb_log_name>_<k>`` there), or None when tensorboard is not installed (the CSV files only)
    """
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401  (SB3 writes its event files with it)
    except ImportError:
        return None
    return str(directory / "tb")


def model_kwargs(preset: Preset, seed: int) -> dict[str, Any]:
    """
    What every model of a study is built with: the preset's network (``net_arch``, ``layer_norm``), the seed, and the
    preset's device (``--device``). Models that continue a paused job load onto that device too, so that a run in
    parts computes what an uninterrupted one does.

    :param preset: the study's preset
    :param seed: the model's seed
    :return: ``policy_kwargs``, ``seed`` and ``device``, as constructor arguments
    """
    return dict(
        policy_kwargs=dict(net_arch=list(preset.net_arch), layer_norm=preset.layer_norm), seed=seed, device=preset.device
    )


def value_support(reward_range: tuple[float, float], gamma: float, scales: Sequence[float] = ()) -> dict[str, float]:
    """
    The support of a categorical critic that holds every return of the data: no value outside it can be learnt, so
    the critic cannot diverge (the paper's critic is distributional).

    :param reward_range: the smallest and largest stored reward (:meth:`LifelongReplayBuffer.reward_range`)
    :param gamma: the discount factor
    :param scales: per-source reward scales applied at sampling time (the bounds cover each of them)
    :return: ``v_min`` and ``v_max`` (policy kwargs)
    """
    if not 0 <= gamma < 1:
        raise ValueError(f"a bounded value support needs 0 <= gamma < 1, got {gamma}")
    factors = [1.0, *scales]
    low = min(0.0, *(reward_range[0] * f for f in factors), *(reward_range[1] * f for f in factors))
    high = max(0.0, *(reward_range[0] * f for f in factors), *(reward_range[1] * f for f in factors))
    if low == high:
        high = low + 1.0  # all rewards 0: any non-empty support
    return dict(v_min=low / (1 - gamma), v_max=high / (1 - gamma))


def job_callbacks(
    preset: Preset,
    directory: pathlib.Path,
    eval_freq: int,
    seed: int,
    data: Optional[Any] = None,
    q: bool = True,
    reward_scale: Optional[dict[int, float]] = None,
    **eval_kwargs: Any,
) -> list[Any]:
    """
    The callbacks of one job: its ``train/`` values (``train.csv``), its evaluations in one copy of the robot per
    stage (:func:`~sb3_lifelong.envs.stage_envs`, ``eval.csv``, the same episodes at every evaluation, seeded from
    ``EVAL_SEED_OFFSET + seed``) and, with a
    critic, its average Q per source (``q_sources.csv``).

    :param preset: the protocol's settings
    :param directory: the job's directory
    :param eval_freq: the evaluation period (environment steps, or updates for a student)
    :param seed: the seed of the evaluations
    :param data: the transitions the Q-values are measured on (None: the model's replay buffer)
    :param q: measure the average Q per source
    :param reward_scale: per-source reward scales the model trains with, for the Monte-Carlo returns
    :param eval_kwargs: further arguments of :class:`~sb3_lifelong.evaluation.callbacks.MultiEnvEvalCallback`
    :return: the callbacks
    """
    # the train/ values first: the evaluation dumps the logger, which clears them
    callbacks: list[Any] = [
        TrainLogCallback(directory / "train.csv", log_freq=eval_freq),
        MultiEnvEvalCallback(
            stage_envs(preset.env_id, list(preset.stages), preset.env_names, preset.env_kwargs, append_params=True),
            eval_freq,
            preset.eval_episodes,
            log_path=directory / "eval.csv",
            seed=EVAL_SEED_OFFSET + seed,
            same_episodes=True,
            **eval_kwargs,
        ),
    ]
    if q:
        q_log = directory / "q_sources.csv"
        callbacks.append(SourceQCallback(log_freq=eval_freq, log_path=q_log, data=data, reward_scale=reward_scale))
    return callbacks
