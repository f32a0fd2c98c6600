import math
import os

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from testkit import Recorder, flat_params, pendulum_data

from sb3_lifelong import CRR
from sb3_lifelong.crr.distributional import CategoricalCritic, categorical_projection
from sb3_lifelong.crr.losses import advantage_baseline, advantage_weights, crr_weights

SMALL = dict(policy_kwargs=dict(net_arch=[32, 32]), batch_size=32, learning_starts=50)
LOGGED = ("critic_loss", "actor_loss", "advantage_mean", "weight_mean", "weight_clip_frac", "q_mean")


@pytest.fixture(scope="module")
def data() -> dict:
    return pendulum_data()


def offline_model(data: dict, seed: int = 0, **kwargs) -> CRR:
    params = {**SMALL, **kwargs}
    params.pop("learning_starts")
    return CRR.from_offline_data(data, env=None, action_space=spaces.Box(-2, 2, (1,)), seed=seed, **params)


@pytest.fixture(scope="module")
def default_offline_run(data) -> CRR:
    """CRR at ``SMALL``'s settings, seed 0, after 110 updates: what a variant that changes nothing would equal"""
    return offline_model(data).learn_offline(110, log_interval=0)


def test_the_default_offline_run_is_reproducible(data, default_offline_run):
    again = offline_model(data).learn_offline(110, log_interval=0)
    assert th.equal(flat_params(again), flat_params(default_offline_run))


# ---------------------------------------------------------------------------------------------------------------------
# Policy improvement on hand-computed values
# ---------------------------------------------------------------------------------------------------------------------


def test_exp_transform_hand_computed():
    advantages = th.tensor([-1.0, 0.0, 1.0, 5.0, 1e6])
    weights, clipped = crr_weights(advantages, "exp", beta=1.0, max_weight=20.0)
    expected = [math.exp(-1), 1.0, math.e, 20.0, 20.0]  # exp(5) = 148 > 20: clipped; no overflow at 1e6
    np.testing.assert_allclose(weights.numpy(), expected, rtol=1e-6)
    assert clipped.tolist() == [False, False, False, True, True]
    weights, clipped = crr_weights(advantages[:4], "exp", beta=2.0, max_weight=20.0)
    np.testing.assert_allclose(weights.numpy(), [math.exp(-0.5), 1.0, math.exp(0.5), math.exp(2.5)], rtol=1e-6)
    assert not clipped.any()
    weights, _ = crr_weights(th.tensor([1.0, 3.0]), "exp", beta=1.0, max_weight=1.0)
    np.testing.assert_allclose(weights.numpy(), [1.0, 1.0])


def test_normalized_advantages_scale_free():
    data_q = th.tensor([10.0, 12.0, 14.0, 16.0])
    sampled_q = th.full((3, 4), 13.0)  # baseline 13: advantages -3, -1, 1, 3 (std 2.582)
    plain = advantage_weights(data_q, sampled_q, "mean", "exp", beta=1.0, max_weight=20.0)
    normalized = advantage_weights(data_q, sampled_q, "mean", "exp", beta=1.0, max_weight=20.0, normalize=True)
    scale = th.tensor([-3.0, -1.0, 1.0, 3.0]).std().item()
    np.testing.assert_allclose(plain.weights.numpy(), np.minimum(np.exp([-3.0, -1.0, 1.0, 3.0]), 20.0), rtol=1e-6)
    np.testing.assert_allclose(normalized.weights.numpy(), np.exp(np.array([-3.0, -1.0, 1.0, 3.0]) / scale), rtol=1e-6)
    assert normalized.advantages.tolist() == [-3.0, -1.0, 1.0, 3.0]  # logged as they are
    scaled = advantage_weights(100 * data_q, 100 * sampled_q, "mean", "exp", 1.0, 20.0, normalize=True)
    np.testing.assert_allclose(scaled.weights.numpy(), normalized.weights.numpy(), rtol=1e-5)  # reward scale drops out
    CRR("MlpPolicy", "Pendulum-v1", normalize_advantages=True, learning_starts=10, batch_size=8).learn(20)


