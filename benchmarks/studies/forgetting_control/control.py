"""
The forgetting control: what does the change cost MPO in Env-A, against the same agent continuing in Env-A?

Pre-registered in ``README.md`` beside this script (design, per-seed values, readings) before any run. Per seed, MPO
learns Env-A for 120k steps (``stage1``); when Env-A was learnt (the screen's rule), the Stage-1 (agent, optimisers,
duals, buffer) continues in two branches of 120k steps each: ``switched`` (the back leg's motors reversed, the
screen's closest candidate) and ``control`` (the nominal robot: Env-A goes on). Both branches see the same seeded
evaluation episodes, so their Env-A returns compare seed by seed.

One command runs seeds in order and skips what is done; a killed command continues from its last part::

    OMP_NUM_THREADS=1 python benchmarks/studies/forgetting_control/control.py queue --seeds 30 32 --runs /work/runs
    python benchmarks/studies/forgetting_control/control.py progress --runs /work/runs
    # K4 (amendment 2), once both branches of a seed have ended and while its agents are still in --runs
    OMP_NUM_THREADS=1 python benchmarks/studies/forgetting_control/control.py true-error --seeds 30 --runs /work/runs
    python benchmarks/studies/forgetting_control/control.py report      # results/control.csv, results.md, control.png

Small results go to ``results/`` beside this script; buffers and agents stay in ``--runs``.
"""

import argparse
import csv
import dataclasses
import functools
import json
import math
import pathlib
import time
from collections.abc import Sequence
from typing import Any, Optional

import numpy as np

STUDY = pathlib.Path(__file__).resolve().parent
RESULTS = STUDY / "results"
PRESETS_FILE = STUDY / "presets.py"

#: the screen's candidate whose change the switched branch makes
CANDIDATE = "cheetah_back_reversed"
ENV_A_STEPS = 120_000
STAGE2_STEPS = 120_000
#: Stage 2 of each branch: the change, or the nominal value of the same parameter (the same appended column)
BRANCHES: dict[str, dict[str, float]] = {"switched": {"leg_motor_scale": -1.0}, "control": {"leg_motor_scale": 1.0}}
#: the screen's readings: last-LAST means, SAME_EPISODES seeded episodes per agent, collections in parts of PART steps
LAST = 5
SAME_EPISODES = 10
PART = 20_000
#: fresh seeds (the screen used 0-3, the pipeline study 10-17), started in this order until FIVE learnt Env-A
SEEDS = tuple(range(30, 42))
LEARNT_SEEDS_WANTED = 5
#: a change is a change when the frozen Stage-1 agent's zero-shot Env-B return is at most this share of its Env-A one
CHANGE_IS_REAL = 0.8
COSTS_A_FIFTH = 0.8  # K1: reported when the whole interval of the cost ratio is below it
NO_COST = (0.9, 1.1)  # K1: the equivalence margin of "no cost"
FORGETS = 0.8  # K2: the screen's threshold
SAME_GROWTH = 15.0  # K3: the equivalence margin of the overestimation growth's difference (Q units)


def _print(message: str) -> None:
    print(message, flush=True)


@functools.cache
def presets() -> dict[str, Any]:
    from sb3_lifelong.experiments.presets import load_presets

    return load_presets(PRESETS_FILE)


def preset(branch: str) -> Any:
    """The collection of one branch: the screen's collector and candidate, with this study's stages and budgets."""
    if branch not in BRANCHES:
        raise ValueError(f"no branch {branch!r}: one of {sorted(BRANCHES)}")
    return dataclasses.replace(presets()[f"control_{branch}"], stage_steps=(ENV_A_STEPS, STAGE2_STEPS))


def stage1_dir(runs: pathlib.Path, seed: int) -> pathlib.Path:
    return runs / "forgetting_control" / "stage1" / f"seed_{seed}"


def branch_dir(runs: pathlib.Path, branch: str, seed: int) -> pathlib.Path:
    return runs / "forgetting_control" / branch / f"seed_{seed}"


