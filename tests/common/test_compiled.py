"""The compiled forward passes of CRR and MPO (``compile_losses``): the same training as eager up to rounding, the
"auto" rule, the eager fallback when compiling fails, the bf16 scoring passes kept."""

import warnings

import pytest
import torch as th
from gymnasium import spaces
from testkit import flat_params, pendulum_data

from sb3_lifelong import CRR, MPO
from sb3_lifelong.crr import distributional
from sb3_lifelong.numerics import compiling, hardware, scoring

# on the CPU even where a GPU is present: these tests pin the CPU's arithmetic (bit-identical eager steps, inductor's
# C++ kernels); tests/test_cuda.py covers a GPU
KWARGS = dict(
    device="cpu",
    batch_size=32,
    policy_kwargs=dict(net_arch=[32, 32], layer_norm=True, distributional_critic=True, v_min=-100.0, v_max=10.0),
    target_update_interval=4,
)


@pytest.fixture(scope="module")
def data() -> dict:
    return pendulum_data(300)


def student(data: dict, **kwargs) -> CRR:
    return CRR.from_offline_data(data, env=None, action_space=spaces.Box(-2, 2, (1,)), seed=0, **{**KWARGS, **kwargs})


def ran_compiled(model, eager_params: th.Tensor, params=flat_params) -> None:
    """
    Assert that ``model`` trained with its compiled update, which passed its first call's check. Where this machine's
    compiler gets the update wrong, the check refuses it and the run is the eager one, bit for bit: that is asserted,
    then the test is skipped with the reason (the comparisons after this call need a compiled run).
    """
    forward = model._forward
    if forward.failed and "CompiledMismatch" in str(forward.failure):
        assert th.equal(params(model), eager_params)
        # the compiler has been seen wrong on an AMX Xeon with torch 2.11 only; elsewhere a refusal is a failure
        assert "amx_bf16" in hardware.cpu_matrix_flags(), forward.failure
        pytest.skip(f"refused here, and trained eagerly: {forward.failure}")
    assert forward.compiled is not None and not forward.failed and forward.checked


@pytest.mark.skipif(not compiling.can_compile(th.device("cpu")), reason="inductor needs a C++ compiler")
def test_compiled_training_matches_eager_and_saves(data, tmp_path):
    # a gradient clip that binds at every step, so that the joint backward's clipping is compared too
    eager = student(data, compute=dict(compile_losses=False), max_grad_norm=1e-3).learn_offline(12, log_interval=0)
    with warnings.catch_warnings(record=True):
        compiled = student(data, compute=dict(compile_losses=True), max_grad_norm=1e-3).learn_offline(12, log_interval=0)
    ran_compiled(compiled, flat_params(eager))
    assert eager._forward.compiled is None
    # the same batches and noise: the parameters differ by rounding only, after 12 updates and 3 target updates
    difference = (flat_params(compiled) - flat_params(eager)).abs().max()
    assert difference <= 1e-4, float(difference)
    assert not th.equal(flat_params(compiled), flat_params(student(data)))  # it trained
    compiled.save(tmp_path / "student.zip")
    loaded = CRR.load(tmp_path / "student.zip", device="cpu")
    assert loaded.compute.compile_losses is True and loaded._forward.compiled is None  # compiled again when it trains
    assert th.equal(flat_params(loaded), flat_params(compiled))


def test_auto_compiles_only_a_long_run_where_it_can(data, monkeypatch):
    model = student(data)
    assert model.compute.compile_losses == "auto"
    model._total_timesteps, model.num_timesteps = compiling.AUTO_MIN_UPDATES - 1, 0
    monkeypatch.setattr(compiling, "can_compile", lambda device: True)
    assert not model._compiles_now()  # too short to pay for the compilation
    model._total_timesteps = compiling.AUTO_MIN_UPDATES
    assert model._compiles_now()
    monkeypatch.setattr(compiling, "can_compile", lambda device: False)
    assert not model._compiles_now()  # no compiler here
    model.learn_offline(3, log_interval=0)  # a short run stays eager
    assert model._forward.compiled is None
    per_source = student(data, compute=dict(compile_losses=True))
    per_source.actor_per_source = True  # (as if built with one actor per source) stays eager
    assert not per_source._compiles_now()
    with pytest.raises(ValueError, match="compile_losses"):
        student(data, compute=dict(compile_losses="yes"))