def test_indicator_transform_hand_computed():
    weights, clipped = crr_weights(th.tensor([-2.0, 0.0, 1e-6, 3.0]), "indicator", beta=123.0)
    assert weights.tolist() == [0.0, 0.0, 1.0, 1.0]
    assert not clipped.any()
    with pytest.raises(ValueError, match="transform"):
        crr_weights(th.zeros(2), "softmax")


def test_mean_and_max_baselines():
    sampled_q = th.tensor([[1.0, 4.0], [3.0, 0.0], [2.0, -1.0]])  # N=3 samples, B=2 states
    assert advantage_baseline(sampled_q, "mean").tolist() == [2.0, 1.0]
    assert advantage_baseline(sampled_q, "max").tolist() == [3.0, 4.0]
    data_q = th.tensor([2.5, 2.5])
    assert (data_q - advantage_baseline(sampled_q, "mean")).tolist() == [0.5, 1.5]
    assert (data_q - advantage_baseline(sampled_q, "max")).tolist() == [-0.5, -1.5]
    with pytest.raises(ValueError, match="baseline"):
        advantage_baseline(sampled_q, "median")


def test_categorical_projection_hand_computed():
    support = th.tensor([0.0, 1.0, 2.0])
    probs = th.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.2, 0.3, 0.5], [1.0, 0.0, 0.0]])
    rewards = th.tensor([[0.5], [1.0], [-5.0], [0.25]])
    discounts = th.tensor([[1.0], [0.0], [1.0], [0.5]])
    target = categorical_projection(probs, rewards, discounts, support)
    expected = [
        [0.0, 0.5, 0.5],  # 1 -> 1.5: split between atoms 1 and 2
        [0.0, 1.0, 0.0],  # terminal: all the mass at the reward, 1
        [1.0, 0.0, 0.0],  # below the support: clipped to v_min
        [0.75, 0.25, 0.0],  # 0 -> 0.25
    ]
    np.testing.assert_allclose(target.numpy(), expected, atol=1e-6)
    np.testing.assert_allclose(target.sum(dim=1).numpy(), 1.0, rtol=1e-6)


def test_categorical_critic_returns_expected_values(data):
    model = offline_model(data, policy_kwargs=dict(net_arch=[16], distributional_critic=True, v_min=-10.0, v_max=10.0))
    critic = model.critic
    assert isinstance(critic, CategoricalCritic) and isinstance(model.critic_target, CategoricalCritic)
    obs, actions = th.randn(5, 3, device=model.device), th.rand(5, 1, device=model.device) * 2 - 1
    (logits,) = critic.logits(obs, actions)
    assert logits.shape == (5, 51)
    (q,) = critic(obs, actions)
    expected = (th.softmax(logits, dim=-1) * th.linspace(-10, 10, 51, device=model.device)).sum(-1, keepdim=True)
    th.testing.assert_close(q, expected)
    th.testing.assert_close(critic.q1_forward(obs, actions), expected)


# ---------------------------------------------------------------------------------------------------------------------
# Online, like any SB3 algorithm
# ---------------------------------------------------------------------------------------------------------------------


def test_online_learn_logs_and_predict():
    model = CRR("MlpPolicy", "Pendulum-v1", seed=1, **SMALL)
    model.learn(150)
    for key in LOGGED:
        assert np.isfinite(model.logger.name_to_value[f"train/{key}"]), key
    obs = model.env.reset()
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (1, 1) and np.all(np.abs(action) <= 2.0)
    with pytest.raises(ValueError, match="offline"):
        CRR("MlpPolicy", "Pendulum-v1", critic_target="sarsa", **SMALL).learn(10)


