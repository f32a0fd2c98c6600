"""
Golden numbers for CRR (issue 66), from networks whose weights are set by hand (linear Q-networks and actor heads), so
that every expected number is a short formula written here, never a call of the code under test:

- the advantage ``A = min_i Q_i(s, a) - baseline`` of the data's actions for each ``advantage_baseline`` (``"mean"``
  and ``"max"`` of ``min_i Q_i`` over the policy's clipped samples) and their weights for each ``advantage_transform``
  (``"indicator"``: ``1[A > 0]``; ``"exp"``: ``min(exp(A / beta), max_weight)``, with rows at the clip; and with
  ``normalize_advantages``), through a whole ``learn_offline`` update, down to the weights the actor's loss gets;
- the categorical critic's TD target with two Q-networks that disagree: per transition *and* per next action the
  distribution of the Q-network with the lowest expected value, averaged over the next actions, then shifted by
  ``r + gamma (1 - done) z`` and projected onto the 5-atom support, atom by atom by hand.
"""

import math

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from testkit import Recorder

import sb3_lifelong.crr.crr as crr_module
from sb3_lifelong import CRR
from sb3_lifelong.core.datasets import OfflineSamples

OBS_DIM, ACTION_DIM = 2, 2
BETA, MAX_WEIGHT = 0.5, 2.0
INIT_STD = 0.5

# the online critic, by hand: Q_i(s, a) = W_i . [s, a] + b_i (two Q-networks, each the lowest somewhere)
Q_WEIGHTS = np.array([[0.5, 0.0, 1.0, -2.0], [0.0, -0.4, -1.0, 1.0]])
Q_BIASES = np.array([0.1, 0.3])
# the online actor, by hand: mean = tanh(M s + m), std = softplus(0) * init_std / log 2 + min_std = init_std + min_std
MU_WEIGHT = np.array([[0.8, 0.0], [0.3, -0.6]])
MU_BIAS = np.array([0.1, -0.2])


def data(n: int = 16, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "observations": rng.uniform(-1, 1, size=(n, OBS_DIM)).astype(np.float32),
        "actions": rng.uniform(-1, 1, size=(n, ACTION_DIM)).astype(np.float32),
        "rewards": rng.normal(size=n).astype(np.float32),
        "next_observations": rng.uniform(-1, 1, size=(n, OBS_DIM)).astype(np.float32),
        "terminals": rng.random(n) < 0.25,
    }


def linear_crr(**kwargs) -> CRR:
    """A CRR whose actor and Q-networks are one linear layer each (no hidden layer), float32, eager, on the CPU."""
    return CRR.from_offline_data(
        data(),
        action_space=spaces.Box(-1, 1, (ACTION_DIM,)),
        normalized_actions=True,
        policy_kwargs=dict(net_arch=dict(pi=[], qf=[]), n_critics=2, layer_norm=False, init_std=INIT_STD),
        compute=dict(scoring_dtype="float32", compile_losses=False),
        seed=0,
        device="cpu",
        **kwargs,
    )


def set_linear(layer: th.nn.Linear, weight, bias) -> None:
    with th.no_grad():
        layer.weight.copy_(th.tensor(np.asarray(weight), dtype=th.float32).reshape(layer.weight.shape))
        layer.bias.copy_(th.tensor(np.asarray(bias), dtype=th.float32).reshape(layer.bias.shape))


