"""The scoring engine: the low-precision (bfloat16) pass (accuracy against float32, synchronisation, the "auto" rule,
resume), the categorical critic in it, and the fast elementwise operations."""

import gymnasium as gym
import pytest
import torch as th
from stable_baselines3.common.torch_layers import FlattenExtractor

from sb3_lifelong import CRR, MPO
from sb3_lifelong.common.policies import QCritic, mlp_layers, sample_gaussian
from sb3_lifelong.mpo.losses import dual_value, temperature_loss_and_weights
from sb3_lifelong.numerics import compiling, fast_ops, scoring
from sb3_lifelong.numerics.hardware import fused_products_supported
from sb3_lifelong.numerics.scoring import LowPrecisionCopy, resolve_scoring_dtype, score_actions

# Stated tolerances of the bf16 pass, on a critic trained on Pendulum (256x256, 20 samples per state; measured:
# mean error 6 % of the spread, max error 0.3 % of |Q|, max weight change 0.0034):
#: mean Q error, as a fraction of the spread (std) of Q over a state's sampled actions, averaged over states
Q_MEAN_ERROR_OF_SPREAD = 0.1
#: largest Q error, as a fraction of the mean |Q|
Q_MAX_ERROR_OF_SCALE = 0.01
#: largest change of an E-step weight at the model's temperature (the weights of a state sum to 1)
WEIGHT_ERROR = 0.01


@pytest.fixture(scope="module", params=[False, True], ids=["plain", "layer_norm"])
def trained_mpo(request):
    model = MPO(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=dict(net_arch=[256, 256], layer_norm=request.param),
        learning_starts=200,
        compute=dict(scoring_dtype="float32"),
        seed=0,
        device="cpu",  # the CPU engine's paths (fused products, compiled kernels), also where a GPU is present
    )
    model.learn(700)
    return model


BF16_FUSED = pytest.mark.skipif(
    not fused_products_supported(th.bfloat16), reason="oneDNN fuses bf16 products only with AVX-512 or AMX"
)


COMPILER = pytest.mark.skipif(not compiling.can_compile(th.device("cpu")), reason="inductor needs a C++ compiler")


@pytest.mark.parametrize(
    "fused, compile_layer_norm",
    [(False, False), pytest.param(False, True, marks=COMPILER), pytest.param(True, False, marks=BF16_FUSED)],
    ids=["unfused", "compiled_layer_norm", "fused"],
)
def test_bf16_scores_within_stated_tolerance(trained_mpo, fused, compile_layer_norm):
    model = trained_mpo
    th.manual_seed(0)
    batch = model.replay_buffer.sample(256)
    with th.no_grad():
        mean, std = model.actor_target.distribution_params(batch.next_observations)
        actions = sample_gaussian(mean, std, 20)
        q32 = score_actions(model.critic_target, batch.next_observations, actions)
        copy = LowPrecisionCopy(model.critic_target, th.bfloat16, fused=fused)
        copy.compile_layer_norm = compile_layer_norm
        q16 = score_actions(model.critic_target, batch.next_observations, actions, copy)
    assert copy.fused == fused and bool(copy._packed) == fused  # the fused products ran where asked
    kernel_ran = compile_layer_norm and model.policy_kwargs["layer_norm"]
    assert (copy._layer_norm_tanh.compiled is not None) == kernel_ran and not copy._layer_norm_tanh.failed
    assert q16.dtype == th.float32 and q16.shape == q32.shape == (20, 256)
    spread, scale, error = q32.std(dim=0).mean(), q32.abs().mean(), (q16 - q32).abs()
    assert spread > 0 and error.max() > 0  # the two passes differ: the bf16 pass ran
    assert error.mean() <= Q_MEAN_ERROR_OF_SPREAD * spread, (float(error.mean()), float(spread))
    assert error.max() <= Q_MAX_ERROR_OF_SCALE * scale, (float(error.max()), float(scale))
    temperature = dual_value(model.log_temperature)
    _, w32 = temperature_loss_and_weights(q32, temperature, model.policy_loss.epsilon)
    _, w16 = temperature_loss_and_weights(q16, temperature, model.policy_loss.epsilon)
    assert (w16 - w32).abs().max() <= WEIGHT_ERROR