def test_online_multi_env_then_offline_on_own_buffer():
    model = CRR("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=0), seed=0, **SMALL)
    model.learn(200)
    assert model.replay_buffer.size() * 2 == 200
    updates = model._n_updates
    model.learn_offline(30, log_interval=0)  # continue on the collected data, no env steps
    assert model._n_updates == updates + 30


# ---------------------------------------------------------------------------------------------------------------------
# Offline
# ---------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(),
        dict(advantage_transform="indicator", advantage_baseline="max"),
        dict(critic_target="sarsa"),
        dict(n_target_samples=3, tau=0.005, target_update_interval=1, policy_kwargs=dict(net_arch=[32, 32], n_critics=2)),
        dict(policy_kwargs=dict(net_arch=[32, 32], distributional_critic=True, v_min=-200.0, v_max=0.0, n_critics=2)),
        dict(critic_target="sarsa", policy_kwargs=dict(net_arch=[32, 32], distributional_critic=True, v_min=-200.0)),
        dict(max_grad_norm=1.0, beta=0.1, max_weight=5.0),
        dict(policy_kwargs=dict(net_arch=[32, 32], layer_norm=True), compute=dict(scoring_dtype="bfloat16")),
        dict(policy_kwargs=dict(net_arch=[32, 32], layer_norm=True, distributional_critic=True, v_min=-200.0, v_max=0.0)),
    ],
)
def test_offline_variants_train(data, kwargs, default_offline_run):
    model = offline_model(data, **kwargs)
    before = [p.clone() for p in model.actor_target.parameters()]
    recorder = Recorder()
    model.learn_offline(110, callback=recorder, log_interval=0)
    for key in LOGGED:
        assert np.isfinite(recorder.values[f"train/{key}"]), key
    assert 0.0 <= recorder.values["train/weight_clip_frac"] <= 1.0
    assert any(not th.equal(a, b) for a, b in zip(before, model.actor_target.parameters()))
    assert th.isfinite(flat_params(model)).all()
    if kwargs.get("advantage_transform") == "indicator":  # its weights are 0 or 1
        assert recorder.values["train/weight_clip_frac"] == 0.0
    if kwargs and "policy_kwargs" not in kwargs:  # the defaults' networks and seed: the option changed the training
        assert not th.equal(flat_params(model), flat_params(default_offline_run))


def test_hard_target_update_interval(data):
    model = offline_model(data, target_update_interval=50)
    model.learn_offline(49, log_interval=0)
    for online, target in zip(model.critic.parameters(), model.critic_target.parameters()):
        assert not th.equal(online, target)
    model.learn_offline(1, reset_num_timesteps=False, log_interval=0)
    for online, target in zip(model.critic.parameters(), model.critic_target.parameters()):
        assert th.equal(online, target)


def test_callbacks_count_updates(data, tmp_path):
    calls = []

    class Counter(BaseCallback):
        def _on_step(self) -> bool:
            calls.append(self.num_timesteps)
            return len(calls) < 40  # stops training early

    model = offline_model(data)
    checkpoint = CheckpointCallback(save_freq=10, save_path=str(tmp_path), name_prefix="crr")
    eval_callback = EvalCallback(gym.make("Pendulum-v1"), eval_freq=25, n_eval_episodes=1, verbose=0)
    model.learn_offline(100, callback=[Counter(), checkpoint, eval_callback], log_interval=0)
    assert calls == list(range(1, 41)) and model.num_timesteps == 40
    assert sorted(os.listdir(tmp_path)) == [f"crr_{n}_steps.zip" for n in (10, 20, 30, 40)]
    assert np.isfinite(eval_callback.last_mean_reward)  # evaluated at update 25


def test_eval_progress_bar_and_tensorboard(data, tmp_path):
    pytest.importorskip("tensorboard")
    pytest.importorskip("tqdm")
    pytest.importorskip("rich")
    model = offline_model(data)
    model.tensorboard_log = str(tmp_path)
    envs = {"default": gym.make("Pendulum-v1"), "heavy": gym.make("Pendulum-v1", g=12.0)}
    model.learn_offline(40, eval_env=envs, eval_freq=20, n_eval_episodes=1, log_interval=10, progress_bar=True)
    model.learn_offline(20, eval_env=envs, eval_freq=20, n_eval_episodes=1, log_interval=10, reset_num_timesteps=False)
    assert sorted(os.listdir(tmp_path)) == ["CRR_1"]
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    accumulator = EventAccumulator(str(tmp_path / "CRR_1"))
    accumulator.Reload()
    tags = accumulator.Tags()["scalars"]
    for name in ("default", "heavy"):
        steps = [event.step for event in accumulator.Scalars(f"eval/{name}/mean_reward")]
        assert steps == [20, 40, 60]  # against the update count, continued by the second call
    assert "train/weight_mean" in tags and "time/updates_per_second" in tags


