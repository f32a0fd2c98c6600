"""
MPO at the field's bar: one resumable run of MPO (Acme's MuJoCo baseline, :func:`sb3_lifelong.mpo.presets.acme_mujoco`)
or of SB3's SAC at the same update ratio, batch and network sizes, with a deterministic evaluation every
``--eval-every`` steps (10 seeded episodes, as Acme's example), written as one CSV row per evaluation.

One command is one run; it checkpoints (model, optimisers, replay buffer, random streams) every
``--checkpoint-every`` steps and a killed command continues from its last checkpoint::

    OMP_NUM_THREADS=1 python benchmarks/studies/mpo_1m/mpo_1m.py run --algo mpo --env HalfCheetah-v5 --seed 0 \\
        --runs /work/runs/mpo_1m
    python benchmarks/studies/mpo_1m/mpo_1m.py report       # results.md and curves.png from results/*.csv

``queue`` runs every registered run that has not reached ``--steps`` (MPO and SAC of a task and seed side by side,
tasks then seeds in order), ``--slots`` at a time, each as its own ``run`` command, until all are done or it is
stopped; a run another command holds (its lock, ``<runs>/<name>/run.lock``) is left to it::

    nohup python benchmarks/studies/mpo_1m/mpo_1m.py queue --runs /work/runs/mpo_1m --results /work/results/mpo_1m &

The same command measures OP3's Stage 1 for the paper's study (``--env sb3_lifelong/OP3Walk-v0 --appended
hip_deformation``: the observation carries the hip's true parameter, as in the study's Stage 1), with the distance
walked and the falls of each evaluation beside the return. Small results go to ``--results``; checkpoints and
buffers stay in ``--runs``.
"""

import argparse
import csv
import fcntl
import json
import math
import os
import pathlib
import platform
import subprocess
import sys
import time
from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch as th

STUDY = pathlib.Path(__file__).resolve().parent
RESULTS = STUDY / "results"
FIELDS = [
    "timesteps",
    "updates",
    "mean_return",
    "std_return",
    "mean_length",
    "falls",
    "mean_distance",
    "episodes",
    "wall_s",
]
#: reset seeds of the evaluation episodes (the same at every evaluation: differences are the policy's alone)
EVAL_SEED = 10_000
#: a stage switch that never comes: the study's Stage-1 observation (the appended parameter at its nominal value)
NEVER = 10**12


def make_env(env_id: str, appended: Optional[str]) -> gym.Env:
    """:return: the env, with ``appended``'s true value in the observation (at its nominal value) when given"""
    import sb3_lifelong.envs  # noqa: F401  (registers sb3_lifelong/OP3Walk-v0)
    from sb3_lifelong.envs import DynamicsSchedule

    env = gym.make(env_id)
    if appended:
        env = DynamicsSchedule(env, stages=[{}, {appended: 0.3}], switch_at=[NEVER], append_params=True)
    return env


def make_model(algo: str, env: gym.Env, seed: int, net_arch: Optional[list[int]] = None) -> Any:
    """
    :param net_arch: hidden layers instead of the preset's 256x256x256 (small-scale checks only)
    :return: MPO at Acme's MuJoCo baseline, or SB3's SAC at its update ratio, batch and network sizes
    """
    from stable_baselines3 import SAC

    from sb3_lifelong import MPO
    from sb3_lifelong.mpo.presets import acme_mujoco

    preset = acme_mujoco(**({"policy_kwargs": {"net_arch": net_arch}} if net_arch else {}))
    if algo == "mpo":
        return MPO("MlpPolicy", env, seed=seed, compute=dict(compile_losses=False), **preset)
    same = {key: preset[key] for key in ("train_freq", "gradient_steps", "batch_size", "learning_rate", "learning_starts")}
    return SAC("MlpPolicy", env, seed=seed, policy_kwargs={"net_arch": preset["policy_kwargs"]["net_arch"]}, **same)


def evaluate(model: Any, env: gym.Env, episodes: int) -> dict[str, float]:
    """
    Deterministic episodes from the reset seeds ``EVAL_SEED + k``.

    :return: mean and sd of the return, mean length, falls (terminated before the time limit) and the mean distance
        walked along x (from ``info["x_position"]`` where the env gives it, else NaN)
    """
    returns, lengths, falls, distances = [], [], 0, []
    for k in range(episodes):
        obs, info = env.reset(seed=EVAL_SEED + k)
        x0 = info.get("x_position")
        total, length, done = 0.0, 0, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, info = env.step(action)
            total, length = total + float(reward), length + 1
            done = terminated or truncated
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


