"""
Learning from data with no environment: the offline path shared by CRR, BC (and policy distillation).

:class:`OfflineLearning`, the part of the algorithms that can learn from data alone (CRR, BC), mixed in before this
package's off-policy algorithm (``class CRR(OfflineLearning, LifelongOffPolicyAlgorithm)``, with
:class:`~sb3_lifelong.common.base.LifelongOffPolicyAlgorithm`), adds three methods to it:

- ``Algo.from_offline_data(data, policy="MlpPolicy", **hyperparameters)``: build a model from data, taking the
  observation and action spaces from the data (or ``env=`` / ``observation_space=`` / ``action_space=``);
- ``model.set_offline_data(data)``: (re)attach data, e.g. after ``Algo.load(path)``;
- ``model.learn_offline(total_updates, ...)``: gradient updates on the data, where ``num_timesteps`` counts
  updates, so that SB3 callbacks, ``progress_bar=True``, tensorboard logging and ``reset_num_timesteps=False``
  resumption all work in update units.

``data`` may be an SB3 ``ReplayBuffer`` (including ``LifelongReplayBuffer``; used as it is), a d4rl-style dict,
the path of a ``.npz`` file holding one, or a Minari dataset (id or object; needs ``minari``).
"""

import time
from collections import deque
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Callable, Optional, TypeVar

import gymnasium as gym
from gymnasium import spaces
from stable_baselines3.common import utils
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, ProgressBarCallback
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_lifelong.buffers.loading import resolve_data
from sb3_lifelong.common.base import LifelongOffPolicyAlgorithm
from sb3_lifelong.common.policies import policy_alias_for
from sb3_lifelong.core.datasets import (
    OfflineData,
    OfflineDataError,
)
from sb3_lifelong.evaluation.callbacks import EvalEnvs, MultiEnvEvalCallback

__all__ = ["NoEnvironment", "OfflineLearning", "OfflineProgressBarCallback"]

SelfOffline = TypeVar("SelfOffline", bound="OfflineLearning")


class NoEnvironment(gym.Env):
    """
    Stand-in training environment while a model with no environment trains offline, so that callbacks which look
    at ``training_env`` (SB3's ``EvalCallback``, ...) work. It cannot be reset or stepped.

    :param observation_space: the model's observation space
    :param action_space: the model's action space
    """

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space):
        self.observation_space = observation_space
        self.action_space = action_space

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict[str, Any]] = None) -> Any:
        raise RuntimeError("offline training has no environment: this placeholder cannot be reset or stepped")

    def step(self, action: Any) -> Any:
        raise RuntimeError("offline training has no environment: this placeholder cannot be reset or stepped")


class OfflineProgressBarCallback(ProgressBarCallback):
    """SB3's progress bar, advancing by one per gradient update (there is no training env to count)."""

    def _on_step(self) -> bool:
        self.pbar.update(1)
        return True


if TYPE_CHECKING:
    # the part is checked as the algorithm it is mixed into; at run time it is a plain mixin
    _Algorithm = LifelongOffPolicyAlgorithm
else:
    _Algorithm = object


