"""
Policies shared by the algorithms of this package: a Gaussian actor and an actor-critic with target networks, the
Gaussian's arithmetic (log-density, KL, samples) and the networks' building blocks (:func:`mlp_layers`, the
optimizer's defaults).
"""

import copy
import math
from collections.abc import Iterable
from typing import Any, Callable, Optional, Union

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel, BasePolicy, ContinuousCritic
from stable_baselines3.common.preprocessing import get_action_dim, is_image_space, is_image_space_channels_first
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    CombinedExtractor,
    FlattenExtractor,
    NatureCNN,
    create_mlp,
    get_actor_critic_arch,
)
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn
from torch.nn import functional as F

from sb3_lifelong.numerics.fast_ops import HiddenLinear, Tanh

LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def gaussian_log_prob(actions: th.Tensor, mean: th.Tensor, std: th.Tensor) -> th.Tensor:
    """
    Log-density of a diagonal Gaussian, summed over the last (action) dimension.

    Written out rather than through ``torch.distributions`` (no argument validation, no object creation):
    it is called several times per gradient step.

    :param actions: points at which to evaluate the density, shape ``[..., action_dim]``
    :param mean: mean, broadcastable to ``actions``
    :param std: standard deviation (> 0), broadcastable to ``actions``
    :return: log-density, shape ``[...]``
    """
    z = (actions - mean) / std
    return (-0.5 * z.pow(2) - th.log(std) - LOG_SQRT_2PI).sum(dim=-1)


def set_training_flags(owner: nn.Module, mode: bool, *roots: nn.Module) -> None:
    """
    ``root.train(mode)`` for every root, through a flat list of their modules cached on ``owner``: SB3 switches
    modes twice per environment step (``predict`` then ``train``), and ``nn.Module.train``'s recursion costs
    about as much as a whole small-network update step's optimizer.

    :param owner: the module that keeps the list (its own ``training`` flag is set too)
    :param mode: training (True) or evaluation (False)
    :param roots: the modules to switch with all their submodules
    """
    cached = owner.__dict__.get("_mode_modules")
    if cached is None or len(cached[0]) != len(roots) or any(a is not b for a, b in zip(cached[0], roots)):
        # the roots are kept with the list: a policy whose networks were replaced builds a new one
        cached = owner.__dict__["_mode_modules"] = (roots, [m for root in roots for m in root.modules()])
    for module in cached[1]:
        module.training = mode
    owner.training = mode


def gaussian_kl_per_dim(mean_p: th.Tensor, std_p: th.Tensor, mean_q: th.Tensor, std_q: th.Tensor) -> th.Tensor:
    """
    ``KL(N(mean_p, std_p) || N(mean_q, std_q))`` for each action dimension (no sum).

    :return: KL divergence with the broadcast shape of the inputs
    """
    var_ratio = (std_p / std_q).pow(2)
    return 0.5 * (var_ratio + ((mean_p - mean_q) / std_q).pow(2) - 1.0 - th.log(var_ratio))


def sample_gaussian(mean: th.Tensor, std: th.Tensor, num_samples: int, noise: Optional[th.Tensor] = None) -> th.Tensor:
    """
    :param mean: ``[batch, action_dim]``
    :param std: ``[batch, action_dim]``
    :param num_samples: number of samples per state
    :param noise: standard normal draws ``[num_samples, batch, action_dim]`` to use (None: drawn here, the same
        draws as ``th.randn((num_samples, *mean.shape))`` would give)
    :return: samples ``[num_samples, batch, action_dim]`` (not clipped)
    """
    if noise is None:
        noise = th.randn((num_samples, *mean.shape), dtype=mean.dtype, device=mean.device)
    return mean.unsqueeze(0) + std.unsqueeze(0) * noise