def test_copy_follows_the_critic_only_on_sync(trained_mpo):
    critic = trained_mpo.critic_target
    copy = LowPrecisionCopy(critic, th.bfloat16)
    first = critic.q_networks[0][0]
    weight_t, _ = copy.weights[id(first)]
    assert id(critic.q_networks[0][-1]) not in copy.weights  # the output layer stays float32
    th.testing.assert_close(weight_t, first.weight.detach().t().to(th.bfloat16), rtol=0, atol=0)
    with th.no_grad():
        first.weight.add_(1.0)
    try:
        assert not th.equal(weight_t, first.weight.detach().t().to(th.bfloat16))
        copy.sync()
        th.testing.assert_close(weight_t, first.weight.detach().t().to(th.bfloat16), rtol=0, atol=0)
    finally:
        with th.no_grad():
            first.weight.sub_(1.0)


def _copy_matches(copy: LowPrecisionCopy) -> bool:
    for q_net in copy.critic.q_networks:
        for module in q_net:
            if id(module) in copy.weights:
                weight_t, bias = copy.weights[id(module)]
                if not th.equal(weight_t, module.weight.detach().t().to(copy.dtype)):
                    return False
                if not th.equal(bias, module.bias.detach().to(copy.dtype)):
                    return False
    return True


def test_mpo_keeps_its_copy_in_sync_through_target_updates_and_loads(tmp_path):
    model = MPO(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=dict(net_arch=[32, 32]),
        batch_size=32,
        learning_starts=50,
        target_update_interval=10,
        compute=dict(scoring_dtype="bfloat16"),
        seed=0,
    )
    assert model._target_scoring_copy is not None and _copy_matches(model._target_scoring_copy)
    model.learn(125)  # 75 updates: 7 target updates, the last 5 updates before the next one
    assert _copy_matches(model._target_scoring_copy)
    model.save(tmp_path / "model.zip")
    loaded = MPO.load(tmp_path / "model.zip")
    assert loaded.compute.scoring_dtype == "bfloat16"
    assert _copy_matches(loaded._target_scoring_copy)
    th.testing.assert_close(
        loaded._target_scoring_copy.weights[id(loaded.critic_target.q_networks[0][0])][0],
        model._target_scoring_copy.weights[id(model.critic_target.q_networks[0][0])][0],
        rtol=0,
        atol=0,
    )


def test_crr_scores_in_bf16_and_trains():
    model = CRR("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[32, 32]), batch_size=32, learning_starts=50)
    assert model._online_scoring_copy is None  # auto: too narrow for bf16 to pay
    model = CRR(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=dict(net_arch=[32, 32]),
        batch_size=32,
        learning_starts=50,
        compute=dict(scoring_dtype="bfloat16"),
        target_update_interval=5,
    )
    model.learn(100)
    assert _copy_matches(model._target_scoring_copy)
    assert th.isfinite(th.cat([p.flatten() for p in model.policy.parameters()])).all()


def test_auto_rule(monkeypatch):
    narrow = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[64, 64]), compute=dict(scoring_dtype="float32"))
    wide = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[256, 256]), compute=dict(scoring_dtype="float32"))
    cpu = th.device("cpu")
    monkeypatch.setattr(scoring, "cpu_has_fast_bf16", lambda: True)
    assert resolve_scoring_dtype("auto", wide.critic, cpu) == th.bfloat16
    assert resolve_scoring_dtype("auto", narrow.critic, cpu) == th.float32
    assert resolve_scoring_dtype("float32", wide.critic, cpu) == th.float32
    assert resolve_scoring_dtype("bfloat16", narrow.critic, cpu) == th.bfloat16
    monkeypatch.setattr(scoring, "cpu_has_fast_bf16", lambda: False)
    assert resolve_scoring_dtype("auto", wide.critic, cpu) == th.float32
    with pytest.raises(ValueError, match="scoring_dtype"):
        resolve_scoring_dtype("float16", wide.critic, cpu)
    with pytest.raises(ValueError, match="scoring_dtype"):
        MPO("MlpPolicy", "Pendulum-v1", compute=dict(scoring_dtype="half"))


@pytest.mark.parametrize("dtype", [th.bfloat16, th.float32])
def test_relu_in_place_matches_relu(dtype):
    values = th.tensor([-3.5, -0.0, 0.0, 1e-30, -1e-30, 2.25, float("inf"), float("-inf"), 65280.0, -65280.0])
    x = th.cat([values, th.randn(4096)]).to(dtype).reshape(-1, 2)
    expected = th.relu(x)
    out = fast_ops.relu_in_place(x)
    assert out is x and out.dtype == dtype
    assert th.equal(out, expected) and not (out < 0).any()
    assert (out == 0).sum() == (expected == 0).sum()