def test_save_load_without_env(data, tmp_path):
    model = offline_model(data, policy_kwargs=dict(net_arch=[32, 32], distributional_critic=True, v_min=-300.0, v_max=0.0))
    model.learn_offline(60, log_interval=0)
    model.save(tmp_path / "crr.zip")
    loaded = CRR.load(tmp_path / "crr.zip")
    assert loaded.get_env() is None
    th.testing.assert_close(flat_params(model), flat_params(loaded), rtol=0, atol=0)
    assert isinstance(loaded.critic, CategoricalCritic) and loaded.critic.v_min == -300.0
    assert loaded.action_space == model.action_space and loaded.beta == model.beta
    original = model.critic.optimizer.state_dict()["state"]
    restored = loaded.critic.optimizer.state_dict()["state"]
    th.testing.assert_close(original[0]["exp_avg"], restored[0]["exp_avg"], rtol=0, atol=0)
    obs = np.random.default_rng(0).normal(size=(4, 3)).astype(np.float32)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    # learn on: the data are re-attached
    loaded.set_offline_data(data)
    loaded.learn_offline(10, reset_num_timesteps=False, log_interval=0)
    assert loaded.num_timesteps == 70


@pytest.mark.parametrize("reattach", ["set_offline_data", "load_replay_buffer"])
def test_offline_resume_is_exact(data, tmp_path, reattach):
    uninterrupted = offline_model(data, seed=3, target_update_interval=30)
    uninterrupted.learn_offline(50, log_interval=0)
    uninterrupted.learn_offline(50, reset_num_timesteps=False, log_interval=0)

    first = offline_model(data, seed=3, target_update_interval=30)
    first.learn_offline(50, log_interval=0)
    first.save(tmp_path / "model.zip")
    first.save_replay_buffer(tmp_path / "buffer.pkl")
    del first
    th.manual_seed(999)
    np.random.seed(999)

    resumed = CRR.load(tmp_path / "model.zip")
    th.rand(5), np.random.rand(5)  # draws between the load and the training do not change the run
    if reattach == "set_offline_data":
        resumed.set_offline_data(data)
    else:
        resumed.load_replay_buffer(tmp_path / "buffer.pkl")
    resumed.learn_offline(50, reset_num_timesteps=False, log_interval=0)
    assert resumed.num_timesteps == uninterrupted.num_timesteps == 100
    th.testing.assert_close(flat_params(resumed), flat_params(uninterrupted), rtol=0, atol=0)


def test_same_seed_same_run(data):
    runs = []
    for seed in (5, 5, 6):
        model = offline_model(data, seed=seed)
        model.learn_offline(40, log_interval=0)
        runs.append(flat_params(model))
    th.testing.assert_close(runs[0], runs[1], rtol=0, atol=0)
    assert not th.equal(runs[0], runs[2])


def test_bad_hyperparameters():
    for kwargs, match in (
        (dict(num_samples=0), "num_samples"),
        (dict(advantage_transform="softmax"), "advantage_transform"),
        (dict(advantage_baseline="median"), "advantage_baseline"),
        (dict(beta=0.0), "beta"),
        (dict(max_weight=0.5), "max_weight"),
        (dict(critic_target="q"), "critic_target"),
        (dict(tau=0.0), "tau"),
        (dict(actor_averaging=0.0), "actor_averaging"),
        (dict(actor_averaging=1.5), "actor_averaging"),
    ):
        with pytest.raises(ValueError, match=match):
            CRR("MlpPolicy", "Pendulum-v1", **kwargs)
    with pytest.raises(AssertionError, match="Box"):
        CRR("MlpPolicy", "CartPole-v1")


