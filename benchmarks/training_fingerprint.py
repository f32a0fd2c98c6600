"""
A fingerprint of training: what a refactor that claims to change no numbers must leave bit-identical.

A few small configurations (MPO online, in memory and on disk with two environments; CRR students of every kind
offline; BC; the distillation pipeline; the buffer's sampling) run with fixed seeds, and their end state is hashed:
every parameter and buffer of the policy, every optimiser's state, every value logged under ``train/`` (each dump),
and the batches the buffer samples. Save the fingerprint before a refactor, compare after::

    OMP_NUM_THREADS=1 python benchmarks/training_fingerprint.py --save /tmp/before.json
    ... refactor ...
    OMP_NUM_THREADS=1 python benchmarks/training_fingerprint.py --compare /tmp/before.json

``--compare`` prints the configurations and the parts that differ and exits 1 when any does. The hashes are of
the exact bytes: any change of arithmetic (an op's order, a dtype) shows, so run both on the same machine and
torch version.
"""

import argparse
import hashlib
import json
import pathlib
import sys
import tempfile
from typing import Any, Callable

import numpy as np
import torch as th
from stable_baselines3.common.logger import KVWriter, Logger


class _Capture(KVWriter):
    """Keeps every dumped ``train/`` value, in order."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, Any], step: int = 0) -> None:
        row = {k: v for k, v in sorted(key_values.items()) if k.startswith("train/") and isinstance(v, (int, float))}
        self.rows.append(dict(step=step, **row))


def _digest(value: Any) -> str:
    h = hashlib.sha256()

    def feed(x: Any) -> None:
        if isinstance(x, th.Tensor):
            h.update(str(x.dtype).encode() + str(tuple(x.shape)).encode())
            h.update(x.detach().cpu().contiguous().view(-1).view(th.uint8).numpy().tobytes() if x.numel() else b"")
        elif isinstance(x, np.ndarray):
            h.update(str(x.dtype).encode() + str(x.shape).encode() + np.ascontiguousarray(x).tobytes())
        elif isinstance(x, dict):
            for key in sorted(x, key=str):
                h.update(str(key).encode())
                feed(x[key])
        elif isinstance(x, (list, tuple)):
            for item in x:
                feed(item)
        else:
            h.update(repr(x).encode())

    feed(value)
    return h.hexdigest()[:16]


def _state(model: Any, capture: _Capture) -> dict[str, str]:
    """The hashes of a trained model: parameters, every optimiser, the logged values."""
    out = {"policy": _digest(model.policy.state_dict())}
    for module_name, module in model.policy.named_modules(prefix="policy"):
        for name, value in sorted(vars(module).items()):
            if isinstance(value, th.optim.Optimizer):
                out[f"{module_name}.{name}"] = _digest(value.state_dict())
    for name, value in sorted(vars(model).items()):
        if isinstance(value, th.optim.Optimizer):
            out[name] = _digest(value.state_dict())
        elif isinstance(value, th.Tensor):
            out[name] = _digest(value)
    out["logged"] = _digest(capture.rows)
    out["updates"] = str(model._n_updates)
    return out


def _with_capture(model: Any) -> _Capture:
    capture = _Capture()
    model.set_logger(Logger(None, [capture]))
    return capture


def mpo_memory(tmp: pathlib.Path) -> dict[str, str]:
    from sb3_lifelong import MPO

    model = MPO("MlpPolicy", "Pendulum-v1", learning_starts=100, batch_size=32, num_samples=8, seed=1,
                policy_kwargs=dict(net_arch=[32, 32], layer_norm=True))  # fmt: skip
    capture = _with_capture(model)
    model.learn(400, log_interval=1)
    return _state(model, capture)


def mpo_disk(tmp: pathlib.Path) -> dict[str, str]:
    import gymnasium as gym

    from sb3_lifelong import MPO, LifelongReplayBuffer
    from sb3_lifelong.envs import DynamicsSchedule

    def make() -> Any:
        return DynamicsSchedule(gym.make("Hopper-v5"), stages=[{}, {"foot_scale": 1.5}], switch_at=[200], append_params=True)

    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env(make, n_envs=2, seed=3)
    model = MPO("MlpPolicy", env, learning_starts=100, batch_size=32, num_samples=6, seed=2, n_steps=3,
                replay_buffer_class=LifelongReplayBuffer, replay_buffer_kwargs=dict(path=tmp / "buffer", chunk_size=64),
                policy_kwargs=dict(net_arch=[32, 32]))  # fmt: skip
    capture = _with_capture(model)
    model.learn(500, log_interval=1)
    model.replay_buffer.flush()
    return _state(model, capture)


def _students(tmp: pathlib.Path) -> dict[str, dict[str, Any]]:
    support = dict(v_min=-300.0, v_max=300.0, n_atoms=21)
    return {
        "crr_indicator": dict(advantage_transform="indicator"),
        "crr_exp_beta": dict(advantage_transform="exp", beta=1.0, advantage_baseline="max"),
        "crr_ess_categorical": dict(
            advantage_transform="exp", target_ess=0.9, policy_kwargs=dict(distributional_critic=True, **support)
        ),
        "crr_sarsa_per_source": dict(critic_target="sarsa", actor_per_source=True),
    }


def students(tmp: pathlib.Path) -> dict[str, dict[str, str]]:
    from sb3_lifelong import BC, CRR, LifelongReplayBuffer

    out = {}
    with LifelongReplayBuffer.open(tmp / "buffer", read_only=True) as buffer:
        for name, kwargs in _students(tmp).items():
            kwargs = dict(kwargs)
            policy_kwargs = dict(net_arch=[32, 32], **kwargs.pop("policy_kwargs", {}))
            model = CRR.from_offline_data(buffer, batch_size=32, num_samples=4, seed=4, policy_kwargs=policy_kwargs, **kwargs)
            capture = _with_capture(model)
            model.learn_offline(150, log_interval=50)
            out[name] = _state(model, capture)
        model = BC.from_offline_data(buffer, batch_size=32, seed=5, policy_kwargs=dict(net_arch=[32, 32]))
        capture = _with_capture(model)
        model.learn_offline(150, log_interval=50)
        out["bc"] = _state(model, capture)
    return out


def distill_pipeline(tmp: pathlib.Path) -> dict[str, str]:
    from sb3_lifelong import CRR, MPO

    teacher = MPO("MlpPolicy", "Pendulum-v1", learning_starts=100, batch_size=32, num_samples=4, seed=6,
                  policy_kwargs=dict(net_arch=[16]))  # fmt: skip
    teacher.learn(300)
    student = teacher.distill(CRR, total_updates=100, batch_size=32, seed=7, policy_kwargs=dict(net_arch=[16]))
    return {"policy": _digest(student.policy.state_dict()), "updates": str(student._n_updates)}


def buffer_sampling(tmp: pathlib.Path) -> dict[str, str]:
    from sb3_lifelong import LifelongReplayBuffer

    out = {}
    with LifelongReplayBuffer.open(tmp / "buffer", read_only=True) as buffer:
        for name, kwargs in dict(plain={}, sources=dict(return_sources=True), next_actions=dict(next_actions=True)).items():
            th.manual_seed(0)
            np.random.seed(0)
            batches = [buffer.sample(16, **kwargs) for _ in range(5)]
            out[name] = _digest([tuple(b) for b in batches])
        out["d4rl"] = _digest(buffer.to_d4rl(by_episode=True, normalized_actions=True))
    return out


CONFIGS: dict[str, Callable[[pathlib.Path], Any]] = {
    "mpo_memory": mpo_memory,
    "mpo_disk": mpo_disk,  # writes the buffer the next ones read
    "students": students,
    "distill": distill_pipeline,
    "buffer_sampling": buffer_sampling,
}


def fingerprint() -> dict[str, Any]:
    th.set_num_threads(1)
    with tempfile.TemporaryDirectory() as name:
        tmp = pathlib.Path(name)
        return {config: make(tmp) for config, make in CONFIGS.items()}


def _flat(tree: Any, prefix: str = "") -> dict[str, str]:
    if not isinstance(tree, dict):
        return {prefix: tree}
    out: dict[str, str] = {}
    for key, value in tree.items():
        out.update(_flat(value, f"{prefix}/{key}" if prefix else key))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--save", help="write the fingerprint to this JSON file")
    group.add_argument("--compare", help="compare with the fingerprint in this JSON file")
    args = parser.parse_args()
    now = fingerprint()
    if args.save:
        pathlib.Path(args.save).write_text(json.dumps(now, indent=1))
        print(f"{len(_flat(now))} hashes -> {args.save}")
        return
    before, after = _flat(json.loads(pathlib.Path(args.compare).read_text())), _flat(now)
    differ = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    for key in sorted(before.keys() | after.keys()):
        print(f"{'DIFFERS' if key in differ else 'same':8s} {key}")
    print(f"{len(differ)} of {len(before.keys() | after.keys())} differ")
    sys.exit(1 if differ else 0)


if __name__ == "__main__":
    main()