def mlp_layers(
    input_dim: int, output_dim: int, net_arch: list[int], activation_fn: type[nn.Module], layer_norm: bool = False
) -> list[nn.Module]:
    """
    SB3's ``create_mlp``, or with ``layer_norm`` the torso of Acme's ``LayerNormMLP`` (its MPO's actor and critic
    networks): the first hidden layer is ``Linear -> LayerNorm -> tanh``, the others ``Linear -> activation_fn``. The
    tanh is :class:`sb3_lifelong.numerics.fast_ops.Tanh` (an ``nn.Tanh``, faster on a CPU, within about 1e-7 of it).

    :param input_dim: Input features
    :param output_dim: Output units of a last ``Linear`` without activation (none if <= 0)
    :param net_arch: Hidden layer widths
    :param activation_fn: Activation of the hidden layers (all of them without ``layer_norm``; the later ones with)
    :param layer_norm: LayerNorm and tanh after the first hidden layer
    :return: the modules, for ``nn.Sequential``; the ``Linear`` layers from one hidden layer to the next are
        :class:`~sb3_lifelong.numerics.fast_ops.HiddenLinear` (the same parameters, initialised as SB3 does)
    """
    if not layer_norm or not net_arch:
        layers = create_mlp(input_dim, output_dim, net_arch, activation_fn)
    else:
        first = [nn.Linear(input_dim, net_arch[0]), nn.LayerNorm(net_arch[0]), Tanh()]
        layers = first + create_mlp(net_arch[0], output_dim, net_arch[1:], activation_fn)
    linears = [layer for layer in layers if isinstance(layer, nn.Linear)]
    between_hidden = {id(layer) for layer in (linears[1:-1] if output_dim > 0 else linears[1:])}
    return [
        HiddenLinear.of(layer) if isinstance(layer, nn.Linear) and id(layer) in between_hidden else layer for layer in layers
    ]


def policy_alias_for(observation_space: spaces.Space) -> str:
    """
    The policy alias an observation space calls for, as SB3 names them: ``"MultiInputPolicy"`` for a Dict space,
    ``"CnnPolicy"`` for a channel-first image (SB3's ``is_image_space``: a ``uint8`` Box ``(C, H, W)`` of bounds 0 and
    255, as SB3 stores an environment's images), ``"MlpPolicy"`` otherwise, channel-last images ``(H, W, C)``
    included (a CNN would read their height as channels). What a model built from data uses when it is given no
    policy (``from_offline_data(data, policy=None)``, ``distill`` from data).

    :param observation_space: the model's observation space
    :return: the alias
    """
    if isinstance(observation_space, spaces.Dict):
        return "MultiInputPolicy"
    box = observation_space if isinstance(observation_space, spaces.Box) else None
    if box is not None and is_image_space(box, check_channels=False) and is_image_space_channels_first(box):
        return "CnnPolicy"
    return "MlpPolicy"


def with_fast_optimizer(optimizer_class: type[th.optim.Optimizer], optimizer_kwargs: Optional[dict]) -> dict:
    """
    :param optimizer_class: the optimizer class a policy was given
    :param optimizer_kwargs: the keyword arguments it was given (None: none)
    :return: the keyword arguments, with Adam's fused implementation unless the user chose an implementation
    """
    kwargs = dict(optimizer_kwargs or {})
    if optimizer_class in (th.optim.Adam, th.optim.AdamW) and not {"fused", "foreach"} & set(kwargs):
        kwargs["fused"] = True
    return kwargs