def run_stage1(seed: int, runs: pathlib.Path, results: pathlib.Path) -> dict[str, Any]:
    """MPO learns Env-A (either branch's preset: Env-A is the same), then the screen's reading, kept in ``results``."""
    from sb3_lifelong.experiments.collection import collect_in_parts
    from sb3_lifelong.experiments.scores import switch_reading

    out = results / "stage1" / f"seed_{seed}.json"
    if out.exists():
        return json.loads(out.read_text())
    run_dir = stage1_dir(runs, seed)
    settings = preset("switched")
    if not (run_dir / "collect" / "stage1.zip").exists():
        collect_in_parts(settings, seed, run_dir, ENV_A_STEPS, PART, log=_print)
    eval_csv = run_dir / "collect" / "eval.csv"
    reading = switch_reading(eval_csv, ENV_A_STEPS, settings.env_a_learnt, settings.max_switch_spread, LAST)
    record = dict(seed=seed, **reading)
    out.parent.mkdir(parents=True, exist_ok=True)
    (out.parent / f"seed_{seed}_eval.csv").write_text((run_dir / "collect" / "eval.csv").read_text())
    out.write_text(json.dumps(record, indent=1) + "\n")
    state = "learnt" if record["learnt"] else "not learnt"
    print(f"seed {seed}: Env-A {state} (last 5: {record['mean']:.0f}, spread {record['spread']:.2f})", flush=True)
    return record


def measure(branch: str, seed: int, run_dir: pathlib.Path) -> dict[str, Any]:
    """One branch's measurements at its end (README, "Per seed"): the screen's, on this study's budgets."""
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.experiments.branching import measure_agent
    from sb3_lifelong.experiments.scores import last_evaluations, overestimation_at

    settings = preset(branch)
    switch, end = settings.stage_steps[0], sum(settings.stage_steps)
    eval_csv, q_csv = run_dir / "collect" / "eval.csv", run_dir / "collect" / "q_sources.csv"
    end_a = last_evaluations(eval_csv, "Env-A", None, LAST)
    out: dict[str, Any] = dict(
        branch=branch, seed=seed, switch=switch, end=end, end_evals_env_a=end_a, end_env_a=float(np.mean(end_a)),
        overestimation_env_a_switch=overestimation_at(q_csv, "Env-A", switch),
        overestimation_env_a_end=overestimation_at(q_csv, "Env-A", end),
    )  # fmt: skip
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        for name in ("stage1", "final"):
            out.update(measure_agent(name, run_dir, buffer, settings, seed, SAME_EPISODES))
    return out


def run_branch(branch: str, seed: int, runs: pathlib.Path, results: pathlib.Path) -> dict[str, Any]:
    """One branch of a learnt seed from its Stage-1, then its measurement (skipped when measured)."""
    from sb3_lifelong.experiments.branching import adopt_stage1

    out = results / branch / f"seed_{seed}" / "measure.json"
    if out.exists():
        return json.loads(out.read_text())
    settings = preset(branch)
    run_dir = branch_dir(runs, branch, seed)
    if not run_dir.exists():
        adopt_stage1(settings, stage1_dir(runs, seed), run_dir)
    if not (run_dir / "adopted.json").exists():  # adopt_stage1 writes it last: a stopped adoption left a partial copy
        raise SystemExit(f"{run_dir} holds an unfinished adoption of the Stage-1 (no adopted.json): move it away, run again")
    from sb3_lifelong.experiments.collection import collect_in_parts

    start = time.perf_counter()
    collect_in_parts(settings, seed, run_dir, sum(settings.stage_steps), PART, log=_print)
    measured = measure(branch, seed, run_dir)
    measured["seconds"] = time.perf_counter() - start
    out.parent.mkdir(parents=True, exist_ok=True)
    for name in ("eval.csv", "q_sources.csv"):
        (out.parent / name).write_text((run_dir / "collect" / name).read_text())
    out.write_text(json.dumps(measured, indent=1) + "\n")
    print(f"{branch} seed {seed}: Env-A at the end {measured['end_env_a']:.0f} -> {out}", flush=True)
    return measured


