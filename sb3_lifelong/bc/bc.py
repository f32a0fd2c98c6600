"""Behaviour cloning (BC) with a Gaussian policy, trained offline."""

from typing import Any, ClassVar, Optional, TypeVar, Union

import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule

from sb3_lifelong.bc.policies import BCPolicy, CnnPolicy, MlpPolicy, MultiInputPolicy
from sb3_lifelong.common.arguments import check_sizes_of
from sb3_lifelong.common.base import LifelongOffPolicyAlgorithm
from sb3_lifelong.common.offline import OfflineLearning
from sb3_lifelong.common.policies import GaussianActor, gaussian_log_prob

SelfBC = TypeVar("SelfBC", bound="BC")

BC_LOSSES = ("nll", "mse")


class BC(OfflineLearning, LifelongOffPolicyAlgorithm):
    """
    Behaviour cloning: maximum likelihood of the data's actions under a Gaussian policy (``loss="nll"``), or
    regression of the policy's mean on them (``loss="mse"``). The paper's BC baseline.

    Train it offline: ``BC.from_offline_data(data).learn_offline(total_updates)``. It is an SB3
    ``OffPolicyAlgorithm`` like CRR, so ``learn(...)`` online also runs, cloning the policy's own rollouts,
    which is only useful to test a pipeline.

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, MultiInputPolicy, ...)
    :param env: environment (optional: gives the spaces, and can be used for evaluation); None for offline data
    :param learning_rate: learning rate (Adam), a constant or a schedule of the remaining progress
    :param buffer_size: size of the replay buffer (online; offline it is the data's size)
    :param learning_starts: how many steps of the model to collect transitions for before learning starts (online)
    :param batch_size: Minibatch size for each gradient update
    :param gamma: the discount factor (unused by the loss, kept for n-step buffers and SB3 compatibility)
    :param train_freq: Update the model every ``train_freq`` steps (online)
    :param gradient_steps: How many gradient steps to do after each rollout (online)
    :param replay_buffer_class: Replay buffer class to use
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation
    :param loss: ``"nll"`` (negative log-likelihood of the Gaussian; learns the standard deviation too) or
        ``"mse"`` (squared error of the mean; the standard deviation is left as initialised)
    :param max_grad_norm: maximum norm of the gradient (None: no clipping)
    :param stats_window_size: Window size for the rollout logging
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation (``net_arch``, ...)
    :param verbose: Verbosity level: 0 for no output, 1 for info messages, 2 for debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: BCPolicy
    actor: GaussianActor

    def __init__(
        self,
        policy: Union[str, type[BCPolicy]],
        env: Optional[Union[GymEnv, str]] = None,
        learning_rate: Union[float, Schedule] = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        gamma: float = 0.99,
        train_freq: Union[int, tuple[int, str]] = 1,
        gradient_steps: int = 1,
        replay_buffer_class: Optional[type[ReplayBuffer]] = None,
        replay_buffer_kwargs: Optional[dict[str, Any]] = None,
        loss: str = "nll",
        max_grad_norm: Optional[float] = None,
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
            1.0,
            gamma,
            train_freq,
            gradient_steps,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
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
        check_sizes_of(self)
        if loss not in BC_LOSSES:
            raise ValueError(f"Invalid BC hyperparameters: loss={loss!r} (must be one of {BC_LOSSES})")
        if max_grad_norm is not None and max_grad_norm <= 0:
            raise ValueError(f"Invalid BC hyperparameters: max_grad_norm={max_grad_norm!r} (must be > 0 or None)")
        self.loss = loss
        self.max_grad_norm = max_grad_norm
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        super()._setup_model()
        self.actor = self.policy.actor

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer])
        losses, nlls, errors, stds = [], [], [], []
        assert self.replay_buffer is not None
        for _ in range(gradient_steps):
            self._n_updates += 1
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            mean, std = self.actor.distribution_params(replay_data.observations)
            nll = -gaussian_log_prob(replay_data.actions, mean, std).mean()
            mse = (mean - replay_data.actions).pow(2).sum(dim=-1).mean()
            loss = nll if self.loss == "nll" else mse
            self._gradient_step((self.actor, loss), max_grad_norm=self.max_grad_norm)
            losses.append(loss.detach())
            nlls.append(nll.detach())
            errors.append(mse.detach())
            stds.append(std.detach().mean())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        if losses:
            for key, values in (("actor_loss", losses), ("nll", nlls), ("mse", errors), ("std_mean", stds)):
                self.logger.record_mean(f"train/{key}", th.stack(values).mean().item())

    def learn(
        self: SelfBC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "BC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfBC:
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "actor"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", "actor.optimizer"], []
