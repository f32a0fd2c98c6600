"""
The imbalance as a dose: does CRR with the indicator transform drop in Env-A as Env-B's share of the batches or
Env-B's reward grows, while a student held close to the data (the exp transform at a fixed effective sample size,
``target_ess``) stays flat? Pre-registered in ``benchmarks/studies/imbalance_dose/README.md`` (design, preconditions,
pass criteria) before any run.

One seed is two commands: the collection (``python -m sb3_lifelong.experiments run --presets $S/presets.py --preset
dose_hopper --seed K --output runs/imbalance_dose_hopper``), then this script's ``run``, which measures the collector
(frozen Stage-1 agent against the end, on the same evaluation episodes; its critic's overestimation per source at the
switch and at the end; the Monte-Carlo value of each source at each reward dose) and trains the eight students on the
seed's buffer (a finished student is skipped when the command is run again). With ``S=benchmarks/studies/imbalance_dose``::

    OMP_NUM_THREADS=1 python $S/imbalance_dose.py screen --robot hopper --seed 0   # at the switch, optional
    OMP_NUM_THREADS=1 python $S/imbalance_dose.py run --robot hopper --seed 0
    python $S/imbalance_dose.py report     # preconditions, claims.csv, tables, the figure, every seed so far
    python $S/imbalance_dose.py same-collection --robot cheetah_hip --seed 0 --runs runs   # a collection
        # run again (after its run directory was lost) against the committed one's Q log: the same training?
    OMP_NUM_THREADS=1 python $S/imbalance_dose.py run --robot cheetah_hip --seed 0 --student-seed 1000 \\
        --students ess_x1_1to5 ess_x1_1to20    # the same students again on the buffer, another student seed
    python $S/imbalance_dose.py replicates --robot cheetah_hip   # each replicate beside the study's student

Small results go to ``$S/results/<robot>/seed_<k>/``; buffers and students stay in ``runs/``.
"""

import argparse
import csv
import dataclasses
import json
import math
import pathlib
import time
from typing import Any, Callable, Optional

import numpy as np

from sb3_lifelong.experiments.branching import adopt_stage1 as adopt
from sb3_lifelong.experiments.branching import measure_agent
from sb3_lifelong.experiments.statistics import t_interval

RESULTS = pathlib.Path(__file__).parent / "results"


#: this study's presets file, as a command line names it
STUDY_PRESETS = "benchmarks/studies/imbalance_dose/presets.py"


def study_preset(name: str) -> Any:
    """:return: the preset ``name``: this study's own (``presets.py`` beside this script) or the package's (``tiny``)"""
    from sb3_lifelong.experiments.presets import PRESETS, load_presets

    return {**PRESETS, **load_presets(pathlib.Path(__file__).parent / "presets.py")}[name]


#: robot -> (the collection's preset, P1's Env-A return threshold)
#: (``tiny``: the tests' smoke run, no threshold)
ROBOTS = {
    "hopper": ("dose_hopper", 1000.0),
    "cheetah": ("dose_cheetah", 1500.0),
    "cheetah_hip": ("dose_cheetah_hip", 1500.0),  # the long Env-B design (README, "Long Env-B")
    "tiny": ("tiny", 0.0),
}
#: robot -> (the commit its collections run from, the commit its students run from): the study's code, fixed
PINNED = {"cheetah_hip": ("f6bda69", "6d063c0")}
#: the seeds pre-registered per robot: a claim stays *pending* while a seed it could still be tested on is missing
PLANNED_SEEDS = {"hopper": (0, 1, 2), "cheetah": (0,), "cheetah_hip": (0, 1, 2), "tiny": (0,)}
#: the conservative student's effective sample size, as a fraction of the batch
TARGET_ESS = 0.9
#: the doses: Env-B reward scale and the Env-A : Env-B sampling share
DOSES = {"x1_1to5": (1.0, (1, 5)), "x3_1to5": (3.0, (1, 5)), "x1_1to20": (1.0, (1, 20))}
BASE_DOSE = "x1_1to5"
#: the students trained on one source's data: the references of the doses
REFERENCES = ("A_only", "B_only")
#: the transforms: the indicator, and exp at a fixed effective sample size
TRANSFORMS = {"ind": dict(advantage_transform="indicator"), "ess": dict(advantage_transform="exp", target_ess=TARGET_ESS)}
#: the score of an evaluated policy: the mean of its last evaluations (students) / of the collector's
LAST_STUDENT_EVALS = 3
LAST_MPO_EVALS = 5
#: the preconditions' thresholds (pre-registered)
A_ONLY_SHARE = 0.5
FORGETTING_SHARE = 0.8
VALUE_GAP = 1.1
MIN_ESS = 0.8
MAX_CLIP = 0.01
#: the change screen: MPO learnt Env-B when its last evaluations are this far above its first after the switch
LEARNT_MARGIN = 1000.0


def student_settings(support: dict[str, float]) -> dict[str, Any]:
    """The eight students of a seed, all with the same categorical support (it holds the x3 rewards): the seven of the
    pre-registration, and ``B_only``, the secondary design's reference."""
    from sb3_lifelong.experiments.presets import Student

    network = {"policy_kwargs": dict(support)}
    students = {"A_only": Student("CRR", {**TRANSFORMS["ind"], **network}, ratio=(1, 0), about="indicator, Env-A only")}
    # the secondary design's reference (README, "Students against the students' reference"): P2s
    students["B_only"] = Student("CRR", {**TRANSFORMS["ind"], **network}, ratio=(0, 1), about="indicator, Env-B only")
    for transform, kwargs in TRANSFORMS.items():
        for dose, (reward, share) in DOSES.items():
            students[f"{transform}_{dose}"] = Student(
                "CRR",
                {**kwargs, **network},
                ratio=share,
                reward_scale=None if reward == 1.0 else {1: reward},
                about=f"{transform}, Env-B reward x{reward:g}, sampled {share[0]}:{share[1]}",
            )
    return students


# ------------------------------------------------------------------------------------------------- the collector
def last_mean(eval_csv: pathlib.Path, env: str, upto: Optional[int], count: int) -> tuple[float, list[float]]:
    """:return: the mean of the last ``count`` evaluations in ``env`` at timesteps <= ``upto``, and those values"""
    rows = [row for row in csv.DictReader(open(eval_csv)) if row["env"] == env]
    rows = [row for row in rows if upto is None or int(row["timesteps"]) <= upto]
    values = [float(row["mean_reward"]) for row in rows[-count:]]
    return float(np.mean(values)), values


def measure_collector(robot: str, seed: int, study: pathlib.Path, episodes: int) -> dict[str, Any]:
    """The collector's side of the preconditions and claims C1, C5; the data's Monte-Carlo value per source."""
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.evaluation.overestimation import discounted_returns

    preset = study_preset(ROBOTS[robot][0])
    run_dir = study / f"seed_{seed}"
    eval_csv = run_dir / "collect" / "eval.csv"
    switch = preset.stage_steps[0]
    out: dict[str, Any] = dict(robot=robot, seed=seed, preset=ROBOTS[robot][0], switch=switch)
    for env in preset.env_names:
        out[f"stage1_last5_{env}"], out[f"stage1_evals_{env}"] = last_mean(eval_csv, env, switch, LAST_MPO_EVALS)
        out[f"end_last5_{env}"], out[f"end_evals_{env}"] = last_mean(eval_csv, env, None, LAST_MPO_EVALS)
    out["same_episodes"] = episodes
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        names = {source: meta.get("name", f"source_{source}") for source, meta in buffer.sources.items()}
        for name in ("stage1", "final"):  # the frozen Stage-1 agent and the end agent on the same evaluation episodes
            out.update(measure_agent(name, run_dir, buffer, preset, seed, episodes))
        columns = buffer.to_d4rl(by_episode=True, normalized_actions=True)
    sources = columns["sources"].reshape(-1)
    for reward in sorted({r for r, _ in DOSES.values()}):
        scale = np.where(sources == 1, reward, 1.0)
        mc = discounted_returns(columns["rewards"].reshape(-1) * scale, columns["terminals"], columns["timeouts"], 0.99)
        for source, name in names.items():
            rows = (sources == source) & mc.valid
            out[f"mc_return_x{reward:g}_{name}"] = float(mc.returns[rows].mean()) if rows.any() else math.nan
    out["reward_range"] = [float(columns["rewards"].min()), float(columns["rewards"].max())]
    out["rows"] = {names[s]: int((sources == s).sum()) for s in names}
    return out


