"""
The forgetting screen: where does MPO, keeping every transition, lose Env-A after the robot changes?

Pre-registered in ``README.md`` beside this script (candidates, budgets, thresholds, the selection rule) before any
run. Per robot and seed, MPO learns Env-A once (``stage1``); each candidate change of that robot continues from that
Stage-1 (agent, optimisers, buffer) into its own Env-B for three times as long (``candidate``). The measurement at the
end: the Env-A return at the end against the Stage-1 agent's (last evaluations, the same seeded episodes every
evaluation), the frozen Stage-1 agent and the end agent on the same ten episodes, and the critic's overestimation of
Env-A data against its Monte-Carlo return through Stage 2.

One seed is one command that runs the pre-registered order and skips what is done; a killed command continues from
its last part (``PART`` steps)::

    OMP_NUM_THREADS=1 python benchmarks/studies/forgetting_screen/screen.py queue --seed 0 --runs /work/runs
    python benchmarks/studies/forgetting_screen/screen.py progress --runs /work/runs
    python benchmarks/studies/forgetting_screen/screen.py stage1 --runs /work/runs   # results/stage1: learnt or not
    python benchmarks/studies/forgetting_screen/screen.py report      # screen.csv, results.md, screen.png

Small results go to ``results/<candidate>/seed_<k>/`` beside this script; buffers and agents stay in ``--runs``.
"""

import argparse
import csv
import dataclasses
import json
import math
import pathlib
import time
from collections.abc import Sequence
from typing import Any, Optional

import numpy as np

from sb3_lifelong.experiments import collection, scores

STUDY = pathlib.Path(__file__).resolve().parent
RESULTS = STUDY / "results"


@dataclasses.dataclass(frozen=True)
class Robot:
    """A robot of the screen: its environment, its Env-A budget and what counts as Env-A learnt."""

    env_id: str
    env_a_steps: int
    threshold: float


#: the robots, in the order a seed runs them
ROBOTS = {
    "cheetah": Robot("HalfCheetah-v5", 60_000, 1500.0),
    "hopper": Robot("Hopper-v5", 100_000, 1000.0),
    "walker": Robot("Walker2d-v5", 100_000, 1000.0),
}
#: the candidate changes (Env-A is the nominal robot), in the order a seed runs them
CANDIDATES: dict[str, tuple[str, dict[str, float]]] = {
    "cheetah_back_reversed": ("cheetah", {"leg_motor_scale": -1.0}),
    "cheetah_back_knee_locked": ("cheetah", {"joint_lock": 1.0}),
    "cheetah_back_weak": ("cheetah", {"leg_motor_scale": 0.25}),
    "cheetah_hip": ("cheetah", {"hip_deformation": 1.0}),
    "hopper_reversed": ("hopper", {"leg_motor_scale": -1.0}),
    "hopper_feet": ("hopper", {"foot_scale": 2.0}),
    "walker_right_reversed": ("walker", {"leg_motor_scale": -1.0}),
    "walker_right_knee_locked": ("walker", {"joint_lock": 1.0}),
    "walker_soft_ground": ("walker", {"ground_softness": 0.1}),
}
SEEDS = (0, 1)
#: amendment 1 (README, pre-registered before its runs): seeds 2 and 3 of the two HalfCheetah candidates measured first;
#: such a candidate is testable when Env-A was learnt on two of its four seeds (the reading below, unchanged)
AMENDED_SEEDS = {"cheetah_back_reversed": (0, 1, 2, 3), "cheetah_back_knee_locked": (0, 1, 2, 3)}


def candidate_seeds(candidate: str) -> tuple[int, ...]:
    """:return: the seeds a candidate is read on (the registered two, or the amendment's four)"""
    return AMENDED_SEEDS.get(candidate, SEEDS)


ENV_B_FACTOR = 3  # Env-B runs three times as long as Env-A
EVAL_FREQ = 5_000
EVAL_EPISODES = 5  # per evaluation and environment, the same seeded episodes every time
LAST = 5  # evaluations in a last-k mean
SAME_EPISODES = 10  # episodes of the frozen-against-end comparison
MAX_SPREAD = 0.2  # Env-A steady: sd / mean of the last LAST Env-A evaluations before the switch
FORGETS = 0.8  # a seed forgets when the end's Env-A last-k mean is at most this share of the Stage-1 agent's
PART = 20_000  # steps per part of a collection: a killed command loses at most this much