def queue(args: argparse.Namespace) -> None:
    """The given seeds in order: Stage 1, then, when Env-A was learnt, the switched branch and the control."""
    runs, results = pathlib.Path(args.runs), pathlib.Path(args.results)
    for seed in args.seeds:
        if seed not in SEEDS:
            raise SystemExit(f"seed {seed} is not one of the registered seeds {SEEDS[0]}-{SEEDS[-1]}")
        if not run_stage1(seed, runs, results)["learnt"]:
            print(f"seed {seed}: Env-A not learnt at the switch; by the README it stops here", flush=True)
            continue
        for branch in BRANCHES:
            run_branch(branch, seed, runs, results)


def progress(args: argparse.Namespace) -> list[str]:
    """Where each seed stands."""
    from sb3_lifelong.experiments.collection import paused_at

    runs, results = pathlib.Path(args.runs), pathlib.Path(args.results)
    lines = []
    for seed in SEEDS:
        stage1 = results / "stage1" / f"seed_{seed}.json"
        if not stage1.exists():
            at = paused_at(stage1_dir(runs, seed))
            lines.append(f"seed {seed}: Stage 1 " + (f"paused at {at:,}" if at else "not started"))
            continue
        if not json.loads(stage1.read_text())["learnt"]:
            lines.append(f"seed {seed}: Env-A not learnt (stops)")
            continue
        states = []
        for branch in BRANCHES:
            if (results / branch / f"seed_{seed}" / "measure.json").exists():
                states.append(f"{branch} measured")
            else:
                at = paused_at(branch_dir(runs, branch, seed)) if branch_dir(runs, branch, seed).exists() else 0
                states.append(f"{branch} " + (f"paused at {at:,}" if at else "not started"))
        lines.append(f"seed {seed}: " + ", ".join(states))
    print("\n".join(lines))
    return lines


# ------------------------------------------------------------------------------------------------- K4 (amendment 2)
TRUE_ERROR_ROWS = 256


def env_a_rows(run_dir: pathlib.Path, seed: int, count: int = TRUE_ERROR_ROWS) -> dict[str, np.ndarray]:
    """:return: ``count`` Env-A rows (source 0) of a branch's final buffer, drawn with ``seed`` (normalised actions)"""
    from sb3_lifelong import LifelongReplayBuffer

    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        columns = buffer.to_d4rl(by_episode=True, normalized_actions=True)
    candidates = np.flatnonzero(np.asarray(columns["sources"]).reshape(-1) == 0)
    picked = np.sort(np.random.default_rng(seed).choice(candidates, size=min(count, len(candidates)), replace=False))
    return dict(observations=columns["observations"][picked], actions=columns["actions"][picked])


def restore(env: Any, observation: np.ndarray) -> None:
    """
    Put a HalfCheetah copy in the state an observation was made in: ``qpos = (0, obs[:8])``, ``qvel = obs[8:17]``
    (the x position is left out of the observation; the dynamics and the reward do not depend on it).

    :raises ValueError: the restored state does not give the observation back (another robot, another layout)
    """
    robot = env.unwrapped
    nq, nv = robot.model.nq, robot.model.nv
    if len(observation) < nq - 1 + nv:
        raise ValueError(f"an observation of {len(observation)} values did not give it back: {nq - 1 + nv} expected")
    qpos = np.concatenate([[0.0], observation[: nq - 1]]).astype(np.float64)
    robot.set_state(qpos, np.asarray(observation[nq - 1 : nq - 1 + nv], dtype=np.float64))
    back = robot._get_obs()
    if back.shape != (nq - 1 + nv,) or not np.allclose(back, observation[: len(back)], atol=1e-4):
        raise ValueError(f"restoring {robot.__class__.__name__} from an observation did not give it back: not HalfCheetah?")