def settings_of(model: Any) -> dict[str, Any]:
    """:return: what a run's cost and learning depend on most: the update ratio, n-step returns, batch and networks"""
    return {
        "train_freq": model.train_freq.frequency,
        "gradient_steps": model.gradient_steps,
        "updates_per_step": model.gradient_steps / model.train_freq.frequency,
        "n_steps": getattr(model, "n_steps", 1),
        "batch_size": model.batch_size,
        "learning_rate": model.learning_rate,
        "net_arch": model.policy_kwargs.get("net_arch"),
    }


def run_name(algo: str, env_id: str, seed: int, appended: Optional[str]) -> str:
    return f"{algo}_{env_id.split('/')[-1]}{'_' + appended if appended else ''}_s{seed}"


def _read_rows(path: pathlib.Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def _write_rows(path: pathlib.Path, rows: list[dict[str, Any]]) -> None:
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)


def machine() -> dict[str, Any]:
    """:return: what the cost of a run depends on: CPU model and flags, versions, torch threads"""
    cpuinfo = pathlib.Path("/proc/cpuinfo").read_text() if pathlib.Path("/proc/cpuinfo").exists() else ""
    model = next((line.split(":", 1)[1].strip() for line in cpuinfo.splitlines() if line.startswith("model name")), "")
    flags = sorted({flag for flag in cpuinfo.split() if flag.startswith("amx") or flag == "avx512_bf16"})
    import mujoco
    import stable_baselines3

    import sb3_lifelong

    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=STUDY, capture_output=True, text=True).stdout
    except OSError:
        commit = ""
    return {
        "cpu": model or platform.processor(),
        "cpu_flags": flags,
        "torch_threads": th.get_num_threads(),
        "python": platform.python_version(),
        "torch": th.__version__,
        "stable_baselines3": stable_baselines3.__version__,
        "sb3_lifelong": sb3_lifelong.__version__,
        "mujoco": mujoco.__version__,
        "gymnasium": gym.__version__,
        "commit": commit.strip(),
    }


def run(args: argparse.Namespace) -> None:
    """One run to ``--steps``, from its last checkpoint in ``--runs`` when there is one."""
    from stable_baselines3 import SAC

    from sb3_lifelong import MPO

    if args.steps <= 0 or args.eval_every <= 0 or args.checkpoint_every % args.eval_every:
        raise SystemExit("--steps and --eval-every must be > 0, and --checkpoint-every a multiple of --eval-every")
    th.set_num_threads(1)
    name = run_name(args.algo, args.env, args.seed, args.appended)
    folder = pathlib.Path(args.runs) / name
    folder.mkdir(parents=True, exist_ok=True)
    lock = open(folder / "run.lock", "a")  # held until this process ends: one command per run at a time
    try:
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        raise SystemExit(f"{name} is being run by another command (it holds {folder / 'run.lock'})") from None
    results = pathlib.Path(args.results)
    results.mkdir(parents=True, exist_ok=True)
    csv_path, meta_path, state_path = results / f"{name}.csv", results / f"{name}.json", folder / "state.json"
    env, eval_env = make_env(args.env, args.appended), make_env(args.env, args.appended)
    algo_class = MPO if args.algo == "mpo" else SAC
    if state_path.exists():
        state = json.loads(state_path.read_text())
        model = algo_class.load(folder / "model.zip", env=env)
        model.load_replay_buffer(folder / "replay.pkl")
        done, wall = int(state["timesteps"]), float(state["wall_s"])
        # the rows after the checkpoint are evaluated again
        rows: list[dict[str, Any]] = [row for row in _read_rows(csv_path) if int(row["timesteps"]) <= done]
        print(f"{name}: resumed at {done} steps ({wall / 3600:.2f} h so far)", flush=True)
    else:
        model, done, wall = make_model(args.algo, env, args.seed, args.net_arch), 0, 0.0
        rows = []
        rows.append({"timesteps": 0, "updates": 0, **evaluate(model, eval_env, args.eval_episodes), "wall_s": 0.0})
        _write_rows(csv_path, rows)
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {"machines": []}
    meta.update({"algo": args.algo, "env": args.env, "appended": args.appended, "seed": args.seed, "steps": args.steps})
    meta["settings"] = settings_of(model)
    meta.update({"eval_every": args.eval_every, "eval_episodes": args.eval_episodes, "command": " ".join(sys.argv)})
    meta["machines"].append({"from_timesteps": done, **machine()})
    meta_path.write_text(json.dumps(meta, indent=1) + "\n")
    while done < args.steps:
        chunk = min(args.eval_every, args.steps - done)
        start = time.perf_counter()
        model.learn(chunk, reset_num_timesteps=done == 0 and model.num_timesteps == 0)
        wall += time.perf_counter() - start
        done = model.num_timesteps
        updates = int(getattr(model, "_n_updates", 0))
        rows.append({"timesteps": done, "updates": updates, **evaluate(model, eval_env, args.eval_episodes), "wall_s": wall})
        _write_rows(csv_path, rows)
        last = rows[-1]
        print(
            f"{name}: {done} steps, {updates} updates, return {last['mean_return']:.0f}, falls {last['falls']}, "
            f"{wall / done * 1000:.1f} ms/step",
            flush=True,
        )
        if done % args.checkpoint_every == 0 or done >= args.steps:
            model.save(folder / "model.tmp.zip")
            model.save_replay_buffer(folder / "replay.tmp.pkl")
            os.replace(folder / "model.tmp.zip", folder / "model.zip")
            os.replace(folder / "replay.tmp.pkl", folder / "replay.pkl")
            state_path.write_text(json.dumps({"timesteps": done, "wall_s": wall}) + "\n")
    print(f"{name}: done at {done} steps in {wall / 3600:.2f} h", flush=True)


