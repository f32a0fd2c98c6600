"""
Benchmarks of sb3_lifelong.envs: DynamicsSchedule overhead per step, cost of a parameter change, OP3 env speed,
and how much the paper's presets hurt a fixed open-loop OP3 gait (for a policy *trained* on the default robot see
``op3_trained_presets.py``).

Usage (one core, as the results were made)::

    OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 MENAGERIE_ROOT=../shared/menagerie \
        python benchmarks/speed/bench_envs.py --steps 20000 --repeats 3 --out benchmarks/results/speed/envs.md
"""

import argparse
import os
import sys
import time
from functools import partial
from typing import Callable, Dict, List, Optional, Tuple

import gymnasium as gym
import numpy as np

from sb3_lifelong.envs import OP3_WALK_ID, PAPER_STAGES, DynamicsSchedule, LinearRamp


def steps_per_second(make: Callable[[], gym.Env], steps: int, repeats: int) -> float:
    """Best of ``repeats`` runs of ``steps`` random-action steps (resets included)."""
    return max(interleaved([make], steps, repeats)[0])


def interleaved(makers: List[Callable[[], gym.Env]], steps: int, repeats: int) -> List[List[float]]:
    """
    Steps/s of several envs measured in alternating blocks of ``steps`` steps (same actions), so that load changes
    on a shared machine hit all of them alike. Returns every block's rate per env.
    """
    envs = [make() for make in makers]
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(1000, *envs[0].action_space.shape)).astype(envs[0].action_space.dtype)
    for env in envs:
        env.reset(seed=0)
    rates: List[List[float]] = [[] for _ in envs]
    counters = [0 for _ in envs]
    for _ in range(repeats):
        for k, env in enumerate(envs):
            start = time.perf_counter()
            for _ in range(steps):
                _, _, terminated, truncated, _ = env.step(actions[counters[k] % 1000])
                counters[k] += 1
                if terminated or truncated:
                    env.reset()
            rates[k].append(steps / (time.perf_counter() - start))
    for env in envs:
        env.close()
    return rates


def make_wrapped(env_id: str, kwargs: Dict) -> gym.Env:
    return DynamicsSchedule(gym.make(env_id), **kwargs)


def overhead(raw: List[float], wrapped: List[float]) -> Tuple[float, float]:
    """Median over paired blocks of the relative overhead and of the added microseconds per step."""
    r, w = np.array(raw), np.array(wrapped)
    return float(np.median(r / w - 1)), float(np.median(1e6 / w - 1e6 / r))


def change_cost(make: Callable[[], gym.Env], settings: List[Dict[str, float]], repeats: int = 20) -> float:
    """Median seconds of one ``set_params(..., immediate=True)`` cycling through ``settings``."""
    env = make()
    assert isinstance(env, DynamicsSchedule)
    env.reset(seed=0)
    for s in settings:  # warm caches (recompiled variants are cached per value)
        env.set_params(s, immediate=True)
    times = []
    for i in range(repeats * len(settings)):
        start = time.perf_counter()
        env.set_params(settings[i % len(settings)], immediate=True)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def recompile_cost(make: Callable[[], gym.Env], value: float, repeats: int = 3) -> float:
    """Median seconds of a foot_scale change that compiles the model again (cache cleared)."""
    env = make()
    assert isinstance(env, DynamicsSchedule)
    times = []
    for i in range(repeats):
        env.editor._compiled.clear()
        start = time.perf_counter()
        env.set_params(foot_scale=value + 0.01 * i, immediate=True)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--pairs", type=int, default=50, help="raw/wrapped block pairs for the overhead")
    parser.add_argument("--out", type=str, default=None)
    parser.add_argument("--gait-only", action="store_true", help="only the fixed open-loop gait table of the OP3 presets")
    parser.add_argument("--skip-speed", action="store_true", help="skip the overhead, change-cost and speed tables")
    args = parser.parse_args()
    lines = [f"# sb3_lifelong.envs benchmark\n\nCommand: `{' '.join(['python', *sys.argv])}`\n"]
    lines += gait_table()
    if args.gait_only:
        write(lines, args.out)
        return
    lines.append(f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}, random actions.\n")

    if not args.skip_speed:
        speed_tables(args, lines)
    write(lines, args.out)


