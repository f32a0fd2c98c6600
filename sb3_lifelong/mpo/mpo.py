"""Maximum a Posteriori Policy Optimisation (MPO), online; its losses are in :mod:`sb3_lifelong.mpo.losses`."""

from typing import Any, ClassVar, NamedTuple, Optional, TypeVar, Union

import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy, ContinuousCritic
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, ReplayBufferSamples, Schedule
from torch.profiler import record_function

from sb3_lifelong.common.arguments import check_sizes_of
from sb3_lifelong.common.base import LifelongOffPolicyAlgorithm
from sb3_lifelong.common.losses import bootstrap_discount, q_regression_loss, td_target
from sb3_lifelong.common.policies import GaussianActor, sample_gaussian, with_fast_optimizer
from sb3_lifelong.core.settings import Settings
from sb3_lifelong.mpo.losses import DUAL_RAW_FLOOR, dual_value, e_step, inverse_softplus, m_step_loss, trust_region
from sb3_lifelong.mpo.policies import CnnPolicy, MlpPolicy, MPOPolicy, MultiInputPolicy
from sb3_lifelong.mpo.settings import PolicyLossConfig
from sb3_lifelong.numerics.compiling import LazyCompiled
from sb3_lifelong.numerics.scoring import score_actions
from sb3_lifelong.numerics.settings import ComputeSettings

SelfMPO = TypeVar("SelfMPO", bound="MPO")


class TargetSamples(NamedTuple):
    """One no-grad pass of the target networks, shared by the critic's target and the E-step."""

    #: the critic's expected-SARSA target ``[batch, 1]``
    critic_target: th.Tensor
    #: the target policy's mean and std on the states the policy is improved on, ``[batch, action_dim]`` each
    mean: th.Tensor
    std: th.Tensor
    #: actions sampled from the target policy on those states ``[num_samples, batch, action_dim]``
    actions: th.Tensor
    #: their Q-values under the target critic ``[num_samples, batch]``
    q_values: th.Tensor


class CriticFit(NamedTuple):
    """What the critic's update logs."""

    critic_loss: th.Tensor
    q_mean: th.Tensor


class PolicyImprovement(NamedTuple):
    """What the actor's and duals' update logs (``penalty_temperature`` only with the action penalty)."""

    actor_loss: th.Tensor
    temperature: th.Tensor
    alpha_mean: th.Tensor
    alpha_stddev: th.Tensor
    kl_mean: th.Tensor
    kl_stddev: th.Tensor
    std_min: th.Tensor
    std_max: th.Tensor
    #: effective sample size of the E-step weights, as a fraction of ``num_samples``
    ess: th.Tensor
    penalty_temperature: Optional[th.Tensor] = None


