"""
The paper's two-stage experiment on OP3 (``README.md``, Design and Amendment 3): Stage 1, the four Env-B runs, the
three offline students of a seed, the support sweep and the claims report, each one resumable job (one command) whose
checkpoints live in ``--runs`` and whose small results (CSV, JSON) go to ``--results``::

    OMP_NUM_THREADS=1 python benchmarks/studies/paper_op3/paper_op3.py stage1 --seed 0 --runs /work/runs/paper_op3
    OMP_NUM_THREADS=1 python benchmarks/studies/paper_op3/paper_op3.py env_b --seed 0 --method mpo --runs ...
    OMP_NUM_THREADS=1 python benchmarks/studies/paper_op3/paper_op3.py sweep --runs ...
    OMP_NUM_THREADS=1 python benchmarks/studies/paper_op3/paper_op3.py student --seed 0 --student exp_combined --runs ...
    python benchmarks/studies/paper_op3/paper_op3.py report
    python benchmarks/studies/paper_op3/paper_op3.py status

``stage1``: MPO at Acme's MuJoCo baseline in Env-A (the hip's deformation appended to the observation at its
nominal value), until Amendment 3's switch rule ends it, then the registered gate on the frozen agent.
``env_b --method``: ``mpo`` (the same agent, buffer, optimisers and duals, now in Env-B), ``mpo_a`` (the same, left
in Env-A: the no-change control of C1), ``online_crr_indicator`` and ``online_crr_exp`` (a CRR given the Stage-1
policy's weights and a copy of its buffer, online in Env-B at the same update ratio).
``student --student``: an offline CRR (categorical critic, 51 atoms, batch 256, 500k updates) on MPO's lifetime buffer
``<runs>/seed_<S>/env_b_mpo/replay.pkl`` (its ``sources``: 0 Env-A rows, 1 Env-B rows), no task boundaries:
``exp_combined`` (exp, beta = 1) and ``indicator_combined`` on the whole buffer, ``indicator_a_only`` on its Env-A
rows alone (:data:`STUDENTS`). Each records the rows it drew per source and C4b's instrument, its critic's mean Q on
1,024 fixed Env-A rows (:func:`q_rows`). Its support is the experiments' ``value_support`` times the sweep's choice:
without ``support.json`` a student refuses to start, unless ``--support-scale`` is given for a small check.
``sweep``: the exp student at 100k updates with the support at 1x and 3x its width on the first three testable seeds'
buffers (:func:`sweep_seeds`), then ``--results/support.json`` (:func:`support_record`).
``report``: ``--results/claims.md`` and ``claims.json``: C1..C5 read by the README's rules (:data:`CLAIMS`,
:func:`read_interval`, :func:`read_claim`) on the testable seeds. ``RUNNING.md`` has the commands in order.

Files of a seed (``--results/seed_<S>/``): ``stage1.csv`` (one row per evaluation, :data:`STAGE1_FIELDS`),
``stage1.json`` (see :func:`stage1_record`), ``stage1_runs.json`` (Stage 1's settings, and the machine of each start
or resume), ``env_b_<method>.csv`` (one row per evaluation and environment,
:data:`ENV_B_FIELDS`), ``env_b_<method>.json`` (see :func:`run_env_b`), ``student_<student>.csv`` and
``sweep_exp_combined_<k>x.csv`` (one row per evaluation and environment, :data:`STUDENT_FIELDS`) and their JSON
files (see :func:`run_student`). Checkpoints (``--runs/seed_<S>/<job>/``): ``model.zip``, ``replay.pkl`` (the whole
buffer, a pickle of a ``LifelongReplayBuffer`` in memory; not for students, which read ``env_b_mpo``'s) and
``state.json``; Stage 1's final agent is ``stage1/agent.zip`` with its buffer ``stage1/replay.pkl``.
"""

import argparse
import csv
import hashlib
import json
import os
import pathlib
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch as th

STUDY = pathlib.Path(__file__).resolve().parent
RESULTS = STUDY / "results"
OP3 = "sb3_lifelong/OP3Walk-v0"
#: the change of Env-B: the right hip pitch link rotated by 0.3 rad (``--param`` names another for small checks)
PARAM, CHANGE = "hip_deformation", 0.3
#: a stage switch that never comes (Env-A for the whole run)
NEVER = 10**12
#: reset seeds of the evaluations during training (``EVAL_SEED + k``) and of the end scores (``END_SEED + k``)
EVAL_SEED, END_SEED = 10_000, 20_000
ENVS = ("Env-A", "Env-B")
#: Amendment 3's switch criterion: the mean over the last SWITCH_WINDOW evaluations has at most FALL_SHARE of the
#: episodes falling (1 of 10) and walks at least MIN_DISTANCE metres along x
SWITCH_WINDOW, FALL_SHARE, MIN_DISTANCE = 3, 0.1, 2.0
#: the registered gate on the frozen Stage-1 agent's end score: at most GATE_FALL_SHARE falls (2 of 20), MIN_DISTANCE m
GATE_FALL_SHARE = 0.1
METHODS = ("mpo", "mpo_a", "online_crr_indicator", "online_crr_exp")
#: the online CRRs' own settings: the experiments' ONLINE baselines (``sb3_lifelong.experiments.presets.ONLINE``)
CRR_TRANSFORMS = {"online_crr_indicator": "CRR_indicator", "online_crr_exp": "CRR_exp_beta1"}
SCORE_FIELDS = ["mean_return", "std_return", "mean_length", "falls", "mean_distance", "episodes"]
STAGE1_FIELDS = ["timesteps", "updates", *SCORE_FIELDS, "wall_s"]
ENV_B_FIELDS = ["timesteps", "stage2_steps", "updates", "env", *SCORE_FIELDS, "wall_s"]
#: the three offline students (Design item 3): CRR's settings (the experiments' ``EXP`` and ``INDICATOR``)
STUDENTS: dict[str, dict[str, Any]] = {
    "exp_combined": {"advantage_transform": "exp", "beta": 1.0},
    "indicator_combined": {"advantage_transform": "indicator"},
    "indicator_a_only": {"advantage_transform": "indicator"},
}
#: the students that train on the Env-A rows of the lifetime buffer only
A_ONLY = ("indicator_a_only",)
#: the registered student: 500k updates at batch 256, evaluated every 25k, a categorical critic of 51 atoms
STUDENT_UPDATES, STUDENT_EVAL_EVERY, STUDENT_BATCH, N_ATOMS = 500_000, 25_000, 256, 51
STUDENT_FIELDS = ["updates", "env", *SCORE_FIELDS, "q_env_a_rows", "wall_s"]
#: C4b's instrument: the critic's mean Q on Q_ROWS Env-A rows, drawn with a generator seeded by (Q_ROWS_SEED, seed)
Q_ROWS, Q_ROWS_SEED = 1024, 1024
#: the support sweep: the exp student at each width (times the data's own) for SWEEP_UPDATES updates on the first
#: SWEEP_SEEDS testable seeds; its choice is written to SUPPORT_FILE in --results
SUPPORT_SCALES, SWEEP_UPDATES, SWEEP_SEEDS, SWEEP_STUDENT, SUPPORT_FILE = (1, 3), 100_000, 3, "exp_combined", "support.json"
#: the claims' readings: at least MIN_SEEDS testable seeds; a ratio's denominator above MIN_DENOMINATOR on every seed
MIN_SEEDS, MIN_DENOMINATOR = 3, 100.0


# ------------------------------------------------------------------------------------------------ the rules
def switch_met(rows: Sequence[dict[str, Any]]) -> bool:
    """
    Amendment 3's criterion, read at the last of ``rows`` (evaluations in order).

    :param rows: evaluations with ``falls``, ``episodes`` and ``mean_distance``
    :return: whether the mean of the last :data:`SWITCH_WINDOW` evaluations has at most :data:`FALL_SHARE` of its
        episodes falling and at least :data:`MIN_DISTANCE` m (False with fewer evaluations than the window)
    """
    if len(rows) < SWITCH_WINDOW:
        return False
    window = rows[-SWITCH_WINDOW:]
    falls = float(np.mean([float(row["falls"]) for row in window]))
    episodes = float(np.mean([float(row["episodes"]) for row in window]))
    distance = float(np.mean([float(row["mean_distance"]) for row in window]))
    return falls <= FALL_SHARE * episodes and distance >= MIN_DISTANCE


def switch_step(rows: Sequence[dict[str, Any]], min_steps: int, max_steps: int) -> Optional[int]:
    """
    Where Stage 1 ends by Amendment 3, read on a sequence of evaluations.

    :param rows: evaluations in order of ``timesteps``
    :param min_steps: the first evaluation the criterion may be read at (200k)
    :param max_steps: the latest end (500k)
    :return: the first ``timesteps`` >= ``min_steps`` at which :func:`switch_met` holds, else ``max_steps`` once an
        evaluation has reached it, else None (Stage 1 goes on)
    """
    for index, row in enumerate(rows):
        step = int(row["timesteps"])
        if min_steps <= step <= max_steps and switch_met(rows[: index + 1]):
            return step
    return max_steps if rows and int(rows[-1]["timesteps"]) >= max_steps else None