def speed_tables(args: argparse.Namespace, lines: List[str]) -> None:
    lines.append(
        f"## Wrapper overhead per step\n\nRaw and wrapped env stepped in alternating blocks of 200 steps "
        f"({args.pairs} pairs); medians over the pairs.\n\n"
        "| env | raw steps/s | wrapped steps/s | overhead | added us/step |\n"
        "| --- | --- | --- | --- | --- |"
    )
    configs = {
        "stages (2, switch at 10^9)": dict(stages=[{}, {"gravity": 5.0}], switch_at=[10**9]),
        "stages + append_params": dict(stages=[{}, {"gravity": 5.0}], switch_at=[10**9], append_params=True),
        # a value that changes every step but leaves the simulation (and its cost) practically unchanged
        "LinearRamp mass_scale 1 -> 1.001, mid-episode (re-applied every step)": dict(
            schedules={"mass_scale": LinearRamp(1.0, 1.001, 0, 10**9)}, mid_episode=True
        ),
    }
    for env_id in ["HalfCheetah-v5", "Walker2d-v5", "Humanoid-v5"]:
        for name, kwargs in configs.items():
            makers = [partial(gym.make, env_id), partial(make_wrapped, env_id, kwargs)]
            rates = interleaved(makers, 200, args.pairs)
            rel, added = overhead(rates[0], rates[1])
            raw, wrapped = float(np.median(rates[0])), float(np.median(rates[1]))
            line = f"| {env_id}, {name} | {raw:.0f} | {wrapped:.0f} | {100 * rel:+.1f} % | {added:+.0f} |"
            lines.append(line)
            print(line, flush=True)

    lines.append("\n## Cost of one parameter change\n\n| env | change | ms |\n| --- | --- | --- |")
    op3 = lambda: DynamicsSchedule(gym.make(OP3_WALK_ID))  # noqa: E731
    walker = lambda: DynamicsSchedule(gym.make("Walker2d-v5"))  # noqa: E731
    rows = [
        ("Walker2d-v5", "friction / ground_softness (field edit + mj_setConst)", change_cost(walker, [{"friction": 0.3}, {}])),
        ("Walker2d-v5", "hip_deformation (field edit + mj_setConst)", change_cost(walker, [{"hip_deformation": 0.3}, {}])),
        ("Walker2d-v5", "foot_scale, feet with mass: recompile (MjSpec)", recompile_cost(walker, 1.3)),
        ("Walker2d-v5", "foot_scale, recompiled variant cached", change_cost(walker, [{"foot_scale": 1.3}, {}])),
        ("OP3", "hip_deformation (field edit + mj_setConst)", change_cost(op3, [{"hip_deformation": 0.3}, {}])),
        ("OP3", "foot_scale, massless feet (field edit)", change_cost(op3, [{"foot_scale": 1.6}, {}])),
    ]
    env = op3()
    start = time.perf_counter()
    env.editor.handle.make_spec().compile()
    rows.append(("OP3", "for comparison: compiling the OP3 spec once", time.perf_counter() - start))
    for env_id, what, seconds in rows:
        lines.append(f"| {env_id} | {what} | {1e3 * seconds:.3f} |")
        print(lines[-1], flush=True)

    lines.append(
        "\n## OP3 env speed (50 Hz control, 10 physics steps per env step)\n\nBoth measured in alternating blocks of 200 "
        f"steps ({args.pairs} pairs), medians.\n\n| env | steps/s |\n| --- | --- |"
    )
    names = ["OP3Walk-v0", "OP3Walk-v0 in DynamicsSchedule, hip_0.3 + append_params"]
    makers = [partial(gym.make, OP3_WALK_ID), partial(make_wrapped, OP3_WALK_ID, dict(stages=["hip_0.3"], append_params=True))]
    for name, rates in zip(names, interleaved(makers, 200, args.pairs)):
        lines.append(f"| {name} | {np.median(rates):.0f} |")
        print(lines[-1], flush=True)


def write(lines: List[str], out: Optional[str]) -> None:
    text = "\n".join(lines) + "\n"
    print(text)
    if out:
        with open(out, "w") as f:
            f.write(text)


def gait_table() -> List[str]:
    """Zero-shot return of the fixed open-loop gait (OP3OpenLoopGait) on each paper preset, 300 steps (6 s)."""
    from sb3_lifelong.envs.op3 import OP3OpenLoopGait

    gait = OP3OpenLoopGait()
    lines = [
        "## OP3 presets vs a fixed open-loop gait (deterministic, 300 steps = 6 s, reset seed 0)\n",
        "| robot | return | change | x travelled (m) | change |",
        "| --- | --- | --- | --- | --- |",
    ]
    base = base_x = None
    for preset in ["default", *PAPER_STAGES]:
        env = DynamicsSchedule(gym.make(OP3_WALK_ID), stages=[preset])
        env.reset(seed=0)
        total = 0.0
        for i in range(300):
            _, reward, terminated, _, info = env.step(gait(i))
            total += float(reward)
            if terminated:
                break
        x = info["x_position"]
        base = total if base is None else base
        base_x = x if base_x is None else base_x
        change = "" if preset == "default" else f"{100 * (total / base - 1):+.1f} %"
        change_x = "" if preset == "default" else f"{100 * (x / base_x - 1):+.1f} %"
        lines.append(f"| {preset} | {total:.1f} | {change} | {x:.3f} | {change_x} |")
        print(lines[-1], flush=True)
    return lines


if __name__ == "__main__":
    main()