def preset(candidate: str) -> Any:
    """The collection of one candidate: the ``cpu`` preset's collector on the candidate's robot and change."""
    from sb3_lifelong.experiments.presets import load_presets

    robot_name, change = CANDIDATES[candidate]
    robot = ROBOTS[robot_name]
    hopper_hip = load_presets(STUDY.parent / "paper_cpu" / "presets.py")["cpu_hopper_hip"]  # the collector it ran with
    return dataclasses.replace(
        hopper_hip,
        env_id=robot.env_id,
        stages=({}, dict(change)),
        stage_steps=(robot.env_a_steps, ENV_B_FACTOR * robot.env_a_steps),
        eval_freq=EVAL_FREQ,
        eval_episodes=EVAL_EPISODES,
        env_a_learnt=robot.threshold,
        max_switch_spread=MAX_SPREAD,
        students=(),
        online=False,
        note=f"forgetting screen, {candidate}",
    )


def first_candidate(robot: str) -> str:
    return next(name for name, (r, _) in CANDIDATES.items() if r == robot)


def collect_in_parts(settings: Any, seed: int, run_dir: pathlib.Path, stop: int) -> None:
    """Collect to ``stop`` steps in parts of ``PART`` (the runner's ``collect_in_parts``)."""
    collection.collect_in_parts(settings, seed, run_dir, stop, PART, log=lambda message: print(message, flush=True))


def stage1_dir(runs: pathlib.Path, robot: str, seed: int) -> pathlib.Path:
    return runs / "forgetting_screen" / robot / "stage1" / f"seed_{seed}"


def run_stage1(robot: str, seed: int, runs: pathlib.Path) -> pathlib.Path:
    """MPO learns Env-A of ``robot`` (the Stage-1 every candidate of the robot continues from)."""
    run_dir = stage1_dir(runs, robot, seed)
    if not (run_dir / "collect" / "stage1.zip").exists():
        collect_in_parts(preset(first_candidate(robot)), seed, run_dir, ROBOTS[robot].env_a_steps)
    return run_dir


def run_candidate(candidate: str, seed: int, runs: pathlib.Path, results: pathlib.Path) -> Optional[dict[str, Any]]:
    """One candidate's Env-B from its robot's Stage-1, then its measurement (skipped when measured)."""
    from sb3_lifelong.experiments.branching import adopt_stage1

    out = results / candidate / f"seed_{seed}" / "measure.json"
    if out.exists():
        return json.loads(out.read_text())
    robot = CANDIDATES[candidate][0]
    source = run_stage1(robot, seed, runs)
    settings = preset(candidate)
    run_dir = runs / "forgetting_screen" / candidate / f"seed_{seed}"
    if not run_dir.exists():
        adopt_stage1(settings, source, run_dir)
    start = time.perf_counter()
    collect_in_parts(settings, seed, run_dir, sum(settings.stage_steps))
    measured = measure(candidate, seed, run_dir)
    measured["measure_seconds"] = time.perf_counter() - start
    out.parent.mkdir(parents=True, exist_ok=True)
    for name in ("eval.csv", "q_sources.csv"):
        (out.parent / name).write_text((run_dir / "collect" / name).read_text())
    out.write_text(json.dumps(measured, indent=1))
    print(f"{candidate} seed {seed}: forgetting ratio {measured['forgetting_ratio']:.3f} -> {out}", flush=True)
    return measured


def last_evaluations(eval_csv: pathlib.Path, env: str, upto: Optional[int], count: int = LAST) -> list[float]:
    """:return: the mean returns of the last ``count`` evaluations in ``env`` at timesteps <= ``upto``"""
    return scores.last_evaluations(eval_csv, env, upto, count)


def stage1_level(evals: Sequence[float], threshold: float) -> tuple[float, float, bool]:
    """
    :param evals: the Stage-1 agent's last Env-A evaluations
    :param threshold: the robot's return at which Env-A counts as learnt
    :return: their mean, their spread (sd / mean), and whether Env-A was learnt (README: at least the threshold, a
        spread of at most ``MAX_SPREAD``)
    """
    return scores.learnt_level(evals, threshold, MAX_SPREAD)