#: rl-zoo3's SAC at 1M steps (one update per step), the reference lines of the curves and M2's band
ZOO_SAC = {"HalfCheetah-v5": 9535.0, "Walker2d-v5": 3863.0, "Hopper-v5": 2326.0}
TASKS = ("HalfCheetah-v5", "Walker2d-v5", "Hopper-v5")
#: a run's final return: the mean of its last FINAL_EVALS evaluations
FINAL_EVALS = 10
NON_INFERIORITY = 0.10
ZOO_BAND = 0.9


def load_runs(results: pathlib.Path) -> list[dict[str, Any]]:
    """:return: every run in ``results``: its settings (JSON) and its evaluations (CSV) as float arrays"""
    runs = []
    for meta_path in sorted(results.glob("*.json")):
        meta = json.loads(meta_path.read_text())
        rows = _read_rows(meta_path.with_suffix(".csv"))
        if not rows:
            continue
        curve = {key: np.asarray([float(row[key]) for row in rows]) for key in FIELDS}
        runs.append({**meta, "name": meta_path.stem, "curve": curve, "finished": curve["timesteps"][-1] >= meta["steps"]})
    return runs


def final_return(run: dict[str, Any]) -> float:
    """:return: the mean of the run's last :data:`FINAL_EVALS` evaluations (NaN until the run has finished)"""
    returns = run["curve"]["mean_return"]
    return float(np.mean(returns[-FINAL_EVALS:])) if run["finished"] else float("nan")


def _interval(values: list[float]) -> tuple[float, float, float, float]:
    from sb3_lifelong.experiments.statistics import t_interval

    return t_interval(values)


