"""MPO's named presets: Acme's MuJoCo baseline, its zoo file, and what it builds."""

import math

import numpy as np
import pytest
import torch as th
import yaml
from torch import nn

from sb3_lifelong import MPO
from sb3_lifelong.mpo.presets import ACME_MUJOCO, ACME_MUJOCO_SOURCES, acme_mujoco
from sb3_lifelong.zoo import PRESETS, hyperparams_file

SMALL = {"learning_starts": 100, "policy_kwargs": {"net_arch": [32, 32]}, "batch_size": 32, "num_samples": 4}


def test_every_setting_has_a_source():
    grouped = ("policy_kwargs", "policy_loss")
    names = {key for key in ACME_MUJOCO if key not in grouped}
    names |= {f"{group}.{key}" for group in grouped for key in ACME_MUJOCO[group]}
    assert set(ACME_MUJOCO_SOURCES) == names
    assert all("acme" in source for source in ACME_MUJOCO_SOURCES.values())


def test_overrides_merge_and_copies_are_fresh():
    kwargs = acme_mujoco(learning_starts=5, policy_kwargs={"net_arch": [8]})
    assert kwargs["learning_starts"] == 5 and kwargs["policy_kwargs"]["net_arch"] == [8]
    assert kwargs["policy_kwargs"]["init_std"] == 0.5  # the rest of the preset's policy_kwargs stays
    kwargs["policy_kwargs"]["init_std"] = 9.0
    assert ACME_MUJOCO["policy_kwargs"]["init_std"] == 0.5 and acme_mujoco()["learning_starts"] == 1_000
    with pytest.raises(TypeError, match=r"\['not_an_mpo_setting'\]"):
        acme_mujoco(not_an_mpo_setting=1)
    kwargs = acme_mujoco(policy_loss={"epsilon_mean": 0.05})
    assert kwargs["policy_loss"]["epsilon_mean"] == 0.05 and kwargs["policy_loss"]["init_alpha_stddev"] == 1000.0
    assert ACME_MUJOCO["policy_loss"]["epsilon_mean"] == 0.01


def test_builds_acme_networks_duals_and_ratio():
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **acme_mujoco())
    actor = model.actor
    linears = [module for module in actor.latent_pi if isinstance(module, nn.Linear)]
    assert [layer.out_features for layer in linears] == [256, 256, 256]
    kinds = [type(module).__name__ for module in actor.latent_pi]
    assert kinds[:3] == ["Linear", "LayerNorm", "Tanh"] and kinds.count("ELU") == 2
    critic_kinds = [type(module).__name__ for module in model.critic.q_networks[0]]
    assert critic_kinds.count("LayerNorm") == 1 and critic_kinds.count("ELU") == 2
    assert not actor.squash_mean and model.policy_loss.action_penalty
    assert math.isclose(actor._std_scale * math.log(2.0), 0.5)  # the std at a zero pre-activation: the init scale
    assert model.train_freq.frequency == 4 and model.gradient_steps == 1 and model.n_steps == 4
    assert model.replay_buffer.n_steps == 4
    assert model.policy_loss.epsilon_mean == 0.01 and model.learning_rate == 3e-4 and model.target_update_interval == 100
    assert math.isclose(model.temperature, 10.0, rel_tol=1e-4)
    assert np.allclose(model.log_alpha_stddev.detach().numpy(), 1000.0)  # softplus is the identity up there


def test_one_update_per_four_steps():
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **acme_mujoco(**SMALL))
    model.learn(500)
    # rollouts of 4 steps; learning after the 100 warm-up steps: (500 - 100) / 4 updates
    assert model._n_updates == 100


def test_zoo_file_is_the_preset():
    path = hyperparams_file("mpo", "acme")
    assert path.name == "mpo_acme.yml" and PRESETS["mpo"] == ("acme",)
    entries = yaml.safe_load(path.read_text())
    expected = acme_mujoco()
    for env_id, entry in entries.items():
        settings = {key: value for key, value in entry.items() if key not in ("n_timesteps", "policy")}
        settings["policy_kwargs"] = eval(settings["policy_kwargs"], {"nn": nn})  # the zoo evaluates it so
        assert settings == expected, env_id
    assert {"HalfCheetah-v5", "Walker2d-v5", "Hopper-v5", "sb3_lifelong/OP3Walk-v0"} <= set(entries)
    with pytest.raises(ValueError, match="no preset 'paper' for mpo"):
        hyperparams_file("mpo", "paper")


def test_head_init_scale_starts_every_state_at_mean_zero_and_the_init_std():
    kwargs = acme_mujoco(**SMALL)
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **kwargs)
    obs = th.as_tensor(np.random.default_rng(0).uniform(-5, 5, size=(512, 3)), dtype=th.float32)
    with th.no_grad():
        mean, std = model.actor.distribution_params(obs)
    assert mean.abs().max() < 0.05 and float((std - 0.5).abs().max()) < 0.01
    assert th.count_nonzero(model.actor.mu.bias) == 0 and th.count_nonzero(model.actor.std_head.bias) == 0
    fan_in = model.actor.mu.in_features
    assert float(model.actor.mu.weight.std()) == pytest.approx(math.sqrt(1e-4 / fan_in) * 0.88, rel=0.25)  # truncated
    default = MPO(
        "MlpPolicy",
        "Pendulum-v1",
        seed=0,
        **acme_mujoco(**{**SMALL, "policy_kwargs": {"net_arch": [32, 32], "head_init_scale": None}}),
    )
    with th.no_grad():
        spread = default.actor.distribution_params(obs)[1]
    assert float((spread - 0.5).abs().max()) > 0.02  # torch's default heads: the std varies by state


def test_head_init_scale_is_saved_and_checked(tmp_path):
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **acme_mujoco(**SMALL))
    model.save(tmp_path / "model")
    loaded = MPO.load(tmp_path / "model")
    assert loaded.actor.head_init_scale == 1e-4 and loaded.actor.min_std == 1e-6
    assert th.equal(loaded.actor.mu.weight, model.actor.mu.weight)
    with pytest.raises(ValueError, match="head_init_scale must be None or a number > 0, got -1"):
        MPO("MlpPolicy", "Pendulum-v1", policy_kwargs={"head_init_scale": -1})
