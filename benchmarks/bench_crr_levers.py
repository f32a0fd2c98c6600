"""
Would these changes make CRR's update faster? Each variant is a CRR model on the same offline dataset and settings as
``bench_crr.py`` (256x256, batch 256, 4 policy samples, exp weights, one critic, ``scoring_dtype="auto"``), changed
only as its name says; the variants train in interleaved blocks in one process, so that they see the same machine
load, and the table gives each variant's median time per update and the median of its per-block ratios to the
current code.

- ``bf16 target actor``: the target policy's torso (its hidden layers) runs on a bfloat16 copy, as the target
  critic's does, for the TD target's next actions (the mean and std heads stay float32).
- ``plain-layout copy``: the online critic's bfloat16 copy keeps the weights in their own layout (a plain
  conversion at every update, against a transposed copy) and hands the matrix product a transposed view.
- ``lean Adam``: the two optimizer steps call the fused Adam kernel on cached lists of tensors, without
  ``torch.optim.Adam.step``'s per-call bookkeeping (the same update, bit for bit).
- ``all three``.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_crr_levers.py --blocks 12 --updates 150
"""

import argparse
import json
import os
import statistics
import time
from typing import Any, Callable

import numpy as np
import torch as th
import torch.nn.functional as F
from bench_crr import make_ours
from stable_baselines3.common.logger import configure
from torch import nn

import sb3_lifelong.crr.crr as crr_module
from sb3_lifelong import CRR
from sb3_lifelong.common.policies import sample_gaussian
from sb3_lifelong.common.scoring import LowPrecisionCopy, _run_mlp_no_grad

CURRENT_TARGET_ACTIONS = crr_module.target_actions


def make_model(data: dict, env_id: str) -> CRR:
    model = make_ours(data, env_id, seed=0)
    model.set_logger(configure(None, []))
    model.train(50, 256)  # warm-up
    return model


class ActorTorsoCopy(LowPrecisionCopy):
    """A bfloat16 copy of an actor's hidden layers (its torso ``latent_pi``; the mean and std heads stay float32)."""

    def _hidden_layers(self) -> list[nn.Linear]:
        actor: Any = self.critic  # the copied module: here an actor
        return [module for module in actor.latent_pi.modules() if isinstance(module, nn.Linear)]


def bf16_target_actions(model: CRR) -> Callable[..., th.Tensor]:
    """:return: ``target_actions`` with the target actor's hidden layers on a bfloat16 copy of them"""
    copy = ActorTorsoCopy(model.actor_target)  # type: ignore[arg-type]
    update_targets = model._update_targets

    def update_and_sync() -> None:
        update_targets()
        copy.sync()

    model._update_targets = update_and_sync  # type: ignore[method-assign]

    def target_actions(actor_target: Any, replay_data: Any, heads: Any, n: int, data_next_actions: bool = False) -> th.Tensor:
        features = actor_target.extract_features(replay_data.next_observations, actor_target.features_extractor)
        latent = _run_mlp_no_grad(actor_target, 0, actor_target.latent_pi, features.bfloat16(), copy).float()
        mean = actor_target.mu(latent)
        mean = th.tanh(mean) if actor_target.squash_mean else mean
        std = F.softplus(actor_target.std_head(latent)) * actor_target._std_scale + actor_target.min_std
        return sample_gaussian(mean, std, n).clamp(-1.0, 1.0)

    return target_actions


class PlainLayoutCopy(LowPrecisionCopy):
    """A bfloat16 copy of the critic's hidden layers in their own layout; the product reads a transposed view."""

    def __init__(self, critic: Any) -> None:
        self.critic, self.dtype = critic, th.bfloat16
        self.layers = self._hidden_layers()
        self.plain = {id(m): m.weight.detach().bfloat16() for m in self.layers}
        self.weights = {id(m): (self.plain[id(m)].t(), m.bias.detach().bfloat16()) for m in self.layers}

    @th.no_grad()
    def sync(self) -> None:
        for module in self.layers:
            self.plain[id(module)].copy_(module.weight)
            self.weights[id(module)][1].copy_(module.bias)  # type: ignore[union-attr]


def lean_adam(optimizer: th.optim.Optimizer) -> None:
    """Replace ``optimizer.step`` by one call of the fused kernel on cached lists (same update)."""
    group = optimizer.param_groups[0]
    params = list(group["params"])
    for p in params:  # the state exists after the warm-up
        assert "exp_avg" in optimizer.state[p]
    states = [optimizer.state[p] for p in params]
    exp_avgs, exp_avg_sqs = [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states]
    steps = [s["step"] for s in states]
    beta1, beta2 = group["betas"]

    def step() -> None:
        th._foreach_add_(steps, 1)
        grads = [p.grad for p in params]
        th._fused_adam_(  # type: ignore[attr-defined]
            params,
            grads,
            exp_avgs,
            exp_avg_sqs,
            [],
            steps,
            amsgrad=False,
            lr=group["lr"],
            beta1=beta1,
            beta2=beta2,
            weight_decay=group["weight_decay"],
            eps=group["eps"],
            maximize=False,
        )

    optimizer.step = step  # type: ignore[method-assign,assignment]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="benchmarks/results/crr_hopper_medium_replay.npz")
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--blocks", type=int, default=12, help="interleaved blocks per variant")
    parser.add_argument("--updates", type=int, default=150, help="updates per block")
    parser.add_argument("--output", default="benchmarks/results/crr_levers.json")
    args = parser.parse_args()
    th.set_num_threads(1)
    with np.load(args.data) as npz:
        data = {key: npz[key] for key in npz.files}
    models: dict[str, CRR] = {}
    actions: dict[str, Callable[..., th.Tensor]] = {}
    for name in ("current", "bf16 target actor", "plain-layout copy", "lean Adam", "all three"):
        model = make_model(data, args.env)
        actions[name] = bf16_target_actions(model) if name in ("bf16 target actor", "all three") else CURRENT_TARGET_ACTIONS
        if name in ("plain-layout copy", "all three"):
            model._online_scoring_copy = PlainLayoutCopy(model.critic)
        if name in ("lean Adam", "all three"):
            lean_adam(model.actor.optimizer)
            lean_adam(model.critic.optimizer)
        models[name] = model
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.blocks):
        for name, model in models.items():
            crr_module.target_actions = actions[name]  # type: ignore[assignment]
            start = time.perf_counter()
            model.train(args.updates, 256)
            times[name].append((time.perf_counter() - start) * 1e3 / args.updates)
    crr_module.target_actions = CURRENT_TARGET_ACTIONS
    lines = [
        f"| variant | ms per update (median of {args.blocks} blocks of {args.updates}) | speed-up vs current "
        "(median of per-block ratios) | range of the ratios |",
        "| --- | --- | --- | --- |",
    ]
    for name, values in times.items():
        ratios = [c / v for c, v in zip(times["current"], values)]
        lines.append(
            f"| {name} | {statistics.median(values):.2f} | {statistics.median(ratios):.3f}x | "
            f"{min(ratios):.2f}-{max(ratios):.2f} |"
        )
    print("\n".join(lines))
    os.makedirs(os.path.dirname(args.output) or ".", exist_ok=True)
    with open(args.output, "w") as file:
        json.dump({"args": vars(args), "ms_per_update": times, "table": lines}, file, indent=1)


if __name__ == "__main__":
    main()
