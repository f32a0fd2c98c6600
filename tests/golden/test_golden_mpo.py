"""
Golden numbers for MPO's critic target (issue 66): ``r + (1 - done) * discount * mean_j min_i Q'_i(s', a'_j)``, with
``a'_j = clip(mu'(s') + sigma'(s') * noise_j, -1, 1)`` drawn from the *target* policy with the update's own noise,
computed in NumPy from the networks' weights (never by calling the code under test), for both ways of bootstrapping
(``policy_on_next_obs=True``: the samples on the next observations serve the E-step too; ``False``: one pass over
``[obs; next_obs]``, the first half of the noise for the E-step's samples, the second half for the target). The eager
path only (``compile_losses=False``): a compiled update is compared with it elsewhere, this pins the eager one itself.
"""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from torch import nn

from sb3_lifelong import MPO

GAMMA = 0.9
OBS_DIM, ACTION_DIM, BATCH, SAMPLES = 3, 2, 5, 4
TRAIN_BATCH = 12


class BoxEnv(gym.Env):
    """A 3-D observation, 2-D action task with a random walk for observations: only its spaces and data matter."""

    observation_space = spaces.Box(-5.0, 5.0, (OBS_DIM,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self.np_random.normal(size=OBS_DIM).astype(np.float32), {}

    def step(self, action):
        self.t += 1
        obs = self.np_random.normal(size=OBS_DIM).astype(np.float32)
        return obs, float(np.sum(action) - obs[0]), bool(self.t % 3 == 0), False, {}


# ---------------------------------------------------------------------------------------------------------------------
# NumPy references of the networks (MPO's default torso: Linear -> LayerNorm -> tanh -> Linear -> ReLU)
# ---------------------------------------------------------------------------------------------------------------------


def np_param(tensor: th.Tensor) -> np.ndarray:
    return tensor.detach().double().numpy()


def np_linear(x: np.ndarray, layer: nn.Module) -> np.ndarray:
    assert isinstance(layer, nn.Linear)
    return x @ np_param(layer.weight).T + np_param(layer.bias)


def np_torso(x: np.ndarray, net: nn.Sequential) -> np.ndarray:
    assert isinstance(net[1], nn.LayerNorm) and isinstance(net[2], nn.Tanh) and isinstance(net[4], nn.ReLU)
    h = np_linear(x, net[0])
    h = (h - h.mean(-1, keepdims=True)) / np.sqrt(h.var(-1, keepdims=True) + net[1].eps)
    h = np.tanh(h * np_param(net[1].weight) + np_param(net[1].bias))
    return np.maximum(np_linear(h, net[3]), 0.0)


def np_actor(actor, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """mean ``tanh(mu(h))`` and std ``softplus(s(h)) * init_std / log 2 + min_std``"""
    latent = np_torso(obs, actor.latent_pi)
    std = np.log1p(np.exp(np_linear(latent, actor.std_head))) * actor.init_std / math.log(2.0) + actor.min_std
    return np.tanh(np_linear(latent, actor.mu)), std


def np_q_each(critic, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """each Q-network's values ``[C, ..., batch]`` of ``actions`` ``[..., batch, action_dim]`` in ``obs`` ``[batch, dim]``"""
    inputs = np.concatenate([np.broadcast_to(obs, actions.shape[:-1] + obs.shape[-1:]), actions], axis=-1)
    return np.stack([np_linear(np_torso(inputs, net), net[5])[..., 0] for net in critic.q_networks])


def np_target(model: MPO, obs, next_obs, rewards, bootstrap, noise) -> dict:
    """The critic's target and the E-step's samples and their Q-values, from the target networks, in NumPy."""
    batch = len(rewards)
    if model.policy_on_next_obs:
        e_obs, e_noise, t_noise = next_obs, noise, noise
    else:
        e_obs, e_noise, t_noise = obs, noise[:, :batch], noise[:, batch:]
    next_mean, next_std = np_actor(model.actor_target, next_obs)
    next_actions = np.clip(next_mean[None] + next_std[None] * t_noise, -1.0, 1.0)  # the critic sees clipped actions
    next_q = np_q_each(model.critic_target, next_obs, next_actions).min(axis=0)  # [N, B]: lowest Q-network
    e_mean, e_std = np_actor(model.actor_target, e_obs)
    e_actions = e_mean[None] + e_std[None] * e_noise  # the M-step fits the samples as drawn (not clipped)
    return {
        "target": rewards + bootstrap * next_q.mean(axis=0)[:, None],
        "mean": e_mean,
        "std": e_std,
        "actions": e_actions,
        "q_values": np_q_each(model.critic_target, e_obs, np.clip(e_actions, -1.0, 1.0)).min(axis=0),
    }


def make_model(policy_on_next_obs: bool, **kwargs) -> MPO:
    model = MPO(
        "MlpPolicy",
        BoxEnv(),
        policy_kwargs=dict(net_arch=[4, 4], n_critics=2),
        gamma=GAMMA,
        num_samples=SAMPLES,
        policy_on_next_obs=policy_on_next_obs,
        compute=dict(compile_losses=False, scoring_dtype="float32"),
        seed=1,
        device="cpu",
        **kwargs,
    )
    gen = th.Generator().manual_seed(2)
    with th.no_grad():  # every parameter away from its initial value (LayerNorm's too), the targets away from the online
        for parameter in model.policy.parameters():
            parameter.add_(0.5 * th.randn(parameter.shape, generator=gen))
    return model


def f32(x) -> th.Tensor:
    return th.tensor(np.asarray(x), dtype=th.float32)


@pytest.mark.parametrize("policy_on_next_obs", [True, False])
@pytest.mark.parametrize("buffer_discounts", [False, True])
def test_critic_target_against_numpy(policy_on_next_obs, buffer_discounts):
    model = make_model(policy_on_next_obs)
    rng = np.random.default_rng(3)
    obs, next_obs = rng.normal(size=(BATCH, OBS_DIM)), rng.normal(size=(BATCH, OBS_DIM))
    actions = rng.uniform(-1, 1, size=(BATCH, ACTION_DIM))
    rewards = rng.normal(size=(BATCH, 1))
    dones = np.array([[0.0], [1.0], [0.0], [0.0], [1.0]])
    rows = BATCH * (1 if policy_on_next_obs else 2)
    noise = rng.normal(size=(SAMPLES, rows, ACTION_DIM)) * 1.5  # wide enough that some samples leave [-1, 1]
    # the buffer's n-step discounts (gamma^k, k steps taken) replace gamma where it gives them
    discounts = np.array([[GAMMA**3], [GAMMA**2], [GAMMA**1], [GAMMA**3], [GAMMA**3]]) if buffer_discounts else None
    replay = ReplayBufferSamples(
        f32(obs), f32(actions), f32(next_obs), f32(dones), f32(rewards), None if discounts is None else f32(discounts)
    )
    assert model._sampling_noise(replay).shape == noise.shape
    with th.no_grad():  # as in the update
        got = model._sample_and_score(replay, f32(noise))
    bootstrap = (1.0 - dones) * (GAMMA if discounts is None else discounts)
    want = np_target(model, obs, next_obs, rewards, bootstrap, noise)
    np.testing.assert_allclose(got.critic_target.numpy(), want["target"], rtol=1e-5, atol=1e-6)
    for name in ("mean", "std", "actions", "q_values"):
        np.testing.assert_allclose(getattr(got, name).numpy(), want[name], rtol=1e-5, atol=1e-6, err_msg=name)
    # the inputs make every part of the formula matter: clipped samples, both Q-networks the lowest somewhere, dones
    t_noise = noise if policy_on_next_obs else noise[:, BATCH:]
    mean, std = np_actor(model.actor_target, next_obs)
    samples = mean[None] + std[None] * t_noise
    assert (np.abs(samples) > 1).any() and (np.abs(samples) < 1).any()
    lowest = np_q_each(model.critic_target, next_obs, np.clip(samples, -1, 1)).argmin(axis=0)
    assert (lowest == 0).any() and (lowest == 1).any()


@pytest.mark.parametrize("policy_on_next_obs", [True, False])
def test_one_eager_update_regresses_the_critic_on_the_hand_computed_target(policy_on_next_obs):
    """Through ``train``: the batch and noise it draws, the pre-update critic's loss ``0.5 sum_i mean (Q_i - y)^2``."""
    model = make_model(policy_on_next_obs, learning_starts=10_000)
    model.learn(30)  # fills the buffer (30 steps, 10 three-step episodes), no update
    assert model._n_updates == 0
    seen = {}
    sample, sampling_noise = model.replay_buffer.sample, model._sampling_noise

    def recording_sample(*args, **kwargs):
        seen["batch"] = sample(*args, **kwargs)
        return seen["batch"]

    def recording_noise(replay_data):
        seen["noise"] = sampling_noise(replay_data)
        return seen["noise"]

    model.replay_buffer.sample, model._sampling_noise = recording_sample, recording_noise
    before = {name: p.detach().clone() for name, p in model.critic.named_parameters()}
    model.train(gradient_steps=1, batch_size=TRAIN_BATCH)
    after = {name: p.detach().clone() for name, p in model.critic.named_parameters()}
    with th.no_grad():  # evaluate the pre-update online critic in NumPy
        for name, p in model.critic.named_parameters():
            p.copy_(before[name])
    batch, noise = seen["batch"], seen["noise"].numpy()
    obs, next_obs = batch.observations.double().numpy(), batch.next_observations.double().numpy()
    rewards, dones = batch.rewards.double().numpy(), batch.dones.double().numpy()
    assert batch.discounts is None  # one-step: gamma
    assert (dones == 1).any() and (dones == 0).any()
    target = np_target(model, obs, next_obs, rewards, (1.0 - dones) * GAMMA, noise)["target"][:, 0]
    q = np_q_each(model.critic, obs, batch.actions.double().numpy())  # [C, B]
    want = 0.5 * ((q - target[None]) ** 2).mean(axis=1).sum()
    assert model.logger.name_to_value["train/critic_loss"] == pytest.approx(want, rel=1e-5)
    assert model.logger.name_to_value["train/q_mean"] == pytest.approx(q[0].mean(), rel=1e-5, abs=1e-6)
    assert any(not th.equal(before[name], after[name]) for name in before)  # and the critic took its step


# ---------------------------------------------------------------------------------------------------------------------
# What ``train`` logs over several updates, and the defaults a user gets (mutation survivors of ``mpo/mpo.py``)
# ---------------------------------------------------------------------------------------------------------------------


class Recording:
    """An update's forward pass (``model._forward``), calling ``record(args, out[, before(args)])`` after each call."""

    def __init__(self, forward, record, before=None):
        self.forward, self.record, self.before = forward, record, before

    def __getattr__(self, name):
        return getattr(self.forward, name)

    def __call__(self, *args, **kwargs):
        seen = None if self.before is None else self.before(args)
        out = self.forward(*args, **kwargs)
        if self.before is None:
            self.record(args, out)
        else:
            self.record(args, out, seen)
        return out


def test_train_logs_the_mean_of_its_updates_for_every_statistic():
    """With several updates per call, each ``train/<statistic>`` is the mean over the updates (not their sum)."""
    from stable_baselines3.common.logger import configure

    model = make_model(
        policy_on_next_obs=True, learning_starts=0, batch_size=TRAIN_BATCH, policy_loss=dict(action_penalty=True)
    )
    model.learn(40)
    model.set_logger(configure(None, []))
    steps = []
    model._forward = Recording(model._forward, lambda args, out: steps.append((out[0], out[1])))  # type: ignore[assignment]
    model.train(gradient_steps=3, batch_size=TRAIN_BATCH)
    assert len(steps) == 3
    logged = model.logger.name_to_value
    for fields in ([fit for fit, _ in steps], [improvement for _, improvement in steps]):
        for key in fields[0]._fields:
            values = [float(getattr(step, key)) for step in fields]
            assert logged[f"train/{key}"] == pytest.approx(np.mean(values), rel=1e-6, abs=1e-9), key
            if len(set(values)) > 1:  # a sum would differ from the mean
                assert logged[f"train/{key}"] != pytest.approx(np.sum(values), rel=1e-6)
    assert logged["train/n_updates"] == model._n_updates


def test_the_defaults_a_user_gets():
    """The defaults a user gets without arguments (a change of one is a change of behaviour: a CHANGELOG line)."""
    import inspect

    defaults = {name: p.default for name, p in inspect.signature(MPO.__init__).parameters.items() if p.default is not p.empty}
    assert defaults["learning_rate"] == 3e-4
    assert defaults["num_samples"] == 20
    assert defaults["batch_size"] == 256
    assert defaults["n_steps"] == 1
    assert defaults["gamma"] == 0.99
    assert defaults["policy_on_next_obs"] is True
    assert (defaults["tau"], defaults["target_update_interval"]) == (1.0, 100)  # Acme's periodic hard target update
    model = MPO("MlpPolicy", BoxEnv(), device="cpu", seed=0)
    assert (model.learning_rate, model.num_samples, model.batch_size) == (3e-4, 20, 256)


def test_every_constructor_default_of_mpo_and_crr():
    """Every default of the two constructors, written out (the docs' parameter tables say the same): a change of one is
    a change of behaviour, with a CHANGELOG line and a change here."""
    from testkit import signature_defaults

    from sb3_lifelong import CRR

    def defaults(cls: type) -> dict:
        return signature_defaults(cls.__init__)

    shared = dict(
        learning_rate=3e-4,
        buffer_size=1_000_000,
        learning_starts=100,
        batch_size=256,
        tau=1.0,
        gamma=0.99,
        train_freq=1,
        gradient_steps=1,
        action_noise=None,
        replay_buffer_class=None,
        replay_buffer_kwargs=None,
        optimize_memory_usage=False,
        n_steps=1,
        target_update_interval=100,
        compute=None,
        stats_window_size=100,
        tensorboard_log=None,
        policy_kwargs=None,
        verbose=0,
        seed=None,
        device="auto",
        _init_setup_model=True,
    )
    assert defaults(MPO) == dict(
        shared, num_samples=20, policy_loss=None, dual_learning_rate=0.01, max_grad_norm=40.0, policy_on_next_obs=True
    )
    assert defaults(CRR) == dict(
        shared,
        env=None,
        num_samples=4,
        advantage_baseline="mean",
        advantage_transform="exp",
        beta=1.0,
        max_weight=20.0,
        normalize_advantages=False,
        target_ess=None,
        critic_target="policy",
        n_target_samples=1,
        actor_per_source=False,
        max_grad_norm=None,
        actor_averaging=None,
    )
    for name, value in shared.items():  # the same value is the same type: 1.0 is not 1, 0 is not False
        assert type(defaults(MPO)[name]) is type(value) and type(defaults(CRR)[name]) is type(value), name


def test_the_hyperparameters_at_the_edges_of_their_ranges():
    """num_samples and target_update_interval from 1, tau in (0, 1], dual_learning_rate above 0: the edges by hand."""
    import pytest

    small = dict(policy_kwargs=dict(net_arch=[8]), device="cpu")
    MPO("MlpPolicy", BoxEnv(), num_samples=1, target_update_interval=1, tau=1.0, dual_learning_rate=1e-9, **small)
    for bad in (dict(num_samples=0), dict(target_update_interval=0), dict(tau=0.0), dict(tau=1.0 + 1e-9),
                dict(dual_learning_rate=0.0)):  # fmt: skip
        name = next(iter(bad))
        with pytest.raises(ValueError, match=f"Invalid MPO hyperparameters: {name}="):
            MPO("MlpPolicy", BoxEnv(), **bad, **small)


def test_each_update_logs_the_duals_it_used_and_counts_itself():
    """Each update's logged duals are the duals before its step (the temperatures, and the mean over the action's
    dimensions of the per-dimension alphas); ``_n_updates`` grows by one an update; every dual is trained (the action
    penalty's temperature too); and ``learn``'s defaults are SB3's."""
    import inspect

    from stable_baselines3.common.logger import configure

    from sb3_lifelong.mpo.losses import dual_value

    model = make_model(
        policy_on_next_obs=True, learning_starts=0, batch_size=TRAIN_BATCH, policy_loss=dict(action_penalty=True)
    )
    model.learn(40)
    model.set_logger(configure(None, []))
    raws = ("log_temperature", "log_alpha_mean", "log_alpha_stddev", "log_penalty_temperature")
    seen = []

    def before(args):
        duals = {name: dual_value(getattr(model, name)).detach().clone() for name in raws}
        with th.no_grad():  # the policy's std on the batch's next observations (policy_on_next_obs=True)
            duals["std"] = model.actor.distribution_params(args[1].next_observations)[1].clone()
        return duals

    model._forward = Recording(  # type: ignore[assignment]
        model._forward, lambda args, out, duals: seen.append((duals, out[1], model._n_updates)), before=before
    )
    before = {name: getattr(model, name).detach().clone() for name in raws}
    start = model._n_updates
    model.train(gradient_steps=3, batch_size=TRAIN_BATCH)
    assert [n for _, _, n in seen] == [start + 1, start + 2, start + 3] and model._n_updates == start + 3
    for duals, improvement, _ in seen:
        assert duals["log_alpha_mean"].numel() == ACTION_DIM > 1
        assert float(improvement.temperature) == pytest.approx(float(duals["log_temperature"]))
        assert float(improvement.alpha_mean) == pytest.approx(float(duals["log_alpha_mean"].mean()))
        assert float(improvement.alpha_stddev) == pytest.approx(float(duals["log_alpha_stddev"].mean()))
        assert float(improvement.penalty_temperature) == pytest.approx(float(duals["log_penalty_temperature"]))
        assert float(improvement.std_min) == pytest.approx(float(duals["std"].min()))
        assert float(improvement.std_max) == pytest.approx(float(duals["std"].max()))
    for name in raws:
        assert not th.equal(getattr(model, name).detach(), before[name]), f"{name} was not trained"
    defaults = {n: p.default for n, p in inspect.signature(MPO.learn).parameters.items() if p.default is not p.empty}
    assert defaults == dict(callback=None, log_interval=4, tb_log_name="MPO", reset_num_timesteps=True, progress_bar=False)
