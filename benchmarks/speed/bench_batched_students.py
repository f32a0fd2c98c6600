"""
What training several students in one process, batched, would buy: the arithmetic core of a dose-study student's
update (a categorical critic and a Gaussian actor, each a 256x256 LayerNorm torso; HalfCheetah sizes, batch 256),
for K students either one after the other (K sets of ``nn.Linear`` networks, K optimizers) or batched (the K
students' weights stacked, each product one ``baddbmm`` over the K students, one optimizer step over the stacks).

One update per student, both ways, is the same arithmetic:
- no gradient: the target critic on the batch's next states and one sampled next action (the TD target's pass);
- no gradient: the critic on 4 sampled actions per state (the advantage baseline, 1024 rows);
- with gradients: the critic's cross-entropy on the batch and the actor's weighted log-likelihood; one backward; Adam.

It is not CRR: no categorical projection, no data sampling, no weights from advantages (constants stand in), so its
times are the products and the framework's fixed costs of an update, which is what batching shares. The table gives,
per K, the milliseconds per student-update of each way (median of interleaved blocks) and their ratio.

    OMP_NUM_THREADS=1 python benchmarks/speed/bench_batched_students.py                 # K = 1, 2, 4, 8
    OMP_NUM_THREADS=1 python benchmarks/speed/bench_batched_students.py --compile       # each way's update compiled
"""

import argparse
import json
import pathlib
import statistics
import time
from typing import Callable

import torch as th
import torch.nn.functional as F
from torch import nn

RESULTS = pathlib.Path(__file__).resolve().parents[1] / "results" / "speed" / "batched_students.json"
OBS, ACT, HIDDEN, ATOMS, BATCH, SAMPLES = 19, 6, 256, 51, 256, 4