class GaussianActor(BasePolicy):
    """
    Diagonal Gaussian actor for Box action spaces, working in the normalised action space ``[-1, 1]``.

    The mean is squashed by ``tanh`` (optional) and the standard deviation is
    ``softplus(h) * init_std / softplus(0) + min_std``, so that a freshly initialised actor has a standard
    deviation close to ``init_std``. Sampled actions are clipped to ``[-1, 1]`` before they reach the environment.

    :param observation_space: Observation space
    :param action_space: Action space
    :param net_arch: Network architecture
    :param features_extractor: Network to extract features
    :param features_dim: Number of features
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param squash_mean: Whether to squash the mean with ``tanh`` into ``[-1, 1]``
    :param init_std: Standard deviation of the initial policy (normalised action units)
    :param min_std: Lower bound of the standard deviation
    :param layer_norm: LayerNorm and tanh after the first hidden layer, as Acme's ``LayerNormMLP`` (see
        :func:`mlp_layers`)
    :param head_init_scale: None for torch's default initialisation of the mean's and the standard deviation's output
        layers; a float ``s`` draws their weights from a normal truncated at two standard deviations, of variance
        ``s / fan_in``, with zero biases (Acme's ``MultivariateNormalDiagHead``: ``s = 1e-4``), so that the initial policy
        has a mean near 0 and a standard deviation near ``init_std`` in every state
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: nn.Module,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        squash_mean: bool = True,
        init_std: float = 0.7,
        min_std: float = 1e-4,
        layer_norm: bool = False,
        head_init_scale: Optional[float] = None,
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor=features_extractor,
            normalize_images=normalize_images,
            squash_output=True,
        )
        if init_std <= 0 or min_std < 0:
            raise ValueError(f"init_std must be > 0 and min_std >= 0, got init_std={init_std}, min_std={min_std}")
        if head_init_scale is not None and not (isinstance(head_init_scale, (int, float)) and head_init_scale > 0):
            raise ValueError(f"head_init_scale must be None or a number > 0, got {head_init_scale!r}")
        self.net_arch = net_arch
        self.features_dim = features_dim
        self.activation_fn = activation_fn
        self.squash_mean = squash_mean
        self.init_std = init_std
        self.min_std = min_std
        self.layer_norm = layer_norm
        action_dim = get_action_dim(self.action_space)
        self.latent_pi = nn.Sequential(*mlp_layers(features_dim, -1, net_arch, activation_fn, layer_norm))
        last_layer_dim = net_arch[-1] if len(net_arch) > 0 else features_dim
        self.mu = nn.Linear(last_layer_dim, action_dim)
        self.std_head = nn.Linear(last_layer_dim, action_dim)
        self._std_scale = init_std / math.log(2.0)  # softplus(0) = log(2)
        self.head_init_scale = head_init_scale
        if head_init_scale is not None:
            for head in (self.mu, self.std_head):
                std = math.sqrt(head_init_scale / head.in_features)
                nn.init.trunc_normal_(head.weight, std=std, a=-2.0 * std, b=2.0 * std)
                nn.init.zeros_(head.bias)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                net_arch=self.net_arch,
                features_dim=self.features_dim,
                activation_fn=self.activation_fn,
                features_extractor=self.features_extractor,
                squash_mean=self.squash_mean,
                init_std=self.init_std,
                min_std=self.min_std,
                layer_norm=self.layer_norm,
                head_init_scale=self.head_init_scale,
            )
        )
        return data

    def distribution_params(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """
        :param obs: Observation
        :return: mean and standard deviation of the action distribution, each ``[batch, action_dim]``
        """
        features = self.extract_features(obs, self.features_extractor)
        latent = self.latent_pi(features)
        mean = self.mu(latent)
        if self.squash_mean:
            mean = th.tanh(mean)
        std = F.softplus(self.std_head(latent)) * self._std_scale + self.min_std
        return mean, std

    def log_prob(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """
        :param obs: Observation
        :param actions: actions in the normalised action space, ``[batch, action_dim]``
        :return: log-likelihood of ``actions``, ``[batch]``
        """
        mean, std = self.distribution_params(obs)
        return gaussian_log_prob(actions, mean, std)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        mean, std = self.distribution_params(obs)
        if deterministic:
            return mean.clamp(-1.0, 1.0)
        return (mean + std * th.randn_like(mean)).clamp(-1.0, 1.0)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self(observation, deterministic)


class GaussianPolicy(BasePolicy):
    """
    What every policy of this package has: a :class:`GaussianActor`'s settings, a features extractor and an
    optimizer. Its subclasses build the networks (:class:`GaussianActorCriticPolicy` for MPO and CRR, BC's
    ``BCPolicy``) and add their own parameters by keyword.

    :param observation_space: Observation space
    :param action_space: Action space (Box)
    :param lr_schedule: Learning rate schedule (could be constant)
    :param net_arch: The hidden layers (a list; or a dict with ``pi`` and ``qf`` for an actor-critic)
    :param activation_fn: Activation function
    :param squash_mean: Whether the actor's mean is squashed by ``tanh``
    :param init_std: Standard deviation of the initial policy (normalised action units)
    :param min_std: Lower bound of the policy's standard deviation
    :param layer_norm: LayerNorm and tanh after the first hidden layer of every network (actor and critics), as
        Acme's ``LayerNormMLP`` (see :func:`mlp_layers`)
    :param head_init_scale: the initial weight scale of the actor's output layers (None: torch's default; see
        :class:`GaussianActor`)
    :param features_extractor_class: Features extractor to use
    :param features_extractor_kwargs: Keyword arguments to pass to the features extractor
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param optimizer_class: The optimizer to use, ``th.optim.Adam`` by default
    :param optimizer_kwargs: Additional keyword arguments, excluding the learning rate, to pass to the optimizer
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: Optional[Union[list[int], dict[str, list[int]]]] = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        squash_mean: bool = True,
        init_std: float = 0.7,
        min_std: float = 1e-4,
        layer_norm: bool = False,
        head_init_scale: Optional[float] = None,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: Optional[dict[str, Any]] = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: Optional[dict[str, Any]] = None,
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=optimizer_class,
            optimizer_kwargs=with_fast_optimizer(optimizer_class, optimizer_kwargs),
            squash_output=True,
            normalize_images=normalize_images,
        )
        if not isinstance(action_space, spaces.Box):
            raise TypeError(f"{type(self).__name__} supports only gymnasium.spaces.Box actions, got {action_space}")
        self.net_arch = [256, 256] if net_arch is None else net_arch
        self.activation_fn = activation_fn
        self.squash_mean = squash_mean
        self.init_std = init_std
        self.min_std = min_std
        self.layer_norm = layer_norm
        self.head_init_scale = head_init_scale
        self.actor_kwargs: dict[str, Any] = {
            "observation_space": self.observation_space,
            "action_space": self.action_space,
            "net_arch": get_actor_critic_arch(self.net_arch)[0],
            "activation_fn": activation_fn,
            "normalize_images": normalize_images,
            "squash_mean": squash_mean,
            "init_std": init_std,
            "min_std": min_std,
            "layer_norm": layer_norm,
            "head_init_scale": head_init_scale,
        }

    #: a :class:`GaussianActor` (see the subclasses' declarations; CRR's may be one actor per data source)
    actor: BasePolicy

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                net_arch=self.net_arch,
                activation_fn=self.activation_fn,
                squash_mean=self.squash_mean,
                init_std=self.init_std,
                min_std=self.min_std,
                layer_norm=self.layer_norm,
                head_init_scale=self.head_init_scale,
                lr_schedule=self._dummy_schedule,  # dummy lr schedule, not needed for loading policy alone
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
                features_extractor_class=self.features_extractor_class,
                features_extractor_kwargs=self.features_extractor_kwargs,
            )
        )
        return data

    def make_actor(self, features_extractor: Optional[BaseFeaturesExtractor] = None) -> GaussianActor:
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return GaussianActor(**actor_kwargs).to(self.device)

    def make_optimizer(self, parameters: Iterable[nn.Parameter], lr_schedule: Schedule) -> th.optim.Optimizer:
        """
        :param parameters: what the optimizer trains
        :param lr_schedule: the learning rate schedule (its value at the start is used)
        :return: an ``optimizer_class`` with ``optimizer_kwargs``
        """
        # called as the constructor it is: the learning rate is a keyword of every optimizer, not of the base class
        optimizer_class: Callable[..., th.optim.Optimizer] = self.optimizer_class
        return optimizer_class(parameters, lr=lr_schedule(1), **self.optimizer_kwargs)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self.actor(observation, deterministic)


