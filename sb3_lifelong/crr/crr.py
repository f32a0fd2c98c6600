"""Critic Regularized Regression (CRR), online and offline; its losses are in :mod:`sb3_lifelong.crr.losses`."""

import inspect
from typing import Any, ClassVar, NamedTuple, Optional, TypeVar, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy, ContinuousCritic
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import polyak_update

from sb3_lifelong.buffers.loading import as_lifelong_data
from sb3_lifelong.common.arguments import check_sizes_of
from sb3_lifelong.common.base import LifelongOffPolicyAlgorithm
from sb3_lifelong.common.losses import bootstrap_discount
from sb3_lifelong.common.offline import OfflineLearning
from sb3_lifelong.common.policies import GaussianActor, sample_gaussian
from sb3_lifelong.core.settings import Settings
from sb3_lifelong.crr.distributional import CategoricalCritic, CriticLoss
from sb3_lifelong.crr.losses import (
    ADVANTAGE_BASELINES,
    ADVANTAGE_TRANSFORMS,
    AdvantageWeights,
    actor_loss,
    advantage_weights,
    effective_sample_size,
)
from sb3_lifelong.crr.policies import CnnPolicy, CRRPolicy, MlpPolicy, MultiInputPolicy, PerSourceActor, actor_distribution
from sb3_lifelong.crr.targets import critic_loss, critic_td_target, target_actions
from sb3_lifelong.numerics.compiling import LazyCompiled
from sb3_lifelong.numerics.scoring import score_actions
from sb3_lifelong.numerics.settings import ComputeSettings

SelfCRR = TypeVar("SelfCRR", bound="CRR")

CRITIC_TARGETS = ("policy", "sarsa")


class CRRStepStats(NamedTuple):
    """What one gradient step logs, under ``train/<field>`` (the mean over the steps of a ``train`` call)."""

    critic_loss: th.Tensor
    actor_loss: th.Tensor
    advantage_mean: th.Tensor
    weight_mean: th.Tensor
    weight_clip_frac: th.Tensor
    #: the weights' effective sample size, as a fraction of the batch (:func:`effective_sample_size`)
    weight_ess: th.Tensor
    #: the ``exp`` transform's temperature (the batch's with ``target_ess``; NaN for the indicator)
    beta: th.Tensor
    q_mean: th.Tensor

    @classmethod
    def of(cls, fit: CriticLoss, actor_loss: th.Tensor, advantage: AdvantageWeights) -> "CRRStepStats":
        return cls(
            critic_loss=fit.loss.detach(),
            actor_loss=actor_loss.detach(),
            advantage_mean=advantage.advantages.mean(),
            weight_mean=advantage.weights.mean(),
            weight_clip_frac=advantage.clipped.float().mean(),
            weight_ess=effective_sample_size(advantage.weights),
            beta=advantage.beta.float(),
            q_mean=fit.q_values.mean(),
        )