def gate_passed(score: dict[str, Any]) -> bool:
    """:return: the registered gate on an end score: at most 2 falls in 20 episodes and at least 2 m on average"""
    return (
        float(score["falls"]) <= GATE_FALL_SHARE * float(score["episodes"]) and float(score["mean_distance"]) >= MIN_DISTANCE
    )


# ------------------------------------------------------------------------------------------------ envs and models
def make_env(env_id: str, param: str, switch_at: int = NEVER, stage: Optional[int] = None) -> gym.Env:
    """
    :param switch_at: the global timestep from which Env-B's setting holds (NEVER: Env-A for the whole run)
    :param stage: pin the env to Env-A (0) or Env-B (1), for evaluations
    :return: the env with ``param``'s true value appended to the observation (Env-A: its nominal value; Env-B:
        ``CHANGE``), as a :class:`~sb3_lifelong.envs.DynamicsSchedule` (transitions carry their stage: 0 or 1)
    """
    import sb3_lifelong.envs  # noqa: F401  (registers sb3_lifelong/OP3Walk-v0)
    from sb3_lifelong.envs import DynamicsSchedule

    env = DynamicsSchedule(gym.make(env_id), stages=[{}, {param: CHANGE}], switch_at=[switch_at], append_params=True)
    if stage is not None:
        env.set_stage(stage, immediate=True)
    return env


def eval_envs(env_id: str, param: str) -> dict[str, gym.Env]:
    """:return: Env-A and Env-B, each pinned to its stage"""
    return {name: make_env(env_id, param, stage=index) for index, name in enumerate(ENVS)}


def new_mpo(env: gym.Env, seed: int, net_arch: Optional[list[int]]) -> Any:
    """:return: MPO at Acme's MuJoCo baseline with a ``LifelongReplayBuffer`` in memory (its sources named)"""
    from sb3_lifelong import MPO, LifelongReplayBuffer
    from sb3_lifelong.mpo.presets import acme_mujoco

    preset = acme_mujoco(**({"policy_kwargs": {"net_arch": net_arch}} if net_arch else {}))
    model = MPO(
        "MlpPolicy", env, seed=seed, replay_buffer_class=LifelongReplayBuffer, compute=dict(compile_losses=False), **preset
    )
    buffer: Any = model.replay_buffer
    for index in reversed(range(len(ENVS))):
        buffer.set_source(index, name=ENVS[index])
    return model


def new_online_crr(method: str, stage1: Any, env: gym.Env, seed: int, replay: pathlib.Path) -> Any:
    """
    A CRR continued from the Stage-1 agent, as the experiments' online baselines
    (:func:`sb3_lifelong.experiments.protocol.online`): the Stage-1 policy's weights (actor and critic), a private
    copy of its buffer, the experiments' ``ONLINE`` settings (advantage transform, beta), CRR's defaults otherwise
    (1-step returns, 4 action samples, hard target copies every 100 updates), and the collector's update ratio,
    batch and learning rate (:func:`~sb3_lifelong.mpo.presets.acme_mujoco`), updates from the first step.
    """
    from sb3_lifelong import CRR, LifelongReplayBuffer
    from sb3_lifelong.buffers.views import merge_buffers
    from sb3_lifelong.experiments.presets import ONLINE
    from sb3_lifelong.mpo.presets import acme_mujoco

    preset = acme_mujoco()
    same = {key: preset[key] for key in ("train_freq", "gradient_steps", "batch_size", "learning_rate", "gamma")}
    model = CRR(
        "MlpPolicy",
        env,
        seed=seed,
        replay_buffer_class=LifelongReplayBuffer,
        learning_starts=0,
        policy_kwargs=dict(stage1.policy_kwargs),
        **same,
        **ONLINE[CRR_TRANSFORMS[method]],
    )
    model.policy.load_state_dict(stage1.policy.state_dict())
    model.load_replay_buffer(replay)  # Stage 1's buffer, unpickled: this agent's own copy
    # re-made at CRR's own n-step length (the pickle holds MPO's 4-step sampler), as protocol.online's merge_buffers
    buffer: Any = model.replay_buffer
    model.replay_buffer = merge_buffers([buffer], n_steps=model.n_steps, gamma=model.gamma)
    model.num_timesteps = stage1.num_timesteps
    return model


def evaluate(model: Any, env: gym.Env, episodes: int, first_seed: int) -> dict[str, float]:
    """
    Deterministic episodes from the reset seeds ``first_seed + k``.

    :return: mean and sd of the return, mean length, falls (episodes terminated before the time limit), the mean
        distance along x (``info["x_position"]`` at the end minus at the reset; NaN where the env gives none), episodes
    """
    returns, lengths, falls, distances = [], [], 0, []
    for k in range(episodes):
        obs, info = env.reset(seed=first_seed + k)
        x0 = info.get("x_position")
        total, length, done = 0.0, 0, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, info = env.step(action)
            total, length, done = total + float(reward), length + 1, terminated or truncated
        falls += int(terminated)
        returns.append(total)
        lengths.append(length)
        distances.append(info["x_position"] - x0 if x0 is not None and "x_position" in info else float("nan"))
    return {
        "mean_return": float(np.mean(returns)),
        "std_return": float(np.std(returns)),
        "mean_length": float(np.mean(lengths)),
        "falls": falls,
        "mean_distance": float(np.mean(distances)),
        "episodes": episodes,
    }


def end_scores(model: Any, envs: dict[str, gym.Env], episodes: int) -> dict[str, dict[str, float]]:
    """:return: the end score (``episodes`` episodes from the reset seeds 20000...) in each environment"""
    return {name: evaluate(model, env, episodes, END_SEED) for name, env in envs.items()}


def settings_of(model: Any) -> dict[str, Any]:
    """:return: what a run's cost and learning depend on most: the update ratio, n-step returns, batch and networks"""
    return {
        "algorithm": type(model).__name__,
        "train_freq": model.train_freq.frequency,
        "gradient_steps": model.gradient_steps,
        "n_steps": getattr(model, "n_steps", 1),
        "batch_size": model.batch_size,
        "learning_rate": model.learning_rate,
        "net_arch": model.policy_kwargs.get("net_arch"),
        **{key: getattr(model, key) for key in ("advantage_transform", "beta") if hasattr(model, key)},
    }


def machine() -> dict[str, Any]:
    """:return: what a run's cost depends on: the CPU and its matrix flags (AMX, BF16, ...), torch threads, versions,
    the commit"""
    import sb3_lifelong
    from sb3_lifelong.numerics.hardware import cpu_matrix_flags, cpu_model

    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=STUDY, capture_output=True, text=True).stdout
    except OSError:
        commit = ""
    return {
        "cpu": cpu_model(),
        "cpu_flags": cpu_matrix_flags(),
        "torch_threads": th.get_num_threads(),
        "torch": th.__version__,
        "sb3_lifelong": sb3_lifelong.__version__,
        "commit": commit.strip(),
    }


# ------------------------------------------------------------------------------------------------ files
def read_rows(path: pathlib.Path) -> list[dict[str, str]]:
    """:return: a CSV's rows (none when it does not exist)"""
    if not path.exists():
        return []
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def write_rows(path: pathlib.Path, rows: list[dict[str, Any]], fields: list[str]) -> None:
    """Write a CSV atomically (a killed job leaves the previous file)."""
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)


def write_json(path: pathlib.Path, data: dict[str, Any]) -> None:
    """Write a JSON file atomically."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)


def seed_results(args: argparse.Namespace) -> pathlib.Path:
    """:return: the seed's results folder (created)"""
    folder = pathlib.Path(args.results) / f"seed_{args.seed}"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def job_folder(args: argparse.Namespace, job: str) -> pathlib.Path:
    """:return: the job's checkpoint folder in ``--runs`` (created)"""
    folder = pathlib.Path(args.runs) / f"seed_{args.seed}" / job
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def save_checkpoint(model: Any, folder: pathlib.Path, state: dict[str, Any], name: str = "model") -> None:
    """Save the model, its whole buffer and ``state`` (the timestep they reach), each file replaced atomically."""
    model.save(folder / f"{name}.tmp.zip")
    model.save_replay_buffer(folder / "replay.tmp.pkl")
    os.replace(folder / f"{name}.tmp.zip", folder / f"{name}.zip")
    os.replace(folder / "replay.tmp.pkl", folder / "replay.pkl")
    write_json(folder / "state.json", state)


def load_checkpoint(algo_class: Any, folder: pathlib.Path, env: gym.Env, name: str = "model") -> Any:
    """:return: the model of a checkpoint with its buffer (n-step returns never chain across the resume)"""
    model = algo_class.load(folder / f"{name}.zip", env=env)
    model.load_replay_buffer(folder / "replay.pkl")
    model.replay_buffer.end_streams()
    return model


def check_run(record: dict[str, Any], args: argparse.Namespace, what: str) -> None:
    """:raises SystemExit: a job continued with another env, parameter, network or Stage-1 rule than it started with"""
    for key in ("env", "param", "net_arch", "min_steps", "max_steps"):
        if key in record and hasattr(args, key) and record[key] != getattr(args, key):
            raise SystemExit(f"{what} ran with --{key.replace('_', '-')} {record[key]}, not {getattr(args, key)}")