def hand_q(obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """``min_i Q_i`` of ``actions`` ``[..., batch, 2]`` in ``obs`` ``[batch, 2]``"""
    inputs = np.concatenate([np.broadcast_to(obs, actions.shape), actions], axis=-1)
    return (inputs @ Q_WEIGHTS.T + Q_BIASES).min(axis=-1)


@pytest.mark.parametrize(
    "baseline,transform,normalize",
    [
        ("mean", "indicator", False),
        ("max", "indicator", False),
        ("mean", "exp", False),
        ("max", "exp", False),
        ("mean", "exp", True),
        ("max", "exp", True),
    ],
)
def test_advantages_and_weights_of_one_update_by_hand(monkeypatch, baseline, transform, normalize):
    batch, samples = 16, 3
    model = linear_crr(
        batch_size=batch,
        num_samples=samples,
        advantage_baseline=baseline,
        advantage_transform=transform,
        beta=BETA,
        max_weight=MAX_WEIGHT,
        normalize_advantages=normalize,
    )
    for net, weight, bias in zip(model.critic.q_networks, Q_WEIGHTS, Q_BIASES):
        set_linear(net[0], weight, bias)
    set_linear(model.actor.mu, MU_WEIGHT, MU_BIAS)
    set_linear(model.actor.std_head, np.zeros((ACTION_DIM, OBS_DIM)), np.zeros(ACTION_DIM))
    seen: dict = {}
    policy_action_values, sample = model._policy_action_values, model._sample

    def recording_sample(batch_size):
        seen["batch"] = sample(batch_size)
        return seen["batch"]

    def recording_policy_action_values(obs, mean, std, noise):
        seen["sample_noise"] = noise
        return policy_action_values(obs, mean, std, noise)

    def recording_actor_loss(actions, mean, std, weights):
        seen["weights"] = weights
        return crr_module_actor_loss(actions, mean, std, weights)

    crr_module_actor_loss = crr_module.actor_loss
    monkeypatch.setattr(model, "_sample", recording_sample)
    monkeypatch.setattr(model, "_policy_action_values", recording_policy_action_values)
    monkeypatch.setattr(crr_module, "actor_loss", recording_actor_loss)
    recorder = Recorder()
    model.learn_offline(1, callback=recorder)

    replay, _ = seen["batch"]
    obs, actions = replay.observations.double().numpy(), replay.actions.double().numpy()
    noise = seen["sample_noise"].double().numpy()
    assert noise.shape == (samples, batch, ACTION_DIM)
    # the policy's samples (clipped for the critic, as the environment would clip them) and their lowest Q
    mean, std = np.tanh(obs @ MU_WEIGHT.T + MU_BIAS), INIT_STD + model.actor.min_std
    sampled = np.clip(mean[None] + std * noise, -1.0, 1.0)
    sampled_q = hand_q(obs, sampled)  # [N, B]
    value = sampled_q.mean(axis=0) if baseline == "mean" else sampled_q.max(axis=0)
    advantages = hand_q(obs, actions) - value
    if transform == "indicator":
        weights = (advantages > 0).astype(float)
    else:
        scale = advantages.std(ddof=1) if normalize else 1.0  # torch's std: the unbiased one
        weights = np.minimum(np.exp(advantages / scale / BETA), MAX_WEIGHT)
    np.testing.assert_allclose(seen["weights"].double().numpy(), weights, rtol=1e-5, atol=1e-7)
    logged = recorder.values
    assert logged["train/advantage_mean"] == pytest.approx(advantages.mean(), rel=1e-5, abs=1e-7)
    assert logged["train/weight_mean"] == pytest.approx(weights.mean(), rel=1e-5)
    if transform == "exp":
        assert logged["train/weight_clip_frac"] == pytest.approx(np.mean(weights == MAX_WEIGHT))
        assert logged["train/beta"] == pytest.approx(BETA * (advantages.std(ddof=1) if normalize else 1.0), rel=1e-5)
    # inputs where every part matters: both signs of A, some samples clipped, rows at the exp clip and below it
    assert (advantages > 0).any() and (advantages < 0).any()
    assert (np.abs(mean[None] + std * noise) > 1).any()
    lowest = (np.concatenate([obs, actions], axis=1) @ Q_WEIGHTS.T + Q_BIASES).argmin(axis=1)
    assert (lowest == 0).any() and (lowest == 1).any()
    if transform == "exp":
        assert 0 < np.sum(weights == MAX_WEIGHT) < batch


# ---------------------------------------------------------------------------------------------------------------------
# The categorical critic's TD target, with two Q-networks that disagree
# ---------------------------------------------------------------------------------------------------------------------

SUPPORT = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
GAMMA = 0.5


def softmax(x: np.ndarray) -> np.ndarray:
    e = np.exp(x - x.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


# logits of the two target Q-networks, linear in [s, a]: net 0's return grows with a_0, net 1's falls with it, so
# which one is lower changes with the sampled action
LOGIT_WEIGHTS = [
    np.stack([0.2 * SUPPORT, 0.0 * SUPPORT, 1.0 * SUPPORT, 0.3 * SUPPORT], axis=1),  # [5 atoms, 4 inputs]
    np.stack([0.0 * SUPPORT, -0.3 * SUPPORT, -0.8 * SUPPORT, 0.0 * SUPPORT], axis=1),
]
LOGIT_BIASES = [np.array([0.0, 0.5, 0.0, -0.5, 0.0]), np.array([0.3, 0.0, 0.0, 0.0, 0.3])]


def hand_probs(obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """each target Q-network's probabilities ``[2, ..., batch, 5]``"""
    inputs = np.concatenate([np.broadcast_to(obs, actions.shape), actions], axis=-1)
    return np.stack([softmax(inputs @ w.T + b) for w, b in zip(LOGIT_WEIGHTS, LOGIT_BIASES)])


def categorical_model() -> CRR:
    model = CRR.from_offline_data(
        data(),
        action_space=spaces.Box(-1, 1, (ACTION_DIM,)),
        normalized_actions=True,
        policy_kwargs=dict(
            net_arch=dict(pi=[], qf=[]), n_critics=2, distributional_critic=True, n_atoms=5, v_min=-2.0, v_max=2.0
        ),
        gamma=GAMMA,
        n_target_samples=2,
        compute=dict(scoring_dtype="float32", compile_losses=False),
        seed=0,
        device="cpu",
    )
    for net, weight, bias in zip(model.critic_target.q_networks, LOGIT_WEIGHTS, LOGIT_BIASES):
        set_linear(net[0], weight, bias)
    # the target actor's mean is tanh(0.2) everywhere, its std init_std + min_std
    set_linear(model.actor_target.mu, np.zeros((ACTION_DIM, OBS_DIM)), np.full(ACTION_DIM, 0.2))
    set_linear(model.actor_target.std_head, np.zeros((ACTION_DIM, OBS_DIM)), np.zeros(ACTION_DIM))
    return model


def test_categorical_td_target_projects_the_lowest_network_per_next_action_by_hand():
    model = categorical_model()
    std = model.actor_target.init_std + model.actor_target.min_std
    obs = np.array([[0.5, -0.5], [-1.0, 0.2], [0.3, 0.9], [0.0, 0.0], [-0.4, -0.7]])
    next_obs = np.array([[0.2, 0.4], [-0.6, 0.1], [0.9, -0.3], [0.1, -0.8], [-0.5, 0.5]])
    rewards = np.array([[0.5], [1.0], [1.5], [-3.0], [0.25]])
    dones = np.array([[0.0], [0.0], [0.0], [1.0], [1.0]])
    # per row, one next action with a_0 high and one with a_0 low (the first beyond the bounds: clipped to 1)
    noise = np.zeros((2, 5, ACTION_DIM))
    noise[0, :, 0], noise[1, :, 0] = [3.0, 1.2, 0.8, 2.0, 1.5], [-2.0, -1.5, -0.9, -1.2, -3.0]
    noise[:, :, 1] = [[0.4, -0.3, 0.1, 0.0, 0.2], [-0.2, 0.5, 0.0, 0.3, -0.1]]
    replay = OfflineSamples(
        *(th.tensor(x, dtype=th.float32) for x in (obs, np.zeros((5, 2)), next_obs, dones, rewards)), None, None, None
    )
    with th.no_grad():  # as in the update: the scoring engine's no-grad pass
        got = model._critic_target_values(replay, None, th.tensor(noise, dtype=th.float32)).double().numpy()
    eager = model._critic_target_values(replay, None, th.tensor(noise, dtype=th.float32)).detach().double().numpy()
    np.testing.assert_allclose(eager, got, rtol=1e-6, atol=1e-7)  # the critic's own call gives the same

    next_actions = np.clip(math.tanh(0.2) + std * noise, -1.0, 1.0)  # [2 actions, 5 rows, 2]
    probs = hand_probs(next_obs, next_actions)  # [2 nets, 2 actions, 5 rows, 5 atoms]
    expected = probs @ SUPPORT  # [2 nets, 2 actions, 5 rows]
    lowest = expected.argmin(axis=0)  # [2 actions, 5 rows]
    # the networks disagree, and which one is lower changes from one next action to the other in every row
    assert (lowest[0] != lowest[1]).all()
    picked = np.where((lowest == 0)[..., None], probs[0], probs[1])  # [2 actions, 5 rows, 5 atoms]
    p = picked.mean(axis=0)  # [5 rows, 5 atoms]: averaged over the next actions, before the projection
    # the projection of r + 0.5 (1 - done) z onto z = -2, -1, 0, 1, 2, atom by atom (a shifted atom halfway between
    # two atoms gives each half its mass; beyond the support it is clipped to the end)
    want = np.array(
        [
            # r = 0.5: z -> -0.5, 0, 0.5, 1, 1.5
            [0, p[0, 0] / 2, p[0, 0] / 2 + p[0, 1] + p[0, 2] / 2, p[0, 2] / 2 + p[0, 3] + p[0, 4] / 2, p[0, 4] / 2],
            # r = 1: z -> 0, 0.5, 1, 1.5, 2
            [0, 0, p[1, 0] + p[1, 1] / 2, p[1, 1] / 2 + p[1, 2] + p[1, 3] / 2, p[1, 3] / 2 + p[1, 4]],
            # r = 1.5: z -> 0.5, 1, 1.5, 2, 2.5 (clipped to 2)
            [0, 0, p[2, 0] / 2, p[2, 0] / 2 + p[2, 1] + p[2, 2] / 2, p[2, 2] / 2 + p[2, 3] + p[2, 4]],
            # done, r = -3: every atom at -3, clipped to -2
            [1, 0, 0, 0, 0],
            # done, r = 0.25: every atom at 0.25, a quarter of the way from 0 to 1
            [0, 0, 0.75, 0.25, 0],
        ]
    )
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    # the rules a bug would follow give other targets: always one network, or the one lower on average over the actions
    for wrong in (probs[0].mean(axis=0), probs[1].mean(axis=0), probs.mean(axis=(0, 1))):
        assert np.abs(wrong - p).max() > 0.02
    by_average = np.where((expected.mean(axis=1).argmin(axis=0) == 0)[:, None], probs[0].mean(0), probs[1].mean(0))
    assert np.abs(by_average - p).max() > 0.02

    # and the critic's loss regresses the online critic's distributions on it: sum_i mean_b -sum_k t log softmax
    actions = np.array([[0.3, -0.2], [-0.5, 0.5], [0.9, 0.1], [0.0, -1.0], [-0.7, 0.4]])
    replay = replay._replace(actions=th.tensor(actions, dtype=th.float32))
    online = [
        (net[0].weight.detach().double().numpy(), net[0].bias.detach().double().numpy()) for net in model.critic.q_networks
    ]
    fit = model._forward_pass(replay, None, th.tensor(noise, dtype=th.float32), th.zeros((4, 5, ACTION_DIM)))[0]
    inputs = np.concatenate([obs, actions], axis=1)
    log_probs = [np.log(softmax(inputs @ w.T + b)) for w, b in online]
    assert fit.loss.item() == pytest.approx(sum(-(want * lp).sum(axis=1).mean() for lp in log_probs), rel=1e-5)
    q = np.min([softmax(inputs @ w.T + b) @ SUPPORT for w, b in online], axis=0)
    np.testing.assert_allclose(fit.q_values.numpy(), q, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------------------------------------
# Falsy values are values: seed=0, verbose=0, gamma=0.0 reach a distilled student
# ---------------------------------------------------------------------------------------------------------------------


def test_distill_forwards_zero_seed_verbose_and_gamma(capsys):
    from sb3_lifelong import MPO

    teacher = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8]), learning_starts=1_000, seed=5, device="cpu")
    teacher.learn(200)  # 200 random-action steps of Pendulum (one time-out), no update
    teacher.verbose = 1  # a student left to the teacher's default would print
    small = dict(policy_kwargs=dict(net_arch=[8]), batch_size=16, num_samples=2)
    compute = dict(scoring_dtype="float32", compile_losses=False)
    capsys.readouterr()
    student = teacher.distill(CRR, total_updates=3, seed=0, verbose=0, gamma=0.0, compute=compute, **small)
    assert capsys.readouterr().out == ""
    assert (student.seed, student.verbose, student.gamma) == (0, 0, 0.0)
    teacher.distill(CRR, total_updates=1, seed=0, verbose=1, compute=compute, **small)  # verbose 1 says what it does
    assert "Distilling 200 transitions into CRR: 1 gradient updates" in capsys.readouterr().out
    # gamma = 0: the TD target is the reward, whatever the next state's value
    batch = student.replay_buffer.sample(16)
    assert (batch.dones == 0).all()
    with th.no_grad():
        th.testing.assert_close(student._critic_target_values(batch, None), batch.rewards, rtol=0, atol=0)
    # seed 0: the student is the one CRR builds and trains with seed 0 on the same data
    reference = CRR.from_offline_data(
        teacher.replay_buffer,
        observation_space=teacher.observation_space,
        action_space=teacher.action_space,
        seed=0,
        verbose=0,
        gamma=0.0,
        compute=compute,
        device="cpu",
        **small,
    ).learn_offline(3, log_interval=1_000)
    for (name, got), want in zip(student.policy.state_dict().items(), reference.policy.state_dict().values()):
        assert th.equal(got, want), name


def test_the_student_logs_beside_a_teacher_with_a_logger_of_its_own(tmp_path):
    """A teacher given a logger with ``set_logger`` (no ``tensorboard_log``): the student writes its CSV in
    ``<that logger's folder>/<tb_log_name>``, the teacher's formats."""
    from stable_baselines3.common.logger import configure

    from sb3_lifelong import MPO

    teacher = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8]), learning_starts=1_000, seed=5, device="cpu")
    teacher.set_logger(configure(str(tmp_path), ["csv"]))
    teacher.learn(200)
    compute = dict(scoring_dtype="float32", compile_losses=False)
    teacher.distill(CRR, total_updates=4, tb_log_name="student", verbose=0, compute=compute, log_interval=2,
                    policy_kwargs=dict(net_arch=[8]), batch_size=16, num_samples=2)  # fmt: skip
    progress = tmp_path / "student" / "progress.csv"
    assert progress.is_file() and "time/updates" in progress.read_text().splitlines()[0]
