"""``train_dtype``: the hidden-to-hidden products of the gradient passes in bfloat16 (:class:`HiddenLinear`), the
networks built as before, the setting resolved, applied and kept through save and load, and training that learns."""

import pytest
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3.common.torch_layers import create_mlp
from testkit import benchmark_module, flat_params, pendulum_data
from torch import nn

from sb3_lifelong import CRR, MPO
from sb3_lifelong.common.policies import mlp_layers
from sb3_lifelong.numerics import compiling, hardware
from sb3_lifelong.numerics.fast_ops import HiddenLinear

KWARGS = dict(device="cpu", batch_size=64, policy_kwargs=dict(net_arch=[64, 64], layer_norm=True), seed=0)


def hidden_layers(model) -> list[HiddenLinear]:
    return [module for module in model.policy.modules() if isinstance(module, HiddenLinear)]


def student(data: dict, **kwargs) -> CRR:
    return CRR.from_offline_data(data, env=None, action_space=spaces.Box(-2, 2, (1,)), **{**KWARGS, **kwargs})


def test_hidden_linear_rounds_only_the_gradient_passes():
    th.manual_seed(0)
    layer = HiddenLinear.of(nn.Linear(64, 64))
    x = th.randn(32, 64, requires_grad=True)
    exact = F.linear(x, layer.weight, layer.bias)
    assert th.equal(layer(x), exact)  # no compute_dtype: the layer's own product
    layer.compute_dtype = th.bfloat16
    with th.no_grad():
        assert th.equal(layer(x), exact)  # a pass without gradients stays float32
    out = layer(x)
    assert out.dtype == th.float32 and not th.equal(out, exact)  # rounded through bf16
    # bf16 keeps 8 bits: the products are within a few of its rounding steps of float32's, relative to their scale
    assert float((out - exact).detach().abs().max()) <= 3e-2 * float(exact.detach().abs().max())
    grads = th.autograd.grad((out * out).sum(), [x, layer.weight, layer.bias])
    exact_grads = th.autograd.grad((exact * exact).sum(), [x, layer.weight, layer.bias])
    for grad, reference in zip(grads, exact_grads):
        assert grad.dtype == th.float32  # the parameters and their gradients stay float32
        assert float((grad - reference).abs().max()) <= 3e-2 * float(reference.abs().max())


def test_mlp_layers_are_built_as_before_with_the_hidden_products_marked():
    for layer_norm in (False, True):
        th.manual_seed(0)
        layers = mlp_layers(5, 3, [16, 16, 16], nn.ReLU, layer_norm)
        kinds = [type(layer) for layer in layers if isinstance(layer, nn.Linear)]
        assert kinds == [nn.Linear, HiddenLinear, HiddenLinear, nn.Linear]  # first and output layers stay plain
        if not layer_norm:  # SB3's create_mlp, initialised alike (the same random draws, the same values)
            th.manual_seed(0)
            reference = create_mlp(5, 3, [16, 16, 16], nn.ReLU)
            assert all(
                th.equal(a, b) for a, b in zip(nn.Sequential(*layers).parameters(), nn.Sequential(*reference).parameters())
            )
    latent = mlp_layers(5, -1, [16, 16], nn.ReLU)  # an actor's torso: its last Linear feeds the heads, it is hidden
    assert [type(layer) for layer in latent if isinstance(layer, nn.Linear)] == [nn.Linear, HiddenLinear]
    plain = nn.Linear(4, 4)
    assert HiddenLinear.of(plain).weight is plain.weight  # the same tensors, nothing initialised again


def test_train_dtype_is_resolved_applied_and_kept_through_save_and_load(tmp_path, monkeypatch):
    data = pendulum_data(300)
    model = student(data, compute=dict(train_dtype="bfloat16"))
    assert len(hidden_layers(model)) == 4  # actor, critic and their targets: one hidden product each
    assert all(layer.compute_dtype == th.bfloat16 for layer in hidden_layers(model))
    model.learn_offline(3, log_interval=0)
    model.save(tmp_path / "student.zip")
    loaded = CRR.load(tmp_path / "student.zip", device="cpu")
    assert loaded.compute.train_dtype == "bfloat16"
    assert all(layer.compute_dtype == th.bfloat16 for layer in hidden_layers(loaded))
    assert th.equal(flat_params(loaded), flat_params(model))
    assert all(layer.compute_dtype is None for layer in hidden_layers(student(data)))  # the default: float32
    for native, expected in ((True, th.bfloat16), (False, None)):
        monkeypatch.setattr(hardware, "cpu_has_fast_bf16", lambda native=native: native)
        assert all(layer.compute_dtype == expected for layer in hidden_layers(student(data, compute=dict(train_dtype="auto"))))
    mpo = MPO(
        "MlpPolicy", "Pendulum-v1", compute=dict(train_dtype="bfloat16"), device="cpu", policy_kwargs=dict(net_arch=[32, 32])
    )
    assert len(hidden_layers(mpo)) == 4 and all(layer.compute_dtype == th.bfloat16 for layer in hidden_layers(mpo))
    with pytest.raises(ValueError, match="train_dtype='bf16'"):
        student(data, compute=dict(train_dtype="bf16"))
    with pytest.raises(ValueError, match="train_dtype must be one of"):
        hardware.resolve_train_dtype("half", th.device("cpu"))