def test_actor_averaging_is_an_average_of_the_iterates_and_leaves_training_alone(data, tmp_path):
    plain = offline_model(data, seed=4)
    plain.learn_offline(30, log_interval=0)  # (the seed sets the global generators: one model at a time)
    averaged = offline_model(data, seed=4, actor_averaging=0.1)
    assert plain.policy.actor_average is None and averaged.policy.actor_average is not None
    # by hand: the average after each actor update, from the actor's weights after that update
    expected = [p.detach().clone() for p in averaged.actor.parameters()]

    class Follow(BaseCallback):
        def _on_step(self) -> bool:
            for mean, p in zip(expected, averaged.actor.parameters()):
                mean.mul_(0.9).add_(p.detach(), alpha=0.1)
            return True

    averaged.learn_offline(30, log_interval=0, callback=Follow())  # one update per step
    # the online networks are those of the same run without averaging, bit for bit
    for name in ("actor", "critic", "actor_target", "critic_target"):
        th.testing.assert_close(
            th.cat([p.flatten() for p in getattr(plain.policy, name).parameters()]),
            th.cat([p.flatten() for p in getattr(averaged.policy, name).parameters()]),
            rtol=0,
            atol=0,
        )
    for mean, p in zip(expected, averaged.policy.actor_average.parameters()):
        th.testing.assert_close(p, mean, rtol=1e-5, atol=1e-6)
    # predict uses the averaged actor, which differs from the actor after 30 updates
    obs = np.random.default_rng(1).normal(size=(8, 3)).astype(np.float32)
    tensor = th.as_tensor(obs, device=averaged.device)
    with th.no_grad():
        want = averaged.policy.actor_average(tensor, deterministic=True).cpu().numpy()
        online = averaged.actor(tensor, deterministic=True).cpu().numpy()
    assert not np.allclose(want, online)
    np.testing.assert_allclose(averaged.policy.unscale_action(want), averaged.predict(obs, deterministic=True)[0], rtol=1e-6)
    # saved and loaded exactly, and training resumes with it
    averaged.save(tmp_path / "crr.zip")
    loaded = CRR.load(tmp_path / "crr.zip")
    assert loaded.actor_averaging == 0.1 and loaded.policy.actor_average is not None
    th.testing.assert_close(flat_params(loaded), flat_params(averaged), rtol=0, atol=0)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], averaged.predict(obs, deterministic=True)[0])
    loaded.set_offline_data(data)
    loaded.learn_offline(5, reset_num_timesteps=False, log_interval=0)


def test_sarsa_next_actions_row_by_row():
    """The data's next action where the mask is 1, the policy's samples where it is 0, for every sample."""
    from sb3_lifelong.crr.losses import sarsa_next_actions

    sampled = th.arange(12, dtype=th.float32).reshape(2, 3, 2)  # [n_samples, batch, action_dim]
    data = th.tensor([[-1.0, -2.0], [-3.0, -4.0], [-5.0, -6.0]])
    mask = th.tensor([[1.0], [0.0], [1.0]])
    out = sarsa_next_actions(sampled, data, mask)
    for k in range(2):
        assert th.equal(out[k, 0], data[0]) and th.equal(out[k, 2], data[2])  # shown in the data: the data's
        assert th.equal(out[k, 1], sampled[k, 1])  # not shown (an episode's last stored step): the policy's sample


def test_the_offline_progress_bar_counts_updates(data, monkeypatch):
    pytest.importorskip("tqdm")
    pytest.importorskip("rich")
    from sb3_lifelong.common.offline import OfflineProgressBarCallback

    seen = []
    original = OfflineProgressBarCallback._on_training_end

    def record(self):
        seen.append((self.pbar.n, self.pbar.total))
        original(self)

    monkeypatch.setattr(OfflineProgressBarCallback, "_on_training_end", record)
    offline_model(data).learn_offline(30, log_interval=0, progress_bar=True)
    assert seen == [(30, 30)]