def check_intervals(args: argparse.Namespace) -> None:
    """:raises SystemExit: an evaluation interval that is not positive, or checkpoints off the evaluations"""
    if args.eval_every <= 0 or args.checkpoint_every <= 0 or args.checkpoint_every % args.eval_every:
        raise SystemExit("--eval-every must be > 0 and --checkpoint-every a positive multiple of --eval-every")


# ------------------------------------------------------------------------------------------------ stage 1
def stage1_record(args: argparse.Namespace, switch: int, rows: list[dict[str, Any]], end: dict[str, Any]) -> dict:
    """
    :return: what ``stage1.json`` holds: ``switch_step`` (L), ``criterion_met`` (Amendment 3's criterion at L;
        False when Stage 1 ran to ``--max-steps`` without it), ``gate`` (the frozen agent's Env-A end score:
        ``falls`` of ``episodes``, ``mean_distance``, ``mean_return``, ``passed``), ``learnt`` (criterion met and gate
        passed: the seed continues into Env-B), ``end`` (the frozen agent's end scores in Env-A and Env-B), and the
        run's settings
    """
    met = switch_met([row for row in rows if int(row["timesteps"]) <= switch])
    gate = {key: end["Env-A"][key] for key in ("falls", "episodes", "mean_distance", "mean_return")}
    gate["passed"] = gate_passed(end["Env-A"])
    return {
        "seed": args.seed,
        "env": args.env,
        "param": args.param,
        "change": CHANGE,
        "net_arch": args.net_arch,
        "switch_step": switch,
        "criterion_met": met,
        "gate": gate,
        "learnt": bool(met and gate["passed"]),
        "end": end,
        "min_steps": args.min_steps,
        "max_steps": args.max_steps,
        "eval_every": args.eval_every,
        "eval_episodes": args.eval_episodes,
        "end_episodes": args.end_episodes,
    }


def run_stage1(args: argparse.Namespace) -> dict[str, Any]:
    """Stage 1 of a seed to Amendment 3's switch, then the gate (resumes from its last checkpoint)."""
    from sb3_lifelong import MPO

    check_intervals(args)
    if not 0 < args.min_steps <= args.max_steps:
        raise SystemExit("--min-steps must be > 0 and at most --max-steps")
    th.set_num_threads(1)
    results, folder = seed_results(args), job_folder(args, "stage1")
    csv_path, json_path, state_path, meta_path = (
        results / "stage1.csv",
        results / "stage1.json",
        folder / "state.json",
        results / "stage1_runs.json",
    )
    if json_path.exists():
        record = json.loads(json_path.read_text())
        check_run(record, args, "stage 1")
        print(f"stage 1 of seed {args.seed} has finished: L = {record['switch_step']}, learnt: {record['learnt']}")
        return record
    env, evals = make_env(args.env, args.param), eval_envs(args.env, args.param)
    if state_path.exists():
        state = json.loads(state_path.read_text())
        check_run(state, args, "stage 1's checkpoint")
        finished = bool(state.get("finished"))  # killed between the agent's save and stage1.json
        model = load_checkpoint(MPO, folder, env, name="agent" if finished else "model")
        done, wall = int(state["timesteps"]), float(state["wall_s"])
        rows: list[dict[str, Any]] = [row for row in read_rows(csv_path) if int(row["timesteps"]) <= done]
        print(f"stage 1, seed {args.seed}: resumed at {done} steps", flush=True)
    else:
        model, done, wall, finished = new_mpo(env, args.seed, args.net_arch), 0, 0.0, False
        rows = [
            {"timesteps": 0, "updates": 0, **evaluate(model, evals["Env-A"], args.eval_episodes, EVAL_SEED), "wall_s": 0.0}
        ]
        write_rows(csv_path, rows, STAGE1_FIELDS)
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {"machines": []}
    meta.update({"settings": settings_of(model), "command": " ".join(sys.argv)})
    meta["machines"].append({"from_timesteps": done, **machine()})
    write_json(meta_path, meta)
    state = {key: getattr(args, key) for key in ("env", "param", "net_arch", "min_steps", "max_steps")}
    switch = switch_step(rows, args.min_steps, args.max_steps)
    while switch is None:
        start = time.perf_counter()
        model.learn(min(args.eval_every, args.max_steps - done), reset_num_timesteps=done == 0 and model.num_timesteps == 0)
        wall += time.perf_counter() - start
        done = model.num_timesteps
        score = evaluate(model, evals["Env-A"], args.eval_episodes, EVAL_SEED)
        rows.append({"timesteps": done, "updates": int(model._n_updates), **score, "wall_s": wall})
        write_rows(csv_path, rows, STAGE1_FIELDS)
        print(f"stage 1, seed {args.seed}: {done} steps, return {score['mean_return']:.0f}, falls {score['falls']}, "
              f"{score['mean_distance']:.2f} m", flush=True)  # fmt: skip
        switch = switch_step(rows, args.min_steps, args.max_steps)
        if switch is None and done % args.checkpoint_every == 0:
            save_checkpoint(model, folder, {**state, "timesteps": done, "wall_s": wall})
    if not finished:
        save_checkpoint(model, folder, {**state, "timesteps": done, "wall_s": wall, "finished": True}, name="agent")
        (folder / "model.zip").unlink(missing_ok=True)  # the agent is the last checkpoint
    record = stage1_record(args, switch, rows, end_scores(model, evals, args.end_episodes))
    write_json(json_path, record)
    print(f"stage 1, seed {args.seed}: L = {switch}, criterion met: {record['criterion_met']}, gate: "
          f"{record['gate']}, learnt: {record['learnt']}", flush=True)  # fmt: skip
    return record


# ------------------------------------------------------------------------------------------------ stage 2
def stage1_for(args: argparse.Namespace) -> dict[str, Any]:
    """
    :return: the seed's ``stage1.json``
    :raises SystemExit: Stage 1 has not finished, or its gate says Env-A was not learnt (unless ``--force``), or it
        ran with another env, parameter or network
    """
    path = seed_results(args) / "stage1.json"
    if not path.exists():
        raise SystemExit(f"env_b refused: stage 1 of seed {args.seed} has not finished ({path} does not exist)")
    record = json.loads(path.read_text())
    check_run(record, args, "stage 1")
    if not record["learnt"] and not args.force:
        gate = record["gate"]
        raise SystemExit(
            f"env_b refused: Env-A not learnt on seed {args.seed} (switch at {record['switch_step']}, criterion met: "
            f"{record['criterion_met']}; gate: {gate['falls']} falls of {gate['episodes']}, {gate['mean_distance']:.2f} "
            f"m, passed: {gate['passed']}); --force runs it anyway"
        )
    return record


def start_env_b(args: argparse.Namespace, env: gym.Env, switch: int) -> Any:
    """:return: the method's agent at the start of Env-B, continued from the frozen Stage-1 agent"""
    from sb3_lifelong import MPO

    stage1 = job_folder(args, "stage1")
    if args.method in ("mpo", "mpo_a"):
        model = load_checkpoint(MPO, stage1, env, name="agent")
    else:
        frozen = MPO.load(stage1 / "agent.zip")
        model = new_online_crr(args.method, frozen, env, args.seed, stage1 / "replay.pkl")
    if model.num_timesteps != switch:
        raise SystemExit(f"the Stage-1 agent is at {model.num_timesteps} steps, but stage1.json says L = {switch}")
    return model


def evaluation_rows(model: Any, evals: dict[str, gym.Env], args: argparse.Namespace, switch: int, wall: float) -> list:
    """:return: one row per environment of an evaluation at the model's timestep"""
    base = {"timesteps": model.num_timesteps, "stage2_steps": model.num_timesteps - switch}
    base["updates"] = int(model._n_updates)
    return [
        {**base, "env": name, **evaluate(model, env, args.eval_episodes, EVAL_SEED), "wall_s": wall}
        for name, env in evals.items()
    ]