def stage1_reading(eval_csv: pathlib.Path, switch: int, threshold: float) -> dict[str, Any]:
    """
    Whether Env-A was learnt at the switch, by the screen's rule (the runner's ``switch_reading``): the mean of the
    last ``LAST`` Env-A evaluations up to ``switch`` at least ``threshold``, their spread at most ``MAX_SPREAD``.

    :return: ``evals``, ``mean``, ``spread``, ``threshold``, ``max_spread``, ``learnt``
    """
    return scores.switch_reading(eval_csv, switch, threshold, MAX_SPREAD, LAST)


def measure(candidate: str, seed: int, run_dir: pathlib.Path) -> dict[str, Any]:
    """The pre-registered measurements of one candidate and seed (README, "What is measured")."""
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.experiments.branching import measure_agent

    settings = preset(candidate)
    robot_name, change = CANDIDATES[candidate]
    robot = ROBOTS[robot_name]
    switch, end = settings.stage_steps[0], sum(settings.stage_steps)
    eval_csv = run_dir / "collect" / "eval.csv"
    stage1 = last_evaluations(eval_csv, "Env-A", switch)
    end_a = last_evaluations(eval_csv, "Env-A", None)
    end_b = last_evaluations(eval_csv, "Env-B", None)
    stage1_mean, spread, learnt = stage1_level(stage1, robot.threshold)
    end_mean = float(np.mean(end_a))
    out: dict[str, Any] = dict(
        candidate=candidate, robot=robot_name, change=change, seed=seed, switch=switch, end=end,
        stage1_evals_env_a=stage1, end_evals_env_a=end_a, end_evals_env_b=end_b,
        stage1_env_a=stage1_mean, end_env_a=end_mean, end_env_b=float(np.mean(end_b)), stage1_spread=spread,
        env_a_learnt=learnt, forgetting_ratio=end_mean / stage1_mean if stage1_mean else math.nan,
    )  # fmt: skip
    out["forgets"] = bool(out["forgetting_ratio"] <= FORGETS) if learnt else None
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        for name in ("stage1", "final"):
            out.update(measure_agent(name, run_dir, buffer, settings, seed, SAME_EPISODES))
    out["same_episode_ratio"] = out["final_same_episodes_Env-A"] / out["stage1_same_episodes_Env-A"]
    out["zero_shot_env_b"] = out["stage1_same_episodes_Env-B"]
    q_csv = run_dir / "collect" / "q_sources.csv"
    out["overestimation_env_a_switch"] = scores.overestimation_at(q_csv, "Env-A", switch)
    out["overestimation_env_a_end"] = scores.overestimation_at(q_csv, "Env-A", end)
    return out


def queue(args: argparse.Namespace) -> None:
    """One seed: every robot's Stage-1 and candidates, in the pre-registered order (what is measured is skipped)."""
    runs, results = pathlib.Path(args.runs), pathlib.Path(args.results)
    names = args.candidates or list(CANDIDATES)
    for candidate in names:
        run_candidate(candidate, args.seed, runs, results)


def progress(args: argparse.Namespace) -> list[str]:
    """Where each candidate and seed stands."""
    runs, results = pathlib.Path(args.runs), pathlib.Path(args.results)
    lines = []
    for candidate in CANDIDATES:
        for seed in candidate_seeds(candidate):
            if (results / candidate / f"seed_{seed}" / "measure.json").exists():
                state = "measured"
            else:
                run_dir = runs / "forgetting_screen" / candidate / f"seed_{seed}"
                robot = CANDIDATES[candidate][0]
                at = collection.paused_at(run_dir) if run_dir.exists() else collection.paused_at(stage1_dir(runs, robot, seed))
                state = f"paused at {at:,}" if at else "not started"
            lines.append(f"{candidate:28s} seed {seed}: {state}")
    print("\n".join(lines))
    return lines


# ------------------------------------------------------------------------------------------------- the report
SCREEN_COLUMNS = [
    "candidate", "seed", "env_a_learnt", "forgetting_ratio", "robot", "change", "stage1_env_a", "stage1_spread",
    "end_env_a", "same_episode_ratio", "stage1_same_episodes_Env-A", "final_same_episodes_Env-A", "zero_shot_env_b",
    "end_env_b", "overestimation_env_a_switch", "overestimation_env_a_end", "forgets",
]  # fmt: skip


def measured_rows(results: pathlib.Path) -> list[dict[str, Any]]:
    rows = []
    for candidate in CANDIDATES:
        for seed in candidate_seeds(candidate):
            path = results / candidate / f"seed_{seed}" / "measure.json"
            if path.exists():
                rows.append(json.loads(path.read_text()))
    return rows