# ------------------------------------------------------------------------------------------------- the students
def summarise_student(directory: pathlib.Path, env_names: tuple[str, ...]) -> dict[str, Any]:
    """A finished student's scores, overestimation per source at the end, and its weights' statistics."""
    out: dict[str, Any] = {}
    for env in env_names:
        out[f"return_{env}"], out[f"evals_{env}"] = last_mean(directory / "eval.csv", env, None, LAST_STUDENT_EVALS)
    q_rows = list(csv.DictReader(open(directory / "q_sources.csv")))
    last = max(int(row["timesteps"]) for row in q_rows)
    for row in q_rows:
        if int(row["timesteps"]) == last and row.get("overestimation"):
            out[f"overestimation_{row['name']}"] = float(row["overestimation"])
            out[f"q_{row['name']}"] = float(row["q_probe"])
    train = list(csv.DictReader(open(directory / "train.csv")))
    late = train[len(train) // 2 :]  # the second half of training
    for key in ("weight_ess", "weight_clip_frac", "beta"):
        values = [float(row[key]) for row in late if row.get(key) not in (None, "")]
        out[key] = float(np.mean(values)) if values else math.nan
    out["seconds"] = json.loads((directory / "done.json").read_text()).get("seconds")
    return out


def screen(args: argparse.Namespace) -> None:
    """
    The collection at the switch, before Env-B's budget is spent: the Stage-1 agent's Env-A return (P1's agent part),
    the same agent in Env-B (the zero-shot drop A -> B), its critic's overestimation on Env-A data, the Env-A data's
    Monte-Carlo value. Works on a collection still running in Env-B (it reads the Stage-1 agent and buffer).
    """
    from sb3_lifelong import LifelongReplayBuffer

    preset = study_preset(ROBOTS[args.robot][0])
    run_dir = pathlib.Path(args.study or pathlib.Path(args.runs) / f"imbalance_dose_{args.robot}") / f"seed_{args.seed}"
    switch = preset.stage_steps[0]
    out: dict[str, Any] = dict(robot=args.robot, seed=args.seed, switch=switch, threshold_P1=ROBOTS[args.robot][1])
    eval_csv = run_dir / "collect" / "eval.csv"
    for env in preset.env_names:
        out[f"stage1_last5_{env}"], out[f"stage1_evals_{env}"] = last_mean(eval_csv, env, switch, LAST_MPO_EVALS)
    out["P1_agent"] = out["stage1_last5_Env-A"] >= ROBOTS[args.robot][1]
    out["same_episodes"] = episodes = 2 * preset.eval_episodes
    with LifelongReplayBuffer.open(run_dir / "buffer_stage1", read_only=True) as buffer:
        out.update(measure_agent("stage1", run_dir, buffer, preset, args.seed, episodes))
        out["stage1_rows"] = int(buffer.size())
    out["zero_shot_drop_A_to_B"] = 1 - out["stage1_same_episodes_Env-B"] / out["stage1_same_episodes_Env-A"]
    results = pathlib.Path(args.results) / args.robot / f"seed_{args.seed}"
    results.mkdir(parents=True, exist_ok=True)
    (results / "screen.json").write_text(json.dumps(out, indent=1))
    copy_collection_curve(run_dir, results)
    print(json.dumps(out, indent=1))


def copy_collection_curve(run_dir: pathlib.Path, results: pathlib.Path) -> None:
    """Keep the collector's evaluations and per-source Q log (small) beside the results: the collection figure is
    drawn from them."""
    (results / "collect_eval.csv").write_text((run_dir / "collect" / "eval.csv").read_text())
    q_log = run_dir / "collect" / "q_sources.csv"
    if q_log.exists():
        (results / "collect_q_sources.csv").write_text(q_log.read_text())


def run(args: argparse.Namespace) -> None:
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.experiments.jobs import value_support
    from sb3_lifelong.experiments.protocol import distill_on_study

    preset_name, _ = ROBOTS[args.robot]
    preset = dataclasses.replace(study_preset(preset_name), distill_steps=args.updates)
    study = pathlib.Path(args.study or pathlib.Path(args.runs) / f"imbalance_dose_{args.robot}")
    output = pathlib.Path(args.students_output or pathlib.Path(args.runs) / f"imbalance_dose_{args.robot}_students")
    results = pathlib.Path(args.results) / args.robot / f"seed_{args.seed}"
    if args.student_seed is not None:  # a replicate: its own students' directory and results, the collector's kept
        output = output.with_name(f"{output.name}_student{args.student_seed}")
        results = pathlib.Path(args.results) / args.robot / "replicates" / f"seed_{args.seed}_student{args.student_seed}"
    results.mkdir(parents=True, exist_ok=True)
    collector_json = results / "collector.json"
    if not collector_json.exists():
        start = time.perf_counter()
        measured = measure_collector(args.robot, args.seed, study, episodes=2 * preset.eval_episodes)
        measured["seconds"] = time.perf_counter() - start
        collector_json.write_text(json.dumps(measured, indent=1))
        copy_collection_curve(study / f"seed_{args.seed}", results)
        print(f"collector measured in {measured['seconds']:.0f} s -> {collector_json}")
    with LifelongReplayBuffer.open(study / f"seed_{args.seed}" / "buffer", read_only=True) as buffer:
        support = value_support(buffer.reward_range(), 0.99, [r for r, _ in DOSES.values()])
    students = student_settings(support)
    chosen = {name: students[name] for name in (args.students or students)}
    about = dict(study="imbalance_dose", robot=args.robot, updates=args.updates, support=support)
    distill_on_study(study, args.seed, output, chosen, preset, student_seed=args.student_seed, about=about)
    rows = {}
    for name in students:
        directory = output / f"seed_{args.seed}" / f"distill_{name}"
        if (directory / "done.json").exists():
            rows[name] = {**summarise_student(directory, preset.env_names), "updates": args.updates}
    (results / "students.json").write_text(json.dumps(dict(support=support, students=rows), indent=1))
    print(f"{len(rows)} students summarised -> {results / 'students.json'}")


# ------------------------------------------------------------------------------------------------- other changes
def branch(args: argparse.Namespace) -> None:
    """
    The Env-B stage of a collection with another change, continued from a finished Stage-1 collection.

    Env-A does not depend on the change: its appended parameter column is the nominal value (0 after normalisation)
    whatever the change is, so the Stage-1 agent (weights, optimisers, dual variables) and the Stage-1 buffer of
    ``--study`` are what a collection with ``--change`` (one parameter) would hold at the switch. They are laid out as
    that collection paused at its switch (:func:`adopt`), which the protocol's ``collect`` continues in Env-B; its
    Env-A return after Env-B is P2's test of the change (the change screen, README).
    """
    from sb3_lifelong.experiments.collection import collect

    change = json.loads(args.change)
    if not isinstance(change, dict) or len(change) != 1:
        raise ValueError(f"--change must be one parameter as JSON, e.g. '{{\"hip_deformation\": 1.0}}', got {args.change}")
    base = study_preset(ROBOTS[args.robot][0])
    if len(base.stages) != 2 or base.stages[0] or len(base.stages[1]) != 1:
        raise ValueError(f"{ROBOTS[args.robot][0]} is not a two-stage collection from the nominal robot with one change")
    preset = dataclasses.replace(base, stages=({}, change), stage_steps=(base.stage_steps[0], args.steps))
    source = pathlib.Path(args.study or pathlib.Path(args.runs) / f"imbalance_dose_{args.robot}") / f"seed_{args.seed}"
    run_dir = pathlib.Path(args.output) / f"seed_{args.seed}"
    adopt(preset, source, run_dir)
    (run_dir / "branch.json").write_text(json.dumps(dict(source=str(source), change=change, steps=args.steps), indent=1))
    start = time.perf_counter()
    collect(preset, args.seed, run_dir)
    (run_dir / "collect" / "done.json").write_text(json.dumps(dict(seconds=time.perf_counter() - start)))
    results = pathlib.Path(args.results) / args.robot / "changes" / pathlib.Path(args.output).name / f"seed_{args.seed}"
    results.mkdir(parents=True, exist_ok=True)
    (results / "branch.json").write_text((run_dir / "branch.json").read_text())
    copy_collection_curve(run_dir, results)
    print(f"branch {change} finished -> {run_dir}; its curve -> {results}")


def adopt_stage1(args: argparse.Namespace) -> None:
    """
    A collection of ``--robot``'s preset, paused at its switch, made of another collection's finished Stage-1
    (:func:`adopt`). The protocol's ``run --preset <preset> --seed K --output <output> --until STEPS`` then continues
    it in Env-B, in parts.
    """
    from sb3_lifelong.experiments.protocol import record_settings

    preset = study_preset(ROBOTS[args.robot][0])
    output = pathlib.Path(args.output)
    run_dir = output / f"seed_{args.seed}"
    if run_dir.exists():
        raise FileExistsError(f"{run_dir} exists: the Stage-1 is adopted into a new seed directory only")
    record_settings(preset, output)
    adopt(preset, pathlib.Path(args.source) / f"seed_{args.seed}", run_dir)
    print(f"{run_dir}: paused at the switch ({preset.stage_steps[0]:,} steps); continue with `python -m "
          f"sb3_lifelong.experiments run --presets {STUDY_PRESETS} --preset {ROBOTS[args.robot][0]} --seed {args.seed} "
          f"--output {output} "
          "--until STEPS`")  # fmt: skip


# ------------------------------------------------------------------------------------------------- the report
def fmt(values: list[float]) -> str:
    mean, std, low, high = t_interval(values)
    if len(values) < 2:
        return f"{mean:.0f} (1 seed)" if values else "-"
    return f"{mean:.0f} +- {std:.0f} [{low:.0f}, {high:.0f}]"


def holds(*conditions: Optional[bool]) -> Optional[bool]:
    """:return: False when one condition failed, else None (pending) when one is not measured yet, else True"""
    if any(condition is False for condition in conditions):
        return False
    return None if any(condition is None for condition in conditions) else True


def seed_preconditions(robot: str, collector: dict[str, Any], students: dict[str, Any]) -> dict[str, Any]:
    """Each precondition of one seed with its measured value: True (held), False (failed), None (pending: the students
    it is measured on have not finished)."""
    threshold = ROBOTS[robot][1]
    reference = collector["stage1_last5_Env-A"]
    p: dict[str, Any] = {"stage1_Env-A": reference}
    a_only = students.get("A_only", {}).get("return_Env-A", math.nan)
    p["A_only_Env-A"] = a_only
    p["P1_agent"] = reference >= threshold
    p["P1"] = holds(p["P1_agent"], None if math.isnan(a_only) else a_only >= A_ONLY_SHARE * reference)
    p["end_Env-A"] = collector["end_last5_Env-A"]
    p["P2"] = collector["end_last5_Env-A"] <= FORGETTING_SHARE * reference
    # the secondary design's P2s: the Env-B data alone does not teach Env-A (pending until both students finished)
    b_only = students.get("B_only", {}).get("return_Env-A", math.nan)
    p["B_only_Env-A"] = b_only
    p["P2s"] = None if math.isnan(a_only) or math.isnan(b_only) else bool(b_only <= FORGETTING_SHARE * a_only)
    for reward in sorted({r for r, _ in DOSES.values()}):
        a, b = collector[f"mc_return_x{reward:g}_Env-A"], collector[f"mc_return_x{reward:g}_Env-B"]
        p[f"gap_x{reward:g}"] = b / a if a > 0 else math.nan
        p[f"P3_x{reward:g}"] = a > 0 and b >= VALUE_GAP * a
    conservative = [name for name in students if name.startswith("ess_")]
    ess = [students[name]["weight_ess"] for name in conservative]
    clip = [students[name]["weight_clip_frac"] for name in conservative]
    p["ess_min"], p["clip_max"] = (min(ess), max(clip)) if ess else (math.nan, math.nan)
    measured = bool(ess) and min(ess) >= MIN_ESS and max(clip) <= MAX_CLIP
    p["P4"] = False if ess and not measured else (True if len(ess) == len(DOSES) else None)
    return p


def report(args: argparse.Namespace) -> None:
    root = pathlib.Path(args.results)
    lines = ["# Results (generated by `python benchmarks/studies/imbalance_dose/imbalance_dose.py report`)", ""]
    claims_rows = []
    for robot in ROBOTS:
        changes = sorted(root.glob(f"{robot}/changes/*/seed_*/collect_eval.csv"))
        if changes:
            lines += change_screen(robot, changes, root)
        screens = sorted(root.glob(f"{robot}/seed_*/screen.json"))
        if screens:
            lines += screen_table(robot, [json.loads(path.read_text()) for path in screens])
        curves = sorted(root.glob(f"{robot}/seed_*/collect_eval.csv"))
        if curves:
            collection_figure(robot, curves, root)
        seeds = sorted(root.glob(f"{robot}/seed_*/collector.json"))
        if not seeds:
            continue
        data = {}
        for path in seeds:
            seed = int(path.parent.name.split("_")[1])
            students_path = path.parent / "students.json"
            students = json.loads(students_path.read_text())["students"] if students_path.exists() else {}
            data[seed] = (json.loads(path.read_text()), students)
        lines += [f"## {robot}: seeds {sorted(data)}", ""]
        lines += collector_table(data)
        lines += student_table(data)
        pre = {seed: seed_preconditions(robot, *data[seed]) for seed in data}
        lines += precondition_table(pre)
        rows = claims(robot, data, pre)
        claims_rows += rows
        lines += ["", "| claim | testable seeds | preconditions held | result | evidence |", "| --- | --- | --- | --- | --- |"]
        lines += [
            f"| {r['claim']} | {r['seeds']} | {r['preconditions_held']} | {r['result']} | {r['evidence']} |" for r in rows
        ]
        lines.append("")
        if any(name not in REFERENCES for _, students in data.values() for name in students):  # not before a dosed student
            figure(robot, data, root)
    with open(root / "claims.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["robot", "claim", "seeds", "preconditions_held", "result", "evidence"])
        writer.writeheader()
        writer.writerows(claims_rows)
    (root / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def screen_table(robot: str, screens: list[dict[str, Any]]) -> list[str]:
    """The collections at the switch: P1's agent part and the zero-shot drop, per seed."""
    lines = [
        f"## {robot}: the collection at the switch (`screen`)",
        "",
        "| seed | Env-A, last 5 Stage-1 evaluations | P1 (agent) | Stage-1 agent in A / in B, same episodes "
        "| zero-shot drop A -> B | overestimation on A at the switch (Q - MC) | MC value of the Env-A data |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for s in sorted(screens, key=lambda s: s["seed"]):
        held = "held" if s["P1_agent"] else f"failed (< {s['threshold_P1']:.0f})"
        lines.append(
            f"| {s['seed']} | {s['stage1_last5_Env-A']:.0f} | {held} | {s['stage1_same_episodes_Env-A']:.0f} / "
            f"{s['stage1_same_episodes_Env-B']:.0f} | {s['zero_shot_drop_A_to_B']:+.0%} "
            f"| {s['stage1_overestimation_Env-A']:+.1f} ({s['stage1_q_Env-A']:.1f} - {s['mc_return_x1_Env-A']:.1f}) "
            f"| {s['mc_return_x1_Env-A']:.1f} |"
        )
    return [*lines, ""]


def collection_figure(robot: str, curves: list[pathlib.Path], root: pathlib.Path) -> None:
    """
    MPO's evaluations in both environments through the collection, one line per seed, the switch marked; below, where
    a seed's ``collect_q_sources.csv`` has them, its critic's overestimation on each environment's data (mean Q minus
    the discounted return that followed in the stored episodes).
    """
    from sb3_lifelong.experiments.style import pyplot

    plt = pyplot()
    import pandas as pd

    preset = study_preset(ROBOTS[robot][0])
    q_logs = [path.with_name("collect_q_sources.csv") for path in curves]
    q_frames = {path: pd.read_csv(path) for path in q_logs if path.exists()}
    q_frames = {path: frame for path, frame in q_frames.items() if frame.get("overestimation", pd.Series()).notna().any()}
    if q_frames:
        fig, (ax, low) = plt.subplots(2, 1, figsize=(7, 6.5), sharex=True, gridspec_kw=dict(height_ratios=[3, 2]))
    else:
        fig, ax = plt.subplots(figsize=(7, 4))
    for index, path in enumerate(curves):
        frame = pd.read_csv(path)
        seed = path.parent.name.split("_")[1]
        style = ("-", "--", ":", "-.")[index % 4]  # one line style per seed, one colour per environment
        for env, color in (("Env-A", "C0"), ("Env-B", "C1")):
            rows = frame[frame["env"] == env]
            label = f"evaluated in {env} (seed {seed})"
            ax.plot(rows["timesteps"], rows["mean_reward"], color=color, ls=style, marker=".", label=label)
    ax.axvline(preset.stage_steps[0], color="k", ls="--", lw=1, label="switch: the robot changes (Env-A -> Env-B)")
    ax.axhline(ROBOTS[robot][1], color="grey", ls=":", lw=1, label="P1: competent Env-A")
    if not q_frames:  # else the panel below names the axis
        ax.set_xlabel("environment steps of the collection")
    ax.set_ylabel("MPO's return (deterministic)")
    settings = [", ".join(f"{k}={v:g}" for k, v in dict(stage).items()) or "default" for stage in preset.stages]
    stages = " -> ".join(f"{name} ({setting})" for name, setting in zip(preset.env_names, settings))
    ax.set_title(f"{robot} ({preset.env_id}): MPO collecting, {stages}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, handlelength=4)  # long enough to show each seed's line style
    if q_frames:
        for index, path in enumerate(curves):
            frame = q_frames.get(path.with_name("collect_q_sources.csv"))
            seed, style = path.parent.name.split("_")[1], ("-", "--", ":", "-.")[index % 4]
            if frame is not None:
                for env, color in (("Env-A", "C0"), ("Env-B", "C1")):
                    rows = frame[(frame["name"] == env) & frame["overestimation"].notna()]
                    label = f"on {env} data (seed {seed})"
                    low.plot(rows["timesteps"], rows["overestimation"], color=color, ls=style, marker=".", label=label)
                continue
            measured = path.with_name("collector.json")
            if not measured.exists():
                continue
            # a seed collected before the per-source log: its points measured afterwards (`run`) on the final buffer by
            # the critics at the switch and at the end (the switch's critic on Env-B data, which came later, is not
            # what the line of a logged seed shows there, so it is left out)
            record = json.loads(measured.read_text())
            switch, end = (preset.stage_steps[0], "stage1"), (sum(preset.stage_steps), "final")
            for env, color, points, when in (("Env-A", "C0", (switch, end), "switch and end"), ("Env-B", "C1", (end,), "end")):
                keys = [f"{moment}_overestimation_{env}" for _, moment in points]
                if all(key in record for key in keys):
                    label = f"on {env} data (seed {seed}; {when} only)"
                    steps = [step for step, _ in points]
                    low.plot(steps, [record[key] for key in keys], color=color, ls="", marker="D", ms=5, label=label)
        low.axvline(preset.stage_steps[0], color="k", ls="--", lw=1)
        low.axhline(0, color="grey", lw=0.8)
        missing = [
            path.parent.name.split("_")[1]
            for path in curves
            if path.with_name("collect_q_sources.csv") not in q_frames and not path.with_name("collector.json").exists()
        ]
        note = f" (not recorded for seed {', '.join(missing)})" if missing else ""
        low.set_title(f"MPO's critic: mean Q minus the data's discounted return{note}", fontsize=9)
        low.set_ylabel("overestimation")
        low.set_xlabel("environment steps of the collection")
        low.grid(alpha=0.3)
        low.legend(fontsize=7, handlelength=4, ncol=2, loc="lower right")  # below the curves, which sit above zero
    fig.tight_layout()
    fig.savefig(root / f"collection_{robot}.png", dpi=110)
    plt.close(fig)


def change_verdict(eval_csv: pathlib.Path, switch: int) -> dict[str, Any]:
    """
    The change screen's criterion (README, "Change screen") on one collection's evaluations: P2 (MPO's Env-A return
    after Env-B against the frozen Stage-1 agent's) and whether MPO learnt Env-B.
    """
    out: dict[str, Any] = {}
    out["stage1_Env-A"], _ = last_mean(eval_csv, "Env-A", switch, LAST_MPO_EVALS)
    out["end_Env-A"], _ = last_mean(eval_csv, "Env-A", None, LAST_MPO_EVALS)
    out["end_step"] = max(int(row["timesteps"]) for row in csv.DictReader(open(eval_csv)))
    first_b = [
        float(r["mean_reward"]) for r in csv.DictReader(open(eval_csv)) if r["env"] == "Env-B" and int(r["timesteps"]) > switch
    ]
    out["first_Env-B"] = first_b[0] if first_b else math.nan
    out["end_Env-B"], _ = last_mean(eval_csv, "Env-B", None, LAST_MPO_EVALS)
    out["ratio_A"] = out["end_Env-A"] / out["stage1_Env-A"]
    out["P2"] = out["ratio_A"] <= FORGETTING_SHARE
    first = out["first_Env-B"]
    # (b) as amended before the end results (README): at least 2x a positive first evaluation, and 1000 above it
    out["learnt_B"] = out["end_Env-B"] >= first + LEARNT_MARGIN and (first <= 0 or out["end_Env-B"] >= 2 * first)
    out["qualifies"] = out["P2"] and out["learnt_B"]
    return out


def change_screen(robot: str, curves: list[pathlib.Path], root: pathlib.Path) -> list[str]:
    """The other changes continued from the same Stage-1 (``branch``): the criterion's table and their curves."""
    from sb3_lifelong.experiments.style import pyplot

    plt = pyplot()
    import pandas as pd

    preset = study_preset(ROBOTS[robot][0])
    switch = preset.stage_steps[0]
    study = sorted(root.glob(f"{robot}/seed_0/collect_eval.csv"))  # the study's own change, for comparison
    named = [(p, json.loads((p.parent / "branch.json").read_text())["change"]) for p in curves]
    named += [(p, dict(preset.stages[1])) for p in study]
    lines = [
        f"## {robot}: the change screen (`branch`, seed 0; criterion in the README)",
        "",
        "| Env-B | steps | Stage-1 in A (last 5) | last in A (last 5) | last / Stage-1 | P2 (<= 0.8) "
        "| first in B -> last in B "
        "| learnt B | qualifies |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharex=True)
    for index, (path, change) in enumerate(named):
        v = change_verdict(path, switch)
        name = ", ".join(f"{k}={x:g}" for k, x in change.items())
        finished = v["end_step"] >= sum(preset.stage_steps)
        done = "" if finished else f" (stopped at {v['end_step'] // 1000}k)"
        so_far = "" if finished else " so far"
        verdict = ("**yes**" if v["qualifies"] else "no") if finished else "undecided (unfinished)"
        lines.append(
            f"| {name}{done} | {v['end_step']:,} | {v['stage1_Env-A']:.0f} | {v['end_Env-A']:.0f} | {v['ratio_A']:.2f} "
            f"| {('held' if v['P2'] else 'failed') + so_far} | {v['first_Env-B']:.0f} -> {v['end_Env-B']:.0f} "
            f"| {('yes' if v['learnt_B'] else 'no') + so_far} | {verdict} |"
        )
        frame = pd.read_csv(path)
        for ax, env in zip(axes, ("Env-A", "Env-B")):
            rows = frame[(frame["env"] == env) & ((frame["timesteps"] > switch) | (env == "Env-A"))]
            ax.plot(rows["timesteps"], rows["mean_reward"], color=f"C{index}", marker=".", label=f"Env-B: {name}")
    stage1 = change_verdict(named[0][0], switch)["stage1_Env-A"]
    axes[0].axhline(stage1, color="k", lw=1, label="frozen Stage-1 agent (last 5)")
    axes[0].axhline(FORGETTING_SHARE * stage1, color="grey", ls=":", lw=1, label="P2: 0.8 x frozen")
    for ax, env in zip(axes, ("Env-A", "Env-B")):
        ax.xaxis.set_major_formatter(lambda x, _: f"{x / 1000:.0f}k")
        ax.axvline(switch, color="k", ls="--", lw=1)
        ax.set_title(f"MPO evaluated in {env}", fontsize=9)
        ax.set_xlabel("environment steps (switch at the dashed line)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("return (deterministic, 5 episodes)")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{robot}: which change does MPO forget Env-A in? (same Stage-1, seed 0)", fontsize=10)
    fig.tight_layout()
    fig.savefig(root / f"change_screen_{robot}.png", dpi=110)
    plt.close(fig)
    return [*lines, ""]


def collector_table(data: dict[int, Any]) -> list[str]:
    lines = ["| seed | Stage-1 in A (last 5) | end in A (last 5) | frozen vs end in A, same episodes | Stage-1 / end in B "
             "| overestimation on A: switch -> end | on B at end | MC value A / B (x1) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for seed, (c, _) in sorted(data.items()):
        same = [c[f"{agent}_same_episodes_{env}"] for env in ("Env-A", "Env-B") for agent in ("stage1", "final")]
        over = [c.get(key, math.nan) for key in ("stage1_overestimation_Env-A", "final_overestimation_Env-A")]
        cells = [
            f"{c['stage1_last5_Env-A']:.0f}",
            f"{c['end_last5_Env-A']:.0f}",
            f"{same[0]:.0f} vs {same[1]:.0f}",
            f"{same[2]:.0f} / {same[3]:.0f}",
            f"{over[0]:+.1f} -> {over[1]:+.1f}",
            f"{c.get('final_overestimation_Env-B', math.nan):+.1f}",
            f"{c['mc_return_x1_Env-A']:.1f} / {c['mc_return_x1_Env-B']:.1f}",
        ]
        lines.append(f"| {seed} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def student_table(data: dict[int, Any]) -> list[str]:
    names = sorted({name for _, students in data.values() for name in students}, key=lambda n: (n not in REFERENCES, n))
    if not names:
        return ["(no student finished yet)", ""]
    lines = ["| student | Env-A return (last 3 evals) | Env-B return | overestimation on A | weight ESS | clip | beta "
             "| per seed (Env-A) |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for name in names:
        have = [(seed, s[name]) for seed, (_, s) in sorted(data.items()) if name in s]
        per_seed = ", ".join(f"{seed}: {row['return_Env-A']:.0f}" for seed, row in have)
        ess = np.mean([row["weight_ess"] for _, row in have])
        clip = np.mean([row["weight_clip_frac"] for _, row in have])
        beta = np.nanmean([row["beta"] for _, row in have]) if any(np.isfinite(row["beta"]) for _, row in have) else math.nan
        over = [row.get("overestimation_Env-A", math.nan) for _, row in have]
        lines.append(
            f"| {name} | {fmt([r['return_Env-A'] for _, r in have])} | {fmt([r['return_Env-B'] for _, r in have])} "
            f"| {np.mean(over):+.1f} | {ess:.2f} | {clip:.3f} | {beta:.2f} | {per_seed} |"
        )
    return [*lines, ""]


def precondition_table(pre: dict[int, dict[str, Any]]) -> list[str]:
    lines = ["| seed | P1 Stage-1 in A | P1 A_only in A | P2 end in A | P2s B_only in A | P3 value gap B/A x1 | x3 "
             "| P4 ESS min / clip max |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    mark = {True: "held", False: "failed", None: "pending"}
    for seed, p in sorted(pre.items()):
        a_only = "no student yet" if math.isnan(p["A_only_Env-A"]) else f"{p['A_only_Env-A']:.0f}"
        ess = "no student yet" if math.isnan(p["ess_min"]) else f"{p['ess_min']:.2f} / {p['clip_max']:.3f}"
        b_only = "no student yet" if math.isnan(p["B_only_Env-A"]) else f"{p['B_only_Env-A']:.0f}"
        lines.append(
            f"| {seed} | {p['stage1_Env-A']:.0f} ({mark[p['P1_agent']]}) | {a_only} ({mark[p['P1']]}) "
            f"| {p['end_Env-A']:.0f} ({mark[p['P2']]}) | {b_only} ({mark[p['P2s']]}) "
            f"| {p['gap_x1']:.2f} ({mark[p['P3_x1']]}) "
            f"| {p['gap_x3']:.2f} ({mark[p['P3_x3']]}) | {ess} ({mark[p['P4']]}) |"
        )
    return [*lines, ""]


class Verdicts:
    """
    The claims' rows of one robot. A claim is tested on the seeds where its preconditions held (>= 2 needed). It is
    *pending* while seeds it could still be tested on are missing (not collected, or their students not finished),
    *not testable* when fewer than 2 seeds can hold its preconditions, and decided early only when a testable seed
    already fails a criterion that every seed must meet.
    """

    def __init__(self, robot: str, data: dict[int, Any], pre: dict[int, dict[str, Any]]) -> None:
        self.robot, self.data, self.pre = robot, data, pre
        self.missing = [seed for seed in PLANNED_SEEDS[robot] if seed not in data]
        self.rows: list[dict[str, Any]] = []

    def row(self, claim: str, seeds: list[int], result: str, evidence: str) -> str:
        self.rows.append(dict(robot=self.robot, claim=claim, seeds=" ".join(map(str, seeds)),
                              preconditions_held=f"{len(seeds)} of {len(self.data)} seeds", result=result,
                              evidence=evidence))  # fmt: skip
        return result

    def split(self, condition: Callable[[int], Optional[bool]]) -> tuple[list[int], list[int]]:
        """:return: the seeds where a claim is testable, and those where it may still become so"""
        testable = [s for s in sorted(self.data) if condition(s) is True]
        return testable, [s for s in sorted(self.data) if condition(s) is None] + self.missing

    def decide(self, claim: str, condition: Callable[[int], Optional[bool]], measure: Callable[[int], float],
               passed: Callable[[list[float]], bool], label: str, spec: str = "+.1f") -> str:  # fmt: skip
        """Test a claim: ``measure`` per testable seed, ``passed`` on them all. :return: its result"""
        testable, open_seeds = self.split(condition)
        values = [measure(s) for s in testable]
        evidence = f"{label} " + (", ".join(f"seed {s}: {v:{spec}}" for s, v in zip(testable, values)) or "not measured")
        if len(values) > 1:
            evidence += f" (mean {np.mean(values):{spec}})"
        if len(testable) + len(open_seeds) < 2:
            return self.row(claim, testable, "not testable", f"preconditions held on {len(testable)} seed(s); {evidence}")
        if open_seeds:
            return self.row(claim, testable, "pending", f"waiting for seed(s) {' '.join(map(str, open_seeds))}; {evidence}")
        return self.row(claim, testable, "reproduced" if passed(values) else "not reproduced", evidence)

    def student(self, seed: int, name: str) -> Optional[dict[str, Any]]:
        return self.data[seed][1].get(name)

    def dose_drop(self, seed: int, transform: str, dose: str) -> float:
        """:return: the Env-A return lost from the base dose to ``dose``, over the ``A_only`` reference (NaN: missing)"""
        base, dosed = self.student(seed, f"{transform}_{BASE_DOSE}"), self.student(seed, f"{transform}_{dose}")
        reference = self.student(seed, "A_only")
        if base is None or dosed is None or reference is None:
            return math.nan
        return (base["return_Env-A"] - dosed["return_Env-A"]) / reference["return_Env-A"]

    def overestimation_rise(self, seed: int, dose: str) -> float:
        """:return: the indicator student's Env-A overestimation at ``dose`` minus at the base dose (NaN: missing)"""
        base, dosed = self.student(seed, f"ind_{BASE_DOSE}"), self.student(seed, f"ind_{dose}")
        if base is None or dosed is None:
            return math.nan
        return dosed.get("overestimation_Env-A", math.nan) - base.get("overestimation_Env-A", math.nan)


def measured(value: float) -> Optional[bool]:
    """:return: None (pending) for a value not measured yet (NaN), else True"""
    return None if math.isnan(value) else True


def claims(robot: str, data: dict[int, Any], pre: dict[int, dict[str, Any]]) -> list[dict[str, Any]]:
    """The pre-registered claims C1-C5 (see :class:`Verdicts` for pending and not testable)."""
    v = Verdicts(robot, data, pre)
    # C1: forgetting online; every testable seed must be lower, so one that is not decides it
    c1 = "C1 MPO forgets Env-A"
    testable = [s for s in sorted(data) if pre[s]["P1_agent"]]
    drops = {s: 1 - data[s][0]["end_last5_Env-A"] / data[s][0]["stage1_last5_Env-A"] for s in testable}
    if len(testable) >= 2 and any(d <= 0 for d in drops.values()):
        evidence = "MPO's Env-A return at the end against the frozen agent: " + ", ".join(
            f"seed {s}: {-d:+.0%}" for s, d in drops.items()
        )
        v.row(c1, testable, "not reproduced", evidence + " (every testable seed must be lower)")
    else:
        v.decide(c1, lambda s: pre[s]["P1_agent"], lambda s: drops[s], lambda d: bool(np.mean(d) >= 0.2), "drops", "+.0%")
    for dose in DOSES:
        if dose != BASE_DOSE:
            dose_claims(v, dose)
    for dose in DOSES:  # the secondary design: the same claims with P2s in place of P2
        if dose != BASE_DOSE:
            dose_claims(v, dose, secondary=True)
    # C5: the collector's overestimation on Env-A data grows after the switch
    v.decide(
        "C5 MPO's overestimation on A grows after the switch",
        lambda s: holds(pre[s]["P1"], "final_overestimation_Env-A" in data[s][0]),
        lambda s: data[s][0]["final_overestimation_Env-A"] - data[s][0]["stage1_overestimation_Env-A"],
        lambda rises: bool(np.mean(rises) > 0),
        "rise",
    )
    return v.rows


def dose_claims(v: Verdicts, dose: str, secondary: bool = False) -> None:
    """
    C2, C3 and C4 at one dose; with ``secondary``, the secondary design's S2, S3 and S4: the same claims and criteria
    with P2s (the ``B_only`` student fails in Env-A) in place of P2 (the collector forgot).
    """
    pre, needs_gap = v.pre, DOSES[dose][0] != 1.0
    changed, prefix = ("P2s", "S") if secondary else ("P2", "C")

    def c2_condition(s: int) -> Optional[bool]:
        return holds(pre[s]["P1"], pre[s][changed], pre[s]["P3_x3"] or not needs_gap, measured(v.dose_drop(s, "ind", dose)))

    c2 = v.decide(
        f"{prefix}2 indicator drops in A at {dose}",
        c2_condition,
        lambda s: v.dose_drop(s, "ind", dose),
        lambda drops: bool(np.mean(drops) >= 0.1 and sum(d > 0 for d in drops) >= 2),
        "drop / A_only",
        "+.1%",
    )
    c3 = f"{prefix}3 ESS student flat at {dose}"  # needs C2 passed and P4
    if c2 != "reproduced":
        v.row(c3, [], "pending" if c2 == "pending" else "not testable", f"{prefix}2 {c2}: " + (
            "waiting for it" if c2 == "pending" else "no drop to stay flat against"))  # fmt: skip
    else:
        v.decide(
            c3,
            lambda s: holds(c2_condition(s), pre[s]["P4"], measured(v.dose_drop(s, "ess", dose))),
            lambda s: v.dose_drop(s, "ess", dose) - 0.5 * v.dose_drop(s, "ind", dose),
            lambda excess: bool(np.mean(excess) < 0),  # the ess drop below half the indicator's, on the mean
            "ess drop minus half the indicator's",
            "+.1%",
        )
    v.decide(
        f"{prefix}4 overestimation on A rises at {dose}",
        lambda s: holds(pre[s]["P1"], pre[s][changed], measured(v.overestimation_rise(s, dose))),
        lambda s: v.overestimation_rise(s, dose),
        lambda rises: bool(np.mean(rises) > 0),
        "rise",
    )


def figure(robot: str, data: dict[int, Any], root: pathlib.Path) -> None:
    """
    Env-A and Env-B return of each student against the dose, per seed (thin) and the mean over the seeds that have
    every dose (thick), with the references.
    """
    from sb3_lifelong.experiments.style import pyplot

    plt = pyplot()

    doses = list(DOSES)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.8), sharex=True)
    for ax, env in zip(axes, ("Env-A", "Env-B")):
        for transform, color, label in (("ind", "C3", "indicator"), ("ess", "C0", f"exp, ESS {TARGET_ESS:g}")):
            curves = []
            for _, (_, students) in sorted(data.items()):
                ys = [students.get(f"{transform}_{d}", {}).get(f"return_{env}", math.nan) for d in doses]
                if all(math.isnan(y) for y in ys):  # none of this seed's students of this transform has finished
                    continue
                ax.plot(range(len(doses)), ys, color=color, alpha=0.3, lw=1, marker=".")
                curves.append(ys)
            # the mean over the seeds with every dose, so that no step of it is a change of seeds
            complete = [ys for ys in curves if not any(math.isnan(y) for y in ys)]
            partial = f"; {len(curves) - len(complete)} more incomplete, thin" if len(complete) < len(curves) else ""
            if complete:
                ax.plot(range(len(doses)), np.mean(complete, axis=0), color=color, lw=2.5, marker="o",
                        label=f"{label} (n={len(complete)}{partial})")  # fmt: skip
        # the collector's references over the seeds that have students, so that lines and points share their seeds
        with_students = [c for c, students in data.values() if students]
        for key, style, name in (("stage1_last5", "--", "MPO at the switch (Stage-1)"), ("end_last5", "-.", "MPO at the end")):
            values = [c[f"{key}_{env}"] for c in with_students if not math.isnan(c.get(f"{key}_{env}", math.nan))]
            if values:  # (an adopted Stage-1 was evaluated in Env-A only)
                # no n in the label: the legend is shared, and a Stage-1 adopted from another study has no Env-B value
                ax.axhline(np.mean(values), color="k", ls=style, lw=1, label=f"{name}, mean of the seeds measured")
        for name, color, label in (("A_only", "C2", "Env-A-only student"), ("B_only", "C1", "Env-B-only student")):
            reference = [s[name][f"return_{env}"] for _, s in data.values() if name in s]
            if reference:
                ax.axhline(np.mean(reference), color=color, ls=":", lw=1.5, label=f"{label} (n={len(reference)})")
        ax.set_ylim(bottom=min(0.0, ax.get_ylim()[0]))  # from zero: a drop reads at its size
        ax.set_xticks(range(len(doses)), ["x1, 1:5", "x3, 1:5", "x1, 1:20"])
        ax.set_xlabel("dose: Env-B reward scale, Env-A : Env-B share")
        ax.set_ylabel(f"return in {env} (last 3 evaluations)")
        ax.set_title(f"{robot}: students in {env}")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, ncol=3, loc="lower center")  # below the panels, clear of every line
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    fig.savefig(root / f"dose_{robot}.png", dpi=110)
    plt.close(fig)


def progress(args: argparse.Namespace) -> list[str]:
    """
    Where each pre-registered seed of ``--robot`` stands (its collection, its students: finished in the run directory,
    paused there, or committed in ``--results``) and the commands that go on with it, from the snapshots the study
    runs from (:data:`PINNED`); nothing is changed.

    :return: the lines printed
    """

    preset = study_preset(ROBOTS[args.robot][0])
    total = sum(preset.stage_steps)
    study = pathlib.Path(args.study or pathlib.Path(args.runs) / f"imbalance_dose_{args.robot}")
    students = pathlib.Path(args.students_output or pathlib.Path(args.runs) / f"imbalance_dose_{args.robot}_students")
    results = pathlib.Path(getattr(args, "results", None) or RESULTS)
    names = list(student_settings({}))
    pinned = PINNED.get(args.robot)
    lines = [f"{args.robot}: collection {total:,} steps per seed, {len(names)} students of {args.updates:,} updates"]
    if pinned is not None:
        lines.append(
            f"  runs from snapshots: collections `git worktree add <collect-tree> {pinned[0]}`, students `git worktree "
            f"add <students-tree> {pinned[1]}`; on a CPU with native bf16 put "
            "benchmarks/studies/imbalance_dose/study_float32 after the tree "
            "on PYTHONPATH (benchmarks/studies/imbalance_dose/README.md, last sections)"
        )
    for seed in PLANNED_SEEDS[args.robot]:
        collect = study / f"seed_{seed}" / "collect"
        if (collect / "done.json").exists():
            state = "collection finished"
        elif (collect / "paused.json").exists():
            state = f"collection paused at {json.loads((collect / 'paused.json').read_text())['timesteps']:,}"
        else:
            state = "collection not started"
        summary = results / args.robot / f"seed_{seed}" / "students.json"
        committed = set(json.loads(summary.read_text())["students"]) if summary.exists() else set()
        done, paused = [], []
        for name in names:
            directory = students / f"seed_{seed}" / f"distill_{name}"
            if (directory / "done.json").exists():
                done.append(name)
            elif (directory / "paused.json").exists():
                paused.append(f"{name} at {json.loads((directory / 'paused.json').read_text())['updates']:,}")
        missing = [name for name in names if name not in done and name not in committed]
        lines.append(f"  seed {seed}: {state}; students done {len(done)} of {len(names)}" + (
            f" ({', '.join(done)})" if done else "") + (f"; paused: {', '.join(paused)}" if paused else "") + (
            f"; committed in {results}: {len(committed)}" if committed else ""))  # fmt: skip
        if not missing:
            lines.append("    nothing to run: every student is finished or committed")
            continue
        float32 = "<repo>/benchmarks/studies/imbalance_dose/study_float32"
        tree = f"PYTHONPATH=<collect-tree>:{float32} " if pinned is not None else ""
        if state != "collection finished":
            lines.append(
                f"    next: {tree}OMP_NUM_THREADS=1 python -m sb3_lifelong.experiments run --presets {STUDY_PRESETS} "
                f"--preset {ROBOTS[args.robot][0]} "
                f"--seed {seed} --output {study.resolve()} --until <steps> (or "
                "benchmarks/studies/imbalance_dose/collect_in_parts.sh with "
                f"STUDY_TREE), then the students {', '.join(missing)}"
            )
            continue
        where = f"--runs {pathlib.Path(args.runs).resolve()} --study {study.resolve()} --students-output {students.resolve()}"
        only = f" --students {' '.join(missing)}" if committed else ""
        # `run` writes students.json from the students of its run directory: where some are only committed, it
        # writes elsewhere and merge-students adds the new ones to the committed file
        committed_results = " --results <repo>/benchmarks/studies/imbalance_dose/results"
        into = " --results <scratch>" if committed else (committed_results if pinned else "")
        if pinned is not None:  # the pinned script and library
            tree = "cd <students-tree> && " + tree.replace("<collect-tree>", "<students-tree>")
        lines.append(
            f"    next: {tree}OMP_NUM_THREADS=1 python benchmarks/studies/imbalance_dose/imbalance_dose.py run "
            f"--robot {args.robot} --seed {seed} "
            f"{where}{only}{into}"
        )
        if committed:
            lines.append(
                "    then: python benchmarks/studies/imbalance_dose/imbalance_dose.py merge-students --robot "
                f"{args.robot} --seed {seed} "
                "--from <scratch>   (from this checkout)"
            )
    print("\n".join(lines))
    return lines


def same_collection(args: argparse.Namespace) -> bool:
    """
    Whether a collection run again (on another machine, after its run directory was lost) is the one whose results
    are committed: the critic's mean Q per source at every measurement both logs have (``q_sources.csv``) is a
    fingerprint of the training, and with it of the buffer. Prints the comparison; exit status 1 on a difference.

    :return: True when every common measurement is equal to the last digit (and there is at least one)
    """
    committed = pathlib.Path(args.results) / args.robot / f"seed_{args.seed}" / "collect_q_sources.csv"
    study = pathlib.Path(args.study or pathlib.Path(args.runs) / f"imbalance_dose_{args.robot}")
    rerun = study / f"seed_{args.seed}" / "collect" / "q_sources.csv"
    for path in (committed, rerun):
        if not path.exists():
            raise SystemExit(f"{path} does not exist: nothing to compare")

    def rows(path: pathlib.Path) -> dict[tuple[int, str], str]:
        with open(path, newline="") as handle:
            return {(int(float(row["timesteps"])), row["source"]): row["q_mean"] for row in csv.DictReader(handle)}

    old, new = rows(committed), rows(rerun)
    common = sorted(set(old) & set(new))
    differ = [key for key in common if float(old[key]) != float(new[key])]
    if not common:
        print(f"no measurement in common between {committed} and {rerun}")
        return False
    reach = max(step for step, _ in common)
    if differ:
        step, source = differ[0]
        print(f"seed {args.seed}: differs first at {step:,} steps, source {source}: {new[differ[0]]} here, "
              f"{old[differ[0]]} committed ({len(differ)} of {len(common)} measurements differ)")  # fmt: skip
        return False
    print(f"seed {args.seed}: the same collection so far: {len(common)} measurements equal, up to {reach:,} steps")
    return True


def merge_students(args: argparse.Namespace) -> dict[str, Any]:
    """
    Add the students of another results directory (``--from``: a ``run`` that wrote elsewhere, e.g. the missing
    students of a seed whose run directory was lost) to this one's ``students.json`` of the seed. A student already in
    it is replaced by the new one; none is removed. Both files must have the same categorical support.

    :return: the merged ``students.json``
    """
    target = pathlib.Path(args.results) / args.robot / f"seed_{args.seed}" / "students.json"
    source = pathlib.Path(args.source) / args.robot / f"seed_{args.seed}" / "students.json"
    if not source.exists():
        raise SystemExit(f"{source} does not exist: nothing to merge")
    new = json.loads(source.read_text())
    merged = json.loads(target.read_text()) if target.exists() else dict(support=new["support"], students={})
    if merged["support"] != new["support"]:
        raise SystemExit(
            f"the students of {source} were trained on another support ({new['support']}) than those of {target} "
            f"({merged['support']}): they are not the same study's students, nothing merged"
        )
    merged["students"] = {**merged["students"], **new["students"]}
    target.parent.mkdir(parents=True, exist_ok=True)
    # written as `run` writes it (a student's summary holds NaN, e.g. the indicator's beta, which write_json_atomic refuses)
    staging = target.with_name(target.name + ".staging")
    staging.write_text(json.dumps(merged, indent=1))
    staging.replace(target)
    print(f"{sorted(new['students'])} merged into {target} ({len(merged['students'])} students)")
    return merged


def replicates(args: argparse.Namespace) -> list[str]:
    """
    The students trained again on a seed's buffer with another student seed (``run --student-seed``), beside the
    study's own: each one's Env-A return, and each dose's drop over the study's ``A_only`` of that seed, where the
    replicate holds the base dose's student and the dosed one of a transform. Written to ``replicates.md``.

    :return: the table's lines
    """
    root = pathlib.Path(args.results)
    students = ["| seed | student seed | student | Env-A, replicate | Env-A, study | replicate - study |"]
    students.append("| --- | --- | --- | --- | --- | --- |")
    drops = [
        "| seed | student seed | transform, dose | drop / `A_only`, replicate | drop / `A_only`, study | replicate - study |"
    ]
    drops.append("| --- | --- | --- | --- | --- | --- |")
    for path in sorted(root.glob(f"{args.robot}/replicates/seed_*_student*/students.json")):
        seed, student_seed = path.parent.name[len("seed_") :].split("_student")
        study = json.loads((root / args.robot / f"seed_{seed}" / "students.json").read_text())["students"]
        replicate = json.loads(path.read_text())["students"]
        for name, row in replicate.items():
            original = study.get(name, {}).get("return_Env-A", math.nan)
            returns = f"{row['return_Env-A']:.0f} | {original:.0f} | {row['return_Env-A'] - original:+.0f}"
            students.append(f"| {seed} | {student_seed} | `{name}` | {returns} |")
        reference = study["A_only"]["return_Env-A"]
        for transform in TRANSFORMS:
            for dose in DOSES:
                base, dosed = f"{transform}_{BASE_DOSE}", f"{transform}_{dose}"
                if dose == BASE_DOSE or base not in replicate or dosed not in replicate:
                    continue
                again = (replicate[base]["return_Env-A"] - replicate[dosed]["return_Env-A"]) / reference
                first = (study[base]["return_Env-A"] - study[dosed]["return_Env-A"]) / reference
                values = f"{100 * again:.1f} % | {100 * first:.1f} % | {100 * (again - first):+.1f} points"
                drops.append(f"| {seed} | {student_seed} | {transform}, {dose} | {values} |")
    lines = [f"# Replicates of {args.robot}'s students (another student seed, the same buffer)", "", *students, ""]
    lines += ["Drops, each over the study's `A_only` of the seed (Env-A, last 3 evaluations):", "", *drops]
    (root / "replicates.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return lines


def collection_arguments(parser: argparse.ArgumentParser, robot: str) -> None:
    """The arguments of a command on one seed's collection: the robot (default ``robot``), the seed, where it is."""
    parser.add_argument("--robot", choices=sorted(ROBOTS), default=robot)
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--runs", default="runs", help="where the collections are")
    parser.add_argument("--study", default=None, help="the collection (default: <runs>/imbalance_dose_<robot>)")
    parser.add_argument("--results", default=str(RESULTS), help="where the small results are")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    run_parser = sub.add_parser("run", help="measure one seed's collector and train its students")
    run_parser.add_argument("--robot", choices=sorted(ROBOTS), default="hopper")
    run_parser.add_argument("--seed", type=int, required=True)
    run_parser.add_argument("--updates", type=int, default=200_000, help="updates per student (pre-registered: 200k)")
    run_parser.add_argument("--students", nargs="+", default=None, help="only these students (default: all eight)")
    run_parser.add_argument("--runs", default="runs", help="where the collections are and the students go")
    run_parser.add_argument("--study", default=None, help="the collection (default: <runs>/imbalance_dose_<robot>)")
    run_parser.add_argument("--students-output", default=None, help="default: <runs>/imbalance_dose_<robot>_students")
    run_parser.add_argument("--results", default=str(RESULTS), help="where the small results go")
    run_parser.add_argument("--student-seed", type=int, default=None, help="a replicate: the students' own seed")
    collection_arguments(sub.add_parser("screen", help="the collection at the switch (Stage-1 agent and data) only"), "hopper")
    branch_parser = sub.add_parser("branch", help="a collection with another change, from a finished Stage-1")
    branch_parser.add_argument("--robot", choices=sorted(ROBOTS), default="cheetah")
    branch_parser.add_argument("--seed", type=int, required=True)
    branch_parser.add_argument("--change", required=True, help="Env-B, one parameter as JSON")
    branch_parser.add_argument("--steps", type=int, default=100_000, help="Env-B steps (the collection's: 100k)")
    branch_parser.add_argument("--runs", default="runs", help="where the collections are")
    branch_parser.add_argument("--study", default=None, help="the Stage-1 collection (default: <runs>/imbalance_dose_<robot>)")
    branch_parser.add_argument("--output", required=True, help="the new collection's directory")
    branch_parser.add_argument("--results", default=str(RESULTS), help="where the small results go")
    adopt_parser = sub.add_parser("adopt-stage1", help="a paused collection of --robot's preset from another's Stage-1")
    adopt_parser.add_argument("--robot", choices=sorted(ROBOTS), required=True)
    adopt_parser.add_argument("--seed", type=int, required=True)
    adopt_parser.add_argument("--source", required=True, help="the study whose finished Stage-1 is adopted")
    adopt_parser.add_argument("--output", required=True, help="the new study's directory")
    progress_parser = sub.add_parser("progress", help="where each seed stands, and the commands that go on with it")
    progress_parser.add_argument("--robot", choices=sorted(ROBOTS), default="cheetah_hip")
    progress_parser.add_argument("--updates", type=int, default=200_000, help="updates per student (pre-registered: 200k)")
    progress_parser.add_argument("--runs", default="runs", help="where the collections are and the students go")
    progress_parser.add_argument("--study", default=None, help="the collection (default: <runs>/imbalance_dose_<robot>)")
    progress_parser.add_argument("--students-output", default=None, help="default: <runs>/imbalance_dose_<robot>_students")
    progress_parser.add_argument("--results", default=str(RESULTS), help="where the committed small results are")
    same_parser = sub.add_parser("same-collection", help="is a collection run again the committed one (its Q log)")
    collection_arguments(same_parser, "cheetah_hip")
    merge_parser = sub.add_parser("merge-students", help="add the students of another results directory to this one")
    merge_parser.add_argument("--robot", choices=sorted(ROBOTS), default="cheetah_hip")
    merge_parser.add_argument("--seed", type=int, required=True)
    merge_parser.add_argument("--from", dest="source", required=True, help="the other results directory")
    merge_parser.add_argument("--results", default=str(RESULTS), help="the results directory merged into")
    replicates_parser = sub.add_parser(
        "replicates", help="students trained again with another student seed (run --student-seed)"
    )
    replicates_parser.add_argument("--robot", choices=sorted(ROBOTS), default="cheetah_hip")
    replicates_parser.add_argument("--results", default=str(RESULTS), help="the results directory")
    report_parser = sub.add_parser("report", help="preconditions, claims, tables and figures of every seed so far")
    report_parser.add_argument("--results", default=str(RESULTS), help="the results directory")
    args = parser.parse_args()
    import torch as th

    th.set_num_threads(1)
    if args.command == "same-collection":
        raise SystemExit(0 if same_collection(args) else 1)
    commands = dict(run=run, screen=screen, branch=branch, progress=progress, report=report, replicates=replicates)
    commands["adopt-stage1"] = adopt_stage1
    commands["merge-students"] = merge_students
    commands[args.command](args)


if __name__ == "__main__":
    main()
