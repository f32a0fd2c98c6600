"""MPO and CRR on a CUDA GPU: training, the "auto" scoring precision, the compiled update and save/load, and data
held on the other device (buffers, the per-source Q diagnostic, distill's student, process pools). Skipped where torch
sees no GPU (CI); run them on a machine that has one."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from testkit import flat_params, pendulum_data

from sb3_lifelong import CRR, MPO
from sb3_lifelong.numerics import compiling

pytestmark = pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")
CUDA = th.device("cuda")
STUDENT = dict(
    batch_size=32,
    policy_kwargs=dict(net_arch=[64, 64], layer_norm=True, distributional_critic=True, v_min=-100.0, v_max=10.0),
    target_update_interval=4,
    device="cuda",
)


def test_mpo_trains_predicts_and_loads_on_cuda(tmp_path):
    model = MPO("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=64, batch_size=32, device="cuda", seed=0)
    model.learn(160)
    assert model.device.type == "cuda" and next(model.policy.parameters()).is_cuda
    assert all(th.isfinite(p).all() for p in model.policy.parameters())
    observation = np.zeros(3, np.float32)
    action, _ = model.predict(observation, deterministic=True)
    assert action.shape == (1,) and np.all(np.abs(action) <= 2)
    model.save(tmp_path / "mpo.zip")
    loaded = MPO.load(tmp_path / "mpo.zip", device="cuda")
    np.testing.assert_array_equal(loaded.predict(observation, deterministic=True)[0], action)


def test_auto_scoring_on_cuda_follows_the_gpu_and_the_width():
    space = spaces.Box(-2, 2, (1,))
    narrow = CRR.from_offline_data(pendulum_data(200), env=None, action_space=space, seed=0, **STUDENT)
    assert narrow._target_scoring_copy is None  # 64 wide: below "auto"'s width, float32 on any device
    wide_kwargs = {**STUDENT, "policy_kwargs": {**STUDENT["policy_kwargs"], "net_arch": [256, 256]}}
    wide = CRR.from_offline_data(pendulum_data(200), env=None, action_space=space, seed=0, **wide_kwargs)
    if th.cuda.is_bf16_supported():
        assert wide._target_scoring_copy is not None and wide._target_scoring_copy.dtype == th.bfloat16
    else:
        assert wide._target_scoring_copy is None
    wide.learn_offline(8, log_interval=0)
    assert th.isfinite(flat_params(wide)).all()


@pytest.mark.skipif(not compiling.can_compile(CUDA), reason="inductor needs triton for a GPU")
def test_compiled_student_matches_eager_on_cuda():
    data = pendulum_data(300)
    space = spaces.Box(-2, 2, (1,))
    # a clip that binds at every step keeps rounding differences from growing through Adam's normalisation
    common = dict(env=None, action_space=space, seed=0, max_grad_norm=1e-3, **STUDENT)
    # each built and trained before the next is built: both draw the same noise from the seeded global generator
    eager = CRR.from_offline_data(data, compute=dict(compile_losses=False), **common).learn_offline(12, log_interval=0)
    compiled = CRR.from_offline_data(data, compute=dict(compile_losses=True), **common).learn_offline(12, log_interval=0)
    assert compiled._forward.compiled is not None and not compiled._forward.failed
    difference = (flat_params(compiled) - flat_params(eager)).abs().max()
    assert difference <= 1e-4, float(difference)


def _two_source_buffer(device: str):
    from sb3_lifelong import LifelongReplayBuffer

    buffer = LifelongReplayBuffer(0, spaces.Box(-1, 1, (3,)), spaces.Box(-1, 1, (2,)), device=device)
    for source in (0, 1):
        buffer.set_source(source, name=f"env_{source}")
        for t in range(60):
            obs = np.full((1, 3), t / 60, np.float32)
            buffer.add(obs, obs, np.zeros((1, 2), np.float32), np.ones(1), np.array([t % 20 == 19]), [{}])
    return buffer


def test_a_cpu_buffer_trains_a_cuda_student():
    """A buffer built (or opened) on the CPU samples onto the GPU once a model there uses it: one actor or one per
    source."""
    for per_source in (False, True):
        buffer = _two_source_buffer("cpu")
        model = CRR.from_offline_data(buffer, actor_per_source=per_source, batch_size=32, seed=0, device="cuda")
        model.learn_offline(20, log_interval=0)
        assert buffer.device == CUDA and all(th.isfinite(p).all() for p in model.policy.parameters())


def test_distill_follows_the_teacher_and_the_teacher_keeps_learning():
    """The student runs where its teacher does unless told otherwise; a student on the CPU leaves the teacher's
    buffer to the teacher, which samples on the GPU again when it learns on."""
    teacher = MPO("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=64, batch_size=32, device="cuda", seed=0)
    teacher.learn(128)
    assert teacher.distill(CRR, total_updates=10, batch_size=32).device == CUDA
    assert teacher.distill(CRR, total_updates=10, batch_size=32, device="cpu").device == th.device("cpu")
    teacher.learn(64, reset_num_timesteps=False)
    assert teacher.replay_buffer.device == CUDA


def _cuda_sum(n: int) -> float:
    return float(th.arange(n, device="cuda").sum())


def test_a_process_pool_after_cuda_was_used():
    """A local process pool started after this process used CUDA: its workers can use the GPU too (spawned, not
    forked)."""
    from sb3_lifelong.experiments.runner import map_parallel

    th.zeros(1, device="cuda")
    assert map_parallel(_cuda_sum, [dict(n=n) for n in (3, 4)], workers=2, backend="process") == [3.0, 6.0]


def test_source_q_callback_on_data_held_on_another_device():
    """The per-source Q diagnostic measures a CPU student on data that samples onto the GPU, and the reverse."""
    from sb3_lifelong.evaluation.callbacks import SourceQCallback

    for model_device, data_device in (("cpu", "cuda"), ("cuda", "cpu")):
        model = CRR.from_offline_data(_two_source_buffer(model_device), batch_size=32, seed=0, device=model_device)
        data = _two_source_buffer(data_device)
        callback = SourceQCallback(log_freq=5, batch_size=64, data=data)
        model.learn_offline(10, log_interval=0, callback=callback)
        assert data.device == th.device(data_device) and len(callback.results) == 4  # 2 measurements x 2 sources
        assert all(np.isfinite(row["q_mean"]) and np.isfinite(row["overestimation"]) for row in callback.results)


def test_a_study_runs_every_model_on_the_gpu_with_device_cuda(tmp_path):
    import json

    from sb3_lifelong.experiments.__main__ import main

    output = tmp_path / "study"
    assert (
        main(
            [
                "run",
                "--preset",
                "tiny",
                "--seed",
                "0",
                "--output",
                str(output),
                "--device",
                "cuda",
                "--jobs",
                "distill_CRR_exp_beta1",
            ]
        )
        == 0
    )
    assert json.loads((output / "preset.json").read_text())["device"] == "cuda"
    seed = output / "seed_0"
    collector = MPO.load(seed / "collect" / "final.zip", custom_objects={"replay_buffer_kwargs": {}})
    student = CRR.load(seed / "distill_CRR_exp_beta1" / "student.zip")
    assert collector.device.type == "cuda" and student.device.type == "cuda"
    # the study is one device's: the same seed on the CPU is refused, not mixed in
    with pytest.raises(SystemExit):
        main(["run", "--preset", "tiny", "--seed", "1", "--output", str(output), "--device", "cpu"])