def test_failed_compilation_warns_and_trains_eagerly(data, monkeypatch):
    def broken(function, **kwargs):
        def call(*args):
            raise RuntimeError("no compiler")

        return call

    monkeypatch.setattr(compiling.th, "compile", broken)
    model = student(data, compute=dict(compile_losses=True))
    with pytest.warns(UserWarning, match="torch.compile of CRR's forward pass failed .*no compiler.*eagerly"):
        model.learn_offline(6, log_interval=0)
    assert model._forward.failed and not model._compiles_now()
    eager = student(data, compute=dict(compile_losses=False)).learn_offline(6, log_interval=0)
    # the first update took one joint backward, the others the eager steps: the same arithmetic, bit for bit
    assert th.equal(flat_params(model), flat_params(eager))


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
    eager = student(data, compute=dict(compile_losses=False, scoring_dtype="bfloat16")).learn_offline(6, log_interval=0)
    eager_calls = len(calls)
    with warnings.catch_warnings(record=True):
        compiled = student(data, compute=dict(compile_losses=True, scoring_dtype="bfloat16")).learn_offline(6, log_interval=0)
    ran_compiled(compiled, flat_params(eager))
    # target and baseline, each update, on the engine; and in the first call's check, the eager and the compiled pass
    assert eager_calls == 12 and len(calls) == 24 + 4
    # the copies' LayerNorm and tanh: one compiled kernel in the compiled update, the eager way in the eager one
    for model, compiles in ((eager, False), (compiled, True)):
        for copy in (model._target_scoring_copy, model._online_scoring_copy):
            assert copy.compile_layer_norm == compiles and (copy._layer_norm_tanh.compiled is not None) == compiles
    difference = (flat_params(compiled) - flat_params(eager)).abs().max()
    assert difference <= 1e-4, float(difference)


def test_noise_is_drawn_as_the_eager_updates_always_drew_it(data, monkeypatch):
    """The order and shapes of an update's standard normal draws, which the eager training's reproducibility rests on."""
    shapes = []
    randn = th.randn

    def recording(*args, **kwargs):
        shapes.append(tuple(args[0]) if args and isinstance(args[0], (tuple, list, th.Size)) else args)
        return randn(*args, **kwargs)

    model = student(data, n_target_samples=2)
    model.learn_offline(1, log_interval=0)
    monkeypatch.setattr(th, "randn", recording)
    model.train(1, 32)
    assert shapes == [(2, 32, 1), (4, 32, 1)]  # the TD target's samples, then the advantage baseline's
    for on_next_obs, rows in ((True, 32), (False, 64)):
        shapes.clear()
        online = mpo(False, policy_on_next_obs=on_next_obs)
        monkeypatch.setattr(th, "randn", randn)
        online.learn(45)
        monkeypatch.setattr(th, "randn", recording)
        online.train(1, 32)
        assert shapes == [(20, rows, 1)]  # the target policy's samples, over next observations (and observations)


def mpo(compile_losses, compute=None, **kwargs) -> MPO:
    return MPO(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=dict(net_arch=[32, 32]),
        batch_size=32,
        learning_starts=40,
        target_update_interval=5,
        compute={"compile_losses": compile_losses, **(compute or {})},
        device="cpu",
        seed=0,
        **kwargs,
    )


def mpo_params(model: MPO) -> th.Tensor:
    return th.cat([p.detach().flatten() for p in model.policy.parameters()] + [model.log_temperature.detach()])


