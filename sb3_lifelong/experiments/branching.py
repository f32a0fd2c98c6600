"""
A collection that branches from another's Stage-1 (:func:`adopt_stage1`), and the measurement of a saved collector
agent against the truth (:func:`measure_agent`): the two pieces a study of many Env-B changes from one Env-A needs.

Several changes of one robot share their Env-A: its data, agent and buffer at the switch are the same whichever
change follows, so a screen of changes collects Env-A once per seed and continues each change from there.
"""

import csv
import pathlib
import shutil
from typing import Any

from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_lifelong.buffers import LifelongReplayBuffer, merge_buffers
from sb3_lifelong.core.atomic import atomic_write, write_json_atomic
from sb3_lifelong.evaluation.callbacks import EVAL_SEED_OFFSET
from sb3_lifelong.evaluation.overestimation import MonteCarloProbe
from sb3_lifelong.experiments.collection import COLLECTED_BUFFERS, PAUSED_MODEL, PAUSED_RECORD
from sb3_lifelong.experiments.jobs import claim_directory, eval_envs
from sb3_lifelong.experiments.presets import Preset, describe_stage
from sb3_lifelong.mpo import MPO


def adopt_stage1(preset: Preset, source: pathlib.Path, run_dir: pathlib.Path) -> None:
    """
    Lay out ``preset``'s collection in ``run_dir``, paused at its switch, from the finished Stage-1 of the seed
    directory ``source``: the Stage-1 agent as the pause's checkpoint, the Stage-1 buffer as the lifetime buffer,
    Env-A's evaluations. The protocol's :func:`~sb3_lifelong.experiments.collection.collect` then continues it in Env-B.

    ``source`` must hold the same robot, seed and Env-A. Env-A does not depend on the change when each collection's
    stages vary one parameter: the appended column is that parameter's nominal value, 0 after normalisation, in Env-A
    whatever the parameter.

    :param preset: the collection that continues (its Env-A must be ``source``'s)
    :param source: a seed directory with a finished Stage-1 (``buffer_stage1``, ``collect/stage1.zip``)
    :param run_dir: the new seed directory (must not exist)
    """

    if run_dir.exists():
        raise FileExistsError(f"{run_dir} exists: a Stage-1 is adopted into a new seed directory only")
    switch = preset.stage_steps[0]
    with LifelongReplayBuffer.open(source / "buffer_stage1", read_only=True) as stage1:
        if stage1.size() != switch or set(stage1.source_counts()) != {0}:
            raise ValueError(f"{source / 'buffer_stage1'} holds {stage1.source_counts()}, not {switch:,} Env-A steps")
        directory = run_dir / "collect"
        claim_directory(directory, "collect", beside=COLLECTED_BUFFERS)  # an unfinished collection's, until it is done
        merge_buffers([stage1], path=run_dir / "buffer_stage1").close()
        buffer = merge_buffers([stage1], path=run_dir / "buffer")
    for index in reversed(range(len(preset.env_names))):
        buffer.set_source(index, name=preset.env_names[index], metadata=dict(setting=describe_stage(preset.stages[index])))
    buffer.flush()
    buffer.close()
    for name in ("stage1.zip", "train.csv"):  # (collections before TrainLogCallback have no train.csv)
        if (source / "collect" / name).exists():
            shutil.copy(source / "collect" / name, directory / name)
    shutil.copy(source / "collect" / "stage1.zip", directory / PAUSED_MODEL)
    for name, keep in (("eval.csv", "env"), ("q_sources.csv", "name")):  # Env-A's rows: the other Env-B was not this one
        with open(source / "collect" / name, newline="") as handle:
            rows = list(csv.DictReader(handle))
        with atomic_write(directory / name, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(r for r in rows if int(r["timesteps"]) <= switch and r[keep] == preset.env_names[0])
    write_json_atomic(str(directory / PAUSED_RECORD), dict(timesteps=switch, transitions=switch))
    write_json_atomic(run_dir / "adopted.json", dict(stage1_from=str(source)))


def measure_agent(name: str, run_dir: pathlib.Path, buffer: Any, preset: Preset, seed: int, episodes: int) -> dict[str, Any]:
    """
    One saved collector agent (``collect/<name>.zip``): its return in every environment on the same evaluation
    episodes, and its critic's Q and overestimation on each source of ``buffer``.

    :param name: the agent's file in the collection's directory, without ``.zip`` (``stage1``, ``final``)
    :param run_dir: the seed directory
    :param buffer: the transitions the critic is measured on (an open :class:`LifelongReplayBuffer`)
    :param preset: the collection's settings (its environments)
    :param seed: the seed: the episodes are seeded from ``EVAL_SEED_OFFSET + seed``, as the collection's evaluations
    :param episodes: episodes per environment
    :return: ``<name>_same_episodes_<env>``, ``<name>_q_<source>``, ``<name>_overestimation_<source>``,
        ``mc_return_x1_<source>``
    """
    agent = MPO.load(run_dir / "collect" / f"{name}.zip", device=preset.device, custom_objects={"replay_buffer_kwargs": {}})
    out: dict[str, Any] = {}
    envs = eval_envs(preset)
    for env_name, env in envs.items():
        monitored = Monitor(env)
        monitored.reset(seed=EVAL_SEED_OFFSET + seed)
        mean_return, _ = evaluate_policy(agent, monitored, episodes, deterministic=True)
        out[f"{name}_same_episodes_{env_name}"] = float(mean_return)  # type: ignore[arg-type]
    names = {source: meta.get("name", f"source_{source}") for source, meta in buffer.sources.items()}
    for source, measured in MonteCarloProbe(buffer, agent.gamma, per_source=4096, seed=seed).measure(agent.critic).items():
        out[f"{name}_overestimation_{names[source]}"] = measured.overestimation
        out[f"{name}_q_{names[source]}"] = measured.q_mean
        out[f"mc_return_x1_{names[source]}"] = measured.mc_return
    return out