def candidate_verdict(
    rows: list[dict[str, Any]], seeds: Sequence[int] = SEEDS, stage1_learnt: Optional[dict[int, bool]] = None
) -> tuple[str, float]:
    """
    The pre-registered reading of one candidate's seeds.

    :param rows: the candidate's measured seeds
    :param seeds: the seeds it is read on (:func:`candidate_seeds`)
    :param stage1_learnt: seed -> whether Env-A was learnt at the switch, for the seeds whose Stage-1 has ended
        (:func:`stage1_readings`). A seed not measured yet whose Stage-1 did not learn Env-A cannot count, whatever
        its Env-B shows: the verdict does not wait for it. Without this, every seed must be measured.

    :return: the verdict (``forgets``, ``does not forget``, ``mixed``, ``not testable``, ``pending``) and the mean
        forgetting ratio over the seeds where Env-A was learnt (NaN when none)
    """
    known = stage1_learnt or {}
    learnt = [row for row in rows if row["env_a_learnt"]]
    mean = float(np.mean([row["forgetting_ratio"] for row in learnt])) if learnt else math.nan
    measured = {row["seed"] for row in rows}
    waiting = [seed for seed in seeds if seed not in measured and known.get(seed) is not False]  # may still count
    if len(learnt) + len(waiting) < 2:
        return "not testable", mean
    if waiting:
        return "pending", mean
    if all(row["forgets"] for row in learnt):
        return "forgets", mean
    if not any(row["forgets"] for row in learnt):
        return "does not forget", mean
    return "mixed", mean


def stage1_readings(results: pathlib.Path) -> dict[str, dict[int, bool]]:
    """:return: robot -> seed -> whether Env-A was learnt, from the Stage-1 records (``results/stage1``)"""
    found: dict[str, dict[int, bool]] = {}
    for path in sorted((results / "stage1").glob("*/seed_*.json")):
        record = json.loads(path.read_text())
        found.setdefault(path.parent.name, {})[int(record["seed"])] = bool(record["learnt"])
    return found