@pytest.mark.skipif(not compiling.can_compile(th.device("cpu")), reason="inductor needs a C++ compiler")
@pytest.mark.parametrize(
    "kwargs",
    [{}, dict(policy_on_next_obs=False, policy_loss=dict(action_penalty=True), max_grad_norm=1e-3)],
    ids=["defaults", "obs_penalty_clipped"],
)
def test_mpo_compiled_training_matches_eager(tmp_path, kwargs):
    eager = mpo(False, **kwargs).learn(60)
    with warnings.catch_warnings(record=True):
        compiled = mpo(True, **kwargs).learn(60)  # 20 updates, 4 target updates
    ran_compiled(compiled, mpo_params(eager), mpo_params)
    difference = (mpo_params(compiled) - mpo_params(eager)).abs().max()
    assert difference <= 1e-4, float(difference)
    assert compiled.logger.name_to_value.keys() == eager.logger.name_to_value.keys()
    compiled.save(tmp_path / "mpo.zip")
    assert th.equal(mpo_params(MPO.load(tmp_path / "mpo.zip", device="cpu")), mpo_params(compiled))


def test_mpo_auto_compiles_only_a_long_run(monkeypatch):
    model = mpo("auto")
    model._total_timesteps, model.num_timesteps = compiling.AUTO_MIN_UPDATES - 1, 0
    monkeypatch.setattr(compiling, "can_compile", lambda device: True)
    assert not model._compiles_now()
    model._total_timesteps = compiling.AUTO_MIN_UPDATES
    assert model._compiles_now()
    with pytest.raises(ValueError, match="compile_losses"):
        mpo("always")


def test_clipping_counts_the_parameters_each_optimizer_steps(data):
    """A features extractor shared with the actor is the actor's to step: the critic's clip leaves it out."""
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    from sb3_lifelong.common.updates import optimized_parameters

    class Learnt(BaseFeaturesExtractor):
        def __init__(self, observation_space):
            super().__init__(observation_space, features_dim=8)
            self.linear = th.nn.Linear(observation_space.shape[0], 8)

        def forward(self, observations):
            return self.linear(observations)

    model = student(data, policy_kwargs=dict(net_arch=[16], features_extractor_class=Learnt, share_features_extractor=True))
    shared = {id(p) for p in model.actor.features_extractor.parameters()}
    assert shared and shared <= {id(p) for p in model.critic.parameters()}
    assert not shared & {id(p) for p in optimized_parameters(model.critic)}
    assert shared <= {id(p) for p in optimized_parameters(model.actor)}