def test_a_bf16_student_learns_as_the_float32_one():
    """The critic's cross-entropy falls alike in both precisions (same data, seed and batches)."""
    data = pendulum_data(600)
    losses = {}
    for train_dtype in ("float32", "bfloat16"):
        model = student(data, compute=dict(train_dtype=train_dtype))
        model.learn_offline(20, log_interval=0)
        before = model.logger.name_to_value["train/critic_loss"]
        model.learn_offline(400, log_interval=0, reset_num_timesteps=False)
        model.learn_offline(20, log_interval=0, reset_num_timesteps=False)
        losses[train_dtype] = (before, model.logger.name_to_value["train/critic_loss"])
    for before, after in losses.values():
        assert after < 0.7 * before, losses
    assert abs(losses["bfloat16"][1] - losses["float32"][1]) <= 0.1 * losses["float32"][1], losses


@pytest.mark.skipif(not compiling.can_compile(th.device("cpu")), reason="inductor needs a C++ compiler")
def test_a_compiled_bf16_update_passes_its_check():
    model = student(pendulum_data(300), compute=dict(train_dtype="bfloat16", compile_losses=True)).learn_offline(
        4, log_interval=0
    )
    forward = model._forward
    assert forward.compiled is not None and forward.checked and not forward.failed, forward.failure


def test_simulated_bf16_gives_the_bf16_products_numbers():
    """Rounding around float32 products gives the bf16 kernel's results, forward and backward, up to how the sums are
    formed (one bf16 step, plus 2^-12 of a near-cancelling sum's terms; in few elements); float32 is far from them."""
    check = benchmark_module("bf16_kernel_vs_simulation")
    real, simulated, exact = (check.one_layer(compute) for compute in ("bfloat16", "simulated", "float32"))
    terms = check.sums_of_terms(real[0])
    for name, kernel, simulation, float32, term in zip(check.NAMES, real, simulated, exact, terms):
        assert float(check.bounds_apart(simulation, kernel, term).max()) <= 1.0 + 1e-6, name
        assert float((simulation != kernel).float().mean()) <= 0.02, name  # almost all bit for bit
        assert float(check.bounds_apart(float32, kernel, term).max()) > 1.0, name  # float32 is not what bf16 gives
    plain, x = check.weights_and_inputs()
    layer = HiddenLinear.of(plain)
    layer.compute_dtype, layer.simulated = th.bfloat16, True
    with th.no_grad():  # and a pass without gradients stays float32, as with bf16
        assert th.equal(layer(x), F.linear(x, layer.weight, layer.bias))


def test_simulated_bf16_trains_as_bf16_does_eagerly(tmp_path):
    data = pendulum_data(300)
    models = {}
    for name in ("float32", "bfloat16", "simulated_bfloat16"):  # each built then trained: the same random draws
        models[name] = student(data, compute=dict(train_dtype=name)).learn_offline(30, log_interval=0)
    assert all(layer.simulated and layer.compute_dtype == th.bfloat16 for layer in hidden_layers(models["simulated_bfloat16"]))
    assert not any(layer.simulated for layer in hidden_layers(models["bfloat16"]))
    params = {name: flat_params(model) for name, model in models.items()}
    # the simulation follows bf16 training far closer than float32 does (measured on an AVX2 CPU: 3e-6 against 1.5e-3
    # after 30 updates, the first one bit for bit; later, Adam's normalisation lets sum-order differences grow, and a
    # bf16 kernel with another summation order, e.g. AMX's, may differ in more elements: hence the margin)
    apart = float((params["simulated_bfloat16"] - params["bfloat16"]).abs().max())
    assert apart <= 0.1 * float((params["float32"] - params["bfloat16"]).abs().max())
    model = models["simulated_bfloat16"]
    model.save(tmp_path / "student.zip")
    loaded = CRR.load(tmp_path / "student.zip", device="cpu")
    assert loaded.compute.train_dtype == "simulated_bfloat16" and all(layer.simulated for layer in hidden_layers(loaded))


class LinearDtypes(th.overrides.TorchFunctionMode):
    """Records the input dtype of every ``F.linear`` call: which product a pass ran."""

    def __init__(self) -> None:
        super().__init__()
        self.dtypes: list[th.dtype] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func is F.linear:
            self.dtypes.append(args[0].dtype)
        return func(*args, **(kwargs or {}))


def test_simulated_bf16_multiplies_in_float32():
    """The simulation's products are float32 ones (the bf16 kernel is not what gives its numbers), the real path's bf16."""
    th.manual_seed(0)
    layer = HiddenLinear.of(nn.Linear(16, 16))
    layer.compute_dtype = th.bfloat16
    x = th.randn(8, 16, requires_grad=True)
    for simulated, expected in ((True, th.float32), (False, th.bfloat16)):
        layer.simulated = simulated
        with LinearDtypes() as seen:
            layer(x)
        assert seen.dtypes == [expected]


@pytest.mark.parametrize("algorithm", ["CRR", "MPO"])
def test_simulated_bf16_is_always_eager(algorithm, monkeypatch):
    """ "auto" never compiles it, however long the run and with a compiler present; True is refused before any setup."""
    monkeypatch.setattr(compiling, "can_compile", lambda device: True)

    def build(**kwargs):
        if algorithm == "CRR":
            return student(pendulum_data(300), **kwargs)
        return MPO("MlpPolicy", "Pendulum-v1", device="cpu", policy_kwargs=dict(net_arch=[32, 32]), **kwargs)

    for train_dtype, compiles in (("simulated_bfloat16", False), ("bfloat16", True)):
        model = build(compute=dict(train_dtype=train_dtype, compile_losses="auto"))
        model._total_timesteps = 10 * compiling.AUTO_MIN_UPDATES
        assert model._compiles_now() is compiles, train_dtype
    built = []
    monkeypatch.setattr(type(build()), "_setup_model", lambda self: built.append(self))
    with pytest.raises(ValueError, match="runs eagerly"):
        build(compute=dict(train_dtype="simulated_bfloat16", compile_losses=True))
    assert built == []  # refused before any setup (no buffer made)
