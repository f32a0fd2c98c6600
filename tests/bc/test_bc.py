import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from testkit import flat_params

from sb3_lifelong import BC
from sb3_lifelong.bc.policies import BCPolicy
from sb3_lifelong.numerics.fast_ops import Tanh

SMALL = dict(policy_kwargs=dict(net_arch=[32, 32]), batch_size=32)


def linear_data(n: int = 300, seed: int = 0) -> dict:
    """Actions are a fixed linear function of the observation, in [-2, 2]."""
    rng = np.random.default_rng(seed)
    obs = rng.uniform(-1, 1, size=(n, 2)).astype(np.float32)
    actions = np.clip(1.5 * obs[:, :1] - 0.5 * obs[:, 1:], -2, 2).astype(np.float32)
    return {
        "observations": obs,
        "actions": actions,
        "rewards": np.zeros(n, dtype=np.float32),
        "next_observations": obs,
        "terminals": np.ones(n, dtype=bool),
    }


def bc_model(seed: int = 0, **kwargs) -> BC:
    return BC.from_offline_data(linear_data(), action_space=spaces.Box(-2, 2, (1,)), seed=seed, **{**SMALL, **kwargs})


def test_policy_has_only_an_actor():
    model = bc_model()
    assert isinstance(model.policy, BCPolicy)
    assert not hasattr(model.policy, "critic")
    assert set(model.policy.state_dict()) == {f"actor.{key}" for key in model.actor.state_dict()}


def test_layer_norm_actor_learns():
    model = bc_model(policy_kwargs=dict(net_arch=[32, 32], layer_norm=True))
    assert [type(m) for m in model.actor.latent_pi][:3] == [th.nn.Linear, th.nn.LayerNorm, Tanh]
    first_layer = [p.clone() for p in model.actor.latent_pi[:2].parameters()]
    model.learn_offline(600, log_interval=0)
    # every layer trained (a gradient cut at the LayerNorm would leave the first layer as it was), and the clone fits
    assert all(not th.equal(a, b) for a, b in zip(first_layer, model.actor.latent_pi[:2].parameters()))
    data = linear_data(n=50, seed=1)
    predicted, _ = model.predict(data["observations"], deterministic=True)
    assert np.abs(predicted - data["actions"]).mean() < 0.15


@pytest.mark.parametrize("loss", ["nll", "mse"])
def test_clones_a_linear_policy(loss):
    model = bc_model(loss=loss, learning_rate=3e-3)
    model.learn_offline(600, log_interval=0)
    data = linear_data(n=50, seed=1)
    predicted, _ = model.predict(data["observations"], deterministic=True)
    assert np.abs(predicted - data["actions"]).mean() < 0.15
    if loss == "nll":  # the standard deviation shrinks towards the (zero) noise of the data
        with th.no_grad():
            _, std = model.actor.distribution_params(th.as_tensor(data["observations"], device=model.device))
        assert float(std.mean()) < 0.2
    else:  # mse leaves the standard deviation alone
        with th.no_grad():
            _, std = model.actor.distribution_params(th.as_tensor(data["observations"], device=model.device))
        assert float(std.mean()) == pytest.approx(0.7, rel=0.2)


def test_logs(tmp_path):
    model = bc_model()
    model.tensorboard_log = str(tmp_path)
    model.learn_offline(30, log_interval=10)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    accumulator = EventAccumulator(str(tmp_path / "BC_1"))
    accumulator.Reload()
    tags = accumulator.Tags()["scalars"]
    for key in ("actor_loss", "nll", "mse", "std_mean"):
        assert f"train/{key}" in tags
    assert [event.step for event in accumulator.Scalars("train/nll")] == [10, 20, 30]


def test_save_load_and_resume_exact(tmp_path):
    uninterrupted = bc_model(seed=2)
    uninterrupted.learn_offline(40, log_interval=0)
    uninterrupted.learn_offline(40, reset_num_timesteps=False, log_interval=0)

    first = bc_model(seed=2)
    first.learn_offline(40, log_interval=0)
    first.save(tmp_path / "bc.zip")
    del first
    th.manual_seed(1)
    np.random.seed(1)
    resumed = BC.load(tmp_path / "bc.zip")
    assert resumed.get_env() is None and resumed.loss == "nll"
    resumed.set_offline_data(linear_data())
    resumed.learn_offline(40, reset_num_timesteps=False, log_interval=0)
    assert resumed.num_timesteps == 80
    th.testing.assert_close(flat_params(resumed), flat_params(uninterrupted), rtol=0, atol=0)


