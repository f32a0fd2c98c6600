"""
Updates per second of the study presets' models on each device: MPO (the collector) and a CRR student, at the
``cpu`` and ``paper`` presets' sizes (networks, batches, action samples, input and action dimensions), on the CPU and,
where torch sees one, on the GPU.

Only the gradient updates are timed (``train(gradient_steps, batch_size)`` on a filled buffer of random transitions
shaped like the preset's robot, with its physical parameter appended): no environment steps, so the number is the
one a device changes. The devices are timed in interleaved rounds (cpu, cuda, cpu, cuda, ...) in one process, so both
see the same machine load; the table gives the median over rounds and the GPU / CPU ratio per model. The answer for a
user is in ``docs/guide/install.md`` ("GPU"), with the machine and the command it came from.

Usage (one torch thread on the CPU, as the studies run)::

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_device_presets.py                     # cpu, and cuda if present
    OMP_NUM_THREADS=1 python benchmarks/speed/bench_device_presets.py --rounds 5 --updates 200 --presets cpu
"""

import argparse
import datetime
import json
import pathlib
import statistics
import time
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces

RESULTS = pathlib.Path(__file__).resolve().parents[1] / "results" / "speed" / "device_presets"
#: the robots' observation (with the appended parameter) and action sizes, by preset (measured from the envs:
#: HalfCheetah-v5 17 + 1 and 6; OP3 walking 68 + 1 and 20), so that the benchmark needs no MuJoCo model
SHAPES = {"cpu": (18, 6), "paper": (69, 20)}


class RandomBoxEnv(gym.Env):
    """An environment of the preset's shapes that returns random observations and rewards (fills a buffer fast)."""

    def __init__(self, obs_dim: int, action_dim: int, episode: int = 1000):
        self.observation_space = spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (action_dim,), np.float32)
        self.episode = episode
        self.rng = np.random.default_rng(0)
        self.t = 0

    def reset(self, *, seed: Any = None, options: Any = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self.rng.normal(size=self.observation_space.shape).astype(np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.t += 1
        obs = self.rng.normal(size=self.observation_space.shape).astype(np.float32)
        return obs, float(self.rng.normal()), False, self.t >= self.episode, {}


def models(preset_name: str, device: str, fill: int) -> dict[str, Any]:
    """MPO and a CRR student at the preset's settings on ``device``, their buffers filled with ``fill`` rows."""
    from sb3_lifelong import CRR, MPO
    from sb3_lifelong.experiments.presets import PRESETS

    preset = PRESETS[preset_name]
    obs_dim, action_dim = SHAPES[preset_name]
    policy_kwargs = dict(net_arch=list(preset.net_arch), layer_norm=preset.layer_norm)
    mpo = MPO(
        "MlpPolicy",
        RandomBoxEnv(obs_dim, action_dim),
        batch_size=preset.batch_size,
        num_samples=preset.num_samples,
        learning_rate=preset.learning_rate,
        learning_starts=fill,
        policy_kwargs=policy_kwargs,
        device=device,
        seed=0,
        verbose=0,
    )
    mpo.learn(fill + 1)  # random steps fill the buffer, then one update
    rng = np.random.default_rng(1)
    data = dict(
        observations=rng.normal(size=(fill, obs_dim)).astype(np.float32),
        actions=rng.uniform(-1, 1, (fill, action_dim)).astype(np.float32),
        rewards=rng.normal(size=fill).astype(np.float32),
        next_observations=rng.normal(size=(fill, obs_dim)).astype(np.float32),
        terminals=np.zeros(fill, bool),
        timeouts=np.zeros(fill, bool),
    )
    crr = CRR.from_offline_data(
        data,
        action_space=spaces.Box(-1.0, 1.0, (action_dim,), np.float32),
        batch_size=preset.student_batch_size,
        learning_rate=preset.student_learning_rate,
        policy_kwargs=policy_kwargs,
        advantage_transform="exp",
        beta=1.0,
        device=device,
        seed=0,
    )
    crr.learn_offline(10, log_interval=0)  # warm-up
    return {"MPO": mpo, "CRR student": crr}


def updates_per_second(model: Any, updates: int) -> float:
    """:return: the model's gradient updates per second over one block of ``updates``"""
    if model.device.type == "cuda":
        th.cuda.synchronize(model.device)
    start = time.perf_counter()
    if hasattr(model, "learn_offline"):
        model.learn_offline(updates, log_interval=0, reset_num_timesteps=False)
    else:
        model.train(gradient_steps=updates, batch_size=model.batch_size)
    if model.device.type == "cuda":
        th.cuda.synchronize(model.device)
    return updates / (time.perf_counter() - start)


def machine() -> dict[str, Any]:
    from sb3_lifelong.numerics.hardware import machine_description

    out: dict[str, Any] = dict(machine=machine_description(), torch=th.__version__, threads=th.get_num_threads())
    if th.cuda.is_available():
        out["gpu"] = th.cuda.get_device_name(0)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", nargs="+", default=["cpu", "paper"], choices=sorted(SHAPES))
    parser.add_argument("--devices", nargs="+", default=None, help="default: cpu, and cuda where torch sees a GPU")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds per device (the median is reported)")
    parser.add_argument("--updates", type=int, default=300, help="updates per timed block")
    parser.add_argument("--fill", type=int, default=5_000, help="rows in each buffer")
    parser.add_argument("--output", default=str(RESULTS))
    args = parser.parse_args()
    devices = args.devices or (["cpu", "cuda"] if th.cuda.is_available() else ["cpu"])

    rows = []
    for preset_name in args.presets:
        built = {device: models(preset_name, device, args.fill) for device in devices}
        timings: dict[tuple[str, str], list[float]] = {}
        for _ in range(args.rounds):
            for device in devices:  # interleaved: each round times every device under the same load
                for name, model in built[device].items():
                    timings.setdefault((name, device), []).append(updates_per_second(model, args.updates))
        for name in ("MPO", "CRR student"):
            row: dict[str, Any] = dict(preset=preset_name, model=name)
            for device in devices:
                row[device] = statistics.median(timings[(name, device)])
                row[f"{device} rounds"] = [round(v, 1) for v in timings[(name, device)]]
            if "cuda" in devices:
                row["cuda / cpu"] = row["cuda"] / row["cpu"]
            rows.append(row)

    header = ["preset", "model", *[f"{d} updates/s" for d in devices]] + (["GPU / CPU"] if "cuda" in devices else [])
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        cells = [row["preset"], row["model"], *[f"{row[d]:.0f}" for d in devices]]
        if "cuda" in devices:
            cells.append(f"{row['cuda / cpu']:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    print(table)
    out = pathlib.Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    record = dict(when=stamp, command=vars(args), devices=devices, rows=rows, **machine())
    (out / f"{stamp}.json").write_text(json.dumps(record, indent=1) + "\n")
    (out / f"{stamp}.md").write_text(f"{table}\n\n{json.dumps(machine())}\n")
    print(f"-> {out / stamp}.json")


if __name__ == "__main__":
    main()
