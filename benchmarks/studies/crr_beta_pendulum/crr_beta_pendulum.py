"""
What ``beta`` means on a narrow dataset, and what ``target_ess`` costs: CRR trained offline on 10,000 transitions of
one SAC policy on Pendulum-v1 (the dataset of ``tests/common/test_offline_learning.py``: returns of about -200 per
episode, Q differences of tens) with the indicator transform, ``exp`` at ``beta`` = 1 and 10, and ``exp`` at
``target_ess=0.9``; then the time of the ``target_ess`` temperature search per batch of 256 advantages.

    OMP_NUM_THREADS=1 python benchmarks/studies/crr_beta_pendulum/crr_beta_pendulum.py

Writes ``benchmarks/studies/crr_beta_pendulum/crr_beta_pendulum.md`` (the returns over the 20 evaluation episodes of
the test, the
weights' effective sample size and mean over the last 500 updates, the search's time).
"""

import argparse
import pathlib
import statistics
import time
from typing import Optional

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import SAC

from sb3_lifelong import CRR
from sb3_lifelong.core.datasets import record_transitions
from sb3_lifelong.numerics.hardware import machine_description

HERE = pathlib.Path(__file__).resolve().parent
#: the dataset and evaluation of ``tests/common/test_offline_learning.py``: a briefly trained SAC on Pendulum-v1
EVAL_SEEDS = range(100, 120)
NET = dict(net_arch=[64, 64])


def mean_return(act, seeds) -> float:
    """:return: the policy's mean return over one Pendulum-v1 episode per seed"""
    env, returns = gym.make("Pendulum-v1"), []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(act(obs))
            total, done = total + float(reward), terminated or truncated
        returns.append(total)
    return float(np.mean(returns))


def collect_behaviour() -> tuple[dict, float]:
    """:return: 10,000 transitions of SAC trained for 5,000 steps (acting stochastically), and its return"""
    th.manual_seed(0)
    sac = SAC("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(NET), batch_size=128, learning_rate=1e-3, learning_starts=500,
              seed=0)  # fmt: skip
    sac.learn(5_000)
    data = record_transitions(gym.make("Pendulum-v1"), lambda obs: sac.predict(obs, deterministic=False)[0], 10_000, seed=0)
    return data, mean_return(lambda o: sac.predict(o, deterministic=False)[0], EVAL_SEEDS)


VARIANTS = {
    "indicator": dict(advantage_transform="indicator"),
    "exp, beta=1": dict(advantage_transform="exp", beta=1.0),
    "exp, beta=10": dict(advantage_transform="exp", beta=10.0),
    "exp, target_ess=0.9": dict(advantage_transform="exp", target_ess=0.9),
}


def train(data: dict, kwargs: dict, updates: int, seed: int) -> dict:
    model = CRR.from_offline_data(
        data, env="Pendulum-v1", batch_size=128, learning_rate=1e-3, policy_kwargs=dict(NET), seed=seed, **kwargs
    )
    model.learn_offline(updates - 500, log_interval=0)
    ess, weight = [], []
    for _ in range(10):  # the weights' statistics over the last 500 updates, 50 at a time
        model.learn_offline(50, log_interval=0, reset_num_timesteps=False)
        ess.append(model.logger.name_to_value.get("train/weight_ess", float("nan")))
        weight.append(model.logger.name_to_value.get("train/weight_mean", float("nan")))
    learned = mean_return(lambda o: model.predict(o, deterministic=True)[0], EVAL_SEEDS)
    return dict(ret=learned, ess=float(np.nanmean(ess)), weight=float(np.nanmean(weight)))


def search_ms(repeats: int) -> float:
    """:return: milliseconds per call of the ``target_ess`` temperature search on 256 Gaussian advantages"""
    from sb3_lifelong.crr.losses import ess_temperature

    g = th.Generator().manual_seed(0)
    advantages = [th.randn(256, generator=g) * 5 for _ in range(repeats)]
    previous: Optional[float] = None
    times = []
    for _ in range(5):
        start = time.perf_counter()
        for a in advantages:
            previous = float(ess_temperature(a, 0.9, 20.0, previous))
        times.append((time.perf_counter() - start) / repeats * 1e3)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates", type=int, default=3_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--output", default=str(HERE / "crr_beta_pendulum.md"))
    args = parser.parse_args()
    th.set_num_threads(1)
    data, behaviour_return = collect_behaviour()
    lines = [
        "# CRR's transforms on a narrow Pendulum dataset, and the cost of `target_ess`",
        "",
        "Command: `OMP_NUM_THREADS=1 python benchmarks/studies/crr_beta_pendulum/crr_beta_pendulum.py --updates "
        f"{args.updates} --seeds "
        f"{' '.join(map(str, args.seeds))}`",
        "",
        f"Machine: {machine_description()}",
        "",
        "Data: 10,000 transitions of one SAC policy (as `tests/common/test_offline_learning.py`); its return on the 20 "
        f"evaluation episodes: {behaviour_return:.1f}. CRR: 64x64 networks, batch 128, learning rate 1e-3, "
        f"{args.updates} updates; "
        "the return of the deterministic policy on the same 20 episodes; the weights' effective sample size (a fraction "
        "of the batch) and mean weight over the last 500 updates.",
        "",
        "| transform | seed | return | weight ESS | mean weight |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, kwargs in VARIANTS.items():
        for seed in args.seeds:
            row = train(data, kwargs, args.updates, seed)
            lines.append(f"| {name} | {seed} | {row['ret']:.1f} | {row['ess']:.2f} | {row['weight']:.3f} |")
            print(lines[-1], flush=True)
    ms = search_ms(2_000)
    lines += ["", f"The `target_ess` search on 256 advantages: {ms:.3f} ms per call (median of 5 blocks of 2,000 calls)."]
    print(lines[-1])
    pathlib.Path(args.output).write_text("\n".join(lines) + "\n")
    print(f"-> {args.output}")


if __name__ == "__main__":
    main()