@pytest.mark.parametrize("layer_norm", [False, True], ids=["plain", "layer_norm"])
def test_split_first_layer_for_wide_observations(monkeypatch, layer_norm):
    """OP3-sized inputs (68 + 20): the bf16 pass computes the state's part of the first layer once per state."""
    obs_space, act_space = gym.spaces.Box(-1, 1, (68,)), gym.spaces.Box(-1, 1, (20,))
    th.manual_seed(0)
    # with layer_norm, MPO's default torso: Linear -> LayerNorm -> tanh first
    critic = QCritic(obs_space, act_space, [256, 256], FlattenExtractor(obs_space), 68, n_critics=2, layer_norm=layer_norm)
    assert isinstance(critic.q_networks[0][1], th.nn.LayerNorm if layer_norm else th.nn.ReLU)
    copy = LowPrecisionCopy(critic)
    obs, actions = th.rand(64, 68) * 2 - 1, th.rand(20, 64, 20) * 2 - 1
    with th.no_grad():
        exact = score_actions(critic, obs, actions)
        split = score_actions(critic, obs, actions, copy)
        monkeypatch.setattr(scoring, "SPLIT_MIN_FEATURES", 10_000)  # the stacked bf16 product, for comparison
        stacked = score_actions(critic, obs, actions, copy)
    spread = exact.std(dim=0).mean()
    assert not th.equal(split, stacked)  # the split path ran
    assert (split - exact).abs().mean() <= Q_MEAN_ERROR_OF_SPREAD * spread
    assert (split - exact).abs().mean() <= 2 * (stacked - exact).abs().mean()
    monkeypatch.undo()
    assert scoring._splits_first_layer(critic.q_networks[0], 68, 20, copy)
    assert not scoring._splits_first_layer(critic.q_networks[0], 11, 3, copy)  # Hopper-sized: one product is faster
    assert not scoring._splits_first_layer(critic.q_networks[0], 68, 20, None)  # float32: the exact stacked pass


def test_tanh_in_place_matches_tanh():
    x = th.linspace(-12.0, 12.0, 100_001)
    expected = th.tanh(x)
    assert fast_ops.tanh_in_place(x.clone()).sub(expected).abs().max() <= 2e-7
    small = th.tensor([1e-3, -1e-2, 0.0, 0.5])
    th.testing.assert_close(fast_ops.tanh_in_place(small.clone()), th.tanh(small), rtol=1e-3, atol=1e-7)
    double = x.double()  # other dtypes take torch's own tanh
    assert th.equal(fast_ops.tanh_in_place(double.clone()), th.tanh(double))


def test_layer_norm_torso_in_low_precision_matches_its_modules():
    """The fused LayerNorm -> tanh of a bf16 pass: the modules' own float32 result, rounded to bf16 once."""
    th.manual_seed(0)
    torso = th.nn.Sequential(*mlp_layers(23, 1, [256, 256], th.nn.ReLU, layer_norm=True))
    with th.no_grad():
        torso[1].weight.uniform_(0.5, 1.5)  # a LayerNorm with its own scale and shift
        torso[1].bias.uniform_(-0.5, 0.5)
    hidden = (th.randn(64, 256) * 3).to(th.bfloat16)  # the first Linear's output in a bf16 pass
    holder = th.nn.Module()
    fused = scoring._layer_norm_no_grad(holder, (0, 1), torso[1], hidden, then_tanh=True)
    expected = th.tanh(torso[1](hidden.float())).to(th.bfloat16)
    assert fused.dtype == th.bfloat16 and fused.shape == (64, 256)
    # at most one bf16 rounding step apart (both round the same float32 value up to ~1e-7)
    assert (fused.float() - expected.float()).abs().max() <= 2**-8
    plain = scoring._layer_norm_no_grad(holder, (0, 1), torso[1], hidden, then_tanh=False)
    assert th.equal(plain, torso[1](hidden.float()).to(th.bfloat16))