def true_error(agent: Any, rows: dict[str, np.ndarray], envs: list[Any], seed: int) -> dict[str, float]:
    """
    The critic's error on ``rows`` against its own policy's return (README, amendment 2): each row's state restored in
    Env-A, its stored action applied, then the agent's stochastic policy, ``monte_carlo_horizon(gamma)`` steps in all.

    :param agent: an MPO agent (its critic's first head is read, as by the Monte-Carlo probe)
    :param rows: :func:`env_a_rows`
    :param envs: one Env-A copy per row (``stage_envs``' Env-A, the observation as the agent sees it)
    :param seed: seeds the copies and the policy's sampling
    :return: ``q`` (mean Q(s, a)), ``g`` (mean discounted return), ``true_error`` (mean of their difference)
    """
    import torch as th

    from sb3_lifelong.evaluation import overestimation

    observations, actions = rows["observations"], rows["actions"]
    with th.no_grad():
        obs_t = th.as_tensor(observations, dtype=th.float32, device=agent.device)
        q = agent.critic(obs_t, th.as_tensor(actions, dtype=th.float32, device=agent.device))[0].flatten().double()
    th.manual_seed(seed)
    horizon = overestimation.monte_carlo_horizon(agent.gamma)
    returns = np.zeros(len(envs))
    current = np.zeros_like(observations)
    for i, env in enumerate(envs):
        env.reset(seed=seed + i)
        restore(env, observations[i])
    step_actions = agent.policy.unscale_action(np.asarray(actions))
    for k in range(horizon):
        for i, env in enumerate(envs):
            current[i], reward, terminated, truncated, _ = env.step(step_actions[i])
            if terminated or truncated:
                raise ValueError(f"a rollout ended at step {k} (HalfCheetah does not end before its time limit)")
            returns[i] += agent.gamma**k * reward
        step_actions, _ = agent.predict(current, deterministic=False)
    q_values = q.cpu().numpy()
    return dict(q=float(q_values.mean()), g=float(returns.mean()), true_error=float((q_values - returns).mean()))


def run_true_error(args: argparse.Namespace) -> None:
    """K4 of each given seed with both branches ended: the frozen and both end agents, kept in ``results/true_error``."""
    from sb3_lifelong import MPO
    from sb3_lifelong.envs import stage_envs

    runs, results = pathlib.Path(args.runs), pathlib.Path(args.results)
    for seed in args.seeds:
        out = results / "true_error" / f"seed_{seed}.json"
        dirs = {branch: branch_dir(runs, branch, seed) for branch in BRANCHES}
        if out.exists() or not all((d / "collect" / "final.zip").exists() for d in dirs.values()):
            print(f"seed {seed}: {'measured' if out.exists() else 'both branches have not ended'}", flush=True)
            continue
        rows = {branch: env_a_rows(d, seed, args.rows) for branch, d in dirs.items()}
        if not np.array_equal(rows["switched"]["observations"], rows["control"]["observations"]):
            raise SystemExit(f"seed {seed}: the branches' Env-A rows differ: they should be the same Stage-1 rows")
        settings = preset("switched")
        envs = [
            stage_envs(settings.env_id, list(settings.stages), settings.env_names, settings.env_kwargs, append_params=True)[
                "Env-A"
            ]
            for _ in range(len(rows["switched"]["observations"]))
        ]
        record: dict[str, Any] = dict(seed=seed, rows=len(envs))
        start = time.perf_counter()
        agents = {"stage1": dirs["switched"] / "collect" / "stage1.zip"}
        agents.update({f"final_{branch}": d / "collect" / "final.zip" for branch, d in dirs.items()})
        for name, path in agents.items():
            agent = MPO.load(path, device="cpu", custom_objects={"replay_buffer_kwargs": {}})
            record[name] = true_error(agent, rows["switched"], envs, seed)
        record["true_offline_error"] = record["final_switched"]["true_error"] - record["final_control"]["true_error"]
        record["seconds"] = time.perf_counter() - start
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(record, indent=1) + "\n")
        print(f"seed {seed}: true error measured -> {out}", flush=True)