class _DoubledGradient(th.autograd.Function):
    """The identity forward, twice the gradient backward: a compiled function whose backward is wrong."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, grad):
        return 2 * grad


def wrongly_compiled(kind: str):
    """A stand-in for ``torch.compile`` whose result is wrong: in its gradient ("backward") or its output ("forward")."""

    def compile_(function, **kwargs):
        def call(*args):
            outputs = function(*args)
            if kind == "backward":
                return outputs[0], _DoubledGradient.apply(outputs[1])
            return outputs[0], outputs[1] * 1.01

        return call

    return compile_


@pytest.mark.parametrize("kind", ["backward", "forward"])
def test_a_compiled_function_that_disagrees_with_eager_is_refused(kind, monkeypatch):
    weight, bias = th.nn.Parameter(th.tensor([[1.0, -2.0], [0.5, 3.0]])), th.nn.Parameter(th.tensor([0.1, -0.2]))

    def function(x):
        return (x * 2).sum(), x @ weight + bias

    monkeypatch.setattr(compiling.th, "compile", wrongly_compiled(kind))
    lazy = compiling.LazyCompiled(function, "a layer", lambda: [("weight", weight), ("bias", bias)])
    x = th.tensor([[1.0, 2.0], [3.0, -1.0]])
    state = th.random.get_rng_state()
    with pytest.warns(UserWarning, match="torch.compile of a layer failed .*CompiledMismatch.*eagerly") as caught:
        total, out = lazy(True, x)
    assert th.equal(out, x @ weight + bias) and float(total) == float((x * 2).sum())  # the eager result
    assert lazy.failed and lazy.compiled is None and not lazy.wanted(True, 10**6, th.device("cpu"))
    message = str(caught[0].message)
    assert ("weight" in message and "bias" in message) if kind == "backward" else "output 1" in message
    assert th.equal(th.random.get_rng_state(), state)  # the check's projection is drawn from its own generator
    monkeypatch.setattr(compiling.th, "compile", lambda function, **kwargs: function)  # a right "compilation"
    right = compiling.LazyCompiled(function, "a layer", lambda: [("weight", weight), ("bias", bias)])
    right(True, x)
    assert right.checked and not right.failed and right.compiled is not None


def test_the_check_compares_each_parameter_on_its_own_scale_and_ignores_rounding_noise(monkeypatch):
    """A small parameter's wrong gradient beside a large one's is caught; a logged statistic of 1e-9 is noise."""
    big, small = th.nn.Parameter(th.full((3,), 1000.0)), th.nn.Parameter(th.full((3,), 0.01))
    x = th.tensor([1.0, -2.0, 0.5])

    def function(x):
        return (big * x).sum(), (small * x).sum(), th.zeros(())

    def compile_(function, **kwargs):
        def call(*args):
            total, part, statistic = function(*args)
            return total, _DoubledGradient.apply(part) if wrong_gradient else part, statistic + 1e-9

        return call

    monkeypatch.setattr(compiling.th, "compile", compile_)
    parameters = lambda: [("big", big), ("small", small)]  # noqa: E731
    wrong_gradient = True
    lazy = compiling.LazyCompiled(function, "two parts", parameters)
    with pytest.warns(UserWarning, match=r"1 of 2 parameters: small \(by"):
        lazy(True, x)  # the small gradient is 1e-5 of the large one, and twice what it should be
    wrong_gradient = False
    right = compiling.LazyCompiled(function, "two parts", parameters)
    right(True, x)  # the statistic differs by 1e-9 from an exact 0: rounding noise, not a wrong compilation
    assert right.checked and not right.failed


def test_the_check_tolerates_bf16_rounding_only_where_the_gradient_passes_are_bf16(monkeypatch) -> None:
    """A compiled graph whose bf16 roundings fall elsewhere (a gradient 0.5 % off) passes with bf16 gradient passes and is
    refused in float32; a wrong backward (10 % off, or twice the gradient) is refused with either."""
    weight = th.nn.Parameter(th.tensor([[1.0, -2.0], [0.5, 3.0]]))
    x = th.tensor([[1.0, 2.0], [3.0, -1.0]])

    def function(x):
        return (x @ weight,)

    def compile_with(factor: float):
        class Scaled(th.autograd.Function):
            @staticmethod
            def forward(ctx, y):
                return y.clone()

            @staticmethod
            def backward(ctx, grad):
                return factor * grad

        return lambda function, **kwargs: lambda *args: (Scaled.apply(function(*args)[0]),)

    tolerances = {"float32": compiling.CHECK_TOLERANCE, "bfloat16": compiling.LOW_PRECISION_CHECK_TOLERANCE}
    for factor, passes in ((1.005, {"bfloat16"}), (1.1, set()), (2.0, set())):
        monkeypatch.setattr(compiling.th, "compile", compile_with(factor))
        for dtype, tolerance in tolerances.items():
            lazy = compiling.LazyCompiled(function, "a layer", lambda: [("weight", weight)], tolerance)
            if dtype in passes:
                lazy(True, x)
                assert lazy.checked and not lazy.failed
            else:
                with pytest.warns(UserWarning, match="CompiledMismatch"):
                    lazy(True, x)
                assert lazy.failed


@pytest.mark.parametrize("algorithm", ["MPO", "CRR"])
def test_the_algorithms_widen_the_check_for_bf16_gradient_passes(algorithm, data):
    for train_dtype, tolerance in (
        ("float32", compiling.CHECK_TOLERANCE),
        ("bfloat16", compiling.LOW_PRECISION_CHECK_TOLERANCE),
    ):
        model = (
            mpo(False, compute=dict(train_dtype=train_dtype))
            if algorithm == "MPO"
            else student(data, compute=dict(train_dtype=train_dtype))
        )
        assert model._forward.tolerance == tolerance