class QCritic(ContinuousCritic):
    """
    SB3's ``ContinuousCritic`` (Q-networks on the features and the action), with the option of a LayerNorm first
    layer. The parameters are ``ContinuousCritic``'s, and:

    :param layer_norm: LayerNorm and tanh after the first hidden layer of each Q-network (see
        :func:`mlp_layers`)
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        n_critics: int = 2,
        share_features_extractor: bool = True,
        layer_norm: bool = False,
    ):
        super().__init__(
            observation_space,
            action_space,
            net_arch,
            features_extractor,
            features_dim,
            activation_fn=activation_fn,
            normalize_images=normalize_images,
            n_critics=0,  # the Q-networks are built here, once: SB3's (same modules, same order) or with the LayerNorm
            share_features_extractor=share_features_extractor,
        )
        self.n_critics = n_critics
        self.layer_norm = layer_norm
        q_input = features_dim + get_action_dim(action_space)
        for index in range(n_critics):
            q_net = nn.Sequential(*mlp_layers(q_input, 1, net_arch, activation_fn, layer_norm=layer_norm))
            self.add_module(f"qf{index}", q_net)
            self.q_networks.append(q_net)


class GaussianActorCriticPolicy(GaussianPolicy):
    """
    Gaussian actor, Q-function critic(s) and a target copy of each, as used by MPO and CRR.

    :param observation_space: Observation space
    :param action_space: Action space (Box)
    :param lr_schedule: Learning rate schedule (could be constant)
    :param n_critics: Number of critic networks (the minimum over them is used for targets)
    :param share_features_extractor: Whether to share the features extractor between the actor and the critic
    :param kwargs: the actor's, features extractor's and optimizer's settings, see :class:`GaussianPolicy`
        (``net_arch`` may be a dict with ``pi`` and ``qf``)
    """

    # what _build makes: MPO's are a GaussianActor and a QCritic, CRR's declare theirs (CRRPolicy)
    actor_target: BasePolicy
    critic: BaseModel
    critic_target: BaseModel

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        n_critics: int = 1,
        share_features_extractor: bool = False,
        **kwargs: Any,
    ):
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
        self.n_critics = n_critics
        self.share_features_extractor = share_features_extractor
        self.critic_kwargs: dict[str, Any] = {
            "observation_space": self.observation_space,
            "action_space": self.action_space,
            "net_arch": get_actor_critic_arch(self.net_arch)[1],
            "activation_fn": self.activation_fn,
            "normalize_images": self.normalize_images,
            "n_critics": n_critics,
            "share_features_extractor": share_features_extractor,
            "layer_norm": self.layer_norm,
        }
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        self.actor = self.make_trained_actor()
        self.actor.optimizer = self.make_optimizer(self.actor.parameters(), lr_schedule)
        if self.share_features_extractor:
            self.critic = self.make_critic(features_extractor=self.actor.features_extractor)
            critic_parameters = [param for name, param in self.critic.named_parameters() if "features_extractor" not in name]
        else:
            self.critic = self.make_critic(features_extractor=None)
            critic_parameters = list(self.critic.parameters())
        self.critic.optimizer = self.make_optimizer(critic_parameters, lr_schedule)
        # Target networks: exact copies, never trained by gradient
        self.actor_target = copy.deepcopy(self.actor)
        self.critic_target = copy.deepcopy(self.critic)
        self.actor_target.set_training_mode(False)
        self.critic_target.set_training_mode(False)
        for param in list(self.actor_target.parameters()) + list(self.critic_target.parameters()):
            param.requires_grad_(False)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(dict(n_critics=self.n_critics, share_features_extractor=self.share_features_extractor))
        return data

    def make_trained_actor(self) -> BasePolicy:
        """
        :return: the actor that training updates (its target is a copy of it): a :meth:`make_actor`, unless a subclass
            builds another kind (CRR: one actor per data source)
        """
        return self.make_actor()

    def make_critic(self, features_extractor: Optional[BaseFeaturesExtractor] = None) -> BaseModel:
        """
        :param features_extractor: the actor's, when the critic shares it
        :return: a :class:`QCritic` (a subclass may build another kind: CRR's categorical critic)
        """
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return QCritic(**critic_kwargs).to(self.device)

    def set_training_mode(self, mode: bool) -> None:
        """
        Put the online networks in training or evaluation mode (targets always stay in evaluation mode).

        :param mode: if true, set to training mode, else set to evaluation mode
        """
        set_training_flags(self, mode, self.actor, self.critic)


class DictObservationsMixin(GaussianPolicy):
    """
    Mixed in before a policy class of this package (a :class:`GaussianPolicy`), makes its ``features_extractor_class``
    default to SB3's ``CombinedExtractor``: the policy for Dict observation spaces (``MultiInputPolicy``), as in SB3.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor,
        **kwargs: Any,
    ):
        super().__init__(
            observation_space, action_space, lr_schedule, features_extractor_class=features_extractor_class, **kwargs
        )