# ------------------------------------------------------------------------------------------------- the readings
def seed_values(stage1: dict[str, Any], switched: dict[str, Any], control: dict[str, Any]) -> dict[str, Any]:
    """
    The per-seed values of the README ("Per seed", as amended) from a seed's Stage-1 reading and its two branches'
    measurements.

    :return: ``cost_ratio`` (K1; NaN when the control's end return is not positive), ``forgetting_ratio`` (K2),
        ``control_ratio``, ``same_episode_cost``, ``same_episode_forgetting``, ``growth_switched`` and
        ``growth_control`` (the end agent's overestimation of Env-A data minus the frozen Stage-1 agent's, on the same
        rows), ``offline_growth`` (K3: their difference), the same growths from the logged curves (``logged_growth_*``,
        reported only), ``zero_shot_share`` (NaN when the frozen agent's Env-A return is not positive) and
        ``change_is_real``
    :raises ValueError: a value a claim reads is missing or not finite (named with its seed)
    """
    seed = stage1["seed"]
    needed = ["end_env_a", "stage1_same_episodes_Env-A", "final_same_episodes_Env-A", "stage1_same_episodes_Env-B",
              "stage1_overestimation_Env-A", "final_overestimation_Env-A"]  # fmt: skip
    for name, branch in (("switched", switched), ("control", control)):
        for key in needed:
            if not math.isfinite(float(branch.get(key, math.nan))):
                raise ValueError(f"seed {seed}, {name}: {key} is missing or not finite ({branch.get(key)!r})")

    def ratio(top: float, bottom: float) -> float:
        return top / bottom if bottom > 0 else math.nan

    growth = {
        name: branch["final_overestimation_Env-A"] - branch["stage1_overestimation_Env-A"]
        for name, branch in (("switched", switched), ("control", control))
    }
    logged = {
        name: branch["overestimation_env_a_end"] - branch["overestimation_env_a_switch"]
        for name, branch in (("switched", switched), ("control", control))
    }
    zero_shot = ratio(switched["stage1_same_episodes_Env-B"], switched["stage1_same_episodes_Env-A"])
    return dict(
        seed=seed,
        stage1_env_a=stage1["mean"],
        end_env_a_switched=switched["end_env_a"],
        end_env_a_control=control["end_env_a"],
        cost_ratio=ratio(switched["end_env_a"], control["end_env_a"]),
        forgetting_ratio=ratio(switched["end_env_a"], stage1["mean"]),
        control_ratio=ratio(control["end_env_a"], stage1["mean"]),
        same_episode_cost=ratio(switched["final_same_episodes_Env-A"], control["final_same_episodes_Env-A"]),
        same_episode_forgetting=ratio(switched["final_same_episodes_Env-A"], switched["stage1_same_episodes_Env-A"]),
        growth_switched=growth["switched"],
        growth_control=growth["control"],
        offline_growth=growth["switched"] - growth["control"],
        logged_growth_switched=logged["switched"],
        logged_growth_control=logged["control"],
        zero_shot_share=zero_shot,
        change_is_real=bool(zero_shot <= CHANGE_IS_REAL),  # False for NaN
    )


def interval(values: Sequence[float]) -> tuple[float, float, float, float]:
    """:return: mean, sd and the 95 % t interval of the mean (the README's)"""
    from sb3_lifelong.experiments.statistics import t_interval

    return t_interval(list(values))


def _side(low: float, high: float, line: float, margin: tuple[float, float], below: str, above: str) -> str:
    """The reading of an interval against ``line`` and an equivalence ``margin`` (README, amendment 1's order)."""
    inside = margin[0] <= low and high <= margin[1]
    if high < line:
        return below + (", within the margin" if inside else "")
    if low > line:
        return above + (", within the margin" if inside else "")
    return "no difference" if inside else "inconclusive"