def test_layer_norm_tanh_kernel_matches_the_modules():
    """The LayerNorm-and-tanh kernel, eager and compiled: the modules' float32 result rounded once to bf16 (within a
    bf16 step), written into the reused buffer; a kernel that fails to compile warns once and the eager way goes on."""
    th.manual_seed(0)
    torso = th.nn.Sequential(*mlp_layers(23, 1, [256, 256], th.nn.ReLU, layer_norm=True))
    with th.no_grad():
        torso[1].weight.uniform_(0.5, 1.5)
        torso[1].bias.uniform_(-0.5, 0.5)
    hidden = (th.randn(64, 256) * 3).to(th.bfloat16)
    expected = th.tanh(torso[1](hidden.float())).detach()
    out = th.empty_like(hidden)
    with th.no_grad():
        eager = fast_ops.layer_norm_tanh_into(hidden, torso[1].weight, torso[1].bias, torso[1].eps, out)
    assert eager is out and out.dtype == th.bfloat16
    assert 0 < (out.float() - expected).abs().max() <= 2**-8
    if not compiling.can_compile(th.device("cpu")):
        return
    holder, kernel = th.nn.Module(), compiling.LazyCompiled(fast_ops.layer_norm_tanh_into, "kernel")
    with th.no_grad():
        result = scoring._layer_norm_no_grad(holder, (0, 1), torso[1], hidden, then_tanh=True, kernel=kernel)
        again = scoring._layer_norm_no_grad(holder, (0, 1), torso[1], hidden, then_tanh=True, kernel=kernel)
    assert kernel.compiled is not None and not kernel.failed and again is result
    assert result.dtype == th.bfloat16 and (result.float() - expected).abs().max() <= 2**-8


def test_a_layer_norm_kernel_that_fails_to_compile_leaves_the_eager_way(monkeypatch):
    critic = _wide_critic("layer_norm")
    copy = LowPrecisionCopy(critic, th.float32, fused=False)
    copy.compile_layer_norm = True

    def broken(function, **kwargs):
        def fails(*args):
            raise RuntimeError("no compiler")

        return fails

    monkeypatch.setattr(compiling.th, "compile", broken)
    obs, actions = th.rand(16, 11) * 2 - 1, th.rand(4, 16, 3) * 2 - 1
    with th.no_grad(), pytest.warns(UserWarning, match="LayerNorm and tanh failed"):
        q = score_actions(critic, obs, actions, copy)
    assert copy._layer_norm_tanh.failed and copy.layer_norm_kernel() is None
    with th.no_grad():
        th.testing.assert_close(q, score_actions(critic, obs, actions), rtol=1e-5, atol=1e-5)
        th.testing.assert_close(score_actions(critic, obs, actions, copy), score_actions(critic, obs, actions))


def test_machine_description_names_the_matrix_flags_and_the_bf16_kernel(monkeypatch):
    from sb3_lifelong.numerics import hardware

    flags = hardware.cpu_matrix_flags()
    assert set(flags) <= set(hardware.MATRIX_FLAGS)
    assert hardware.cpu_has_fast_bf16() == ("avx512_bf16" in flags or "amx_bf16" in flags)
    text = hardware.machine_description()
    assert "matrix flags:" in text and "oneDNN bf16 kernel:" in text and th.__version__ in text
    kernel = hardware.onednn_bf16_kernel()
    assert kernel and ("amx" not in kernel or "amx_bf16" in flags)  # an AMX kernel only where the CPU has AMX


def test_fast_tanh_matches_torch_values_and_gradients():
    x = th.linspace(-12.0, 12.0, 100_001, requires_grad=True)
    y = fast_ops.fast_tanh(x)
    assert (y - th.tanh(x)).abs().max() <= 2e-7
    y.sum().backward()
    fast_grad, x.grad = x.grad, None
    th.tanh(x).sum().backward()
    assert (fast_grad - x.grad).abs().max() <= 5e-7  # 1 - y^2 of outputs 2e-7 apart
    double = th.randn(100, dtype=th.float64, requires_grad=True)  # other dtypes take torch's own tanh
    assert th.equal(fast_ops.fast_tanh(double), th.tanh(double))
    assert th.autograd.gradcheck(fast_ops._TanhBySigmoid.apply, (double,))  # the backward is the derivative
    module = fast_ops.Tanh()
    assert isinstance(module, th.nn.Tanh) and th.equal(module(x.detach()), fast_ops.fast_tanh(x.detach()))
    torso = mlp_layers(8, 1, [16, 16], th.nn.ReLU, layer_norm=True)
    assert isinstance(torso[2], fast_ops.Tanh)