class ImageObservationsMixin(GaussianPolicy):
    """
    Mixed in before a policy class of this package (a :class:`GaussianPolicy`), makes its ``features_extractor_class``
    default to SB3's ``NatureCNN``: the policy for image observation spaces (``CnnPolicy``), as SB3's SAC has it. The
    actor and each critic get their own CNN unless ``share_features_extractor=True``; ``normalize_images=False``
    feeds the pixels to the CNN as they are (SB3 then tells ``NatureCNN`` that they are already normalised).

    :param observation_space: Observation space: an image, a ``uint8`` Box ``(C, H, W)`` of bounds 0 and 255, at least
        36x36 for ``NatureCNN`` (an algorithm gets it from SB3, which transposes an environment's ``(H, W, C)`` images)
    :param action_space: Action space (Box)
    :param lr_schedule: Learning rate schedule (could be constant)
    :param features_extractor_class: Features extractor to use (``NatureCNN`` by default)
    :param kwargs: the policy's other settings (``net_arch``, ``features_extractor_kwargs``, ``normalize_images``, ...)
    """

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        features_extractor_class: type[BaseFeaturesExtractor] = NatureCNN,
        **kwargs: Any,
    ):
        super().__init__(
            observation_space, action_space, lr_schedule, features_extractor_class=features_extractor_class, **kwargs
        )
