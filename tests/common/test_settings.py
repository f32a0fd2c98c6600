"""Grouped settings (MPO's ``policy_loss``, MPO's and CRR's ``compute``): given, checked, saved, loaded, migrated."""

import dataclasses
import io
import json
import zipfile

import pytest
import torch as th
from gymnasium import spaces

from sb3_lifelong import CRR, MPO
from sb3_lifelong.mpo import PolicyLossConfig
from sb3_lifelong.numerics import ComputeSettings
from tests.testkit import pendulum_data

SMALL = dict(learning_starts=50, batch_size=16, num_samples=4, policy_kwargs=dict(net_arch=[8]), seed=0, device="cpu")


def small_mpo(**kwargs) -> MPO:
    return MPO("MlpPolicy", "Pendulum-v1", **{**SMALL, **kwargs})


def test_a_dict_and_the_dataclass_give_the_same_settings():
    by_dict = small_mpo(policy_loss=dict(epsilon_mean=0.01, action_penalty=True), compute=dict(compile_losses=False))
    by_class = small_mpo(
        policy_loss=PolicyLossConfig(epsilon_mean=0.01, action_penalty=True), compute=ComputeSettings(compile_losses=False)
    )
    assert by_dict.policy_loss == by_class.policy_loss == PolicyLossConfig(epsilon_mean=0.01, action_penalty=True)
    assert by_dict.compute == by_class.compute and by_dict.compute.scoring_dtype == "auto"
    assert small_mpo().policy_loss == PolicyLossConfig() and small_mpo().compute == ComputeSettings()
    # the settings reach the model: the duals start where policy_loss says, the penalty's dual is trained
    model = small_mpo(policy_loss=dict(init_temperature=3.0, action_penalty=True))
    assert model.temperature == pytest.approx(3.0, rel=1e-5)
    assert "log_penalty_temperature" in dict(model._trained_duals())


def test_unknown_and_invalid_settings_are_refused_by_name():
    with pytest.raises(TypeError, match=r"policy_loss has no setting \['epsilon_men'\]; its settings are \['epsilon'"):
        small_mpo(policy_loss=dict(epsilon_men=0.01))
    with pytest.raises(TypeError, match=r"compute has no setting \['epsilon'\]"):
        CRR("MlpPolicy", "Pendulum-v1", compute=dict(epsilon=0.1))
    with pytest.raises(ValueError, match=r"Invalid PolicyLossConfig: epsilon_mean=-1.0, init_alpha_mean=0"):
        small_mpo(policy_loss=dict(epsilon_mean=-1.0, init_alpha_mean=0))
    with pytest.raises(ValueError, match=r"Invalid ComputeSettings: train_dtype='bf16' \(one of"):
        ComputeSettings(train_dtype="bf16")
    with pytest.raises(ValueError, match=r"compile_losses=True .*runs eagerly"):
        ComputeSettings(train_dtype="simulated_bfloat16", compile_losses=True)
    with pytest.raises(TypeError, match="compute must be a ComputeSettings, a dict of its settings or None, got 'float32'"):
        small_mpo(compute="float32")
    with pytest.raises(dataclasses.FrozenInstanceError):
        small_mpo().policy_loss.epsilon = 1.0  # type: ignore[misc]


def saved_data(path) -> dict:
    with zipfile.ZipFile(path) as archive:
        return json.loads(archive.read("data"))


def test_saved_as_plain_json_and_loaded_back_also_with_safe(tmp_path):
    model = small_mpo(policy_loss=dict(epsilon_mean=0.01), compute=dict(scoring_dtype="float32", compile_losses=False))
    model.learn(80)
    model.save(tmp_path / "model")
    data = saved_data(tmp_path / "model.zip")
    assert data["policy_loss"] == dataclasses.asdict(model.policy_loss)  # readable, no pickle
    assert data["compute"] == {"scoring_dtype": "float32", "train_dtype": "float32", "compile_losses": False}
    assert isinstance(model.policy_loss, PolicyLossConfig)  # the model keeps its dataclass after the save
    for safe in (False, True):
        loaded = MPO.load(tmp_path / "model", safe=safe)
        assert loaded.policy_loss == model.policy_loss and loaded.compute == model.compute
        assert th.equal(loaded.log_alpha_mean, model.log_alpha_mean)


def test_a_dict_given_to_load_changes_only_the_settings_it_names(tmp_path):
    model = small_mpo(compute=dict(scoring_dtype="float32", compile_losses=False))
    model.save(tmp_path / "model")
    loaded = MPO.load(tmp_path / "model", compute=dict(train_dtype="simulated_bfloat16"))
    assert loaded.compute == ComputeSettings(scoring_dtype="float32", train_dtype="simulated_bfloat16", compile_losses=False)
    assert all(layer.simulated for layer in loaded.policy.modules() if hasattr(layer, "simulated"))
    replaced = MPO.load(tmp_path / "model", compute=ComputeSettings())  # a whole instance replaces them
    assert replaced.compute == ComputeSettings()


def flat_zip(source, target, groups: dict[str, dict]) -> None:
    """``source`` rewritten as a zip saved before the settings were grouped: their fields as attributes of their own."""
    with zipfile.ZipFile(source) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(members["data"])
    for name, flat in groups.items():
        del data[name]
        data.update(flat)
    members["data"] = json.dumps(data).encode()
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    target.write_bytes(buffer.getvalue())


def test_a_zip_saved_before_the_grouping_loads_with_its_settings(tmp_path):
    model = small_mpo(policy_loss=dict(epsilon_mean=0.01, init_alpha_stddev=1000.0, action_penalty=True))
    model.learn(80)
    model.save(tmp_path / "model")
    old = dict(epsilon_mean=0.01, init_alpha_stddev=1000.0, action_penalty=True, epsilon=0.2)
    flat_zip(tmp_path / "model.zip", tmp_path / "old.zip", {"policy_loss": old, "compute": dict(scoring_dtype="float32")})
    loaded = MPO.load(tmp_path / "old.zip", env=model.get_env())
    assert loaded.policy_loss == PolicyLossConfig(**old)
    assert loaded.compute == ComputeSettings(scoring_dtype="float32")
    assert not any(name in loaded.__dict__ for name in ("epsilon", "epsilon_mean", "scoring_dtype"))  # moved, not copied
    loaded.learn(16, reset_num_timesteps=False)  # and it trains with them (the penalty's dual among the trained)
    assert "train/penalty_temperature" in loaded.logger.name_to_value


def test_crr_takes_compute_and_saves_it(tmp_path):
    student = CRR.from_offline_data(
        pendulum_data(200),
        env=None,
        action_space=spaces.Box(-2, 2, (1,)),
        policy_kwargs=dict(net_arch=[8]),
        batch_size=16,
        compute=dict(scoring_dtype="float32", compile_losses=False),
    )
    student.learn_offline(4)
    student.save(tmp_path / "student")
    assert saved_data(tmp_path / "student.zip")["compute"]["compile_losses"] is False
    assert CRR.load(tmp_path / "student").compute == ComputeSettings(scoring_dtype="float32", compile_losses=False)
