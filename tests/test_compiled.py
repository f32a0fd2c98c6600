"""The compiled forward passes of CRR and MPO (``compile_losses``): the same training as eager up to rounding, the
"auto" rule, the eager fallback when compiling fails, the bf16 scoring passes kept."""

import pytest
import torch as th
from gymnasium import spaces

from sb3_lifelong import CRR, MPO
from sb3_lifelong.common import compiling, scoring
from sb3_lifelong.crr import crr as crr_module
from sb3_lifelong.crr import distributional
from sb3_lifelong.mpo import mpo as mpo_module
from tests.test_crr import flat_params, pendulum_data

KWARGS = dict(
    batch_size=32,
    policy_kwargs=dict(net_arch=[32, 32], layer_norm=True, distributional_critic=True, v_min=-100.0, v_max=10.0),
    target_update_interval=4,
)


@pytest.fixture(scope="module")
def data() -> dict:
    return pendulum_data(300)


def student(data: dict, **kwargs) -> CRR:
    return CRR.from_offline_data(data, env=None, action_space=spaces.Box(-2, 2, (1,)), seed=0, **{**KWARGS, **kwargs})


@pytest.mark.skipif(not compiling.can_compile(th.device("cpu")), reason="inductor needs a C++ compiler")
def test_compiled_training_matches_eager_and_saves(data, tmp_path):
    eager = student(data, compile_losses=False).learn_offline(12, log_interval=0)
    compiled = student(data, compile_losses=True).learn_offline(12, log_interval=0)
    assert compiled._forward.compiled is not None and not compiled._forward.failed  # it ran compiled
    assert eager._forward.compiled is None
    # the same batches and noise: the parameters differ by rounding only, after 12 updates and 3 target updates
    difference = (flat_params(compiled) - flat_params(eager)).abs().max()
    assert difference <= 1e-4, float(difference)
    assert not th.equal(flat_params(compiled), flat_params(student(data)))  # it trained
    compiled.save(tmp_path / "student.zip")
    loaded = CRR.load(tmp_path / "student.zip")
    assert loaded.compile_losses is True and loaded._forward.compiled is None  # compiled again when it trains
    assert th.equal(flat_params(loaded), flat_params(compiled))


def test_auto_compiles_only_a_long_run_where_it_can(data, monkeypatch):
    model = student(data)
    assert model.compile_losses == "auto"
    model._total_timesteps, model.num_timesteps = compiling.AUTO_MIN_UPDATES - 1, 0
    monkeypatch.setattr(crr_module, "can_compile", lambda device: True)
    assert not model._compiles_now()  # too short to pay for the compilation
    model._total_timesteps = compiling.AUTO_MIN_UPDATES
    assert model._compiles_now()
    monkeypatch.setattr(crr_module, "can_compile", lambda device: False)
    assert not model._compiles_now()  # no compiler here
    model.learn_offline(3, log_interval=0)  # a short run stays eager
    assert model._forward.compiled is None
    per_source = student(data, compile_losses=True)
    per_source.actor_per_source = True  # (as if built with one actor per source) stays eager
    assert not per_source._compiles_now()
    with pytest.raises(ValueError, match="compile_losses"):
        student(data, compile_losses="yes")


def test_failed_compilation_warns_and_trains_eagerly(data, monkeypatch):
    def broken(function, **kwargs):
        def call(*args):
            raise RuntimeError("no compiler")

        return call

    monkeypatch.setattr(compiling.th, "compile", broken)
    model = student(data, compile_losses=True)
    with pytest.warns(UserWarning, match="torch.compile of CRR's forward pass failed .*no compiler.*eagerly"):
        model.learn_offline(6, log_interval=0)
    assert model._forward.failed and not model._compiles_now()
    eager = student(data, compile_losses=False).learn_offline(6, log_interval=0)
    # the first update took one joint backward, the others the eager steps: the same arithmetic
    th.testing.assert_close(flat_params(model), flat_params(eager), rtol=1e-6, atol=1e-7)


@pytest.mark.skipif(not compiling.can_compile(th.device("cpu")), reason="inductor needs a C++ compiler")
def test_compiled_training_keeps_the_bf16_scoring_passes(data, monkeypatch):
    """With a bf16 copy, the scoring passes run on the engine, eagerly, inside the compiled update (a graph break)."""
    calls = []
    eager_twin = scoring.eager_network_outputs

    @th.compiler.disable
    def counting(*args):
        calls.append(th.compiler.is_compiling())
        return eager_twin(*args)

    monkeypatch.setattr(scoring, "eager_network_outputs", counting)
    monkeypatch.setattr(distributional, "eager_network_outputs", counting)
    eager = student(data, compile_losses=False, scoring_dtype="bfloat16").learn_offline(6, log_interval=0)
    eager_calls = len(calls)
    compiled = student(data, compile_losses=True, scoring_dtype="bfloat16").learn_offline(6, log_interval=0)
    assert compiled._forward.compiled is not None and not compiled._forward.failed
    assert eager_calls == 12 and len(calls) == 24 and not any(calls)  # target and baseline, each update, eagerly
    difference = (flat_params(compiled) - flat_params(eager)).abs().max()
    assert difference <= 1e-4, float(difference)


def mpo(compile_losses, **kwargs) -> MPO:
    return MPO(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=dict(net_arch=[32, 32]),
        batch_size=32,
        learning_starts=40,
        target_update_interval=5,
        compile_losses=compile_losses,
        seed=0,
        **kwargs,
    )


def mpo_params(model: MPO) -> th.Tensor:
    return th.cat([p.detach().flatten() for p in model.policy.parameters()] + [model.log_temperature.detach()])


@pytest.mark.skipif(not compiling.can_compile(th.device("cpu")), reason="inductor needs a C++ compiler")
def test_mpo_compiled_training_matches_eager(tmp_path):
    eager = mpo(False).learn(60)
    compiled = mpo(True).learn(60)  # 20 updates, 4 target updates
    assert compiled._forward.compiled is not None and not compiled._forward.failed
    difference = (mpo_params(compiled) - mpo_params(eager)).abs().max()
    assert difference <= 1e-4, float(difference)
    assert compiled.logger.name_to_value.keys() == eager.logger.name_to_value.keys()
    compiled.save(tmp_path / "mpo.zip")
    assert th.equal(mpo_params(MPO.load(tmp_path / "mpo.zip")), mpo_params(compiled))


def test_mpo_auto_compiles_only_a_long_run(monkeypatch):
    model = mpo("auto")
    model._total_timesteps, model.num_timesteps = compiling.AUTO_MIN_UPDATES - 1, 0
    monkeypatch.setattr(mpo_module, "can_compile", lambda device: True)
    assert not model._compiles_now()
    model._total_timesteps = compiling.AUTO_MIN_UPDATES
    assert model._compiles_now()
    with pytest.raises(ValueError, match="compile_losses"):
        mpo("always")