def test_online_learn_runs():
    model = BC("MlpPolicy", "Pendulum-v1", learning_starts=50, seed=0, **SMALL)
    model.learn(100)
    assert model._n_updates > 0


def test_bad_hyperparameters():
    with pytest.raises(ValueError, match="loss"):
        BC("MlpPolicy", "Pendulum-v1", loss="l1")
    with pytest.raises(ValueError, match="max_grad_norm"):
        BC("MlpPolicy", "Pendulum-v1", max_grad_norm=0.0)


@pytest.mark.parametrize("loss", ["nll", "mse"])
def test_one_update_on_a_fixed_batch_against_numpy(loss):
    """BC's losses of one update, from the policy's mean and std in NumPy: the Gaussian's negative log-likelihood and
    the mean's squared error (summed over the action's dimensions, averaged over the batch); the chosen one is the
    one optimised: it falls on the same batch after the step, and Adam's first step moves every parameter by -lr *
    sign(gradient) of that loss."""
    import math

    from stable_baselines3.common.type_aliases import ReplayBufferSamples

    data = linear_data()
    model = BC.from_offline_data(
        {**data, "actions": np.repeat(data["actions"], 2, axis=1)},
        action_space=spaces.Box(-2, 2, (2,)),
        loss=loss,
        learning_rate=1e-3,
        seed=0,
        **SMALL,
    )
    rng = np.random.default_rng(0)
    obs, actions = rng.uniform(-1, 1, size=(16, 2)), rng.uniform(-1, 1, size=(16, 2))
    batch = ReplayBufferSamples(
        *(th.tensor(x, dtype=th.float32) for x in (obs, actions, obs, np.zeros((16, 1)), np.zeros((16, 1))))
    )
    model.replay_buffer.sample = lambda *args, **kwargs: batch  # type: ignore[method-assign]

    def losses() -> tuple[float, float]:
        with th.no_grad():
            mean, std = (x.double().numpy() for x in model.actor.distribution_params(batch.observations))
        nll = -(-0.5 * ((actions - mean) / std) ** 2 - np.log(std) - 0.5 * math.log(2 * math.pi)).sum(axis=1).mean()
        return float(nll), float(((mean - actions) ** 2).sum(axis=1).mean())

    before = losses()
    params = [p.detach().clone() for p in model.actor.parameters()]
    model.actor.optimizer.zero_grad()
    mean, std = model.actor.distribution_params(batch.observations)
    chosen = -th.distributions.Normal(mean, std).log_prob(batch.actions).sum(1).mean() if loss == "nll" else None
    if chosen is None:
        chosen = (mean - batch.actions).pow(2).sum(1).mean()
    grads = th.autograd.grad(chosen, list(model.actor.parameters()), allow_unused=True)
    model.learn_offline(1, log_interval=0)
    logged = model.logger.name_to_value
    assert logged["train/nll"] == pytest.approx(before[0], rel=1e-5)
    assert logged["train/mse"] == pytest.approx(before[1], rel=1e-5)
    assert logged["train/actor_loss"] == pytest.approx(before[0 if loss == "nll" else 1], rel=1e-5)
    after = losses()
    assert after[0 if loss == "nll" else 1] < before[0 if loss == "nll" else 1]
    for old, new, grad in zip(params, model.actor.parameters(), grads):
        if grad is None:  # the std's head, with the mse: no gradient, not moved
            assert loss == "mse" and th.equal(old, new)
            continue
        large = grad.abs() > 1e-4  # Adam's first step is g / (|g| + 1e-8): the sign, where |g| >> 1e-8
        th.testing.assert_close((new.detach() - old)[large], -1e-3 * th.sign(grad[large]), rtol=1e-3, atol=1e-7)
