"""
Offline distillation: train a fresh student (CRR by default, or BC) on everything a robot has collected.

The second half of the Offline Distillation Pipeline (:mod:`sb3_lifelong.common.distillation`), with CRR as the
default student. A model reaches the same pipeline with ``model.distill(CRR, ...)``, which takes the arguments of
:func:`distill` (documented here, once).
"""

from typing import Any, Optional, Union

import torch as th
from stable_baselines3.common.type_aliases import MaybeCallback, Schedule

from sb3_lifelong.common.distillation import DistillSource
from sb3_lifelong.common.distillation import distill as pipeline
from sb3_lifelong.crr import CRR

__all__ = ["DistillSource", "distill"]


def distill(
    source: DistillSource,
    student_class: Optional[type] = None,
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
    Train a new policy offline on a collector's whole replay buffer (or on a buffer or dataset alone):
    ``distill(model, CRR, beta=1.0, eval_env={"Env-A": env_a, "Env-B": env_b})``.

    :param source: an SB3 off-policy model (its replay buffer is used as it is, e.g. MPO / SAC / TD3 with a
        ``LifelongReplayBuffer``; the student logs beside the model's logs), a replay buffer or a view of several, the
        directory of a ``LifelongReplayBuffer`` on disk (opened read-only, so collection may go on in another
        process), a d4rl-style dict / ``.npz`` path, or a Minari dataset (id or object)
    :param student_class: the offline algorithm (default :class:`~sb3_lifelong.CRR`; :class:`~sb3_lifelong.BC` for
        behaviour cloning)
    :param total_updates: number of offline gradient updates (``gradient_steps``, the constructors' updates after
        each rollout, is refused: an offline student makes none)
    :param policy: the student's policy (``"MlpPolicy"``, ``"CnnPolicy"``, ``"MultiInputPolicy"``, a class); None:
        when ``source`` is a model, the policy of the same name as the model's (a ``CnnPolicy`` teacher, MPO's or SAC's,
        gets a ``CnnPolicy`` student; the network settings are the student's own, ``policy_kwargs``), else the one the
        data's observation space calls for: ``"MultiInputPolicy"`` for a Dict space, ``"CnnPolicy"`` for channel-first
        images, ``"MlpPolicy"`` otherwise
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
    return pipeline(
        source,
        CRR if student_class is None else student_class,
        total_updates=total_updates,
        policy=policy,
        eval_env=eval_env,
        eval_freq=eval_freq,
        n_eval_episodes=n_eval_episodes,
        callback=callback,
        log_interval=log_interval,
        tb_log_name=tb_log_name,
        progress_bar=progress_bar,
        eval_sources=eval_sources,
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
        **student_kwargs,
    )
