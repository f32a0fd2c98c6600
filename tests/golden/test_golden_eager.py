"""
Golden numbers of one whole *eager* update (``compile_losses=False``) of MPO and of CRR, through ``train(gradient_steps=1)``:
not only the losses but the step itself, i.e. every parameter after it. It runs on any machine, with no C++ compiler
(``tests/common/test_compiled.py`` compares a compiled update with the eager one only where ``torch.compile`` works, so
it cannot tell when both are wrong, and never runs without a compiler).

What the other golden tests leave out: ``tests/golden/test_golden_mpo.py`` pins MPO's critic target and critic loss,
``tests/mpo/test_mpo_losses.py`` its policy improvement's losses and the duals' gradients (``_policy_improvement``
called alone), ``tests/crr/test_crr_losses.py`` and ``tests/golden/test_golden_crr.py`` CRR's forward pass (losses,
advantages, weights). None checks what ``train`` does with them: which loss steps which network, the gradients
themselves (through the networks), the per-module clipping at ``max_grad_norm``, the duals' own Adam step and their
direction, the order of the critic's and the actor's steps (CRR's weights come from the critic *before* its step), and
the target networks' Polyak update after the step.

Networks with no hidden layer (a linear critic per Q-network, a linear actor: ``mean = tanh(W s + b)``,
``std = softplus(V s + c) * init_std / log 2 + min_std``) with weights set by hand, so that the gradients are short
formulas written here in NumPy (float64), never computed by calling the code under test. The actor and the critic
use plain SGD (``optimizer_class=th.optim.SGD``: the step is ``-lr * clipped gradient``, so the gradients' values are
pinned, not only their signs as Adam's first step would); MPO's duals keep their own Adam, whose first step is
``-dual_lr * g / (|g| + 1e-8)``.
"""

import math
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_lifelong import CRR, MPO

OBS_DIM, ACTION_DIM, BATCH = 2, 2, 4
LR, TAU, GAMMA, INIT_STD, MIN_STD = 0.1, 0.25, 0.9, 0.6, 1e-4
K = INIT_STD / math.log(2.0)  # the std's scale: softplus(0) * K = init_std

# the online and target networks, by hand: Q_i(s, a) = W_i . [s, a] + b_i; mean = tanh(M s + m); std from V s + c
Q_W = np.array([[0.5, -0.3, 1.0, -0.8], [-0.2, 0.4, -0.6, 0.9]])
Q_B = np.array([0.1, -0.2])
Q_W_TARGET = np.array([[0.4, -0.1, 0.9, -0.5], [0.1, 0.3, -0.7, 0.6]])
Q_B_TARGET = np.array([0.0, 0.2])
MU_W, MU_B = np.array([[0.6, -0.4], [0.3, 0.8]]), np.array([0.1, -0.2])
STD_W, STD_B = np.array([[0.5, 0.2], [-0.3, 0.4]]), np.array([0.1, -0.1])
MU_W_TARGET, MU_B_TARGET = np.array([[0.8, -0.1], [0.1, 0.5]]), np.array([-0.1, 0.1])
STD_W_TARGET, STD_B_TARGET = np.array([[0.2, 0.3], [-0.1, 0.1]]), np.array([0.3, -0.4])

# the batch, by hand: one terminal transition
OBS = np.array([[0.5, -0.5], [-0.8, 0.3], [0.2, 0.9], [-0.4, -0.7]])
NEXT_OBS = np.array([[0.3, 0.6], [-0.5, -0.2], [0.9, -0.4], [0.1, 0.8]])
ACTIONS = np.array([[0.3, -0.6], [-0.7, 0.2], [0.9, 0.4], [-0.1, -0.9]])
REWARDS = np.array([[0.5], [-1.0], [1.5], [0.25]])
DONES = np.array([[0.0], [0.0], [1.0], [0.0]])