def _categorical_critic(layer_norm: bool, n_critics: int = 2, width: int = 64):
    from sb3_lifelong.crr.distributional import CategoricalCritic

    obs_space, act_space = gym.spaces.Box(-1, 1, (11,)), gym.spaces.Box(-1, 1, (3,))
    th.manual_seed(0)
    return CategoricalCritic(
        obs_space,
        act_space,
        [width, width],
        FlattenExtractor(obs_space),
        11,
        n_critics=n_critics,
        n_atoms=51,
        v_min=-10.0,
        v_max=10.0,
        layer_norm=layer_norm,
    )


@pytest.mark.parametrize("layer_norm", [False, True], ids=["plain", "layer_norm"])
def test_categorical_critic_runs_the_engine_bit_for_bit(layer_norm):
    """A critic with ``q_values_of`` is scored by the engine: in float32 exactly what calling it gives."""
    critic = _categorical_critic(layer_norm)
    assert scoring.runs_no_grad_pass(critic)
    obs, actions = th.rand(32, 11) * 2 - 1, th.rand(4, 32, 3) * 2 - 1
    called = scoring.q_min(critic(scoring.tile_obs(obs, 4), actions.reshape(-1, 3))).reshape(4, 32).detach()
    with th.no_grad():
        scored = score_actions(critic, obs, actions)
        assert {key[2] for key in critic.__dict__["_no_grad_buffers"]} == {4 * 32}  # the engine ran, on its buffers
        rewards, discounts = th.randn(32, 1), th.full((32, 1), 0.99)
        target = critic.td_target(obs, actions[:2], rewards, discounts)
        assert 2 * 32 in {key[2] for key in critic.__dict__["_no_grad_buffers"]}  # the target's pass too
    assert th.equal(scored, called)
    with th.enable_grad():  # the logits path, by calling the Q-networks
        target_called = critic.td_target(obs, actions[:2], rewards, discounts).detach()
    assert th.equal(target, target_called)
    th.testing.assert_close(target.sum(dim=1), th.ones(32))


def test_categorical_critic_in_bf16_within_stated_tolerance():
    critic = _categorical_critic(layer_norm=True, width=256)
    with th.no_grad():  # logits that spread over the support, as a trained critic's do
        critic.q_networks[0][-1].weight.mul_(20.0)
        critic.q_networks[1][-1].weight.mul_(20.0)
    copy = LowPrecisionCopy(critic, th.bfloat16)
    assert id(critic.q_networks[0][-1]) not in copy.weights  # the logits stay float32
    obs, actions = th.rand(256, 11) * 2 - 1, th.rand(4, 256, 3) * 2 - 1
    rewards, discounts = th.randn(256, 1), th.full((256, 1), 0.99)
    with th.no_grad():
        q32, q16 = score_actions(critic, obs, actions), score_actions(critic, obs, actions, copy)
        p32 = critic.td_target(obs, actions[:1], rewards, discounts)
        p16 = critic.td_target(obs, actions[:1], rewards, discounts, copy)
    spread, error = q32.std(dim=0).mean(), (q16 - q32).abs()
    assert spread > 0 and error.max() > 0  # the bf16 pass ran
    assert error.mean() <= Q_MEAN_ERROR_OF_SPREAD * spread, (float(error.mean()), float(spread))
    # a categorical Q is a mean over the support, and near 0 here: its error is stated against the support's width
    # (measured: 0.5 %); so is the target distributions' mean
    width = critic.v_max - critic.v_min
    assert error.max() <= 0.01 * width, float(error.max())
    assert ((p16 - p32) * critic.support).sum(dim=1).abs().max() <= 0.01 * width
    # their total variation is small (measured: 0.6 % at the median) except where the two Q-networks' values are so
    # close that bf16 picks the other network's distribution (the target's mean then stays within the bound above)
    assert (p16 - p32).abs().sum(dim=1).median() <= 0.02


def test_crr_categorical_student_scores_in_bf16_when_asked_or_native(monkeypatch):
    kwargs = dict(policy_kwargs=dict(net_arch=[128, 128], distributional_critic=True, v_min=-50.0, v_max=50.0))
    exact = CRR("MlpPolicy", "Pendulum-v1", compute=dict(scoring_dtype="float32"), **kwargs)
    assert exact._online_scoring_copy is None and exact._target_scoring_copy is None
    monkeypatch.setattr(scoring, "cpu_has_fast_bf16", lambda: True)
    native = CRR("MlpPolicy", "Pendulum-v1", **kwargs)  # "auto" on a CPU with native bf16
    assert native._online_scoring_copy is not None and native._online_scoring_copy.dtype == th.bfloat16
    model = CRR(
        "MlpPolicy",
        "Pendulum-v1",
        compute=dict(scoring_dtype="bfloat16"),
        batch_size=32,
        learning_starts=50,
        target_update_interval=5,
        **kwargs,
    )
    model.learn(100)
    assert _copy_matches(model._target_scoring_copy)  # the online copy is synced before each use (then it lags)
    assert th.isfinite(th.cat([p.flatten() for p in model.policy.parameters()])).all()