def run_env_b(args: argparse.Namespace) -> dict[str, Any]:
    """
    One method's Env-B run of a seed, ``--steps`` steps from the Stage-1 agent (resumes from its last checkpoint).
    Writes ``env_b_<method>.json``: ``method``, ``seed``, ``switch_step`` (L), ``steps``, ``timesteps`` (L + steps
    at the end), ``train_env`` (Env-A for ``mpo_a``, else Env-B), ``end`` (end scores on ``--end-episodes`` episodes
    per environment, once finished), ``finished``, ``stage1_learnt``, ``forced`` (ever run with ``--force``),
    ``settings``, ``machines``. The CSV's ``updates`` are the agent's own: MPO's continue from Stage 1's, a CRR's
    count from 0.
    """
    from sb3_lifelong import CRR, MPO

    check_intervals(args)
    if args.steps <= 0:
        raise SystemExit("--steps must be > 0")
    th.set_num_threads(1)
    record = stage1_for(args)
    switch = int(record["switch_step"])
    job = f"env_b_{args.method}"
    results, folder = seed_results(args), job_folder(args, job)
    csv_path, json_path, state_path = results / f"{job}.csv", results / f"{job}.json", folder / "state.json"
    train_env = "Env-A" if args.method == "mpo_a" else "Env-B"
    env = make_env(args.env, args.param, switch_at=NEVER if train_env == "Env-A" else switch)
    evals = eval_envs(args.env, args.param)
    if state_path.exists():
        state = json.loads(state_path.read_text())
        model = load_checkpoint(MPO if args.method.startswith("mpo") else CRR, folder, env)
        done, wall = int(state["timesteps"]), float(state["wall_s"])
        rows: list[dict[str, Any]] = [row for row in read_rows(csv_path) if int(row["timesteps"]) <= done]
        print(f"{job}, seed {args.seed}: resumed at {done} steps", flush=True)
    else:
        model, wall = start_env_b(args, env, switch), 0.0
        done = model.num_timesteps
        rows = evaluation_rows(model, evals, args, switch, wall)
        write_rows(csv_path, rows, ENV_B_FIELDS)
    meta = json.loads(json_path.read_text()) if json_path.exists() else {"machines": []}
    meta.update({"method": args.method, "seed": args.seed, "env": args.env, "param": args.param, "switch_step": switch})
    meta.update({"steps": args.steps, "train_env": train_env, "settings": settings_of(model), "finished": False})
    meta.update({"stage1_learnt": record["learnt"], "forced": bool(args.force) or meta.get("forced", False)})
    meta.update({"eval_every": args.eval_every, "eval_episodes": args.eval_episodes, "command": " ".join(sys.argv)})
    meta["machines"].append({"from_timesteps": done, **machine()})
    meta.pop("end", None)
    write_json(json_path, meta)
    target = switch + args.steps
    while done < target:
        start = time.perf_counter()
        model.learn(min(args.eval_every, target - done), reset_num_timesteps=False)
        wall += time.perf_counter() - start
        done = model.num_timesteps
        rows += evaluation_rows(model, evals, args, switch, wall)
        write_rows(csv_path, rows, ENV_B_FIELDS)
        last = {row["env"]: row for row in rows[-len(ENVS) :]}
        print(f"{job}, seed {args.seed}: {done - switch} Env-B steps, return A {last['Env-A']['mean_return']:.0f}, "
              f"B {last['Env-B']['mean_return']:.0f}", flush=True)  # fmt: skip
        if (done - switch) % args.checkpoint_every == 0 or done >= target:
            save_checkpoint(model, folder, {"timesteps": done, "wall_s": wall})
    meta.update({"timesteps": done, "end": end_scores(model, evals, args.end_episodes), "finished": True, "wall_s": wall})
    write_json(json_path, meta)
    print(f"{job}, seed {args.seed}: done at {done} steps ({wall / 3600:.2f} h)", flush=True)
    return meta


# ------------------------------------------------------------------------------------------------ students
def lifetime_record(args: argparse.Namespace) -> dict[str, Any]:
    """
    :return: the seed's ``env_b_mpo.json`` (MPO's collection: its buffer is the students' lifetime buffer)
    :raises SystemExit: the job has not finished, naming its file
    """
    path = pathlib.Path(args.results) / f"seed_{args.seed}" / "env_b_mpo.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    if not record.get("finished"):
        raise SystemExit(
            f"the students of seed {args.seed} need MPO's lifetime buffer: env_b --method mpo has not finished ({path} "
            f"{'says finished: false' if path.exists() else 'does not exist'})"
        )
    check_run(record, args, "env_b mpo")
    return record


def load_lifetime_buffer(args: argparse.Namespace) -> Any:
    """:return: MPO's lifetime buffer of the seed (``<runs>/seed_<S>/env_b_mpo/replay.pkl``, unpickled)"""
    from stable_baselines3.common.save_util import load_from_pkl

    path = pathlib.Path(args.runs) / f"seed_{args.seed}" / "env_b_mpo" / "replay.pkl"
    if not path.exists():
        raise SystemExit(f"the students of seed {args.seed} need MPO's lifetime buffer: {path} does not exist")
    return load_from_pkl(path)


def env_a_rows(sources: np.ndarray) -> int:
    """
    :param sources: the source of every row of the lifetime buffer, in order
    :return: the number of Env-A rows (source 0), which are the buffer's first rows
    :raises SystemExit: a source other than 0 and 1, or Env-A rows after an Env-B row (not Stage 1 then Env-B)
    """
    others = sorted(set(np.unique(sources).tolist()) - {0, 1})
    if others:
        raise SystemExit(f"the lifetime buffer holds sources {others}: only 0 (Env-A) and 1 (Env-B) are known")
    count = int(np.sum(sources == 0))
    if np.any(sources[:count] != 0):
        raise SystemExit("the lifetime buffer's Env-A rows are not its first rows (Stage 1, then Env-B)")
    return count


def q_rows(sources: np.ndarray, seed: int, count: int = Q_ROWS) -> np.ndarray:
    """
    C4b's rows: ``count`` Env-A rows of a seed's lifetime buffer, drawn without replacement with a generator seeded
    by :data:`Q_ROWS_SEED` and the seed alone, so that every student of the seed is measured on the same rows.

    :param sources: the source of every row of the lifetime buffer
    :param seed: the seed of the buffer
    :param count: how many rows
    :return: the rows' indices, in increasing order
    :raises SystemExit: the buffer holds fewer Env-A rows
    """
    env_a = np.flatnonzero(np.asarray(sources) == 0)
    if len(env_a) < count:
        raise SystemExit(f"C4b's instrument needs {count} Env-A rows; the lifetime buffer holds {len(env_a)}")
    return np.sort(np.random.default_rng([Q_ROWS_SEED, seed]).choice(env_a, size=count, replace=False))


def rows_digest(indices: np.ndarray) -> str:
    """:return: a short hash of row indices (two students measured on the same rows have the same)"""
    return hashlib.sha256(np.asarray(indices, dtype=np.int64).tobytes()).hexdigest()[:16]


def gather_rows(buffer: Any, name: str, indices: np.ndarray) -> np.ndarray:
    """:return: the stored field ``name`` at the rows ``indices`` (read one row at a time: no whole-buffer copy)"""
    return np.concatenate([np.asarray(buffer.read_range(name, int(i), int(i) + 1)) for i in indices])


def mean_q(model: Any, observations: np.ndarray, actions: np.ndarray) -> float:
    """:return: the mean Q (the expected value of the categorical critic's first network) of stored rows"""
    obs = th.as_tensor(observations, dtype=th.float32, device=model.device)
    act = th.as_tensor(actions, dtype=th.float32, device=model.device)
    with th.no_grad():
        return float(model.critic(obs, act)[0].mean())


def scaled_support(reward_range: tuple[float, float], scale: float, gamma: float = 0.99) -> dict[str, float]:
    """
    The students' support: the experiments' :func:`~sb3_lifelong.experiments.jobs.value_support` (the buffer's reward
    bounds over 1 - gamma, 0 included), its bounds multiplied by ``scale`` (a support ``scale`` times as wide, 0 at
    the same place).

    :return: ``v_min`` and ``v_max``, and the unscaled ``base_v_min`` and ``base_v_max``
    """
    from sb3_lifelong.experiments.jobs import value_support

    if not scale > 0:
        raise SystemExit(f"the support's scale must be > 0, got {scale}")
    base = value_support(reward_range, gamma)
    return {
        "v_min": base["v_min"] * scale,
        "v_max": base["v_max"] * scale,
        "base_v_min": base["v_min"],
        "base_v_max": base["v_max"],
    }


def support_scale(args: argparse.Namespace) -> tuple[float, str]:
    """
    :return: the support's scale and where it comes from: ``--support-scale``, else the sweep's choice in
        ``<results>/support.json``
    :raises SystemExit: neither is given (the file named), or a registered (500k-update) student would read a
        support.json that is not the registered sweep's
    """
    if args.support_scale is not None:
        return float(args.support_scale), "--support-scale"
    path = pathlib.Path(args.results) / SUPPORT_FILE
    if not path.exists():
        raise SystemExit(
            f"student refused: the support sweep has not fixed the support ({path} does not exist): run `sweep` first "
            f"(or give --support-scale for a small check)"
        )
    record = json.loads(path.read_text())
    if args.updates == STUDENT_UPDATES and not record.get("registered"):
        raise SystemExit(f"student refused: {path} is not the registered sweep ({record.get('why_not_registered')})")
    return float(record["choice"]), str(path)


class SourceTally:
    """
    Counts the source of every row a student draws: replaces its data's ``sample`` by itself (the same draws, the
    batch's sources asked for too), so the counts are those of the batches the student trained on.

    :param data: the student's data (a ``LifelongReplayBuffer`` or view)
    :param counts: counts to continue (a resumed student's)
    """

    def __init__(self, data: Any, counts: Optional[dict[int, int]] = None) -> None:
        self.sample = data.sample
        self.counts: dict[int, int] = dict(counts or {})
        data.sample = self

    def __call__(self, batch_size: int, env: Any = None, **kwargs: Any) -> Any:
        wanted = bool(kwargs.pop("return_sources", False))
        samples, sources = self.sample(batch_size, env=env, return_sources=True, **kwargs)
        ids, counts = np.unique(sources.cpu().numpy(), return_counts=True)
        for source, count in zip(ids.tolist(), counts.tolist()):
            self.counts[int(source)] = self.counts.get(int(source), 0) + int(count)
        return (samples, sources) if wanted else samples