def read_claim(claim: str, values: Sequence[float]) -> str:
    """
    The README's reading of one claim from the 95 % t interval of its per-seed values (amendment 1: which side of
    the line first, then whether the interval also lies within the equivalence margin).

    :param claim: ``K1``, ``K2``, ``K3`` or ``K4`` (K4 reads as K3)
    :param values: one value per counted seed (the first ``LEARNT_SEEDS_WANTED`` are read)
    :return: K1 ``costs at least a fifth`` / ``costs`` / ``helps`` (each with ``, within the margin`` when the interval
        also lies in [0.9, 1.1]), ``no cost`` or ``inconclusive``; K2 ``holds``, ``fails`` or ``inconclusive``; K3
        ``holds`` / ``reversed`` (with ``, within the margin`` when also in [-15, 15]), ``no difference`` or
        ``inconclusive``; ``pending`` with fewer than the wanted seeds
    """
    if claim not in ("K1", "K2", "K3", "K4"):
        raise ValueError(f"no claim {claim!r}: K1, K2, K3 or K4")
    if len(values) < LEARNT_SEEDS_WANTED:
        return "pending"
    _, _, low, high = interval(list(values)[:LEARNT_SEEDS_WANTED])
    if claim == "K1":
        if high < COSTS_A_FIFTH:
            return "costs at least a fifth"
        reading = _side(low, high, 1.0, NO_COST, "costs", "helps")
        return "no cost" if reading == "no difference" else reading
    if claim == "K2":
        return "holds" if high <= FORGETS else "fails" if low > FORGETS else "inconclusive"
    return _side(low, high, 0.0, (-SAME_GROWTH, SAME_GROWTH), "reversed", "holds")


def collected(results: pathlib.Path) -> list[dict[str, Any]]:
    """:return: the per-seed values of every seed with both branches measured, in seed order"""
    rows = []
    for seed in SEEDS:
        paths = [results / "stage1" / f"seed_{seed}.json"] + [
            results / b / f"seed_{seed}" / "measure.json" for b in ("switched", "control")
        ]
        if all(p.exists() for p in paths):
            stage1, switched, control = (json.loads(p.read_text()) for p in paths)
            row = seed_values(stage1, switched, control)
            true = results / "true_error" / f"seed_{seed}.json"  # K4 (amendment 2); a seed without it does not count
            row["true_offline_error"] = json.loads(true.read_text())["true_offline_error"] if true.exists() else math.nan
            rows.append(row)
    return rows


def readings(rows: list[dict[str, Any]], stage1: dict[int, bool]) -> dict[str, Any]:
    """
    :param rows: the per-seed values (:func:`collected`, in seed order)
    :param stage1: seed -> whether Env-A was learnt, for every seed whose Stage-1 has ended
    :return: claim -> (reading, the values it read): each claim reads its first five counted seeds in seed order (K1
        counts a seed where the change is real and its cost ratio is defined; K2 and K3 every measured seed). With
        every registered seed's Stage 1 ended, every learnt seed measured and fewer than five counted, ``not testable``
    """
    out: dict[str, Any] = {}
    series = {
        "K1": [r["cost_ratio"] for r in rows if r["change_is_real"] and math.isfinite(r["cost_ratio"])],
        "K2": [r["forgetting_ratio"] for r in rows],
        "K3": [r["offline_growth"] for r in rows],
        "K4": [r["true_offline_error"] for r in rows if math.isfinite(r.get("true_offline_error", math.nan))],
    }
    measured = {r["seed"] for r in rows}
    finished = len(stage1) == len(SEEDS) and all(seed in measured for seed, learnt in stage1.items() if learnt)
    for claim, values in series.items():
        values = values[:LEARNT_SEEDS_WANTED]
        if finished and len(values) < LEARNT_SEEDS_WANTED:
            out[claim] = ("not testable", values)
        else:
            out[claim] = (read_claim(claim, values), values)
    return out