def _wide_critic(kind: str) -> th.nn.Module:
    if kind == "categorical":
        return _categorical_critic(layer_norm=True, width=128)
    obs_space, act_space = gym.spaces.Box(-1, 1, (11,)), gym.spaces.Box(-1, 1, (3,))
    th.manual_seed(0)
    return QCritic(
        obs_space, act_space, [128, 128], FlattenExtractor(obs_space), 11, n_critics=2, layer_norm=kind == "layer_norm"
    )


@pytest.mark.skipif(not fused_products_supported(th.float32), reason="this torch build has no oneDNN fused products")
@pytest.mark.parametrize("kind", ["plain", "layer_norm", "categorical"])
def test_fused_products_match_the_unfused_pass(kind):
    """The fused path's arithmetic, checked in float32 (every oneDNN CPU runs it): the exact pass up to summation order;
    it follows the critic on sync only, and lays its weights out again after each sync."""
    critic = _wide_critic(kind)
    copy = LowPrecisionCopy(critic, th.float32, fused=True)
    obs, actions = th.rand(64, 11) * 2 - 1, th.rand(4, 64, 3) * 2 - 1
    with th.no_grad():
        exact, fused = score_actions(critic, obs, actions), score_actions(critic, obs, actions, copy)
        assert len(copy._packed) == 4  # two hidden layers in each of the two Q-networks
        th.testing.assert_close(fused, exact, rtol=1e-5, atol=1e-5 * float(exact.abs().mean()))
        packed = dict(copy._packed)
        for q_net in critic.q_networks:
            q_net[0].weight.mul_(1.5)
        assert th.equal(score_actions(critic, obs, actions, copy), fused)  # not synced: the copy's old weights
        copy.sync()
        assert not copy._packed
        moved, exact_moved = score_actions(critic, obs, actions, copy), score_actions(critic, obs, actions)
    assert not th.equal(exact_moved, exact) and all(copy._packed[key] is not packed[key] for key in packed)
    th.testing.assert_close(moved, exact_moved, rtol=1e-5, atol=1e-5 * float(exact_moved.abs().mean()))


def test_fused_products_only_where_supported(monkeypatch):
    critic = _wide_critic("plain")
    monkeypatch.setattr(scoring, "fused_products_supported", lambda dtype: False)
    assert not LowPrecisionCopy(critic, th.bfloat16).fused  # the default: unfused where unsupported, no error
    with pytest.raises(ValueError, match=r"fused products in torch\.bfloat16 are not supported"):
        LowPrecisionCopy(critic, th.bfloat16, fused=True)
    monkeypatch.setattr(scoring, "fused_products_supported", lambda dtype: True)
    assert LowPrecisionCopy(critic, th.bfloat16).fused  # the default where they are: bf16 fused
    assert not LowPrecisionCopy(critic, th.float32).fused  # float32 only when asked: it gained nothing on an AVX2 CPU
    assert not LowPrecisionCopy(critic, th.bfloat16, fused=False).fused


@pytest.mark.skipif(not fused_products_supported(th.float32), reason="this torch build has no oneDNN fused products")
def test_a_refused_fused_product_falls_back_with_one_warning():
    critic = _wide_critic("layer_norm")
    copy = LowPrecisionCopy(critic, th.float32, fused=True)
    copy._packed[id(copy.layers[0])] = th.ones(3, 3)  # a weight oneDNN cannot use for this layer
    obs, actions = th.rand(16, 11) * 2 - 1, th.rand(4, 16, 3) * 2 - 1
    with th.no_grad(), pytest.warns(UserWarning, match="without fusing"):
        q = score_actions(critic, obs, actions, copy)
    assert not copy.fused and not copy._packed
    with th.no_grad():
        th.testing.assert_close(q, score_actions(critic, obs, actions), rtol=0, atol=0)  # the unfused float32 pass