def read_claims(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """:return: M1 and M2 per task, read by the registered rules (README.md)"""
    readings = []
    for task in [task for task in TASKS if any(run["env"] == task for run in runs)]:
        finals = {
            algo: {
                run["seed"]: final_return(run)
                for run in runs
                if run["env"] == task and run["algo"] == algo and run["finished"]
            }
            for algo in ("mpo", "sac")
        }
        paired = sorted(set(finals["mpo"]) & set(finals["sac"]))
        if len(paired) < 3:
            readings.append(
                {"task": task, "claim": "M1", "n": len(paired), "reading": "not testable (fewer than 3 paired seeds)"}
            )
        else:
            difference = [finals["mpo"][seed] - finals["sac"][seed] for seed in paired]
            mean, sd, low, high = _interval(difference)
            margin = NON_INFERIORITY * float(np.mean([finals["sac"][seed] for seed in paired]))
            reading = "holds" if low > -margin else "fails" if high < -margin else "inconclusive"
            readings.append(
                {
                    "task": task,
                    "claim": "M1",
                    "n": len(paired),
                    "mean": mean,
                    "sd": sd,
                    "low": low,
                    "high": high,
                    "bound": -margin,
                    "reading": reading,
                }
            )
        for algo in ("mpo", "sac"):
            values = list(finals[algo].values())
            if len(values) < 3:
                readings.append(
                    {"task": task, "claim": f"M2 {algo}", "n": len(values), "reading": "not testable (fewer than 3 seeds)"}
                )
                continue
            mean, sd, low, high = _interval(values)
            band = ZOO_BAND * ZOO_SAC[task]
            reading = "holds" if low > band else "fails" if high < band else "inconclusive"
            readings.append(
                {
                    "task": task,
                    "claim": f"M2 {algo}",
                    "n": len(values),
                    "mean": mean,
                    "sd": sd,
                    "low": low,
                    "high": high,
                    "bound": band,
                    "reading": reading,
                }
            )
    return readings


#: the Stage-1 lengths the OP3 rule may choose, and its thresholds (paper_op3/stage1/README.md)
STAGE1_LENGTHS = (200_000, 300_000, 400_000, 500_000)
STAGE1_MAX_FALLS = 1.0
STAGE1_MIN_DISTANCE = 2.0


def stage1_rule(runs: list[dict[str, Any]]) -> list[str]:
    """
    :return: the rule's reading, one line per length: at L, per seed, the mean falls (of 10 episodes) and the mean
        distance of the three evaluations ending at L; L is chosen when every seed meets both thresholds
    """
    op3 = [run for run in runs if "OP3" in run["env"] and run["algo"] == "mpo"]
    lines = [
        "| length | per seed: falls / distance (m), mean of the 3 evaluations ending there | every seed meets it |",
        "| --- | --- | --- |",
    ]
    chosen = None
    for length in STAGE1_LENGTHS:
        cells, met = [], True
        for run in op3:
            curve = run["curve"]
            index = np.flatnonzero(curve["timesteps"] == length)
            if not len(index) or index[0] < 2:
                cells.append(f"s{run['seed']}: not reached")
                met = False
                continue
            window = slice(index[0] - 2, index[0] + 1)
            falls, distance = float(curve["falls"][window].mean()), float(curve["mean_distance"][window].mean())
            cells.append(f"s{run['seed']}: {falls:.1f} / {distance:.2f}")
            met = met and falls <= STAGE1_MAX_FALLS and distance >= STAGE1_MIN_DISTANCE
        if met and chosen is None and op3:
            chosen = length
        lines.append(f"| {length // 1000}k | {'; '.join(cells)} | {'yes' if met else 'no'} |")
    verdict = f"{chosen // 1000}k" if chosen else "not fixed yet (no length up to 500k met it on every seed measured so far)"
    return [*lines, "", f"Stage-1 length by the rule: {verdict}"]


def _cost(run: dict[str, Any]) -> str:
    curve = run["curve"]
    steps, updates, wall = curve["timesteps"][-1], curve["updates"][-1], curve["wall_s"][-1]
    flags = run["machines"][-1]["cpu_flags"]
    cpu = run["machines"][-1]["cpu"] + (f" ({', '.join(flags)})" if flags else " (no AMX, no AVX-512 BF16)")
    per_update = 1000 * wall / max(updates, 1)
    return (
        f"{wall / 3600:.2f} h, {1000 * wall / max(steps, 1):.2f} ms/step, ~{per_update:.0f} ms/update (with collection), {cpu}"
    )


def report(args: argparse.Namespace) -> None:
    """``results.md`` and ``curves.png`` from every run's CSV in ``--results``."""
    results = pathlib.Path(args.results)
    runs = load_runs(results)
    if not runs:
        raise SystemExit(f"no runs in {results}")
    lines = [
        "# Results (generated by `python benchmarks/studies/mpo_1m/mpo_1m.py report`)",
        "",
        "## Every run",
        "",
        "| run | steps | updates | last eval | best eval | final (mean of last 10) | falls at last eval "
        "| distance at last eval (m) | cost |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for run in runs:
        curve = run["curve"]
        final = final_return(run)
        lines.append(
            f"| {run['name']} | {curve['timesteps'][-1]:.0f} of {run['steps']} | {curve['updates'][-1]:.0f} | "
            f"{curve['mean_return'][-1]:.0f} | {curve['mean_return'].max():.0f} | "
            f"{'running' if math.isnan(final) else f'{final:.0f}'} | {curve['falls'][-1]:.0f} / {run['eval_episodes']} | "
            f"{curve['mean_distance'][-1]:.2f} | {_cost(run)} |"
        )
    lines += [
        "",
        "## Readings (README.md's rules)",
        "",
        "| task | claim | seeds | mean +- sd [95 % t] | bound | reading |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for reading in read_claims(runs):
        if "mean" in reading:
            value = f"{reading['mean']:.0f} +- {reading['sd']:.0f} [{reading['low']:.0f}, {reading['high']:.0f}]"
            bound = f"{reading['bound']:.0f}"
        else:
            value, bound = "-", "-"
        lines.append(f"| {reading['task']} | {reading['claim']} | {reading['n']} | {value} | {bound} | {reading['reading']} |")
    if any("OP3" in run["env"] for run in runs):
        lines += ["", "## OP3's Stage-1 rule (stage1/README.md)", "", *stage1_rule(runs)]
    (pathlib.Path(args.out) / "results.md").write_text("\n".join(lines) + "\n")
    draw(runs, pathlib.Path(args.out) / "curves.png")
    print("\n".join(lines))


def draw(runs: list[dict[str, Any]], path: pathlib.Path) -> None:
    """Learning curves: one panel per env (and distance and falls for OP3), every seed thin, the mean over seeds bold."""
    from sb3_lifelong.experiments.style import pyplot, save

    plt = pyplot()
    from matplotlib.ticker import FuncFormatter  # after pyplot(): it chooses the backend

    envs = sorted({run["env"] for run in runs}, key=lambda env: TASKS.index(env) if env in TASKS else len(TASKS))
    panels = [(env, "mean_return", "return (10 deterministic episodes)") for env in envs]
    if any("x_position" in env or "OP3" in env for env in envs):
        panels += [(env, "mean_distance", "distance walked (m)") for env in envs if "OP3" in env]
        panels += [(env, "falls", "falls in 10 episodes") for env in envs if "OP3" in env]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.0), squeeze=False)
    colors = {"mpo": "tab:blue", "sac": "tab:orange"}
    for ax, (env, key, label) in zip(axes[0], panels):
        for algo in ("mpo", "sac"):
            mine = [run for run in runs if run["env"] == env and run["algo"] == algo]
            for index, run in enumerate(mine if len(mine) > 1 else []):  # every seed thin, beside their mean
                thin = f"{algo.upper()}, each seed" if index == 0 else None
                ax.plot(run["curve"]["timesteps"], run["curve"][key], color=colors[algo], lw=0.7, alpha=0.45, label=thin)
            if mine:
                length = min(len(run["curve"][key]) for run in mine)
                mean = np.mean([run["curve"][key][:length] for run in mine], axis=0)
                ax.plot(
                    mine[0]["curve"]["timesteps"][:length],
                    mean,
                    color=colors[algo],
                    lw=2.0,
                    label=(
                        f"{algo.upper()} (mean of {len(mine)} seeds, to the shortest)"
                        if len(mine) > 1
                        else f"{algo.upper()} (seed {mine[0]['seed']})"
                    ),
                )
        if key == "mean_return" and env in ZOO_SAC:
            ax.axhline(ZOO_SAC[env], color="gray", ls="--", lw=1, label="rl-zoo3 SAC at 1M (ratio 1)")
        ax.set_title(f"{env.split('/')[-1]}: {label.split(' (')[0]}", fontsize=10)
        ax.set_xlabel("environment steps")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x / 1e6:g}M" if x >= 1e6 else f"{x / 1e3:g}k"))
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=1, frameon=False)
    save(plt, fig, path)