def _fmt(values: Sequence[float], digits: int) -> str:
    if not values:
        return "no seed"
    mean, std, low, high = interval(values)
    if len(values) < 2:
        return f"{mean:.{digits}f} (one seed)"
    return f"{mean:.{digits}f} +- {std:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


COLUMNS = [
    "seed", "stage1_env_a", "end_env_a_switched", "end_env_a_control", "cost_ratio", "forgetting_ratio",
    "control_ratio", "same_episode_cost", "same_episode_forgetting", "growth_switched", "growth_control",
    "offline_growth", "logged_growth_switched", "logged_growth_control", "zero_shot_share", "change_is_real",
    "true_offline_error",
]  # fmt: skip
CLAIM_TEXT = {
    "K1": ("the change costs MPO Env-A: switched / control at the end, Env-A", 3),
    "K2": ("MPO forgets Env-A after a 120k Stage 1: switched end / Stage-1 level", 3),
    "K3": ("Env-A data's overestimation grows more when offline: growth switched - control", 1),
    "K4": ("the critic's error on Env-A rows against its own policy's return, switched - control", 1),
}


def report(args: argparse.Namespace) -> str:
    """``results/control.csv`` (one row per seed), ``results/results.md`` (readings) and ``results/control.png``."""
    results = pathlib.Path(args.results)
    stage1 = {
        int(json.loads(p.read_text())["seed"]): bool(json.loads(p.read_text())["learnt"])
        for p in sorted((results / "stage1").glob("seed_*.json"))
    }
    rows = collected(results)
    with open(results / "control.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows({k: r[k] for k in COLUMNS} for r in rows)
    read = readings(rows, stage1)
    lines = [
        "# Forgetting control: results (generated by `control.py report`)",
        "",
        f"Stage-1s ended: {len(stage1)} (Env-A learnt on {sum(stage1.values())}: seeds "
        f"{', '.join(str(s) for s, ok in stage1.items() if ok) or 'none'}). Seeds with both branches measured: "
        f"{len(rows)}. A reading needs {LEARNT_SEEDS_WANTED} such seeds (95 % t interval of the mean); each claim reads "
        f"its first {LEARNT_SEEDS_WANTED} counted seeds in seed order (K2, K3: "
        f"{', '.join(str(r['seed']) for r in rows[:LEARNT_SEEDS_WANTED]) or 'none'}); later seeds are reported below.",
        "",
        "| claim | values per seed | mean +- sd [95 % t] | reading |",
        "| --- | --- | --- | --- |",
    ]
    for claim, (reading, values) in read.items():
        text, digits = CLAIM_TEXT[claim]
        per_seed = " / ".join(f"{v:.{digits}f}" for v in values) or "-"
        lines.append(f"| {claim} {text} | {per_seed} | {_fmt(values, digits)} | **{reading}** |")
    lines += ["", "Per seed (`control.csv`):", "", "| " + " | ".join(COLUMNS) + " |", "|" + " --- |" * len(COLUMNS)]
    for row in rows:
        cells = [f"{row[k]:.3f}" if isinstance(row[k], float) else str(row[k]) for k in COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    (results / "results.md").write_text(text)
    if rows:
        figure(rows, results, results / "control.png")
    print(text)
    return text


def _curve(path: pathlib.Path, key: str, name: str, value: str) -> list[tuple[int, float]]:
    with open(path, newline="") as handle:
        found = [(int(r["timesteps"]), float(r[value])) for r in csv.DictReader(handle) if r[key] == name and r[value]]
    return sorted(found)


def figure(rows: list[dict[str, Any]], results: pathlib.Path, path: pathlib.Path) -> None:
    """
    Per seed (three seeds a row): the Env-A return of both branches (top), and the overestimation of Env-A data
    against the stored returns with K4's error against the agent's own return at the branch point and the ends (bottom).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = min(3, len(rows))
    pairs = math.ceil(len(rows) / columns)
    fig, axes = plt.subplots(2 * pairs, columns, figsize=(4.8 * columns + 0.4, 5.6 * pairs + 0.8), squeeze=False)
    colours = {"switched": "tab:red", "control": "tab:blue"}
    for index, row in enumerate(rows):
        seed = row["seed"]
        top, bottom = axes[2 * (index // columns), index % columns], axes[2 * (index // columns) + 1, index % columns]
        stage1 = _curve(results / "stage1" / f"seed_{seed}_eval.csv", "env", "Env-A", "mean_reward")
        top.plot(*zip(*stage1), color="k", lw=1.2, label="Stage 1 (Env-A)")
        true_path = results / "true_error" / f"seed_{seed}.json"
        true = json.loads(true_path.read_text()) if true_path.exists() else None
        if true:
            bottom.plot([ENV_A_STEPS], [true["stage1"]["true_error"]], "kx", ms=7, label="own-policy error (K4)")
        for branch, colour in colours.items():
            folder = results / branch / f"seed_{seed}"
            evals = [p for p in _curve(folder / "eval.csv", "env", "Env-A", "mean_reward") if p[0] >= ENV_A_STEPS]
            top.plot(*zip(*evals), color=colour, lw=1.2, label=f"{branch}: Env-A")
            q = _curve(folder / "q_sources.csv", "name", "Env-A", "overestimation")
            if q:
                bottom.plot(*zip(*q), color=colour, lw=1.2, label=f"{branch}: against stored returns")
            if true:
                bottom.plot([ENV_A_STEPS + STAGE2_STEPS], [true[f"final_{branch}"]["true_error"]], "x", color=colour, ms=7)
        top.hlines(row["stage1_env_a"], ENV_A_STEPS, ENV_A_STEPS + STAGE2_STEPS, colors="grey", linestyles=":", lw=1)
        bottom.axhline(0.0, color="grey", lw=0.6)
        for ax in (top, bottom):
            ax.axvline(ENV_A_STEPS, color="k", lw=0.8)
            ax.set_xlabel("environment steps")
        unread = " (reported, not read)" if index >= LEARNT_SEEDS_WANTED else ""
        top.set_title(f"seed {seed}{unread}: cost ratio {row['cost_ratio']:.2f}, forgetting ratio "
                      f"{row['forgetting_ratio']:.2f}", fontsize=9)  # fmt: skip
        top.set_ylabel("Env-A return (5 seeded episodes)")
        bottom.set_ylabel("critic error on Env-A rows")
        for ax in (top, bottom):
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7)
    for index in range(len(rows), pairs * columns):
        axes[2 * (index // columns), index % columns].axis("off")
        axes[2 * (index // columns) + 1, index % columns].axis("off")
    fig.suptitle(
        "MPO after a 120k-step Stage 1: back leg reversed (switched) against the nominal robot (control)\n"
        "top: vertical line the branch point, grey dotted the Stage-1 agent's level; bottom: lines Q minus the stored "
        "return (logged), crosses Q minus the agent's own return",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("queue", "progress", "report", "true-error"):
        command = sub.add_parser(name)
        command.add_argument("--results", default=str(RESULTS), help="where the small results go")
        if name != "report":
            command.add_argument("--runs", default="runs", help="where buffers and agents go")
        if name in ("queue", "true-error"):
            command.add_argument("--seeds", type=int, nargs="+", required=True, help="registered seeds, run in order")
        if name == "true-error":
            command.add_argument("--rows", type=int, default=TRUE_ERROR_ROWS, help="Env-A rows (the README: 256)")
    args = parser.parse_args(argv)
    {"queue": queue, "progress": progress, "report": report, "true-error": run_true_error}[args.command](args)


if __name__ == "__main__":
    main()
