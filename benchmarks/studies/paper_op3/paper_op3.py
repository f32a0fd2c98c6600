"""
The paper's two-stage experiment on OP3 (``README.md``, Design and Amendment 3): Stage 1 and the four Env-B runs of a
seed, each one resumable job (one command) whose checkpoints live in ``--runs`` and whose small results (CSV, JSON)
go to ``--results``::

    OMP_NUM_THREADS=1 python benchmarks/studies/paper_op3/paper_op3.py stage1 --seed 0 --runs /work/runs/paper_op3
    OMP_NUM_THREADS=1 python benchmarks/studies/paper_op3/paper_op3.py env_b --seed 0 --method mpo --runs ...
    python benchmarks/studies/paper_op3/paper_op3.py status

``stage1``: MPO at Acme's MuJoCo baseline in Env-A (the hip's deformation appended to the observation at its
nominal value), until Amendment 3's switch rule ends it, then the registered gate on the frozen agent.
``env_b --method``: ``mpo`` (the same agent, buffer, optimisers and duals, now in Env-B), ``mpo_a`` (the same, left
in Env-A: the no-change control of C1), ``online_crr_indicator`` and ``online_crr_exp`` (a CRR given the Stage-1
policy's weights and a copy of its buffer, online in Env-B at the same update ratio). ``RUNNING.md`` has the commands.

**Not in this script yet (the next part):** the three offline students (CRR exp beta=1 and CRR indicator on the
lifetime buffer of ``mpo``, ``<runs>/seed_<S>/env_b_mpo/replay.pkl``, whose ``sources`` column tells Env-A rows (0)
from Env-B rows (1); CRR indicator on the Env-A rows only), the support sweep (``../shared/DESIGN.md``), and the
claims report, which will read ``stage1.json`` (L, the gate, the frozen agent's end scores) and every
``env_b_<method>.json`` (end scores on 20 episodes per environment) in ``--results/seed_<S>/``.

Files of a seed (``--results/seed_<S>/``): ``stage1.csv`` (one row per evaluation, :data:`STAGE1_FIELDS`),
``stage1.json`` (see :func:`stage1_record`), ``stage1_runs.json`` (Stage 1's settings, and the machine of each start
or resume), ``env_b_<method>.csv`` (one row per evaluation and environment,
:data:`ENV_B_FIELDS`), ``env_b_<method>.json`` (see :func:`run_env_b`). Checkpoints (``--runs/seed_<S>/<job>/``):
``model.zip``, ``replay.pkl`` (the whole buffer, a pickle of a ``LifelongReplayBuffer`` in memory) and
``state.json``; Stage 1's final agent is ``stage1/agent.zip`` with its buffer ``stage1/replay.pkl``.
"""

import argparse
import csv
import json
import os
import pathlib
import subprocess
import sys
import time
from collections.abc import Sequence
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
    for index in reversed(range(len(ENVS))):
        model.replay_buffer.set_source(index, name=ENVS[index])
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
    model.replay_buffer = merge_buffers([model.replay_buffer], n_steps=model.n_steps, gamma=model.gamma)
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


def load_checkpoint(algo_class: type, folder: pathlib.Path, env: gym.Env, name: str = "model") -> Any:
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


# ------------------------------------------------------------------------------------------------ status
def status(args: argparse.Namespace) -> list[str]:
    """:return: (printed) per seed in ``--results``: Stage 1's switch, its gate, and the state of each Env-B job"""
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
        jobs = []
        for method in METHODS:
            path = folder / f"env_b_{method}.json"
            if path.exists() and json.loads(path.read_text()).get("finished"):
                jobs.append(f"{method} done")
            elif path.exists():
                rows = read_rows(folder / f"env_b_{method}.csv")
                jobs.append(f"{method} at {rows[-1]['stage2_steps'] if rows else 0}")
        lines.append(line + ("; env_b: " + ", ".join(jobs) if jobs else "; no env_b job started"))
    print("\n".join(lines) if lines else f"no seed in {args.results}")
    return lines


# ------------------------------------------------------------------------------------------------ command line
def add_common(parser: argparse.ArgumentParser) -> None:
    """The options of both kinds of job."""
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--runs", required=True, help="folder of the checkpoints and buffers (not committed)")
    parser.add_argument("--results", default=str(RESULTS), help="folder of the CSV and JSON files (one folder per seed)")
    parser.add_argument("--eval-every", type=int, default=10_000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--end-episodes", type=int, default=20, help="episodes of the end scores (and the gate)")
    parser.add_argument("--checkpoint-every", type=int, default=50_000, help="a multiple of --eval-every")
    parser.add_argument("--env", default=OP3, help="small-scale checks only: another MuJoCo env (e.g. Hopper-v5)")
    parser.add_argument("--param", default=PARAM, help="small-scale checks only: the parameter Env-B sets to 0.3")
    parser.add_argument("--net-arch", type=int, nargs="+", default=None, help="small-scale checks only: hidden layers")


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
    state = commands.add_parser("status", help="per seed: Stage 1's switch and gate, and which env_b jobs are done")
    state.add_argument("--results", default=str(RESULTS))
    args = parser.parse_args(argv)
    return {"stage1": run_stage1, "env_b": run_env_b, "status": status}[args.command](args)


if __name__ == "__main__":
    main()