def record_stage1(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Read every finished Stage-1 in ``--runs`` by the registered rule and keep it in ``results/stage1`` (with its
    evaluations), so that the report can tell a seed that cannot count from one that is still running."""
    runs, results = pathlib.Path(args.runs), pathlib.Path(args.results)
    records = []
    for robot_name, robot in ROBOTS.items():
        for seed in sorted({s for c, (r, _) in CANDIDATES.items() if r == robot_name for s in candidate_seeds(c)}):
            run_dir = stage1_dir(runs, robot_name, seed)
            if not (run_dir / "collect" / "stage1.zip").exists():
                continue
            evals = last_evaluations(run_dir / "collect" / "eval.csv", "Env-A", robot.env_a_steps)
            mean, spread, learnt = stage1_level(evals, robot.threshold)
            record = dict(robot=robot_name, seed=seed, evals=evals, mean=mean, spread=spread, learnt=learnt)
            out = results / "stage1" / robot_name / f"seed_{seed}.json"
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(record, indent=1) + "\n")
            (out.parent / f"seed_{seed}_eval.csv").write_text((run_dir / "collect" / "eval.csv").read_text())
            records.append(record)
            print(f"{robot_name} seed {seed}: Env-A {'learnt' if record['learnt'] else 'not learnt'} "
                  f"({mean:.0f}, spread {spread:.2f})")  # fmt: skip
    return records


def select(verdicts: dict[str, tuple[str, float]]) -> tuple[Optional[str], str]:
    """The selection rule (README): the forgetting candidate with the lowest mean ratio, else the closest one."""
    cost = {robot: i for i, robot in enumerate(ROBOTS)}

    def key(name: str) -> tuple[float, int]:
        return (round(verdicts[name][1] / 0.05), cost[CANDIDATES[name][0]])  # ratios within 0.05: the cheaper robot

    if any(verdict == "pending" for verdict, _ in verdicts.values()):
        return None, "pending: not every candidate has both seeds"
    forgetting = [name for name, (verdict, _) in verdicts.items() if verdict == "forgets"]
    if forgetting:
        return min(forgetting, key=key), "forgets"
    testable = [name for name, (verdict, mean) in verdicts.items() if verdict != "not testable" and not math.isnan(mean)]
    if testable:
        return min(testable, key=key), "closest (no candidate forgets)"
    return None, "no candidate testable"


def fmt(values: list[float], digits: int = 2) -> str:
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{np.mean(values):.{digits}f} +- {np.std(values, ddof=1):.{digits}f}"


def random_returns_of(candidate: str, results: pathlib.Path) -> dict[str, float]:
    """
    A uniformly random policy's return in each environment of a candidate (the zero of the field's normalised
    scores), measured once and kept in ``results/<candidate>/random_returns.json``.
    """
    from sb3_lifelong.experiments.report import random_returns

    settings = preset(candidate)
    return random_returns(results / candidate, {**settings.describe(), "env_names": list(settings.env_names)})


def field_terms(row: dict[str, Any], random: dict[str, float]) -> dict[str, float]:
    """
    One learnt seed's forgetting and transfer in the continual-learning field's terms
    (:func:`~sb3_lifelong.evaluation.continual.continual_metrics`), from the screen's own last-``LAST`` means: ``R[0]``
    at the switch (Env-A: the Stage-1 level; Env-B: the frozen Stage-1 agent on the same ``SAME_EPISODES`` Env-B
    episodes, as Stage 1 evaluated Env-A only) and ``R[1]`` at the end.
    """
    from sb3_lifelong.evaluation.continual import continual_metrics

    matrix = [[row["stage1_env_a"], row["zero_shot_env_b"]], [row["end_env_a"], row["end_env_b"]]]
    found = continual_metrics(matrix, [random["Env-A"], random["Env-B"]])
    return dict(
        average_performance=found["average_performance"],
        forgetting_env_a=found["forgetting"][0],
        backward_transfer=found["backward_transfer"],
        forward_transfer=found["forward_transfer"],
    )


def field_terms_lines(rows: list[dict[str, Any]], results: pathlib.Path) -> list[str]:
    """:return: the results' section of the field's terms, for every seed that learnt Env-A"""
    from sb3_lifelong.evaluation.continual import NORMALISATION

    learnt = [r for r in rows if r["env_a_learnt"]]
    if not learnt:
        return []
    lines = [
        "",
        "## In the continual-learning field's terms (seeds that learnt Env-A)",
        "",
        f"As Continual World, CORA and GEM report them, from R[i][j] (the return in environment j at the end of stage i, "
        f"last-{LAST} means as above; Env-B before its first step: the frozen Stage-1 agent's zero-shot return on "
        f"{SAME_EPISODES} episodes, as Stage 1 evaluated Env-A only). Normalised per "
        f"environment: {NORMALISATION}; the reference is the seed's best end-of-stage return there, the random policy's "
        "returns are measured once per candidate (`<candidate>/random_returns.json`). Forgetting of Env-A: its score at "
        "the switch minus at the end (positive: forgotten); backward transfer is its negative; forward transfer: the "
        "Env-B score before training in it.",
        "",
        "| candidate | seed | random policy: Env-A, Env-B | average performance | forgetting of Env-A "
        "| backward transfer | forward transfer |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in learnt:
        random = random_returns_of(row["candidate"], results)
        terms = field_terms(row, random)
        lines.append(
            f"| {row['candidate']} | {row['seed']} | {random['Env-A']:.0f}, {random['Env-B']:.0f} | "
            + " | ".join(f"{terms[k]:+.2f}" for k in ("average_performance", "forgetting_env_a", "backward_transfer"))
            + f" | {terms['forward_transfer']:+.2f} |"
        )
    return lines


def report(args: argparse.Namespace) -> None:
    results = pathlib.Path(args.results)
    rows = measured_rows(results)
    with open(results / "screen.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=SCREEN_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({**row, "change": json.dumps(row["change"])})
    stage1 = stage1_readings(results)
    verdicts = {
        c: candidate_verdict([r for r in rows if r["candidate"] == c], candidate_seeds(c), stage1.get(CANDIDATES[c][0]))
        for c in CANDIDATES
    }
    chosen, why = select(verdicts)
    lines = [
        "# Forgetting screen: results",
        "",
        "Generated by `python benchmarks/studies/forgetting_screen/screen.py report` from `results/*/seed_*/measure.json`.",
        f"Forgetting ratio: the end's Env-A last-{LAST} mean over the Stage-1 agent's (same seeded episodes every "
        f"evaluation); a seed forgets at <= {FORGETS}. Same-episode ratio: the end agent over the frozen Stage-1 agent "
        f"on the same {SAME_EPISODES} Env-A episodes.",
        "",
        "| candidate | change | seeds | Env-A learnt | Stage-1 Env-A | forgetting ratio (per seed) | same-episode ratio "
        "| zero-shot Env-B -> end Env-B | overestimation of Env-A data, switch -> end | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for candidate, (_, change) in CANDIDATES.items():
        mine = [r for r in rows if r["candidate"] == candidate]
        verdict, _ = verdicts[candidate]
        if not mine:
            lines.append(f"| {candidate} | `{json.dumps(change)}` | 0 | | | | | | | {verdict} |")
            continue
        learnt = "".join("y" if r["env_a_learnt"] else "n" for r in mine)
        ratios = ", ".join(f"{r['forgetting_ratio']:.2f}" for r in mine)
        lines.append(
            f"| {candidate} | `{json.dumps(change)}` | {len(mine)} | {learnt} | {fmt([r['stage1_env_a'] for r in mine], 0)} "
            f"| {ratios} | {fmt([r['same_episode_ratio'] for r in mine])} "
            f"| {fmt([r['zero_shot_env_b'] for r in mine], 0)} -> {fmt([r['end_env_b'] for r in mine], 0)} "
            f"| {fmt([r['overestimation_env_a_switch'] for r in mine], 0)} -> "
            f"{fmt([r['overestimation_env_a_end'] for r in mine], 0)} | {verdict} |"
        )
    lines += ["", f"**Selection:** {chosen or '-'} ({why})."]
    lines += field_terms_lines(rows, results)
    (results / "results.md").write_text("\n".join(lines) + "\n")
    figure(rows, results / "screen.png")
    print("\n".join(lines))


def figure(rows: list[dict[str, Any]], path: pathlib.Path) -> None:
    """Every candidate's collection: Env-A and Env-B returns per seed, the switch and the Stage-1 agent's level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [c for c in CANDIDATES if any(r["candidate"] == c for r in rows)]
    if not names:
        return
    columns = min(3, len(names))
    grid_rows = math.ceil(len(names) / columns)
    fig, axes = plt.subplots(grid_rows, columns, figsize=(5.4 * columns, 3.6 * grid_rows + 0.6), squeeze=False)
    colours = {"Env-A": "tab:blue", "Env-B": "tab:orange"}
    for ax, candidate in zip(axes.flat, names):
        for row in (r for r in rows if r["candidate"] == candidate):
            curve = path.parent / candidate / f"seed_{row['seed']}" / "eval.csv"
            with open(curve, newline="") as handle:
                evals = list(csv.DictReader(handle))
            styles = ("-", "--", "-.", (0, (1, 1)))
            learnt = row["env_a_learnt"]
            for env, colour in colours.items():
                points = sorted((int(e["timesteps"]), float(e["mean_reward"])) for e in evals if e["env"] == env)
                if points:
                    label = f"{env}, seed {row['seed']}" + ("" if learnt else " (not learnt)")
                    ax.plot(*zip(*points), linestyle=styles[row["seed"] % len(styles)], color=colour,
                            lw=1.2 if learnt else 0.9, alpha=1.0 if learnt else 0.4, label=label)  # fmt: skip
            if learnt:
                ax.hlines(row["stage1_env_a"], row["switch"], row["end"], colors="grey", linestyles=":", lw=1)
            ax.axvline(row["switch"], color="k", lw=0.8)
        ax.set_title(f"{candidate}  {json.dumps(CANDIDATES[candidate][1])}", fontsize=9)
        ax.set_xlabel("environment steps")
        ax.set_ylabel("return")
        ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.22), ncol=2, frameon=False)
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    fig.suptitle(
        "MPO through Env-A then Env-B\n(vertical line: the switch; grey dotted: a learnt Stage-1 agent's Env-A level; faint: "
        "Env-A not learnt)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("queue", "progress", "stage1", "report"):
        command = sub.add_parser(name)
        command.add_argument("--results", default=str(RESULTS), help="where the small results go")
        if name != "report":
            command.add_argument("--runs", default="runs", help="where buffers and agents go")
        if name == "queue":
            command.add_argument("--seed", type=int, required=True)
            command.add_argument("--candidates", nargs="*", choices=list(CANDIDATES), help="default: all, in order")
    args = parser.parse_args()
    {"queue": queue, "progress": progress, "stage1": record_stage1, "report": report}[args.command](args)


if __name__ == "__main__":
    main()