class StackedTorso(nn.Module):
    """K LayerNorm MLPs (``Linear -> LayerNorm -> tanh -> Linear -> ReLU -> Linear``), weights stacked ``[K, in, out]``."""

    def __init__(self, k: int, inputs: int, outputs: int) -> None:
        super().__init__()
        sizes = [(inputs, HIDDEN), (HIDDEN, HIDDEN), (HIDDEN, outputs)]
        self.weights = nn.ParameterList([nn.Parameter(th.randn(k, i, o) / i**0.5) for i, o in sizes])
        self.biases = nn.ParameterList([nn.Parameter(th.zeros(k, 1, o)) for _, o in sizes])
        self.norm_scale, self.norm_shift = nn.Parameter(th.ones(k, 1, HIDDEN)), nn.Parameter(th.zeros(k, 1, HIDDEN))

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``[K, rows, inputs]``"""
        h = th.baddbmm(self.biases[0], x, self.weights[0])
        h = th.tanh(F.layer_norm(h, (HIDDEN,)) * self.norm_scale + self.norm_shift)
        h = th.baddbmm(self.biases[1], h, self.weights[1]).relu()
        return th.baddbmm(self.biases[2], h, self.weights[2])


def torso(inputs: int, outputs: int) -> nn.Module:
    return nn.Sequential(
        nn.Linear(inputs, HIDDEN),
        nn.LayerNorm(HIDDEN),
        nn.Tanh(),
        nn.Linear(HIDDEN, HIDDEN),
        nn.ReLU(),
        nn.Linear(HIDDEN, outputs),
    )


def student_update(critic, target, actor, optimizer, batch: dict[str, th.Tensor]) -> None:
    """One update of one student (or of K stacked ones: every tensor then has a leading K)."""
    obs, act, next_obs = batch["obs"], batch["act"], batch["next_obs"]
    with th.no_grad():
        next_logits = target(th.cat([next_obs, batch["next_act"]], -1))
        target_probs = next_logits.softmax(-1)  # (the projection left out)
        tiled = obs.unsqueeze(-3).expand(*obs.shape[:-2], SAMPLES, *obs.shape[-2:]).flatten(-3, -2)
        baseline = critic(th.cat([tiled, batch["sampled_act"]], -1))
    logits = critic(th.cat([obs, act], -1))
    critic_loss = -(target_probs * logits.log_softmax(-1)).sum(-1).mean()
    mean, log_std = actor(obs).split(ACT, -1)
    log_prob = (-0.5 * ((act - mean) / log_std.exp()) ** 2 - log_std).sum(-1)
    actor_loss = -(batch["weights"] * log_prob).mean() + 0.0 * baseline.mean()
    optimizer.zero_grad(set_to_none=True)
    (critic_loss + actor_loss).backward()
    optimizer.step()


def batch_of(k: int | None) -> dict[str, th.Tensor]:
    lead = () if k is None else (k,)
    return dict(
        obs=th.randn(*lead, BATCH, OBS),
        act=th.rand(*lead, BATCH, ACT) * 2 - 1,
        next_obs=th.randn(*lead, BATCH, OBS),
        next_act=th.rand(*lead, BATCH, ACT) * 2 - 1,
        sampled_act=th.rand(*lead, SAMPLES * BATCH, ACT) * 2 - 1,
        weights=th.rand(*lead, BATCH),
    )


def separate(k: int, compile_: bool) -> Callable[[], None]:
    """:return: one update of each of K students, one after the other"""
    students = []
    for _ in range(k):
        critic, target, actor = torso(OBS + ACT, ATOMS), torso(OBS + ACT, ATOMS), torso(OBS, 2 * ACT)
        optimizer = th.optim.Adam([*critic.parameters(), *actor.parameters()], lr=3e-4, fused=True)
        step = th.compile(student_update, dynamic=False) if compile_ else student_update
        students.append((step, critic, target, actor, optimizer, batch_of(None)))

    def update() -> None:
        for step, *args in students:
            step(*args)

    return update


def batched(k: int, compile_: bool) -> Callable[[], None]:
    """:return: one update of K stacked students"""
    critic, target, actor = StackedTorso(k, OBS + ACT, ATOMS), StackedTorso(k, OBS + ACT, ATOMS), StackedTorso(k, OBS, 2 * ACT)
    optimizer = th.optim.Adam([*critic.parameters(), *actor.parameters()], lr=3e-4, fused=True)
    step = th.compile(student_update, dynamic=False) if compile_ else student_update
    data = batch_of(k)
    return lambda: step(critic, target, actor, optimizer, data)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ks", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--blocks", type=int, default=5)
    parser.add_argument("--updates", type=int, default=20, help="updates per block")
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--output", default=str(RESULTS))
    args = parser.parse_args()
    th.set_num_threads(1)
    th.manual_seed(0)
    from sb3_lifelong.numerics.hardware import machine_description

    machine = machine_description()
    print(machine)
    rows = {}
    for k in args.ks:
        ways = {"separate": separate(k, args.compile), "batched": batched(k, args.compile)}
        for update in ways.values():
            for _ in range(3):  # warm-up (and the compilation)
                update()
        times: dict[str, list[float]] = {name: [] for name in ways}
        for _ in range(args.blocks):
            for name, update in ways.items():
                start = time.perf_counter()
                for _ in range(args.updates):
                    update()
                times[name].append((time.perf_counter() - start) / (args.updates * k) * 1e3)
        ratios = [s / b for s, b in zip(times["separate"], times["batched"])]
        rows[k] = dict(times=times, ratio_median=statistics.median(ratios), ratio_range=[min(ratios), max(ratios)])
    print("\n| K students | separate, ms per student update | batched | separate / batched, median [min, max] |")
    print("| --- | --- | --- | --- |")
    for k, row in rows.items():
        s, b = (statistics.median(row["times"][name]) for name in ("separate", "batched"))
        low, high = row["ratio_range"]
        print(f"| {k} | {s:.2f} | {b:.2f} | {row['ratio_median']:.2f}x [{low:.2f}, {high:.2f}] |")
    out = pathlib.Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(machine=machine, compiled=args.compile, rows=rows), indent=1))
    print(f"-> {out}")


if __name__ == "__main__":
    main()