def by_name(counts: dict[int, int]) -> dict[str, int]:
    """:return: per-source counts keyed by the environments' names (every environment, 0 where none)"""
    return {name: int(counts.get(index, 0)) for index, name in enumerate(ENVS)}


def student_data(buffer: Any, a_only: bool, n_env_a: int, gamma: float) -> Any:
    """
    :return: what a student samples, at 1-step returns (the pickle holds MPO's 4-step sampler): a view of the whole
        lifetime buffer, or for an Env-A-only student a copy of its Env-A rows alone (its first ``n_env_a`` rows)
    """
    from sb3_lifelong.buffers import LifelongBufferView, merge_buffers

    if a_only:
        return merge_buffers([buffer], stops=[n_env_a], n_steps=1, gamma=gamma)
    return LifelongBufferView([buffer], n_steps=1, gamma=gamma)


def student_settings(args: argparse.Namespace, support: dict[str, float]) -> dict[str, Any]:
    """:return: the student's constructor arguments: its transform, 51 atoms on ``support``, the collector's torso"""
    from sb3_lifelong.mpo.presets import acme_mujoco

    net_arch = args.net_arch or acme_mujoco()["policy_kwargs"]["net_arch"]
    policy_kwargs = dict(net_arch=list(net_arch), layer_norm=True, distributional_critic=True, n_atoms=N_ATOMS)
    policy_kwargs.update(v_min=support["v_min"], v_max=support["v_max"])
    kwargs = dict(batch_size=STUDENT_BATCH, seed=args.seed, policy_kwargs=policy_kwargs, device=args.device)
    return {**kwargs, **STUDENTS[args.student]}


def student_rows(model: Any, evals: dict[str, gym.Env], args: argparse.Namespace, q: float, wall: float) -> list:
    """:return: one row per environment of an evaluation of a student, with C4b's mean Q"""
    base = {"updates": model.num_timesteps}
    return [
        {**base, "env": name, **evaluate(model, env, args.eval_episodes, EVAL_SEED), "q_env_a_rows": q, "wall_s": wall}
        for name, env in evals.items()
    ]


def run_student(args: argparse.Namespace, job: Optional[str] = None) -> dict[str, Any]:
    """
    One offline student of a seed (``--student``), ``--updates`` updates on MPO's lifetime buffer, evaluated every
    ``--eval-every`` updates in Env-A and Env-B, then its end scores; resumes from its last checkpoint (the model, with
    its random streams, and ``state.json``; the buffer is read again from the ``env_b_mpo`` job).

    Writes ``<job>.csv`` (:data:`STUDENT_FIELDS`) and ``<job>.json``: ``student``, ``seed``, ``updates``, ``finished``,
    ``a_only``, ``buffer_rows`` (the lifetime buffer's rows per environment), ``rows_per_source`` (the rows of the
    data the student samples), ``drawn_per_source`` (the rows of every batch it drew, counted), ``switch_step`` (L),
    ``support`` (``scale``, ``from``, ``v_min``, ``v_max``, the unscaled bounds, ``n_atoms``), ``q_rows`` (C4b's
    1,024 Env-A rows: ``count``, ``seed``, ``digest``, ``first``), ``q_env_a_rows`` (the critic's mean Q on them at
    the end), ``end`` (``--end-episodes`` episodes per environment), ``settings``, ``machines``.

    :param job: the job's name (default ``student_<student>``; the sweep's are ``sweep_<student>_<scale>x``)
    """
    from sb3_lifelong import CRR
    from sb3_lifelong.distill import distill

    check_intervals(args)
    if args.updates <= 0:
        raise SystemExit("--updates must be > 0")
    th.set_num_threads(1)
    job = job or f"student_{args.student}"
    results, folder = seed_results(args), job_folder(args, job)
    csv_path, json_path, state_path = results / f"{job}.csv", results / f"{job}.json", folder / "state.json"
    if json_path.exists() and json.loads(json_path.read_text()).get("finished"):
        record = json.loads(json_path.read_text())
        check_run(record, args, job)
        if record["updates"] != args.updates:
            raise SystemExit(f"{job} of seed {args.seed} has finished at {record['updates']} updates, not {args.updates}")
        print(f"{job} of seed {args.seed} has finished")
        return record
    lifetime = lifetime_record(args)
    scale, origin = support_scale(args)
    buffer = load_lifetime_buffer(args)
    sources = np.asarray(buffer.read_range("sources", 0, buffer.size()))
    n_env_a = env_a_rows(sources)
    support = scaled_support(buffer.reward_range(), scale)
    a_only = args.student in A_ONLY
    data = student_data(buffer, a_only, n_env_a, gamma=0.99)
    chosen = q_rows(sources, args.seed)
    q_obs, q_actions = gather_rows(buffer, "observations", chosen), gather_rows(buffer, "actions", chosen)
    evals = eval_envs(args.env, args.param)
    identity = {"student": args.student, "total_updates": args.updates, "support_scale": scale}
    identity.update({key: getattr(args, key) for key in ("env", "param", "net_arch", "eval_every")})
    model: Any = None
    if state_path.exists():
        state = json.loads(state_path.read_text())
        for key, value in identity.items():
            if state.get(key) != value:
                raise SystemExit(f"{job}'s checkpoint ran with {key} {state.get(key)}, not {value}")
        model = CRR.load(folder / "model.zip", device=args.device)
        model.set_offline_data(data)
        done, wall, drawn = int(state["updates"]), float(state["wall_s"]), {int(k): v for k, v in state["drawn"].items()}
        rows: list[dict[str, Any]] = [row for row in read_rows(csv_path) if int(row["updates"]) <= done]
        print(f"{job}, seed {args.seed}: resumed at {done} updates", flush=True)
    else:
        done, wall, drawn, rows = 0, 0.0, {}, []
    tally = SourceTally(data, drawn)
    meta = json.loads(json_path.read_text()) if json_path.exists() else {"machines": []}
    meta.update({"student": args.student, "job": job, "seed": args.seed, "env": args.env, "param": args.param})
    meta.update({"net_arch": args.net_arch, "updates": args.updates, "a_only": a_only, "finished": False})
    meta.update({"switch_step": lifetime["switch_step"], "stage1_learnt": lifetime["stage1_learnt"]})
    meta.update({"buffer_rows": by_name({0: n_env_a, 1: len(sources) - n_env_a})})
    meta.update({"rows_per_source": by_name(data.source_counts()), "eval_every": args.eval_every})
    meta.update({"support": {"scale": scale, "from": origin, **support, "n_atoms": N_ATOMS}})
    meta.update({"q_rows": {"count": len(chosen), "seed": Q_ROWS_SEED, "digest": rows_digest(chosen)}})
    meta["q_rows"]["first"] = chosen[:8].tolist()
    meta.update({"eval_episodes": args.eval_episodes, "end_episodes": args.end_episodes, "command": " ".join(sys.argv)})
    meta["machines"].append({"from_updates": done, "device": args.device, **machine()})
    meta.pop("end", None)
    write_json(json_path, meta)
    while done < args.updates:
        chunk = min(args.eval_every, args.updates - done)
        start = time.perf_counter()
        if model is None:
            model = distill(data, CRR, total_updates=chunk, log_interval=0, **student_settings(args, support))
        else:
            model.learn_offline(chunk, reset_num_timesteps=False, log_interval=0)
        wall += time.perf_counter() - start
        done = model.num_timesteps
        rows += student_rows(model, evals, args, mean_q(model, q_obs, q_actions), wall)
        write_rows(csv_path, rows, STUDENT_FIELDS)
        last = {row["env"]: row for row in rows[-len(ENVS) :]}
        print(f"{job}, seed {args.seed}: {done} updates, return A {last['Env-A']['mean_return']:.0f}, "
              f"B {last['Env-B']['mean_return']:.0f}, Q {last['Env-A']['q_env_a_rows']:.1f}", flush=True)  # fmt: skip
        if done % args.checkpoint_every == 0 or done >= args.updates:
            model.save(folder / "model.tmp.zip")
            os.replace(folder / "model.tmp.zip", folder / "model.zip")
            write_json(state_path, {**identity, "updates": done, "wall_s": wall, "drawn": tally.counts})
    meta.update({"settings": {**settings_of(model), "n_atoms": N_ATOMS, "v_min": support["v_min"], "v_max": support["v_max"]}})
    meta.update({"drawn_per_source": by_name(tally.counts), "q_env_a_rows": mean_q(model, q_obs, q_actions)})
    meta.update({"end": end_scores(model, evals, args.end_episodes), "finished": True, "wall_s": wall})
    write_json(json_path, meta)
    print(f"{job}, seed {args.seed}: done at {done} updates ({wall / 3600:.2f} h)", flush=True)
    return meta