class BoxEnv(gym.Env):
    """Only the spaces matter: the update's batch is given by hand."""

    observation_space = spaces.Box(-5.0, 5.0, (OBS_DIM,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)

    def reset(self, *, seed: Any = None, options: Any = None) -> tuple[np.ndarray, dict]:
        return np.zeros(OBS_DIM, np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        return np.zeros(OBS_DIM, np.float32), 0.0, False, False, {}


# ---------------------------------------------------------------------------------------------------------------------
# NumPy references
# ---------------------------------------------------------------------------------------------------------------------


def softplus(x: np.ndarray) -> np.ndarray:
    return np.logaddexp(0.0, x)


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def np_actor(mu_w: np.ndarray, mu_b: np.ndarray, std_w: np.ndarray, std_b: np.ndarray, obs: np.ndarray) -> tuple:
    """:return: the mean, the std and the std head's pre-activation ``u`` of the linear actor"""
    u = obs @ std_w.T + std_b
    return np.tanh(obs @ mu_w.T + mu_b), softplus(u) * K + MIN_STD, u


def np_q(weights: np.ndarray, biases: np.ndarray, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """each Q-network's values ``[C, ..., batch]`` of ``actions`` ``[..., batch, A]`` in ``obs`` ``[batch, O]``"""
    inputs = np.concatenate([np.broadcast_to(obs, actions.shape[:-1] + obs.shape[-1:]), actions], axis=-1)
    return np.moveaxis(inputs @ weights.T + biases, -1, 0)


def actor_gradients(grad_mean: np.ndarray, grad_std: np.ndarray, mean: np.ndarray, u: np.ndarray, obs: np.ndarray) -> dict:
    """The chain rule through ``mean = tanh(M s + m)`` and ``std = softplus(V s + c) K + min_std``."""
    grad_z = grad_mean * (1.0 - mean**2)
    grad_u = grad_std * K * sigmoid(u)
    return {
        "mu.weight": grad_z.T @ obs,
        "mu.bias": grad_z.sum(0),
        "std_head.weight": grad_u.T @ obs,
        "std_head.bias": grad_u.sum(0),
    }


def critic_gradients(target: np.ndarray) -> tuple[float, dict, np.ndarray]:
    """:return: ``0.5 sum_i mean_b (Q_i - y)^2``, its gradient for each Q-network's weight and bias, and the Q-values"""
    q = np_q(Q_W, Q_B, OBS, ACTIONS)  # [2, B]
    inputs = np.concatenate([OBS, ACTIONS], axis=1)
    residual = q - target[None]
    grads = {}
    for i in range(2):
        grads[f"qf{i}.0.weight"] = (residual[i][:, None] * inputs).mean(0)[None]
        grads[f"qf{i}.0.bias"] = np.array([residual[i].mean()])
    return float(0.5 * (residual**2).mean(axis=1).sum()), grads, q


def clipped(grads: dict, max_norm: float) -> dict:
    """``clip_grad_norm_`` over one module's gradients: scaled by ``max_norm / (norm + 1e-6)`` when that is < 1."""
    norm = math.sqrt(sum(float((g**2).sum()) for g in grads.values()))
    scale = min(1.0, max_norm / (norm + 1e-6))
    return {name: g * scale for name, g in grads.items()}


def norm_of(grads: dict) -> float:
    return math.sqrt(sum(float((g**2).sum()) for g in grads.values()))


# ---------------------------------------------------------------------------------------------------------------------
# Setting the networks
# ---------------------------------------------------------------------------------------------------------------------


def t32(x: np.ndarray) -> th.Tensor:
    return th.tensor(np.asarray(x), dtype=th.float32)


def set_linear(layer: th.nn.Linear, weight: np.ndarray, bias: np.ndarray) -> None:
    with th.no_grad():
        layer.weight.copy_(t32(weight).reshape(layer.weight.shape))
        layer.bias.copy_(t32(bias).reshape(layer.bias.shape))


def set_networks(model: Any) -> None:
    for critic, weights, biases in ((model.critic, Q_W, Q_B), (model.critic_target, Q_W_TARGET, Q_B_TARGET)):
        assert len(critic.q_networks) == 2 and all(len(net) == 1 for net in critic.q_networks)  # linear Q-networks
        for net, weight, bias in zip(critic.q_networks, weights, biases):
            set_linear(net[0], weight, bias)
    for actor, values in (
        (model.actor, (MU_W, MU_B, STD_W, STD_B)),
        (model.actor_target, (MU_W_TARGET, MU_B_TARGET, STD_W_TARGET, STD_B_TARGET)),
    ):
        assert len(actor.latent_pi) == 0  # linear actor
        set_linear(actor.mu, values[0], values[1])
        set_linear(actor.std_head, values[2], values[3])
    if getattr(model, "_target_scoring_copy", None) is not None:  # (none in float32: kept in step if there were one)
        model._target_scoring_copy.sync()


def parameters_of(model: Any) -> dict[str, np.ndarray]:
    """The online and target networks' parameters, by ``actor.``/``critic.``/``actor_target.``/``critic_target.`` name."""
    values = {}
    for prefix in ("actor", "critic", "actor_target", "critic_target"):
        for name, parameter in getattr(model, prefix).named_parameters():
            values[f"{prefix}.{name}"] = parameter.detach().double().numpy().copy()
    return values


def batch() -> ReplayBufferSamples:
    return ReplayBufferSamples(t32(OBS), t32(ACTIONS), t32(NEXT_OBS), t32(DONES), t32(REWARDS), None)


def assert_step(before: dict, after: dict, module: str, grads: dict, lr: float) -> None:
    """every parameter of ``module`` moved by ``-lr * grad`` (the SGD step), to float32's precision"""
    for name, grad in grads.items():
        step = (after[f"{module}.{name}"] - before[f"{module}.{name}"]) / lr
        np.testing.assert_allclose(step.reshape(grad.shape), -grad, rtol=2e-4, atol=2e-6, err_msg=f"{module}.{name}")


def assert_targets(before: dict, after: dict) -> None:
    """Polyak: ``target <- (1 - tau) target + tau online`` with the online networks *after* their step"""
    for key in before:
        if key.startswith(("actor_target.", "critic_target.")):
            online = key.replace("_target.", ".", 1)
            want = (1.0 - TAU) * before[key] + TAU * after[online]
            np.testing.assert_allclose(after[key], want, rtol=1e-6, atol=1e-7, err_msg=key)


# ---------------------------------------------------------------------------------------------------------------------
# MPO
# ---------------------------------------------------------------------------------------------------------------------

MPO_SAMPLES = 3
EPSILON, EPSILON_MEAN, EPSILON_STD = 0.1, 0.05, 0.04  # each between the two dimensions' KLs below
DUAL_LR = 0.01
# the E-step's (and the target's) standard normal draws [N, B, A], by hand: some samples leave [-1, 1]
MPO_NOISE = np.array(
    [
        [[1.2, -0.3], [0.4, 2.5], [-1.1, 0.2], [0.7, -0.6]],
        [[-0.5, 0.9], [-2.2, -0.1], [0.3, -1.4], [1.8, 0.5]],
        [[0.1, -1.9], [0.8, 0.6], [2.1, 1.0], [-0.9, -0.2]],
    ]
)
RAW_TEMPERATURE, RAW_ALPHA_MEAN, RAW_ALPHA_STD = 0.3, np.array([0.2, -0.5]), np.array([1.0, 0.4])


def linear_settings(max_grad_norm: float) -> dict:
    """What MPO's and CRR's models share here: linear networks stepped by SGD, one target update per update, eager float32."""
    return dict(
        learning_rate=LR,
        tau=TAU,
        gamma=GAMMA,
        target_update_interval=1,
        max_grad_norm=max_grad_norm,
        policy_kwargs=dict(
            net_arch=dict(pi=[], qf=[]),
            n_critics=2,
            layer_norm=False,
            init_std=INIT_STD,
            min_std=MIN_STD,
            optimizer_class=th.optim.SGD,
        ),
        compute=dict(scoring_dtype="float32", compile_losses=False),
        seed=0,
        device="cpu",
    )


def mpo_model(max_grad_norm: float) -> MPO:
    model = MPO(
        "MlpPolicy",
        BoxEnv(),
        buffer_size=100,
        num_samples=MPO_SAMPLES,
        policy_loss=dict(epsilon=EPSILON, epsilon_mean=EPSILON_MEAN, epsilon_stddev=EPSILON_STD),
        dual_learning_rate=DUAL_LR,
        policy_on_next_obs=True,
        **linear_settings(max_grad_norm),
    )
    set_networks(model)
    with th.no_grad():
        model.log_temperature.fill_(RAW_TEMPERATURE)
        model.log_alpha_mean.copy_(t32(RAW_ALPHA_MEAN))
        model.log_alpha_stddev.copy_(t32(RAW_ALPHA_STD))
    return model


def mpo_reference() -> dict:
    """One MPO update in NumPy: the losses, every gradient (before clipping) and what is logged."""
    # the target: r + gamma (1 - done) mean_N min_i Q'_i(s', clip(a')), a' the target policy's samples on s'
    mean_t, std_t, _ = np_actor(MU_W_TARGET, MU_B_TARGET, STD_W_TARGET, STD_B_TARGET, NEXT_OBS)
    samples = mean_t[None] + std_t[None] * MPO_NOISE  # [N, B, A], as drawn (the M-step fits them unclipped)
    q_samples = np_q(Q_W_TARGET, Q_B_TARGET, NEXT_OBS, np.clip(samples, -1.0, 1.0)).min(axis=0)  # [N, B]
    target = REWARDS[:, 0] + GAMMA * (1.0 - DONES[:, 0]) * q_samples.mean(axis=0)
    critic_loss, critic_grads, q = critic_gradients(target)
    # E-step on the next observations (policy_on_next_obs), with the same samples and values
    eta = softplus(RAW_TEMPERATURE) + 1e-8
    alpha_mean, alpha_std = softplus(RAW_ALPHA_MEAN) + 1e-8, softplus(RAW_ALPHA_STD) + 1e-8
    logits = q_samples / eta
    lse = logits.max(0) + np.log(np.exp(logits - logits.max(0)).sum(0))
    weights = np.exp(logits - lse)  # [N, B]
    # d/d eta of eta (epsilon + mean_B[lse - log N]), the weights' own dependence included (they are detached only
    # in the M-step): epsilon + mean(lse - log N) - mean_B(sum_N w Q) / eta
    grad_eta = EPSILON + np.mean(lse - math.log(MPO_SAMPLES)) - np.mean((weights * q_samples).sum(0)) / eta
    # the online policy on s'
    mean, std, u = np_actor(MU_W, MU_B, STD_W, STD_B, NEXT_OBS)
    w = weights[..., None]
    m_step = -np.mean(
        (
            -0.5 * (w * (samples - mean[None]) ** 2).sum(0) / std_t**2
            - (np.log(std_t) + 0.5 * math.log(2 * math.pi))
            - 0.5 * (w * (samples - mean_t[None]) ** 2).sum(0) / std**2
            - (np.log(std) + 0.5 * math.log(2 * math.pi))
        ).sum(-1)
    )
    grad_mean = -(w * (samples - mean[None])).sum(0) / std_t**2 / BATCH
    grad_std = -((w * (samples - mean_t[None]) ** 2).sum(0) / std**3 - 1.0 / std) / BATCH
    # trust region: KL(pi_target || pi_online) per dimension, the mean's with the target's std and vice versa
    kl_mean = (0.5 * (mean - mean_t) ** 2 / std_t**2).mean(0)
    ratio = std_t**2 / std**2
    kl_std = (0.5 * (ratio - 1.0 - np.log(ratio))).mean(0)
    grad_mean += alpha_mean * (mean - mean_t) / std_t**2 / BATCH
    grad_std += alpha_std * (1.0 / std - std_t**2 / std**3) / BATCH
    return {
        "critic_loss": critic_loss,
        "critic_grads": critic_grads,
        "q_mean": q[0].mean(),
        "actor_loss": m_step,
        "actor_grads": actor_gradients(grad_mean, grad_std, mean, u, NEXT_OBS),
        "temperature": eta,
        "kl_mean": kl_mean,
        "kl_std": kl_std,
        "ess": np.mean(1.0 / (weights**2).sum(0)) / MPO_SAMPLES,
        "dual_grads": {
            "log_temperature": np.array([grad_eta * sigmoid(RAW_TEMPERATURE)]),
            "log_alpha_mean": (EPSILON_MEAN - kl_mean) * sigmoid(RAW_ALPHA_MEAN),
            "log_alpha_stddev": (EPSILON_STD - kl_std) * sigmoid(RAW_ALPHA_STD),
        },
        "samples": samples,
    }


@pytest.mark.parametrize("clip", [False, True])
def test_one_eager_mpo_update_steps_every_parameter_by_hand(clip: bool) -> None:
    """
    Catches a loss stepping the wrong network (the critic's loss into the actor, or the actor's not reaching it), a
    wrong gradient anywhere in the update (a missing factor of the M-step, the trust region's penalty dropped or with
    the wrong sign, a target computed from the online networks), clipping over both networks' gradients together or not
    at all, a dual stepped the wrong way (a trust region that loosens when violated) or not at all, and targets updated
    before the step, with ``1 - tau`` for ``tau``, or not at all.
    """
    want = mpo_reference()
    actor_norm, critic_norm = norm_of(want["actor_grads"]), norm_of(want["critic_grads"])
    # clip: between the two norms (one module clipped, the other not); else far above both (the gradients' own values)
    max_grad_norm = math.sqrt(actor_norm * critic_norm) if clip else 1e6
    assert max(actor_norm, critic_norm) > 1.1 * min(actor_norm, critic_norm)  # a 5% clip at least
    model = mpo_model(max_grad_norm)
    model.set_logger(Logger(None, []))
    model.replay_buffer.sample = lambda *args, **kwargs: batch()  # type: ignore[method-assign]
    model._sampling_noise = lambda replay_data: t32(MPO_NOISE)  # type: ignore[method-assign]
    before = parameters_of(model)
    duals_before = {name: getattr(model, name).detach().double().numpy().copy() for name in want["dual_grads"]}
    model.train(gradient_steps=1, batch_size=BATCH)
    after = parameters_of(model)

    logged = model.logger.name_to_value
    assert logged["train/critic_loss"] == pytest.approx(want["critic_loss"], rel=1e-5)
    assert logged["train/q_mean"] == pytest.approx(want["q_mean"], rel=1e-5)
    assert logged["train/actor_loss"] == pytest.approx(want["actor_loss"], rel=1e-5)
    assert logged["train/temperature"] == pytest.approx(want["temperature"], rel=1e-6)
    assert logged["train/kl_mean"] == pytest.approx(want["kl_mean"].mean(), rel=1e-4)
    assert logged["train/kl_stddev"] == pytest.approx(want["kl_std"].mean(), rel=1e-4)
    assert logged["train/ess"] == pytest.approx(want["ess"], rel=1e-5)
    # the networks: SGD down the clipped gradients, each module clipped on its own norm
    assert_step(before, after, "critic", clipped(want["critic_grads"], max_grad_norm), LR)
    assert_step(before, after, "actor", clipped(want["actor_grads"], max_grad_norm), LR)
    assert_targets(before, after)
    # the duals: Adam's first step, -dual_lr * g / (|g| + 1e-8), down the duals' loss
    for name, grad in want["dual_grads"].items():
        assert np.abs(grad).min() > 1e-4  # a step of dual_lr, whose sign is the test
        step = (getattr(model, name).detach().double().numpy() - duals_before[name]) / DUAL_LR
        np.testing.assert_allclose(step, -grad / (np.abs(grad) + 1e-8), rtol=0, atol=1e-4, err_msg=name)
    # inputs where every part matters: clipped samples, each Q-network the lowest somewhere, one constraint of each
    # kind violated and one not (so that the duals step both ways), a terminal transition
    assert (np.abs(want["samples"]) > 1).any()
    lowest = np_q(Q_W_TARGET, Q_B_TARGET, NEXT_OBS, np.clip(want["samples"], -1, 1)).argmin(axis=0)
    assert (lowest == 0).any() and (lowest == 1).any()
    signs = np.concatenate([np.sign(want["dual_grads"]["log_alpha_mean"]), np.sign(want["dual_grads"]["log_alpha_stddev"])])
    assert (signs > 0).any() and (signs < 0).any()


# ---------------------------------------------------------------------------------------------------------------------
# CRR
# ---------------------------------------------------------------------------------------------------------------------

CRR_SAMPLES, CRR_TARGET_SAMPLES, BETA, MAX_WEIGHT = 3, 2, 0.5, 1.5
NOISE_SEED = 5


def crr_model(max_grad_norm: float) -> CRR:
    rng = np.random.default_rng(0)
    data = {  # only for the spaces: the update's batch is given by hand
        "observations": rng.uniform(-1, 1, size=(8, OBS_DIM)).astype(np.float32),
        "actions": rng.uniform(-1, 1, size=(8, ACTION_DIM)).astype(np.float32),
        "rewards": rng.normal(size=8).astype(np.float32),
        "next_observations": rng.uniform(-1, 1, size=(8, OBS_DIM)).astype(np.float32),
        "terminals": np.zeros(8, dtype=bool),
    }
    model = CRR.from_offline_data(
        data,
        action_space=spaces.Box(-1, 1, (ACTION_DIM,)),
        normalized_actions=True,
        num_samples=CRR_SAMPLES,
        n_target_samples=CRR_TARGET_SAMPLES,
        advantage_baseline="mean",
        advantage_transform="exp",
        beta=BETA,
        max_weight=MAX_WEIGHT,
        **linear_settings(max_grad_norm),
    )
    set_networks(model)
    return model


def crr_noise() -> tuple[np.ndarray, np.ndarray]:
    """the update's draws, in its documented order: the TD target's ``[n_target_samples, B, A]``, then the baseline's"""
    generator = th.Generator().manual_seed(NOISE_SEED)
    target = th.randn((CRR_TARGET_SAMPLES, BATCH, ACTION_DIM), generator=generator)
    sample = th.randn((CRR_SAMPLES, BATCH, ACTION_DIM), generator=generator)
    return target.double().numpy(), sample.double().numpy()


def crr_reference() -> dict:
    """One CRR update in NumPy: the losses, every gradient (before clipping) and what is logged."""
    target_noise, sample_noise = crr_noise()
    mean_t, std_t, _ = np_actor(MU_W_TARGET, MU_B_TARGET, STD_W_TARGET, STD_B_TARGET, NEXT_OBS)
    next_actions = np.clip(mean_t[None] + std_t[None] * target_noise, -1.0, 1.0)
    next_q = np_q(Q_W_TARGET, Q_B_TARGET, NEXT_OBS, next_actions).min(axis=0).mean(axis=0)  # [B]
    target = REWARDS[:, 0] + GAMMA * (1.0 - DONES[:, 0]) * next_q
    critic_loss, critic_grads, q = critic_gradients(target)
    # the advantage of the data's action, with the critic *before* its step, over the policy's clipped samples
    mean, std, u = np_actor(MU_W, MU_B, STD_W, STD_B, OBS)
    samples = mean[None] + std[None] * sample_noise
    baseline = np_q(Q_W, Q_B, OBS, np.clip(samples, -1.0, 1.0)).min(axis=0).mean(axis=0)
    advantages = q.min(axis=0) - baseline
    weights = np.minimum(np.exp(advantages / BETA), MAX_WEIGHT)
    # the actor: -mean_B w log N(a; mean, std)
    z = (ACTIONS - mean) / std
    log_prob = (-0.5 * z**2 - np.log(std) - 0.5 * math.log(2 * math.pi)).sum(-1)
    grad_mean = -(weights[:, None] * (ACTIONS - mean) / std**2) / BATCH
    grad_std = -(weights[:, None] * ((ACTIONS - mean) ** 2 / std**3 - 1.0 / std)) / BATCH
    return {
        "critic_loss": critic_loss,
        "critic_grads": critic_grads,
        "q_mean": q.min(axis=0).mean(),
        "actor_loss": -np.mean(weights * log_prob),
        "actor_grads": actor_gradients(grad_mean, grad_std, mean, u, OBS),
        "advantages": advantages,
        "weights": weights,
        "samples": samples,
        "next_samples": mean_t[None] + std_t[None] * target_noise,
    }


@pytest.mark.parametrize("clip", [False, True])
def test_one_eager_crr_update_steps_every_parameter_by_hand(clip: bool) -> None:
    """
    Catches a loss stepping the wrong network, a wrong gradient of the critic's regression or of the actor's weighted
    likelihood (a weight applied to the wrong row, the std's term dropped), weights taken from the critic *after* its
    step (the eager update steps the critic first), clipping over both networks together or not at all, the noise drawn
    in another order than documented, and targets updated before the step or with ``1 - tau``.
    """
    want = crr_reference()
    actor_norm, critic_norm = norm_of(want["actor_grads"]), norm_of(want["critic_grads"])
    max_grad_norm = math.sqrt(actor_norm * critic_norm) if clip else 1e6
    assert max(actor_norm, critic_norm) > 1.1 * min(actor_norm, critic_norm)  # a 5% clip at least
    model = crr_model(max_grad_norm)
    model.set_logger(Logger(None, []))
    model._sample = lambda batch_size: (batch(), None)  # type: ignore[method-assign]
    before = parameters_of(model)
    th.manual_seed(NOISE_SEED)  # the update draws its noise from torch's global generator
    model.train(gradient_steps=1, batch_size=BATCH)
    after = parameters_of(model)

    logged = model.logger.name_to_value
    assert logged["train/critic_loss"] == pytest.approx(want["critic_loss"], rel=1e-5)
    assert logged["train/q_mean"] == pytest.approx(want["q_mean"], rel=1e-5)
    assert logged["train/actor_loss"] == pytest.approx(want["actor_loss"], rel=1e-5)
    assert logged["train/advantage_mean"] == pytest.approx(want["advantages"].mean(), rel=1e-5)
    assert logged["train/weight_mean"] == pytest.approx(want["weights"].mean(), rel=1e-5)
    assert logged["train/weight_clip_frac"] == pytest.approx(np.mean(want["weights"] == MAX_WEIGHT))
    assert_step(before, after, "critic", clipped(want["critic_grads"], max_grad_norm), LR)
    assert_step(before, after, "actor", clipped(want["actor_grads"], max_grad_norm), LR)
    assert_targets(before, after)
    # inputs where every part matters: both signs of the advantage, rows at the weights' clip and below, clipped
    # samples on both sides, each Q-network the lowest somewhere
    assert (want["advantages"] > 0).any() and (want["advantages"] < 0).any()
    assert 0 < np.sum(want["weights"] == MAX_WEIGHT) < BATCH
    assert (np.abs(want["samples"]) > 1).any() and (np.abs(want["next_samples"]) > 1).any()
    lowest = np_q(Q_W, Q_B, OBS, ACTIONS).argmin(axis=0)
    assert (lowest == 0).any() and (lowest == 1).any()