class CRR(OfflineLearning, LifelongOffPolicyAlgorithm):
    """
    Critic Regularized Regression (CRR), usable online (``learn``) and offline (``from_offline_data`` +
    ``learn_offline``).

    Paper: https://arxiv.org/abs/2006.15134

    The policy regresses the data's actions, weighted by a transform of their advantage
    ``A(s, a) = Q(s, a) - baseline(s)``, where the baseline is the mean (or max) of ``Q`` over ``num_samples``
    actions sampled from the policy (one batched critic call). The critic is trained on the TD target with an
    action sampled from the target policy (or, ``critic_target="sarsa"``, the next action recorded in the data).
    Both the critic loss and the advantages use the same (pre-update) critic, like Acme's CRR.

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, MultiInputPolicy, ...)
    :param env: The environment to learn from (if registered in Gym, can be str); None for offline training
    :param learning_rate: learning rate of the actor and critic (Adam), a constant or a schedule of the
        remaining progress
    :param buffer_size: size of the replay buffer (online; offline it is the data's size)
    :param learning_starts: how many steps of the model to collect transitions for before learning starts (online)
    :param batch_size: Minibatch size for each gradient update
    :param tau: the target networks' update coefficient, applied every ``target_update_interval`` updates
        (1.0: hard copy, the default; use e.g. ``tau=0.005, target_update_interval=1`` for Polyak averaging)
    :param gamma: the discount factor
    :param train_freq: Update the model every ``train_freq`` steps (online). Alternatively pass a tuple of
        frequency and unit like ``(5, "step")`` or ``(2, "episode")``.
    :param gradient_steps: How many gradient steps to do after each rollout (online; -1: as many as env steps)
    :param action_noise: extra action noise (online; the Gaussian policy explores on its own; usually None)
    :param replay_buffer_class: Replay buffer class to use (for instance ``LifelongReplayBuffer``)
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
    :param n_steps: n-step returns for the critic (online; SB3's ``NStepReplayBuffer`` when no buffer class is given)
    :param num_samples: number of policy actions sampled per state for the advantage's baseline
    :param advantage_baseline: ``"mean"`` or ``"max"`` of the sampled actions' Q-values
    :param advantage_transform: ``"exp"`` (``exp(A / beta)`` clipped at ``max_weight``) or ``"indicator"``
        (``1[A > 0]``)
    :param beta: temperature of the ``exp`` transform (higher: closer to behaviour cloning, more conservative)
    :param max_weight: upper bound of the ``exp`` transform's weights
    :param normalize_advantages: divide the advantages by their standard deviation over the batch before the
        transform, which makes ``beta`` independent of the reward's scale (with raw advantages of a few units,
        ``exp`` at ``beta=1`` puts most of a batch's weight on a few transitions)
    :param target_ess: conservativeness with the same meaning at any reward scale (``exp`` only; replaces
        ``beta``): each batch's temperature is chosen so that the weights' effective sample size
        ``(sum w)^2 / (n sum w^2)`` is this fraction of the batch (:func:`ess_temperature`). 1 would be behaviour
        cloning; 0.9 stays close to the data; about 0.5 is as greedy as the indicator. ``train/beta`` logs the
        temperature it picks, ``train/weight_ess`` the size reached. None: the fixed ``beta``
    :param critic_target: ``"policy"`` (TD target with actions sampled from the target policy) or ``"sarsa"``
        (with the data's next action; offline only, falls back to a policy sample where the data does not show it)
    :param n_target_samples: number of target-policy actions averaged in the TD target
    :param target_update_interval: number of gradient updates between two target network updates
    :param actor_per_source: a diagnostic that needs source tags: one independent actor per source of the data
        (its transitions alone train it, its own samples give its advantage baseline and TD targets) with one critic
        shared by all. Offline only, on a ``LifelongReplayBuffer`` (or view / merge); the sources present when the
        model is set up fix the actors (``source_ids``). ``select_source(s)`` chooses the actor that ``predict``
        uses (default: the first source).
    :param max_grad_norm: maximum norm of the actor's and the critic's gradients (None: no clipping)
    :param actor_averaging: Polyak coefficient of an exponential moving average of the actor's weights, updated
        after every actor update (e.g. ``1e-3``: an average over about the last 1,000 updates); ``predict`` and
        evaluation then use the averaged actor (``policy.actor_average``), while training is unchanged. None: off
    :param compute: the updates' precision and compilation: a :class:`~sb3_lifelong.numerics.ComputeSettings` or a
        dict of some of its settings (None: its defaults). With one actor per source the update stays eager
    :param stats_window_size: Window size for the rollout logging
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation (e.g. ``net_arch``,
        ``n_critics``, ``distributional_critic=True, v_min=..., v_max=...``)
    :param verbose: Verbosity level: 0 for no output, 1 for info messages, 2 for debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    settings_groups: ClassVar[dict[str, type[Settings]]] = {"compute": ComputeSettings}
    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: CRRPolicy
    actor: Union[GaussianActor, PerSourceActor]
    actor_target: Union[GaussianActor, PerSourceActor]
    critic: Union[ContinuousCritic, CategoricalCritic]
    critic_target: Union[ContinuousCritic, CategoricalCritic]
    _forward: LazyCompiled

    def __init__(
        self,
        policy: Union[str, type[CRRPolicy]],
        env: Optional[Union[GymEnv, str]] = None,
        learning_rate: Union[float, Schedule] = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 1.0,
        gamma: float = 0.99,
        train_freq: Union[int, tuple[int, str]] = 1,
        gradient_steps: int = 1,
        action_noise: Optional[ActionNoise] = None,
        replay_buffer_class: Optional[type[ReplayBuffer]] = None,
        replay_buffer_kwargs: Optional[dict[str, Any]] = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        num_samples: int = 4,
        advantage_baseline: str = "mean",
        advantage_transform: str = "exp",
        beta: float = 1.0,
        max_weight: float = 20.0,
        normalize_advantages: bool = False,
        target_ess: Optional[float] = None,
        critic_target: str = "policy",
        n_target_samples: int = 1,
        target_update_interval: int = 100,
        actor_per_source: bool = False,
        max_grad_norm: Optional[float] = None,
        actor_averaging: Optional[float] = None,
        compute: Optional[Union[ComputeSettings, dict[str, Any]]] = None,
        stats_window_size: int = 100,
        tensorboard_log: Optional[str] = None,
        policy_kwargs: Optional[dict[str, Any]] = None,
        verbose: int = 0,
        seed: Optional[int] = None,
        device: Union[th.device, str] = "auto",
        _init_setup_model: bool = True,
    ):
        super().__init__(
            policy,
            env,  # type: ignore[arg-type]
            learning_rate,
            buffer_size,
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            action_noise=action_noise,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            sde_support=False,
            supported_action_spaces=(spaces.Box,),
            support_multi_env=True,
        )
        # The names below are saved with the model (its ``data``), so they stay as they are:
        # ``num_samples`` counts the policy's actions per state of the advantage's baseline (not the TD target's,
        # which are ``n_target_samples``), and the ``critic_target`` argument is stored as ``critic_target_type``
        # because ``critic_target`` is the target critic network (as in SB3's algorithms).
        self.num_samples = num_samples
        self.advantage_baseline = advantage_baseline
        self.advantage_transform = advantage_transform
        self.beta = beta
        self.max_weight = max_weight
        self.normalize_advantages = normalize_advantages
        self.target_ess = target_ess
        #: with ``target_ess``: the last batch's temperature, where the next batch's search starts (saved, so that a
        #: resumed run continues exactly)
        self._ess_beta: Optional[float] = None
        self.critic_target_type = critic_target
        self.n_target_samples = n_target_samples
        self.target_update_interval = target_update_interval
        self.actor_per_source = actor_per_source
        #: the sources with an actor each (actor_per_source=True), in the order of the actors
        self.source_ids: Optional[list[int]] = None
        self._head_of_source: Optional[np.ndarray] = None
        self.max_grad_norm = max_grad_norm
        self.actor_averaging = actor_averaging
        self.compute = ComputeSettings.of(compute, "compute")
        self._check_hyperparameters()
        if _init_setup_model:
            self._setup_model()

    def _check_hyperparameters(self) -> None:
        check_sizes_of(self)
        checks = {
            "num_samples": self.num_samples >= 1,
            "advantage_baseline": self.advantage_baseline in ADVANTAGE_BASELINES,
            "advantage_transform": self.advantage_transform in ADVANTAGE_TRANSFORMS,
            "beta": self.beta > 0,
            "max_weight": self.max_weight >= 1.0,
            "critic_target": self.critic_target_type in CRITIC_TARGETS,
            "n_target_samples": self.n_target_samples >= 1,
            "target_update_interval": self.target_update_interval >= 1,
            "tau": 0.0 < self.tau <= 1.0,
            "max_grad_norm": self.max_grad_norm is None or self.max_grad_norm > 0,
            "actor_averaging": self.actor_averaging is None or 0.0 < self.actor_averaging <= 1.0,
            "target_ess": self.target_ess is None or 0.0 < self.target_ess < 1.0,
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            attributes = {"critic_target": "critic_target_type"}
            values = ", ".join(f"{name}={getattr(self, attributes.get(name, name))!r}" for name in bad)
            raise ValueError(
                f"Invalid CRR hyperparameters: {values} (num_samples, n_target_samples and target_update_interval must "
                f"be >= 1, beta > 0, max_weight >= 1, tau and actor_averaging in (0, 1], advantage_baseline in "
                f"{ADVANTAGE_BASELINES}, advantage_transform in {ADVANTAGE_TRANSFORMS}, critic_target in {CRITIC_TARGETS}, "
                "target_ess None or in (0, 1))"
            )
        if self.target_ess is not None and (self.advantage_transform != "exp" or self.normalize_advantages):
            raise ValueError(
                f"target_ess={self.target_ess!r} sets the temperature of the exp transform from the weights' effective "
                f"sample size: it needs advantage_transform='exp' (got {self.advantage_transform!r}) and replaces "
                f"normalize_advantages (got {self.normalize_advantages!r})"
            )

    def _setup_model(self) -> None:
        if self.actor_per_source:
            if self.source_ids is None:
                self.source_ids = self._sources_of_data()
            self.policy_kwargs = {**self.policy_kwargs, "n_actors": len(self.source_ids)}  # the caller's dict unchanged
        if self.actor_averaging is not None:
            self.policy_kwargs = {**self.policy_kwargs, "averaged_actor": True}
        super()._setup_model()
        self._create_aliases()
        self._apply_train_dtype()
        # low-precision copies of the target critic (TD targets) and the online critic (advantage baselines)
        self._target_scoring_copy = self._make_scoring_copy(self.critic_target)
        self._online_scoring_copy = self._make_scoring_copy(self.critic)
        self._forward = LazyCompiled(
            self._forward_pass, "CRR's forward pass", self.policy.named_parameters, self._compiled_check_tolerance()
        )
        if self.actor_per_source:
            assert self.source_ids is not None
            self._head_of_source = np.full(max(self.source_ids) + 1, -1, dtype=np.int64)
            self._head_of_source[self.source_ids] = np.arange(len(self.source_ids))

    def _sources_of_data(self) -> list[int]:
        counts = getattr(self.replay_buffer, "source_counts", None)
        if counts is None or self.replay_buffer is None or self.replay_buffer.size() == 0:
            raise ValueError(
                "actor_per_source=True is an offline diagnostic that needs source-tagged data: build the model with "
                "CRR.from_offline_data(buffer, actor_per_source=True) on a non-empty LifelongReplayBuffer (or a view / "
                "merge of them)"
            )
        return sorted(int(source) for source, count in counts().items() if count > 0)

    def select_source(self: SelfCRR, source: int) -> SelfCRR:
        """
        Choose the actor that ``predict`` (and evaluation) uses, with ``actor_per_source=True``.

        :param source: a source id of the training data (see :attr:`source_ids`)
        :return: the model
        """
        if not isinstance(self.actor, PerSourceActor) or self.source_ids is None:
            raise ValueError("select_source needs a CRR model trained with actor_per_source=True")
        if source not in self.source_ids:
            raise ValueError(f"source {source!r} has no actor; this model has actors for sources {self.source_ids}")
        self.actor.active_head = self.source_ids.index(source)
        if isinstance(self.policy.actor_average, PerSourceActor):
            self.policy.actor_average.active_head = self.actor.active_head
        return self

    @property
    def active_source(self) -> Optional[int]:
        """The source whose actor ``predict`` uses (None without ``actor_per_source``)."""
        if not isinstance(self.actor, PerSourceActor) or self.source_ids is None:
            return None
        return self.source_ids[self.actor.active_head]

    def _sample(self, batch_size: int) -> tuple[Any, Optional[th.Tensor]]:
        """
        :return: a batch, and the actor index of each of its rows (None without ``actor_per_source``: the buffer
            is then asked for the batch only)
        """
        buffer: Any = self.replay_buffer
        # SARSA targets read the next action in the data: the lifelong buffer gives it (learn_offline ensures one)
        extra = {"next_actions": True} if self.critic_target_type == "sarsa" else {}
        if self._head_of_source is None:
            return buffer.sample(batch_size, env=self._vec_normalize_env, **extra), None
        replay_data, sources = buffer.sample(batch_size, env=self._vec_normalize_env, return_sources=True, **extra)
        return replay_data, self._source_heads(sources.cpu().numpy())

    def _source_heads(self, sources: np.ndarray) -> th.Tensor:
        """:return: the actor index of each row of a batch, from the rows' source ids"""
        assert self._head_of_source is not None
        sources = np.asarray(sources, dtype=np.int64)
        known = sources < len(self._head_of_source)
        heads = np.where(known, self._head_of_source[np.minimum(sources, len(self._head_of_source) - 1)], -1)
        if (heads < 0).any():
            unknown = sorted(set(sources[heads < 0].tolist()))
            raise ValueError(f"the data holds sources {unknown} that have no actor (this model's: {self.source_ids})")
        return th.as_tensor(heads, device=self.device)

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.actor_target = self.policy.actor_target
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target

    def _prepare_offline_buffer(self) -> None:
        if self.critic_target_type == "sarsa":
            assert self.replay_buffer is not None
            self.replay_buffer = as_lifelong_data(self.replay_buffer)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        steps: list[CRRStepStats] = []
        sample: Any = getattr(self.replay_buffer, "sample", None)
        if self._head_of_source is not None and "return_sources" not in inspect.signature(sample).parameters:
            raise ValueError("actor_per_source=True needs a replay buffer that records sources (a LifelongReplayBuffer)")

        compiled = self._compiles_now()
        self._compile_scoring_copies(compiled)
        for _ in range(gradient_steps):
            self._n_updates += 1
            replay_data, heads = self._sample(batch_size)
            actions = replay_data.actions
            # the samples' noise, drawn in the order the eager update always drew it (target's, then baseline's)
            noise_shape = tuple(actions.shape)
            target_noise = th.randn((self.n_target_samples, *noise_shape), device=self.device)
            sample_noise = th.randn((self.num_samples, *noise_shape), device=self.device)
            if self._online_scoring_copy is not None:
                self._online_scoring_copy.sync()
            # the critic's loss and the Q-values of the data's actions for the advantage (the same, pre-update critic)
            fit, mean, std, sampled_q = self._forward(compiled, replay_data, heads, target_noise, sample_noise)
            advantage = self._advantage(fit.q_values, sampled_q)
            if self.target_ess is not None:
                self._ess_beta = float(advantage.beta)
            regression_loss = actor_loss(actions, mean, std, advantage.weights)
            critic_part, actor_part = (self.critic, fit.loss), (self.actor, regression_loss)
            if compiled:  # one backward through the compiled graph (the two losses reach disjoint networks)
                self._gradient_step(critic_part, actor_part, max_grad_norm=self.max_grad_norm)
            else:
                self._gradient_step(critic_part, max_grad_norm=self.max_grad_norm)
                self._gradient_step(actor_part, max_grad_norm=self.max_grad_norm)
            # one check per update, before the average and the targets take anything non-finite
            self._raise_if_not_finite(critic_loss=fit.loss, actor_loss=regression_loss)
            if self.actor_averaging is not None:
                self._update_actor_average()
            if self._n_updates % self.target_update_interval == 0:
                self._update_targets()
            steps.append(CRRStepStats.of(fit, regression_loss, advantage))

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in zip(CRRStepStats._fields, zip(*steps)):
            self.logger.record_mean(f"train/{key}", th.stack(values).mean().item())

    @th.no_grad()
    def _advantage(self, q_values: th.Tensor, sampled_q: th.Tensor) -> AdvantageWeights:
        """
        :param q_values: the Q-values of the data's actions (the critic's, before its update)
        :param sampled_q: the Q-values of the policy's samples ``[num_samples, batch]``
        :return: the advantages and the actor's weights, with this student's transform, baseline and temperature
        """
        return advantage_weights(
            q_values,
            sampled_q,
            self.advantage_baseline,
            self.advantage_transform,
            self.beta,
            self.max_weight,
            self.normalize_advantages,
            self.target_ess,
            self._ess_beta,
        )

    def _compiles_now(self) -> bool:
        return not self.actor_per_source and super()._compiles_now()  # one actor per source stays eager

    def _forward_pass(
        self, replay_data: Any, heads: Optional[th.Tensor], target_noise: th.Tensor, sample_noise: th.Tensor
    ) -> tuple[CriticLoss, th.Tensor, th.Tensor, th.Tensor]:
        """
        An update's forward pass, up to the advantages' weights: what ``compute.compile_losses`` compiles.

        :param replay_data: the batch
        :param heads: with one actor per source, the actor of each row
        :param target_noise: the TD target's standard normal draws ``[n_target_samples, batch, action_dim]``
        :param sample_noise: the advantage baseline's ``[num_samples, batch, action_dim]``
        :return: the critic's loss (with the data's actions' Q-values), the policy's mean and std (differentiable),
            and the Q-values of the policy's samples ``[num_samples, batch]``
        """
        obs = replay_data.observations
        with th.no_grad():
            target = self._critic_target_values(replay_data, heads, target_noise)
        fit = critic_loss(self.critic, obs, replay_data.actions, target)
        mean, std = actor_distribution(self.actor, obs, heads)
        with th.no_grad():
            sampled_q = self._policy_action_values(obs, mean, std, sample_noise)
        return fit, mean, std, sampled_q

    def _critic_target_values(
        self, replay_data: Any, heads: Optional[th.Tensor], noise: Optional[th.Tensor] = None
    ) -> th.Tensor:
        """:return: the critic's TD target of the batch (see :func:`critic_td_target`)"""
        bootstrap = bootstrap_discount(replay_data, self.gamma)  # [B, 1]
        next_actions = target_actions(
            self.actor_target,
            replay_data,
            heads,
            self.n_target_samples,
            data_next_actions=self.critic_target_type == "sarsa",
            noise=noise,
        )
        return critic_td_target(
            self.critic_target,
            replay_data.next_observations,
            next_actions,
            replay_data.rewards,
            bootstrap,
            self._target_scoring_copy,
        )

    def _policy_action_values(self, obs: Any, mean: th.Tensor, std: th.Tensor, noise: Optional[th.Tensor] = None) -> th.Tensor:
        """
        :return: Q-values ``[num_samples, batch]`` of ``num_samples`` actions per state sampled from the policy,
            by the online critic (the advantage's baseline; its low-precision copy is synchronised by the caller)
        """
        sampled_actions = sample_gaussian(mean, std, self.num_samples, noise)  # [N, B, A]
        return score_actions(self.critic, obs, sampled_actions, self._online_scoring_copy)

    def _update_actor_average(self) -> None:
        assert self.policy.actor_average is not None and self.actor_averaging is not None
        polyak_update(self.actor.parameters(), self.policy.actor_average.parameters(), self.actor_averaging)

    def learn(
        self: SelfCRR,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "CRR",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfCRR:
        if self.critic_target_type == "sarsa":
            raise ValueError("critic_target='sarsa' needs the data's next actions: it is for offline training only")
        if self.actor_per_source:
            raise ValueError("actor_per_source=True is an offline diagnostic: train it with learn_offline")
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "actor",
            "critic",
            "actor_target",
            "critic_target",
            "_head_of_source",
            "_target_scoring_copy",
            "_online_scoring_copy",
        ]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        return state_dicts, []
