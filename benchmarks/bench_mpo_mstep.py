"""
MPO's M-step from weighted moments (``sb3_lifelong.mpo.mpo.m_step_loss``, autograd over ``[batch, action_dim]``)
against the weighted log-likelihood written over every sample (autograd over ``[num_samples, batch,
action_dim]``, the formula it replaced), in one MPO model, blocks of updates alternating between the two (the order
flips every round). The two give the same loss and gradients (``tests/test_mpo.py``).

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_mpo_mstep.py --envs Walker2d-v5 Humanoid-v5 --rounds 8 --updates 100
"""

import argparse
import statistics
import time

import gymnasium as gym
import torch as th

import sb3_lifelong.mpo.mpo as mpo_module
from sb3_lifelong import MPO
from sb3_lifelong.common.policies import gaussian_log_prob


def m_step_over_samples(
    sampled_actions: th.Tensor,
    all_weights: list[th.Tensor],
    online_mean: th.Tensor,
    online_std: th.Tensor,
    target_mean: th.Tensor,
    target_std: th.Tensor,
) -> th.Tensor:
    """The reference: the log-likelihood of every sample, weighted and summed over the samples."""
    log_prob_mean = gaussian_log_prob(sampled_actions, online_mean.unsqueeze(0), target_std.unsqueeze(0))
    log_prob_std = gaussian_log_prob(sampled_actions, target_mean.unsqueeze(0), online_std.unsqueeze(0))
    return th.stack([-(w * (log_prob_mean + log_prob_std)).sum(dim=0).mean() for w in all_weights]).sum()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["Walker2d-v5", "Humanoid-v5"])
    parser.add_argument("--rounds", type=int, default=8, help="rounds of one block per variant")
    parser.add_argument("--updates", type=int, default=100, help="updates per block")
    args = parser.parse_args()
    th.set_num_threads(1)
    variants = {"over samples": m_step_over_samples, "moments": mpo_module.m_step_loss}
    print("| env | action dims | over samples, ms/update (median) | moments | ratio (median of the rounds' ratios) |")
    print("| --- | --- | --- | --- | --- |")
    for env_id in args.envs:
        env = gym.make(env_id)
        model = MPO(
            "MlpPolicy",
            env,
            learning_starts=0,
            batch_size=256,
            seed=0,
            policy_kwargs=dict(net_arch=[256, 256], layer_norm=False),
        )
        model.learn(600)  # some data to sample
        times: dict[str, list[float]] = {name: [] for name in variants}
        for round_ in range(args.rounds):
            order = list(variants) if round_ % 2 == 0 else list(reversed(variants))
            for name in order:
                mpo_module.m_step_loss = variants[name]  # type: ignore[assignment]
                start = time.perf_counter()
                model.train(args.updates, 256)
                times[name].append((time.perf_counter() - start) * 1e3 / args.updates)
        mpo_module.m_step_loss = variants["moments"]  # type: ignore[assignment]
        ratios = [old / new for old, new in zip(times["over samples"], times["moments"])]
        print(
            f"| {env_id} | {env.action_space.shape[0]} | {statistics.median(times['over samples']):.1f} | "  # type: ignore[index]
            f"{statistics.median(times['moments']):.1f} | {statistics.median(ratios):.2f}x "
            f"({min(ratios):.2f}-{max(ratios):.2f}) |",
            flush=True,
        )


if __name__ == "__main__":
    main()