# ------------------------------------------------------------------------------------------------ the support sweep
def sweep_seeds(results: pathlib.Path, count: int = SWEEP_SEEDS) -> list[int]:
    """
    :param results: the study's results folder
    :param count: how many seeds the sweep reads
    :return: the first ``count`` testable seeds (Env-A learnt by Stage 1's record), in the order seeds are started
    :raises SystemExit: fewer are known so far (naming the first seed whose Stage 1 has not finished)
    """
    seeds: list[int] = []
    seed = 0
    while len(seeds) < count:
        path = results / f"seed_{seed}" / "stage1.json"
        if not path.exists():
            raise SystemExit(
                f"sweep refused: it reads the first {count} testable seeds, and {len(seeds)} are known so far "
                f"({seeds}); stage 1 of seed {seed} has not finished ({path} does not exist)"
            )
        if json.loads(path.read_text())["learnt"]:
            seeds.append(seed)
        seed += 1
    return seeds


def sweep_job(scale: int) -> str:
    """:return: the job name of the sweep's student at a support ``scale`` times as wide"""
    return f"sweep_{SWEEP_STUDENT}_{scale}x"


def support_record(results: pathlib.Path, seeds: Sequence[int]) -> Optional[dict[str, Any]]:
    """
    The sweep's reading (Design item 3): per seed and width, the end returns in Env-A and Env-B and their mean; the
    width with the higher mean over seeds of (Env-A + Env-B) / 2 is fixed (a tie keeps the data's own width, 1x).

    :return: what ``support.json`` holds, or None while a sweep student has not finished
    """
    per_seed: dict[str, dict[str, Any]] = {}
    why_not: set[str] = set()
    for seed in seeds:
        per_seed[str(seed)] = {}
        for scale in SUPPORT_SCALES:
            path = results / f"seed_{seed}" / f"{sweep_job(scale)}.json"
            record = json.loads(path.read_text()) if path.exists() else {}
            if not record.get("finished"):
                return None
            end = {env: float(record["end"][env]["mean_return"]) for env in ENVS}
            per_seed[str(seed)][f"{scale}x"] = {
                **end,
                "mean": float(np.mean(list(end.values()))),
                "v_min": record["support"]["v_min"],
                "v_max": record["support"]["v_max"],
                "updates": record["updates"],
            }
            for what, wrong in (
                (f"{record['updates']} updates, not {SWEEP_UPDATES}", record["updates"] != SWEEP_UPDATES),
                (f"--env {record['env']}", record["env"] != OP3),
                (f"--param {record['param']}", record["param"] != PARAM),
                (f"--net-arch {record['net_arch']}", record["net_arch"] is not None),
                (f"{record['end_episodes']} end episodes", record["end_episodes"] != 20),
                (f"seed {seed}'s Stage 1 forced, not learnt", not record["stage1_learnt"]),
            ):
                if wrong:
                    why_not.add(what)
    means = {f"{scale}x": float(np.mean([per_seed[str(s)][f"{scale}x"]["mean"] for s in seeds])) for scale in SUPPORT_SCALES}
    choice = max(SUPPORT_SCALES, key=lambda scale: (means[f"{scale}x"], -scale))
    return {
        "student": SWEEP_STUDENT,
        "seeds": list(seeds),
        "per_seed": per_seed,
        "mean_over_seeds": means,
        "choice": choice,
        "rule": "the width with the higher mean over seeds of (Env-A + Env-B) / 2 end return (a tie keeps 1x)",
        "registered": not why_not,
        "why_not_registered": "; ".join(sorted(why_not)) or None,
        "machine": machine(),
    }


def run_sweep(args: argparse.Namespace) -> Optional[dict[str, Any]]:
    """
    The support sweep: the exp student at 1x and 3x the support's width on the first three testable seeds' lifetime
    buffers (``--seed`` and ``--support-scale`` run one part of it, e.g. one per core), then ``support.json`` once
    every part has finished.

    :return: what ``support.json`` holds, or None while a part has not finished
    """
    results = pathlib.Path(args.results)
    seeds = sweep_seeds(results)
    if args.seed is not None and args.seed not in seeds:
        raise SystemExit(f"--seed {args.seed} is not one of the sweep's seeds {seeds}")
    for seed in seeds:
        for scale in SUPPORT_SCALES:
            if args.seed in (None, seed) and args.support_scale in (None, scale):
                part = argparse.Namespace(**{**vars(args), "seed": seed, "support_scale": scale, "student": SWEEP_STUDENT})
                run_student(part, job=sweep_job(scale))
    record = support_record(results, seeds)
    if record is None:
        print(f"the sweep's other parts have not finished: support.json is written when all of {len(seeds)} seeds x "
              f"{list(SUPPORT_SCALES)} are", flush=True)  # fmt: skip
        return None
    write_json(results / SUPPORT_FILE, record)
    print(f"support: {record['choice']}x (mean (Env-A + Env-B) / 2 over seeds {seeds}: {record['mean_over_seeds']})")
    return record


# ------------------------------------------------------------------------------------------------ the claims
@dataclass(frozen=True)
class ClaimRule:
    """
    One claim of the README's table: a per-seed series of end scores and the side of a threshold it claims.

    :param name: the claim (``C4a``)
    :param statement: the claim and its series, in words
    :param first: the series' first term, ``(job, env)``: ``job`` is ``stage1`` (the frozen Stage-1 agent), ``env_b_<method>``
        or ``student_<student>``; ``env`` is Env-A or Env-B (the end return there) or ``Q`` (C4b's mean Q)
    :param second: the second term (the largest of several: C3a's max(MPO end, frozen Stage-1))
    :param kind: ``ratio`` (first / second; every seed's second term must be above :data:`MIN_DENOMINATOR`) or
        ``difference`` (first - second)
    :param side: ``below`` or ``above`` the threshold
    :param threshold: the threshold
    :param read: whether the claim is read (False: reported beside another, C1's registered series)
    :param needs: a claim that must hold for this one to be read (C5 needs C4a's drop)
    """

    name: str
    statement: str
    first: tuple[str, str]
    second: tuple[tuple[str, str], ...]
    kind: str
    side: str
    threshold: float
    read: bool = True
    needs: Optional[str] = None


MPO_END_A, MPO_A_END_A, FROZEN_A = ("env_b_mpo", "Env-A"), ("env_b_mpo_a", "Env-A"), ("stage1", "Env-A")
CLAIMS = (
    ClaimRule(
        "C1", "MPO forgets Env-A: MPO end / MPO-A end, Env-A (Amendment 3)", MPO_END_A, (MPO_A_END_A,), "ratio", "below", 0.8
    ),
    ClaimRule("C1 registered", "MPO end / frozen Stage-1, Env-A", MPO_END_A, (FROZEN_A,), "ratio", "below", 0.8, read=False),
    ClaimRule("C1 drift", "MPO-A end / frozen Stage-1, Env-A", MPO_A_END_A, (FROZEN_A,), "ratio", "below", 0.8, read=False),
    ClaimRule(
        "C2a",
        "online CRR keeps Env-A better than MPO: online CRR exp end - MPO end, Env-A",
        ("env_b_online_crr_exp", "Env-A"),
        (MPO_END_A,),
        "difference",
        "above",
        0.0,
    ),
    ClaimRule(
        "C2b",
        "online CRR learns Env-B slower: MPO end - online CRR exp end, Env-B",
        ("env_b_mpo", "Env-B"),
        (("env_b_online_crr_exp", "Env-B"),),
        "difference",
        "above",
        0.0,
    ),
    ClaimRule(
        "C3a",
        "the pipeline's student in Env-A: exp student / max(MPO end, frozen Stage-1), Env-A",
        ("student_exp_combined", "Env-A"),
        (MPO_END_A, FROZEN_A),
        "ratio",
        "above",
        0.9,
    ),
    ClaimRule(
        "C3b",
        "the pipeline's student in Env-B: exp student / MPO end, Env-B",
        ("student_exp_combined", "Env-B"),
        (("env_b_mpo", "Env-B"),),
        "ratio",
        "above",
        0.9,
    ),
    ClaimRule(
        "C4a",
        "the combined indicator student drops in Env-A: indicator combined / indicator Env-A only, Env-A",
        ("student_indicator_combined", "Env-A"),
        (("student_indicator_a_only", "Env-A"),),
        "ratio",
        "below",
        0.8,
    ),
    ClaimRule(
        "C4b",
        "with higher Q on Env-A data: indicator combined - Env-A only, mean Q on 1,024 Env-A rows",
        ("student_indicator_combined", "Q"),
        (("student_indicator_a_only", "Q"),),
        "difference",
        "above",
        0.0,
    ),
    ClaimRule(
        "C5",
        "exp beta = 1 recovers C4's drop: exp combined / indicator Env-A only, Env-A",
        ("student_exp_combined", "Env-A"),
        (("student_indicator_a_only", "Env-A"),),
        "ratio",
        "above",
        0.9,
        needs="C4a",
    ),
)