class OfflineLearning(_Algorithm):
    """
    Learning from data alone, mixed into an off-policy algorithm before its base class
    (``class CRR(OfflineLearning, LifelongOffPolicyAlgorithm)``). The algorithm's ``train(gradient_steps,
    batch_size)`` is reused unchanged: offline training is its training step run on a fixed buffer, with no
    rollouts. Online ``learn`` works as for any off-policy algorithm.

    The algorithm's ``__init__`` must accept ``env=None``.
    """

    @classmethod
    def from_offline_data(
        cls: type[SelfOffline],
        data: OfflineData,
        policy: Any = "MlpPolicy",
        env: Optional[GymEnv] = None,
        observation_space: Optional[spaces.Space] = None,
        action_space: Optional[spaces.Space] = None,
        normalized_actions: Optional[bool] = None,
        **kwargs: Any,
    ) -> SelfOffline:
        """
        Build a model whose replay buffer holds ``data``, ready for :meth:`learn_offline`.

        :param data: an SB3 ``ReplayBuffer`` (used as it is, e.g. a ``LifelongReplayBuffer``; it samples onto the
            model's device from then on, as after SB3's ``load_replay_buffer``), a d4rl-style dict (``observations``,
            ``actions``, ``rewards``, ``next_observations``, ``terminals``, optional ``timeouts``), the path of a
            ``.npz`` file holding one, or a Minari dataset (id or object)
        :param policy: the policy (``"MlpPolicy"``, ``"CnnPolicy"``, ``"MultiInputPolicy"``, a class); None: the one
            the observation space calls for (``sb3_lifelong.common.policies.policy_alias_for``: a Dict space
            ``"MultiInputPolicy"``, channel-first images ``"CnnPolicy"``, anything else ``"MlpPolicy"``)
        :param env: optional environment: gives the spaces, and lets the model ``learn()`` online afterwards
        :param observation_space: observation space (default: the env's, the buffer's, or inferred from the data)
        :param action_space: bounded Box action space (default: the env's, the buffer's, or inferred from the data;
            give it when the data's actions do not reach the true bounds)
        :param normalized_actions: whether dict / ``.npz`` / Minari actions are already normalised to ``[-1, 1]``
            (default False: environment units)
        :param kwargs: the algorithm's hyperparameters (``batch_size``, ``seed``, ``tensorboard_log``, ...);
            ``buffer_size`` is set to the data's size
        :return: the model
        """
        device = kwargs.get("device", "auto")
        # the subclass's own constructor (it takes env=None and _init_setup_model, SB3's OffPolicyAlgorithm does not)
        build: Callable[..., SelfOffline] = cls
        if env is not None:
            model = build(policy, env, _init_setup_model=False, **kwargs)
            observation_space = observation_space or model.observation_space
            action_space = action_space or model.action_space
        buffer = resolve_data(data, observation_space, action_space, utils.get_device(device), normalized_actions)
        if env is None:
            model = build(policy, None, _init_setup_model=False, **kwargs)
            model.observation_space = buffer.observation_space
            model.action_space = buffer.action_space
            model.n_envs = 1
        elif buffer.observation_space.shape != model.observation_space.shape:
            raise OfflineDataError(
                f"the data's observation space {buffer.observation_space} does not match the env's {model.observation_space}"
            )
        model._check_offline_spaces()
        if policy is None:
            model.policy_class = model._get_policy_from_name(policy_alias_for(model.observation_space))
        model.replay_buffer = buffer
        model.buffer_size = buffer.buffer_size
        model._setup_model()
        model._sample_on_model_device()
        return model

    def _check_offline_spaces(self) -> None:
        if not isinstance(self.action_space, spaces.Box):
            raise OfflineDataError(f"{type(self).__name__} needs a continuous (Box) action space, got {self.action_space}")

    def set_offline_data(self, data: OfflineData, normalized_actions: Optional[bool] = None) -> None:
        """
        Replace the replay buffer by ``data`` (same spaces as the model), e.g. to resume offline training after
        ``load`` (``load_replay_buffer`` works too), or to distil another dataset.

        :param data: see :meth:`from_offline_data`
        :param normalized_actions: see :meth:`from_offline_data`
        """
        device = getattr(self, "device", "auto")
        buffer = resolve_data(data, self.observation_space, self.action_space, device, normalized_actions)
        if buffer.observation_space.shape != self.observation_space.shape:
            raise OfflineDataError(
                f"the data's observation space {buffer.observation_space} does not match the model's {self.observation_space}"
            )
        self.replay_buffer = buffer
        self._sample_on_model_device()

    def _prepare_offline_buffer(self) -> None:
        """Hook: adapt ``self.replay_buffer`` before offline training (e.g. add next actions for SARSA)."""

    def learn_offline(
        self: SelfOffline,
        total_updates: int,
        callback: MaybeCallback = None,
        eval_env: Optional[EvalEnvs] = None,
        eval_freq: int = 10_000,
        n_eval_episodes: int = 5,
        log_interval: int = 1_000,
        tb_log_name: Optional[str] = None,
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
        eval_sources: Optional[Mapping[str, int]] = None,
    ) -> SelfOffline:
        """
        Train on the replay buffer's data for ``total_updates`` gradient updates, with no environment interaction.

        ``num_timesteps`` counts gradient updates here: callbacks are called once per update (``EvalCallback`` and
        ``CheckpointCallback`` frequencies are in updates), and tensorboard curves are against updates.

        :param total_updates: number of gradient updates (added to the current count when
            ``reset_num_timesteps=False``). Named apart from the constructors' ``gradient_steps``, which is the number of
            updates after each rollout when the model collects online
        :param callback: callback(s) called after every update
        :param eval_env: environment(s) to evaluate on every ``eval_freq`` updates: an env, a gym id, a list
            (named after the gym ids) or a dict name -> env; logs ``eval/<name>/mean_reward``
        :param eval_freq: evaluation period, in updates
        :param n_eval_episodes: episodes per environment and evaluation
        :param log_interval: dump the logs (``train/*``, ``time/*``) every this many updates
        :param tb_log_name: name of the tensorboard run (default: the algorithm's class name)
        :param reset_num_timesteps: whether to reset the update counter (False: continue a run, e.g. after ``load``;
            the tensorboard run is continued too)
        :param progress_bar: display a progress bar (needs tqdm and rich)
        :param eval_sources: with one actor per source (CRR's ``actor_per_source=True``): the source whose actor acts
            in each evaluation environment, by name (see :class:`MultiEnvEvalCallback`)
        :return: the trained model
        """
        if self.replay_buffer is None or self.replay_buffer.size() == 0:
            raise ValueError(
                "No offline data: build the model with from_offline_data(...), or call set_offline_data(...) or "
                "load_replay_buffer(...) first"
            )
        if total_updates < 0:
            raise ValueError(f"total_updates must be >= 0, got {total_updates}")
        self._check_eval_sources(eval_sources)  # before training, not at the first evaluation
        self._prepare_offline_buffer()
        self._sample_on_model_device()
        self.start_time = time.time_ns()
        if self.ep_info_buffer is None or reset_num_timesteps:
            self.ep_info_buffer = deque(maxlen=self._stats_window_size)
            self.ep_success_buffer = deque(maxlen=self._stats_window_size)
        if reset_num_timesteps:
            self.num_timesteps = 0
            self._episode_num = 0
        total_timesteps = total_updates + self.num_timesteps
        self._total_timesteps = total_timesteps
        self._num_timesteps_at_start = self.num_timesteps
        if not self._custom_logger:
            self._logger = utils.configure_logger(
                self.verbose, self.tensorboard_log, tb_log_name or type(self).__name__, reset_num_timesteps
            )
            self._quiet_stdout()

        self._restore_loaded_rng()  # as learn() does: draws since a load do not change the run
        placeholder = self.env is None
        if placeholder:
            self.env = DummyVecEnv([lambda: NoEnvironment(self.observation_space, self.action_space)])
        try:
            self._run_offline(
                total_timesteps, callback, eval_env, eval_freq, n_eval_episodes, log_interval, progress_bar, eval_sources
            )
        finally:
            if placeholder:
                self.env = None
        return self

    def _check_eval_sources(self, eval_sources: Optional[Mapping[str, int]]) -> None:
        """
        :param eval_sources: evaluation env name -> the source whose actor acts in it (``learn_offline``)
        :raises ValueError: naming the sources the model has no actor for (those of its training data), and the data's
        """
        known = getattr(self, "source_ids", None)
        if not eval_sources or known is None:  # no actor per source: MultiEnvEvalCallback refuses it before training
            return
        unknown = {name: source for name, source in eval_sources.items() if source not in known}
        if unknown:
            names = getattr(self.replay_buffer, "sources", {}) or {}
            described = ", ".join(f"{s} ({names[s]['name']})" if s in names else str(s) for s in known)
            raise ValueError(
                f"eval_sources names sources that the training data does not hold, so that no actor would act in those "
                f"environments: {unknown}. The data's sources: {described}"
            )

    def _run_offline(
        self,
        total_timesteps: int,
        callback: MaybeCallback,
        eval_env: Optional[EvalEnvs],
        eval_freq: int,
        n_eval_episodes: int,
        log_interval: int,
        progress_bar: bool,
        eval_sources: Optional[Mapping[str, int]] = None,
    ) -> None:
        callbacks: list[BaseCallback] = []
        if isinstance(callback, list):
            callbacks.extend(callback)
        elif isinstance(callback, BaseCallback):
            callbacks.append(callback)
        elif callback is not None:
            raise TypeError(f"callback must be a BaseCallback or a list of them, got {type(callback).__name__}")
        if eval_env is not None:
            callbacks.append(
                MultiEnvEvalCallback(eval_env, eval_freq, n_eval_episodes, sources=eval_sources, verbose=self.verbose)
            )
        if progress_bar:
            callbacks.append(OfflineProgressBarCallback())
        callback_list = CallbackList(callbacks)
        callback_list.init_callback(self)
        callback_list.on_training_start(locals(), globals())

        batch_size = self.batch_size
        last_dump = self.num_timesteps
        while self.num_timesteps < total_timesteps:
            self._update_current_progress_remaining(self.num_timesteps, total_timesteps)
            self.train(gradient_steps=1, batch_size=batch_size)
            self.num_timesteps += 1
            callback_list.update_locals(locals())
            if not callback_list.on_step():
                break
            if log_interval > 0 and self.num_timesteps % log_interval == 0:
                self._dump_offline_logs()
                last_dump = self.num_timesteps
        if self.num_timesteps != last_dump and log_interval > 0:
            self._dump_offline_logs()
        callback_list.on_training_end()

    def _dump_offline_logs(self) -> None:
        elapsed = max((time.time_ns() - self.start_time) / 1e9, 1e-9)
        updates = self.num_timesteps - self._num_timesteps_at_start
        self.logger.record("time/updates", self.num_timesteps, exclude="tensorboard")
        self.logger.record("time/updates_per_second", int(updates / elapsed))
        self.logger.record("time/time_elapsed", int(elapsed), exclude="tensorboard")
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.dump(step=self.num_timesteps)