#: the registered runs, in the order ``queue`` starts them: per task (the issue's bar first: HalfCheetah and
#: Walker2d), per seed, MPO then SAC
REGISTERED = [(algo, task, seed) for task in TASKS for seed in (0, 1, 2) for algo in ("mpo", "sac")]


def reached(folders: list[pathlib.Path], name: str, steps: int) -> bool:
    """:return: whether the run's CSV in one of ``folders`` has an evaluation at ``steps`` or later"""
    paths = [folder / f"{name}.csv" for folder in folders]
    return any(path.exists() and any(int(row["timesteps"]) >= steps for row in _read_rows(path)) for path in paths)


def pending(results: pathlib.Path, steps: int) -> list[tuple[str, str, int]]:
    """:return: the registered runs that have not reached ``steps`` (in ``results`` or the committed ones), in order"""
    folders = [results, RESULTS]
    return [run for run in REGISTERED if not reached(folders, run_name(run[0], run[1], run[2], None), steps)]


def queue(args: argparse.Namespace) -> None:
    """Run the pending registered runs, ``--slots`` at a time, each a ``run`` command (one thread)."""
    results = pathlib.Path(args.results)
    todo = pending(results, args.steps)
    print(f"{len(todo)} runs pending: " + ", ".join(run_name(a, t, s, None) for a, t, s in todo), flush=True)
    if args.limit is not None and len(todo) > args.limit:
        todo = todo[: args.limit]  # those a session's time allows: a run not started is not lost with it
        print(f"starting the first {args.limit}: " + ", ".join(run_name(a, t, s, None) for a, t, s in todo), flush=True)
    if args.dry_run:
        return
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    running: list[tuple[str, subprocess.Popen]] = []
    while todo or running:
        while todo and len(running) < args.slots:
            algo, task, seed = todo.pop(0)
            command = [sys.executable, __file__, "run", "--algo", algo, "--env", task, "--seed", str(seed)]
            command += ["--steps", str(args.steps), "--checkpoint-every", str(args.checkpoint_every)]
            command += ["--runs", args.runs, "--results", args.results]
            running.append((run_name(algo, task, seed, None), subprocess.Popen(command, env=env)))
            print(f"started {running[-1][0]}", flush=True)
        time.sleep(args.poll)
        for name, process in list(running):
            if process.poll() is not None:
                running.remove((name, process))
                print(f"{name} ended (exit status {process.returncode})", flush=True)