def read_interval(values: Sequence[float], side: str, threshold: float) -> dict[str, Any]:
    """
    The README's reading of one per-seed series: the mean over the seeds with its 95 % t interval; *holds* when the
    whole interval is on the claimed side (strictly: ``high < threshold`` for ``below``, ``low > threshold`` for
    ``above``), *fails* when it is wholly on the other side (``low >= threshold``, ``high <= threshold``),
    *inconclusive* otherwise, *not testable* with fewer than :data:`MIN_SEEDS` seeds.

    :param values: one value per testable seed
    :param side: ``below`` or ``above``
    :param threshold: the threshold
    :return: ``n``, ``mean``, ``sd``, ``low``, ``high``, ``reading`` and ``why`` (for not testable)
    """
    from sb3_lifelong.experiments.statistics import t_interval

    if side not in ("below", "above"):
        raise ValueError(f"a claim's side is 'below' or 'above', got {side!r}")
    mean, sd, low, high = t_interval(list(values), level=0.95)
    out: dict[str, Any] = {"n": len(values), "mean": mean, "sd": sd, "low": low, "high": high, "why": None}
    if len(values) < MIN_SEEDS:
        return {**out, "reading": "not testable", "why": f"{len(values)} testable seeds (at least {MIN_SEEDS})"}
    if side == "below":
        reading = "holds" if high < threshold else "fails" if low >= threshold else "inconclusive"
    else:
        reading = "holds" if low > threshold else "fails" if high <= threshold else "inconclusive"
    return {**out, "reading": reading}


def term_value(record: dict[str, Any], env: str) -> float:
    """:return: a job's end return in ``env`` (Env-A or Env-B), or its critic's mean Q on C4b's rows (``Q``)"""
    return float(record["q_env_a_rows"]) if env == "Q" else float(record["end"][env]["mean_return"])