class MPO(LifelongOffPolicyAlgorithm):
    """
    Maximum a Posteriori Policy Optimisation (MPO), with a decoupled M-step and per-dimension KL constraints.

    Papers: https://arxiv.org/abs/1806.06920 and https://arxiv.org/abs/1812.02256
    (action penalty: Multi-Objective MPO, https://arxiv.org/abs/2005.07513)

    Each gradient step samples ``num_samples`` actions per state from the target policy and scores them with
    the target critic in one batched call. The same Q-values give the critic's expected-SARSA target and the
    E-step weights, because the policy is improved on the batch's next observations
    (``policy_on_next_obs=True``, as in Acme).

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, MultiInputPolicy, ...)
    :param env: The environment to learn from (if registered in Gym, can be str)
    :param learning_rate: learning rate of the actor and critic (Adam), a constant or a schedule of the
        remaining progress
    :param buffer_size: size of the replay buffer
    :param learning_starts: how many steps of the model to collect transitions for before learning starts
    :param batch_size: Minibatch size for each gradient update
    :param tau: the target networks' update coefficient, applied every ``target_update_interval`` updates
        (1.0: hard copy, the default; use e.g. ``tau=0.005, target_update_interval=1`` for Polyak averaging)
    :param gamma: the discount factor
    :param train_freq: Update the model every ``train_freq`` steps. Alternatively pass a tuple of frequency and
        unit like ``(5, "step")`` or ``(2, "episode")``.
    :param gradient_steps: How many gradient steps to do after each rollout (-1: as many as environment steps)
    :param action_noise: extra action noise (the Gaussian policy explores on its own; usually None)
    :param replay_buffer_class: Replay buffer class to use (for instance ``LifelongReplayBuffer``)
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
    :param n_steps: n-step returns for the critic (SB3's ``NStepReplayBuffer`` when no buffer class is given)
    :param num_samples: number of actions sampled per state in the E-step and for the critic's target
    :param policy_loss: the KL bounds of the policy improvement, the duals' initial values and the action penalty:
        a :class:`~sb3_lifelong.mpo.PolicyLossConfig` or a dict of some of its settings (None: its defaults), e.g.
        ``policy_loss=dict(epsilon_mean=0.01, action_penalty=True)``
    :param dual_learning_rate: learning rate of the dual variables' own Adam optimizer
    :param target_update_interval: number of gradient updates between two target network updates
    :param max_grad_norm: maximum norm of the actor's and the critic's gradients
    :param policy_on_next_obs: improve the policy on the batch's next observations, so that one target critic
        call serves both the E-step and the critic target; if False the policy is improved on the observations
        (still one call, over both observations and next observations)
    :param compute: the updates' precision and compilation: a :class:`~sb3_lifelong.numerics.ComputeSettings` or a
        dict of some of its settings (None: its defaults, ``scoring_dtype="auto"``, ``train_dtype="float32"``,
        ``compile_losses="auto"``)
    :param stats_window_size: Window size for the rollout logging
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation
    :param verbose: Verbosity level: 0 for no output, 1 for info messages, 2 for debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    settings_groups: ClassVar[dict[str, type[Settings]]] = {"policy_loss": PolicyLossConfig, "compute": ComputeSettings}
    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: MPOPolicy
    actor: GaussianActor
    actor_target: GaussianActor
    critic: ContinuousCritic
    critic_target: ContinuousCritic
    _forward: LazyCompiled

    def __init__(
        self,
        policy: Union[str, type[MPOPolicy]],
        env: Union[GymEnv, str],
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
        num_samples: int = 20,
        policy_loss: Optional[Union[PolicyLossConfig, dict[str, Any]]] = None,
        dual_learning_rate: float = 1e-2,
        target_update_interval: int = 100,
        max_grad_norm: float = 40.0,
        policy_on_next_obs: bool = True,
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
            env,
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
        self.num_samples = num_samples
        self.policy_loss = PolicyLossConfig.of(policy_loss, "policy_loss")
        self.dual_learning_rate = dual_learning_rate
        self.target_update_interval = target_update_interval
        self.max_grad_norm = max_grad_norm
        self.policy_on_next_obs = policy_on_next_obs
        self.compute = ComputeSettings.of(compute, "compute")
        if self._policy_has_torso_choice():
            # the torso is written into policy_kwargs, so that every save says which one it has (see _setup_model)
            self.policy_kwargs = {"layer_norm": True, **self.policy_kwargs}
        self._check_hyperparameters()
        if _init_setup_model:
            self._setup_model()

    def _check_hyperparameters(self) -> None:
        check_sizes_of(self)
        checks = {
            "num_samples": self.num_samples >= 1,
            "dual_learning_rate": self.dual_learning_rate > 0,
            "target_update_interval": self.target_update_interval >= 1,
            "tau": 0.0 < self.tau <= 1.0,
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            values = ", ".join(f"{name}={getattr(self, name)!r}" for name in bad)
            raise ValueError(
                f"Invalid MPO hyperparameters: {values} (num_samples and target_update_interval must be >= 1, "
                "dual_learning_rate > 0, tau in (0, 1])"
            )

    def _policy_has_torso_choice(self) -> bool:
        """:return: whether the policy class is one of MPO's (whose ``layer_norm`` defaults to ``True``)"""
        return isinstance(self.policy_class, type) and issubclass(self.policy_class, MPOPolicy)

    def _setup_model(self) -> None:
        super()._setup_model()
        self._create_aliases()
        loss = self.policy_loss
        action_dim = get_action_dim(self.action_space)
        # Dual variables, parametrised through softplus to stay positive, with their own optimizer. The ``log_*``
        # attributes hold the raw (inverse-softplus) parameters, not logarithms: ``dual_value`` gives the variables.
        # They keep these names because saved models store them under them (``_get_torch_save_params``).
        self.log_temperature = th.full((1,), inverse_softplus(loss.init_temperature), device=self.device).requires_grad_(True)
        self.log_alpha_mean = th.full(
            (action_dim,), inverse_softplus(loss.init_alpha_mean), device=self.device
        ).requires_grad_(True)
        self.log_alpha_stddev = th.full(
            (action_dim,), inverse_softplus(loss.init_alpha_stddev), device=self.device
        ).requires_grad_(True)
        self.log_penalty_temperature = th.full(
            (1,), inverse_softplus(loss.init_temperature), device=self.device
        ).requires_grad_(True)
        self.dual_optimizer = th.optim.Adam(
            [dual for _, dual in self._trained_duals()], lr=self.dual_learning_rate, **with_fast_optimizer(th.optim.Adam, None)
        )
        self._apply_train_dtype()
        self._target_scoring_copy = self._make_scoring_copy(self.critic_target)
        self._forward = LazyCompiled(
            self._forward_pass, "MPO's forward pass", self._trained_parameters, self._compiled_check_tolerance()
        )

    def _trained_duals(self) -> list[tuple[str, th.Tensor]]:
        """:return: the duals the update trains, named (the action penalty's temperature only with the penalty)"""
        names = ["log_temperature", "log_alpha_mean", "log_alpha_stddev"]
        names += ["log_penalty_temperature"] * self.policy_loss.action_penalty
        return [(name, getattr(self, name)) for name in names]

    def _trained_parameters(self) -> list[tuple[str, th.Tensor]]:
        """:return: what the update's losses are differentiated with respect to: the policy's parameters and the duals"""
        return [*self.policy.named_parameters(), *self._trained_duals()]

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.actor_target = self.policy.actor_target
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target

    @property
    def temperature(self) -> float:
        """Current value of the E-step temperature dual."""
        return float(dual_value(self.log_temperature).item())

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        logged: list[tuple[CriticFit, PolicyImprovement]] = []
        assert self.replay_buffer is not None

        compiled = self._compiles_now()
        self._compile_scoring_copies(compiled)
        for _ in range(gradient_steps):
            self._n_updates += 1
            with record_function("mpo/sample_batch"):
                replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
                noise = self._sampling_noise(replay_data)
            with record_function("mpo/forward"):
                critic_fit, improvement, actor_and_dual_loss = self._forward(compiled, replay_data, noise)
            with record_function("mpo/backward_and_steps"):
                critic_part, actor_part = (self.critic, critic_fit.critic_loss), (self.actor, actor_and_dual_loss)
                duals = [self.dual_optimizer]  # stepped with the actor, not clipped
                if compiled:  # one backward through the compiled graph (the losses reach disjoint parameters)
                    self._gradient_step(critic_part, actor_part, max_grad_norm=self.max_grad_norm, also_step=duals)
                else:
                    self._gradient_step(critic_part, max_grad_norm=self.max_grad_norm)
                    self._gradient_step(actor_part, max_grad_norm=self.max_grad_norm, also_step=duals)
                with th.no_grad():
                    for raw in self.dual_optimizer.param_groups[0]["params"]:
                        raw.clamp_(min=DUAL_RAW_FLOOR)
            critic_fit = critic_fit._replace(critic_loss=critic_fit.critic_loss.detach())
            logged.append((critic_fit, improvement))
            # one check per update, before the targets take anything non-finite (the duals: after their step)
            self._raise_if_not_finite(
                critic_loss=critic_fit.critic_loss,
                actor_loss=improvement.actor_loss,
                log_temperature=self.log_temperature,
                log_alpha_mean=self.log_alpha_mean,
                log_alpha_stddev=self.log_alpha_stddev,
                log_penalty_temperature=self.log_penalty_temperature,
            )
            if self._n_updates % self.target_update_interval == 0:
                self._update_targets()

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for stats in ([fit for fit, _ in logged], [improvement for _, improvement in logged]):
            for key in stats[0]._fields if stats else ():
                values = [getattr(step, key) for step in stats if getattr(step, key) is not None]
                if values:
                    self.logger.record(f"train/{key}", th.stack(values).mean().item())

    def _sampling_noise(self, replay_data: ReplayBufferSamples) -> th.Tensor:
        """:return: the standard normal draws of the target policy's samples ``[num_samples, rows, action_dim]``"""
        rows = replay_data.rewards.shape[0] * (1 if self.policy_on_next_obs else 2)
        return th.randn((self.num_samples, rows, replay_data.actions.shape[1]), device=self.device)

    def _forward_pass(
        self, replay_data: ReplayBufferSamples, noise: th.Tensor
    ) -> tuple[CriticFit, PolicyImprovement, th.Tensor]:
        """
        An update's forward pass: what ``compute.compile_losses`` compiles.

        :param replay_data: the batch
        :param noise: the target policy's samples' standard normal draws (:meth:`_sampling_noise`)
        :return: the critic's fit (its loss differentiable), what the policy improvement logs, and the loss of the
            actor and the duals (the M-step's, the trust region's and the duals', differentiable)
        """
        with th.no_grad(), record_function("mpo/target_sample_and_score"):
            targets = self._sample_and_score(replay_data, noise)
        with record_function("mpo/critic_loss"):
            critic_fit = self._critic_fit(replay_data, targets.critic_target)
        with record_function("mpo/actor_and_dual_loss"):
            policy_obs = replay_data.next_observations if self.policy_on_next_obs else replay_data.observations
            improvement, loss = self._policy_improvement(policy_obs, targets)
        return critic_fit, improvement, loss

    def _sample_and_score(self, replay_data: ReplayBufferSamples, noise: Optional[th.Tensor] = None) -> TargetSamples:
        """
        Sample ``num_samples`` actions per state from the target policy and score them with the target critic,
        in one critic call that serves both the critic's target and the E-step.

        :param replay_data: the batch
        :param noise: the samples' standard normal draws (None: drawn here)
        :return: the critic's target and the scored samples of the target policy
        """
        num_samples, batch_size = self.num_samples, replay_data.rewards.shape[0]
        obs, next_obs = replay_data.observations, replay_data.next_observations
        if self.policy_on_next_obs:
            target_mean, target_std = self.actor_target.distribution_params(next_obs)
            sampled_actions = sample_gaussian(target_mean, target_std, num_samples, noise)  # [N, B, A]
            sampled_q = score_actions(self.critic_target, next_obs, sampled_actions, self._target_scoring_copy)  # [N, B]
            next_q = sampled_q.mean(dim=0)
        else:
            # One actor call and one critic call over [obs; next_obs]
            both_obs = _concat_obs(obs, next_obs)
            both_mean, both_std = self.actor_target.distribution_params(both_obs)
            both_actions = sample_gaussian(both_mean, both_std, num_samples, noise)  # [N, 2B, A]
            both_q = score_actions(self.critic_target, both_obs, both_actions, self._target_scoring_copy)  # [N, 2B]
            target_mean, target_std = both_mean[:batch_size], both_std[:batch_size]
            sampled_actions, sampled_q = both_actions[:, :batch_size], both_q[:, :batch_size]
            next_q = both_q[:, batch_size:].mean(dim=0)
        # Expected SARSA over the target policy's samples (n-step discount from the buffer when it has one)
        target_q = td_target(replay_data.rewards, bootstrap_discount(replay_data, self.gamma), next_q)
        return TargetSamples(target_q, target_mean, target_std, sampled_actions, sampled_q)

    def _critic_fit(self, replay_data: ReplayBufferSamples, target_q: th.Tensor) -> CriticFit:
        """:return: the critic's loss on the batch (differentiable) and its mean Q"""
        current_q_values = self.critic(replay_data.observations, replay_data.actions)
        critic_loss = q_regression_loss(current_q_values, target_q)
        return CriticFit(critic_loss=critic_loss, q_mean=current_q_values[0].detach().mean())

    def _policy_improvement(self, policy_obs: Any, targets: TargetSamples) -> tuple[PolicyImprovement, th.Tensor]:
        """
        :return: what the policy improvement logs, and the loss of the actor and the duals: the M-step's, its trust
            region's and the duals' (differentiable; the caller steps the actor's and the duals' optimizers)
        """
        # E-step: weights of the sampled actions (one set per objective), temperature duals
        temperature = dual_value(self.log_temperature)
        loss = self.policy_loss
        penalty_temperature = dual_value(self.log_penalty_temperature) if loss.action_penalty else None
        improved = e_step(
            targets.q_values, targets.actions, temperature, loss.epsilon, penalty_temperature, loss.epsilon_penalty
        )

        # M-step, decoupled, under per-dimension KL constraints
        online_mean, online_std = self.actor.distribution_params(policy_obs)
        policy_loss = m_step_loss(targets.actions, improved.weights, online_mean, online_std, targets.mean, targets.std)
        alpha_mean = dual_value(self.log_alpha_mean)
        alpha_stddev = dual_value(self.log_alpha_stddev)
        region = trust_region(
            targets.mean,
            targets.std,
            online_mean,
            online_std,
            alpha_mean,
            alpha_stddev,
            loss.epsilon_mean,
            loss.epsilon_stddev,
        )
        dual_loss = improved.dual_loss + region.dual_loss
        improvement = PolicyImprovement(
            actor_loss=policy_loss.detach(),
            temperature=temperature.detach().squeeze(),
            alpha_mean=alpha_mean.detach().mean(),
            alpha_stddev=alpha_stddev.detach().mean(),
            kl_mean=region.kl_mean.detach().mean(),
            kl_stddev=region.kl_stddev.detach().mean(),
            std_min=online_std.detach().min(),
            std_max=online_std.detach().max(),
            ess=(1.0 / improved.weights[0].pow(2).sum(dim=0)).mean() / self.num_samples,
            penalty_temperature=None if penalty_temperature is None else penalty_temperature.detach().squeeze(),
        )
        return improvement, policy_loss + region.kl_loss + dual_loss

    def learn(
        self: SelfMPO,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "MPO",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMPO:
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
            "_target_scoring_copy",
        ]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer", "dual_optimizer"]
        saved_pytorch_variables = ["log_temperature", "log_alpha_mean", "log_alpha_stddev", "log_penalty_temperature"]
        return state_dicts, saved_pytorch_variables


def _concat_obs(first: Any, second: Any) -> Any:
    if isinstance(first, dict):
        return {key: th.cat([first[key], second[key]], dim=0) for key in first}
    return th.cat([first, second], dim=0)