def main(argv: Optional[list[str]] = None) -> None:
    parser = argparse.ArgumentParser(prog="mpo_1m.py", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    one = commands.add_parser("run", help="one run (resumes from its last checkpoint)")
    one.add_argument("--algo", choices=["mpo", "sac"], required=True)
    one.add_argument("--env", required=True)
    one.add_argument("--seed", type=int, required=True)
    one.add_argument("--steps", type=int, default=1_000_000)
    one.add_argument("--eval-every", type=int, default=10_000)
    one.add_argument("--eval-episodes", type=int, default=10)
    one.add_argument("--checkpoint-every", type=int, default=50_000)
    one.add_argument("--appended", default=None, help="a parameter whose true value the observation carries")
    one.add_argument("--net-arch", type=int, nargs="+", default=None, help="small-scale checks only: hidden layers")
    one.add_argument("--runs", required=True, help="folder of the checkpoints and buffers (not committed)")
    one.add_argument("--results", default=str(RESULTS), help="folder of the CSV and JSON of each run")
    summary = commands.add_parser("report", help="results.md and curves.png from the runs' CSV files")
    summary.add_argument("--results", default=str(RESULTS), help="folder of the runs' CSV and JSON files")
    summary.add_argument("--out", default=str(STUDY), help="folder of results.md and curves.png")
    line = commands.add_parser("queue", help="every registered run not at --steps yet, --slots at a time")
    line.add_argument("--slots", type=int, default=2, help="runs at once (one core each)")
    line.add_argument("--steps", type=int, default=1_000_000)
    line.add_argument("--checkpoint-every", type=int, default=100_000)
    line.add_argument("--runs", required=True, help="folder of the checkpoints and buffers (not committed)")
    line.add_argument("--results", default=str(RESULTS), help="folder of the CSV and JSON of each run")
    line.add_argument("--poll", type=float, default=30.0, help="seconds between looks at the running commands")
    line.add_argument("--limit", type=int, default=None, help="start at most this many runs (the first pending ones)")
    line.add_argument("--dry-run", action="store_true", help="list the pending runs, start none")
    args = parser.parse_args(argv)
    if args.command == "queue" and args.limit is not None and args.limit < 1:
        parser.error(f"--limit must be at least 1, got {args.limit}")
    if args.command == "run":
        run(args)
    elif args.command == "queue":
        queue(args)
    else:
        report(args)


if __name__ == "__main__":
    main()