def read_claim(rule: ClaimRule, jobs: dict[int, dict[str, Any]], earlier: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """
    :param rule: the claim
    :param jobs: per testable seed, its finished jobs' records by job name (``stage1``, ``env_b_mpo``, ...)
    :param earlier: the claims read before, by name (for ``needs``)
    :return: the claim's per-seed ``series`` (seed -> value, on the seeds that have every job it reads),
        ``missing`` (seed -> the jobs it lacks), ``denominators`` (ratios), the interval and the ``reading``
    """
    series, denominators, missing = {}, {}, {}
    for seed, records in sorted(jobs.items()):
        needed = [rule.first[0], *(job for job, _ in rule.second)]
        lacking = sorted({job for job in needed if job not in records})
        if lacking:
            missing[seed] = lacking
            continue
        first = term_value(records[rule.first[0]], rule.first[1])
        second = max(term_value(records[job], env) for job, env in rule.second)
        if rule.kind == "ratio":
            denominators[seed] = second
            series[seed] = first / second if second != 0 else float("nan")
        else:
            series[seed] = first - second
    result: dict[str, Any] = {"claim": rule.name, "statement": rule.statement, "kind": rule.kind, "side": rule.side}
    result.update({"threshold": rule.threshold, "series": series, "missing": missing, "denominators": denominators})
    result.update(read_interval(list(series.values()), rule.side, rule.threshold))
    low = {seed: value for seed, value in denominators.items() if not value > MIN_DENOMINATOR}
    if result["reading"] != "not testable" and low:
        result.update(reading="not testable", why=f"a denominator at or below {MIN_DENOMINATOR} on seeds {low}")
    if rule.needs is not None and result["reading"] != "not testable":
        if earlier.get(rule.needs, {}).get("reading") != "holds":
            result.update(reading="not testable", why=f"read only where {rule.needs} holds (it does not: no drop to recover)")
    if not rule.read:
        result.update(reading="reported, not read", why=None)
    return result


def seed_rows(seed: int, records: dict[str, Any]) -> dict[str, Any]:
    """:return: a seed's L and its lifetime buffer's rows per environment (counted by a student, else MPO's steps)"""
    row: dict[str, Any] = {"seed": seed, "L": records["stage1"]["switch_step"] if "stage1" in records else None}
    counted = [records[job]["buffer_rows"] for job in sorted(records) if "buffer_rows" in records[job]]
    if counted:
        row.update(env_a_rows=counted[0]["Env-A"], env_b_rows=counted[0]["Env-B"], rows_from="counted by a student")
    elif "env_b_mpo" in records:
        mpo = records["env_b_mpo"]
        row.update(env_a_rows=mpo["switch_step"], env_b_rows=mpo["timesteps"] - mpo["switch_step"], rows_from="MPO's steps")
    if row.get("env_a_rows"):
        row["ratio"] = f"1:{row['env_b_rows'] / row['env_a_rows']:.2f}"
    return row


def claims_from(seeds: dict[int, dict[str, Any]], unfinished: dict[int, list[str]]) -> dict[str, Any]:
    """
    Every claim read on the testable seeds (Stage 1 learnt: criterion met and gate passed).

    :param seeds: per seed, its finished jobs' records by job name (``stage1``, ``env_b_<method>``, ``student_<name>``)
    :param unfinished: per seed, the jobs started but not finished
    :return: what ``claims.json`` holds: ``testable`` seeds, ``excluded`` (seed -> why), ``seeds`` (L and the rows
        per environment), ``claims`` (see :func:`read_claim`), ``c2_trade_off``, ``missing`` (seed -> the jobs the
        claims lack there, each ``missing`` or ``running``), ``unregistered`` (the students read that are not the
        registered ones: another number of updates, or the support given by ``--support-scale``)
    """
    testable, excluded = {}, {}
    for seed, records in sorted(seeds.items()):
        if "stage1" not in records:
            excluded[seed] = "stage 1 has not finished"
        elif not records["stage1"]["learnt"]:
            gate = records["stage1"]["gate"]
            excluded[seed] = (
                f"Env-A not learnt (criterion met: {records['stage1']['criterion_met']}; gate: {gate['falls']} falls of "
                f"{gate['episodes']}, {gate['mean_distance']:.2f} m)"
            )
        else:
            testable[seed] = records
    claims: dict[str, dict[str, Any]] = {}
    for rule in CLAIMS:
        claims[rule.name] = read_claim(rule, testable, claims)
    missing: dict[int, dict[str, str]] = {}
    for claim in claims.values():
        for seed, jobs in claim["missing"].items():
            for job in jobs:
                missing.setdefault(seed, {})[job] = "running" if job in unfinished.get(seed, []) else "missing"
    trade_off = claims["C2a"]["reading"] == "holds" and claims["C2b"]["reading"] == "holds"
    unregistered = {
        f"seed {seed}: {job}": f"{record.get('updates')} updates, support from {record.get('support', {}).get('from')}"
        for seed, records in sorted(testable.items())
        for job, record in sorted(records.items())
        if job.startswith("student_")
        and (record.get("updates") != STUDENT_UPDATES or record.get("support", {}).get("from") == "--support-scale")
    }
    return {
        "unregistered": unregistered,
        "testable": sorted(testable),
        "excluded": excluded,
        "seeds": [seed_rows(seed, records) for seed, records in sorted(seeds.items())],
        "claims": list(claims.values()),
        "c2_trade_off": "reproduced" if trade_off else "not reproduced",
        "missing": {seed: dict(sorted(jobs.items())) for seed, jobs in sorted(missing.items())},
    }


def load_seeds(results: pathlib.Path) -> tuple[dict[int, dict[str, Any]], dict[int, list[str]]]:
    """:return: per seed folder of ``results``, its finished jobs' records by job name, and its unfinished jobs"""
    seeds: dict[int, dict[str, Any]] = {}
    unfinished: dict[int, list[str]] = {}
    for folder in sorted(results.glob("seed_*"), key=lambda path: int(path.name.split("_")[1])):
        seed = int(folder.name.split("_")[1])
        seeds[seed], unfinished[seed] = {}, []
        for job in ["stage1", *(f"env_b_{m}" for m in METHODS), *(f"student_{s}" for s in STUDENTS)]:
            path = folder / f"{job}.json"
            if not path.exists():
                continue
            record = json.loads(path.read_text())
            if job == "stage1" or record.get("finished"):
                seeds[seed][job] = record
            else:
                unfinished[seed].append(job)
    return seeds, unfinished


def number(value: float, kind: str) -> str:
    """:return: a ratio with 3 decimals, a difference with 1"""
    return "-" if value is None or not np.isfinite(value) else f"{value:.3f}" if kind == "ratio" else f"{value:.1f}"


def claims_markdown(report: dict[str, Any], support: Optional[dict[str, Any]]) -> str:
    """:return: ``claims.md``: the seeds, the claims table, C2's trade-off and what is missing"""
    lines = ["# OP3 study: the claims read by the README's rules", ""]
    lines += ["Written by `paper_op3.py report` from the seeds' end scores (20 episodes per environment, reset seeds "
              "20000..20019); each claim is read on the 95 % t interval of its mean over the testable seeds."]  # fmt: skip
    lines += ["", "## Seeds", "", "| seed | L | Env-A rows | Env-B rows | Env-A:Env-B | status |"]
    lines.append("| --- | --- | --- | --- | --- | --- |")
    for row in report["seeds"]:
        state = report["excluded"].get(row["seed"], "testable")
        cells = [row["seed"], row["L"], row.get("env_a_rows", "-"), row.get("env_b_rows", "-"), row.get("ratio", "-"), state]
        lines.append("| " + " | ".join("-" if cell is None else str(cell) for cell in cells) + " |")
    if support is None:
        lines += ["", f"Support: not fixed yet (`{SUPPORT_FILE}` does not exist)."]
    else:
        means = support["mean_over_seeds"]
        lines += ["", f"Support: {support['choice']}x the data's own width, from the sweep on seeds {support['seeds']} "
                  f"(mean (Env-A + Env-B) / 2: {means}; registered: {support['registered']})."]  # fmt: skip
    lines += ["", "## Claims", "", "| claim | series | per seed | n | mean +- sd | 95 % t interval | threshold | reading |"]
    lines.append("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for claim in report["claims"]:
        kind = claim["kind"]
        per_seed = ", ".join(f"{seed}: {number(value, kind)}" for seed, value in claim["series"].items()) or "-"
        spread = f"{number(claim['mean'], kind)} +- {number(claim['sd'], kind)}"
        interval = f"[{number(claim['low'], kind)}, {number(claim['high'], kind)}]"
        reading = claim["reading"] + (f" ({claim['why']})" if claim["why"] else "")
        cells = [claim["claim"], claim["statement"], per_seed, claim["n"], spread, interval]
        cells += [f"{claim['side']} {claim['threshold']:g}", reading]
        lines.append("| " + " | ".join(str(cell) for cell in cells) + " |")
    lines += ["", f"C2's trade-off (C2a and C2b both hold): {report['c2_trade_off']}."]
    if report["excluded"]:
        lines += ["", "## Seeds excluded", ""]
        lines += [f"- seed {seed}: {why}" for seed, why in report["excluded"].items()]
    if report["unregistered"]:
        lines += ["", "## Students that are not the registered ones (small checks: their claims are not the study's)", ""]
        lines += [f"- {job}: {why}" for job, why in report["unregistered"].items()]
    if report["missing"]:
        lines += ["", "## Jobs missing (the claims that read them skip the seed)", ""]
        for seed, jobs in report["missing"].items():
            lines.append(f"- seed {seed}: " + ", ".join(f"{job} ({state})" for job, state in jobs.items()))
    return "\n".join(lines) + "\n"


def run_report(args: argparse.Namespace) -> dict[str, Any]:
    """Read every seed's files in ``--results`` and write ``claims.md`` and ``claims.json`` there."""
    results = pathlib.Path(args.results)
    results.mkdir(parents=True, exist_ok=True)
    seeds, unfinished = load_seeds(results)
    report = claims_from(seeds, unfinished)
    support_path = results / SUPPORT_FILE
    support = json.loads(support_path.read_text()) if support_path.exists() else None
    report["support"] = support
    write_json(results / "claims.json", json.loads(json.dumps(report, default=str)))
    text = claims_markdown(report, support)
    tmp = results / "claims.md.tmp"
    tmp.write_text(text)
    os.replace(tmp, results / "claims.md")
    print(text)
    return report


# ------------------------------------------------------------------------------------------------ status
def job_progress(folder: pathlib.Path, job: str, column: str, unit: str, label: Optional[str] = None) -> Optional[str]:
    """
    :param folder: a seed's results folder
    :param job: the job's name (its ``<job>.json`` and ``<job>.csv``)
    :param column: the CSV column that counts its progress
    :param unit: what the count is in (printed after it)
    :param label: the job's name in the line (default ``job``)
    :return: ``"<label> done"``, ``"<label> at <count><unit>"``, or None when the job has not started
    """
    path, label = folder / f"{job}.json", label or job
    if not path.exists():
        return None
    if json.loads(path.read_text()).get("finished"):
        return f"{label} done"
    rows = read_rows(folder / f"{job}.csv")
    return f"{label} at {rows[-1][column] if rows else 0}{unit}"


def status(args: argparse.Namespace) -> list[str]:
    """
    :return: (printed) per seed in ``--results``: Stage 1's switch, its gate, the state of each Env-B job and of each
        student (the sweep's too); then the support (the sweep's choice, or "not swept")
    """
    lines = []
    for folder in sorted(pathlib.Path(args.results).glob("seed_*"), key=lambda path: int(path.name.split("_")[1])):
        stage1 = folder / "stage1.json"
        if stage1.exists():
            record = json.loads(stage1.read_text())
            gate = record["gate"]
            line = (
                f"{folder.name}: L = {record['switch_step']} (criterion met: {record['criterion_met']}), gate "
                f"{gate['falls']}/{gate['episodes']} falls, {gate['mean_distance']:.2f} m: "
                f"{'learnt' if record['learnt'] else 'Env-A not learnt'}"
            )
        else:
            rows = read_rows(folder / "stage1.csv")
            line = f"{folder.name}: stage 1 running ({rows[-1]['timesteps'] if rows else 0} steps evaluated)"
        names = [*(f"student_{name}" for name in STUDENTS), *(sweep_job(scale) for scale in SUPPORT_SCALES)]
        jobs = [j for j in (job_progress(folder, f"env_b_{m}", "stage2_steps", "", m) for m in METHODS) if j is not None]
        students = [j for j in (job_progress(folder, job, "updates", " updates") for job in names) if j is not None]
        line += "; env_b: " + ", ".join(jobs) if jobs else "; no env_b job started"
        lines.append(line + ("; students: " + ", ".join(students) if students else ""))
    support = pathlib.Path(args.results) / SUPPORT_FILE
    if lines:
        lines.append(
            f"support: {json.loads(support.read_text())['choice']}x ({SUPPORT_FILE})"
            if support.exists()
            else "support: not swept"
        )
    print("\n".join(lines) if lines else f"no seed in {args.results}")
    return lines


# ------------------------------------------------------------------------------------------------ command line
def add_common(parser: argparse.ArgumentParser, eval_every: int = 10_000, seed_required: bool = True) -> None:
    """
    The options of every kind of job.

    :param eval_every: the default of ``--eval-every`` (environment steps; a student's: updates)
    :param seed_required: whether ``--seed`` must be given (the sweep runs its seeds unless one is named)
    """
    parser.add_argument("--seed", type=int, required=seed_required, default=None)
    parser.add_argument("--runs", required=True, help="folder of the checkpoints and buffers (not committed)")
    parser.add_argument("--results", default=str(RESULTS), help="folder of the CSV and JSON files (one folder per seed)")
    parser.add_argument("--eval-every", type=int, default=eval_every)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--end-episodes", type=int, default=20, help="episodes of the end scores (and the gate)")
    parser.add_argument("--checkpoint-every", type=int, default=50_000, help="a multiple of --eval-every")
    parser.add_argument("--env", default=OP3, help="small-scale checks only: another MuJoCo env (e.g. Hopper-v5)")
    parser.add_argument("--param", default=PARAM, help="small-scale checks only: the parameter Env-B sets to 0.3")
    parser.add_argument("--net-arch", type=int, nargs="+", default=None, help="small-scale checks only: hidden layers")


def add_student_options(parser: argparse.ArgumentParser, updates: int) -> None:
    """The options of the students and the sweep."""
    parser.add_argument("--updates", type=int, default=updates, help="gradient updates of each student")
    parser.add_argument("--device", default="cpu", help="where the students train (a torch device)")


def main(argv: Optional[list[str]] = None) -> Any:
    parser = argparse.ArgumentParser(prog="paper_op3.py", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    stage1 = commands.add_parser("stage1", help="Stage 1 of a seed, to Amendment 3's switch, then the gate")
    add_common(stage1)
    stage1.add_argument("--min-steps", type=int, default=200_000)
    stage1.add_argument("--max-steps", type=int, default=500_000)
    env_b = commands.add_parser("env_b", help="one method's Env-B run of a seed, from the Stage-1 agent")
    add_common(env_b)
    env_b.add_argument("--method", choices=METHODS, required=True)
    env_b.add_argument("--steps", type=int, default=1_000_000)
    env_b.add_argument("--force", action="store_true", help="run even when the gate says Env-A was not learnt (tests)")
    student = commands.add_parser("student", help="one offline student of a seed, on MPO's lifetime buffer")
    add_common(student, eval_every=STUDENT_EVAL_EVERY)
    student.add_argument("--student", choices=list(STUDENTS), required=True)
    student.add_argument("--support-scale", type=int, choices=SUPPORT_SCALES, default=None,
                         help=f"small checks: the support's width (default: the sweep's in {SUPPORT_FILE})")  # fmt: skip
    add_student_options(student, STUDENT_UPDATES)
    sweep = commands.add_parser("sweep", help="the support sweep (1x and 3x), then support.json")
    add_common(sweep, eval_every=STUDENT_EVAL_EVERY, seed_required=False)
    sweep.add_argument("--support-scale", type=int, choices=SUPPORT_SCALES, default=None, help="run this width only")
    add_student_options(sweep, SWEEP_UPDATES)
    report = commands.add_parser("report", help="claims.md and claims.json from every seed's files")
    report.add_argument("--results", default=str(RESULTS))
    state = commands.add_parser("status", help="per seed: Stage 1's switch and gate, and the state of every job")
    state.add_argument("--results", default=str(RESULTS))
    args = parser.parse_args(argv)
    run = {"stage1": run_stage1, "env_b": run_env_b, "student": run_student, "sweep": run_sweep, "report": run_report}
    return {**run, "status": status}[args.command](args)


if __name__ == "__main__":
    main()
