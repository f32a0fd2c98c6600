"""
Parallel data sharing (the paper's appendix): robots in different environments at the same time, each collecting
into its own lifetime buffer on disk, run side by side on Ray workers or a local process pool
(:func:`~sb3_lifelong.experiments.runner.map_parallel`); their buffers are then merged into one for the
distillation, keeping a shared ancestor's transitions once.

- ``"copy"``: one agent learns Env-A; it is copied (weights and buffer) into two agents that continue at the same
  time, one in Env-B and one in Env-C.
- ``"independent"``: one agent learns Env-A and then Env-B while a second agent learns Env-C from scratch.

Layout of ``<output>/seed_<k>/``::

    agent1_stage1.zip            agent 1 after Env-A (the ancestor of the copies)
    collectors.json              wall time of the two collectors (Stage 2), workers, environment steps per second
    buffer_agent1/, buffer_agent2/   each collector's lifetime buffer (large: never commit them)
    MPO_agent1/, MPO_agent2/     the collectors' evaluations; distilled/, distilled_indicator/: the students'
"""

import json
import pathlib
import time
from collections.abc import Sequence
from typing import Any, Optional

import torch as th

from sb3_lifelong import CRR, MPO, LifelongReplayBuffer
from sb3_lifelong.buffers import LifelongBufferView, merge_buffers
from sb3_lifelong.core.atomic import write_text_atomic
from sb3_lifelong.distill import distill
from sb3_lifelong.envs import stage_envs
from sb3_lifelong.experiments.runner import map_parallel
from sb3_lifelong.experiments.sequential import (
    Stage,
    algo_kwargs,
    episode_limit,
    eval_callbacks,
    final_returns,
    make_collector,
    make_schedule,
    write_layout,
)

SETUPS = ("copy", "independent")
NAMES = ("Env-A", "Env-B", "Env-C")


def collect(
    config: dict[str, Any],
    stages: Sequence[Stage],
    stage: int,
    steps: int,
    seed: int,
    method_dir: str,
    buffer_path: str,
    model_path: Optional[str] = None,
    tensorboard_log: Optional[str] = None,
    tb_log_name: str = "MPO",
    save_path: Optional[str] = None,
) -> dict[str, Any]:
    """
    One collector: MPO for ``steps`` environment steps in the environment of ``stage``, into the buffer at
    ``buffer_path``; run in a worker process.

    :param config: the experiment's settings (:func:`~sb3_lifelong.experiments.sequential.resolve_config`)
    :param stages: the physical setting of every environment
    :param stage: the environment this collector acts in
    :param steps: environment steps
    :param seed: the collector's seed
    :param method_dir: where its evaluations go (``eval.csv`` is appended to)
    :param buffer_path: its buffer directory: continued when ``model_path`` is given, created otherwise
    :param model_path: a saved agent to continue (its weights and timestep count), or None: a new agent
    :param tensorboard_log: tensorboard directory
    :param tb_log_name: tensorboard run name
    :param save_path: where to save the agent at the end (None: not saved)
    :return: ``{"final": return per environment at the end, "size": transitions in its buffer, "seconds"}``
    """
    th.set_num_threads(1)
    start = time.perf_counter()
    env = make_schedule(config["env_id"], stages, None, config.get("max_episode_steps"))
    env.set_stage(stage, immediate=True)
    if model_path is None:
        model = make_collector(env, config, seed, tensorboard_log, buffer_path=buffer_path)
    else:
        # the agent only (an empty in-memory buffer at load), then its own buffer, continued
        model = MPO.load(model_path, env=env, custom_objects={"replay_buffer_kwargs": {}}, tensorboard_log=tensorboard_log)
        model.replay_buffer = LifelongReplayBuffer.open(buffer_path)
        model.set_random_seed(seed)
        env.reset(seed=seed)
        model.learning_starts = 0
    limit = episode_limit(config.get("max_episode_steps"))
    eval_envs = stage_envs(config["env_id"], list(stages), NAMES[: len(stages)], limit, append_params=True)
    callbacks = eval_callbacks(pathlib.Path(method_dir), eval_envs, config, seed=seed)
    model.learn(steps, callback=callbacks, reset_num_timesteps=model_path is None, tb_log_name=tb_log_name)
    if save_path is not None:
        model.save(save_path)
    buffer = model.replay_buffer
    assert isinstance(buffer, LifelongReplayBuffer)
    size = buffer.size()
    buffer.close()
    return dict(final=final_returns(callbacks[0]), size=size, seconds=time.perf_counter() - start)


def run_sharing(
    config: dict[str, Any],
    setup: str,
    stages: Sequence[Stage],
    output: pathlib.Path,
    workers: int = 2,
    backend: str = "auto",
    distill_students: bool = True,
    log: Any = print,
) -> list[dict[str, Any]]:
    """
    Every seed of the parallel-sharing experiment: Stage 1 in this process, then the two collectors side by side,
    then the distillation of their merged buffers.

    :param config: the experiment's settings (``stage_steps``: Env-A steps, then each collector's steps)
    :param setup: ``"copy"`` or ``"independent"``
    :param stages: the settings of Env-A, Env-B, Env-C
    :param output: the output directory
    :param workers: collectors at a time (1: one after the other in this process)
    :param backend: ``"ray"``, ``"process"`` or ``"auto"`` (see :func:`~sb3_lifelong.experiments.runner.map_parallel`)
    :param distill_students: distil the merged buffers (CRR exp beta=1 and indicator)
    :param log: where the progress lines go
    :return: the summary rows (seed, method, env, final_return)
    :raises RuntimeError: when the merged buffer does not hold exactly the transitions collected
    """
    if setup not in SETUPS:
        raise ValueError(f"setup must be one of {SETUPS}, got {setup!r}")
    first, second = config["stage_steps"][0], config["stage_steps"][1]
    tensorboard_log = str(output / "tensorboard")
    rows = []
    for seed in config["seeds"]:
        run_dir = output / f"seed_{seed}"
        buffers = [str(run_dir / "buffer_agent1"), str(run_dir / "buffer_agent2")]
        log(f"seed {seed}: agent 1 learns {NAMES[0]}, {first:,} steps")
        stage1 = str(run_dir / "agent1_stage1.zip")
        common: dict[str, Any] = dict(config=config, stages=stages, tensorboard_log=tensorboard_log)
        collect(**common, stage=0, steps=first, seed=seed, method_dir=str(run_dir / "MPO_agent1"), buffer_path=buffers[0],
                save_path=stage1, tb_log_name=f"agent1_s{seed}")  # fmt: skip
        agent1 = dict(common, stage=1, steps=second, seed=seed, method_dir=str(run_dir / "MPO_agent1"),
                      buffer_path=buffers[0], model_path=stage1, tb_log_name=f"agent1_s{seed}")  # fmt: skip
        agent2 = dict(agent1, stage=2, seed=seed + 1000, method_dir=str(run_dir / "MPO_agent2"),
                      buffer_path=buffers[1], tb_log_name=f"agent2_s{seed}")  # fmt: skip
        if setup == "copy":  # the copy starts with the ancestor's weights and its whole buffer
            with LifelongReplayBuffer.open(buffers[0], read_only=True) as ancestor:
                merge_buffers([ancestor], path=buffers[1]).close()
        else:
            agent2["model_path"] = None
        how = f"{workers} at a time" if workers > 1 else "one after the other in this process"
        log(f"seed {seed}: agent 1 in {NAMES[1]} and agent 2 in {NAMES[2]}, {second:,} steps each, {how}")
        start = time.perf_counter()
        results = map_parallel(collect, [agent1, agent2], workers=workers, backend=backend)
        seconds = time.perf_counter() - start
        log(f"seed {seed}: both collectors done in {seconds / 60:.1f} min ({2 * second / seconds:.0f} env steps/s)")
        timing = dict(workers=workers, backend=backend, steps_per_collector=second, seconds=seconds)
        timing.update(env_steps_per_second=2 * second / seconds, collector_seconds=[r["seconds"] for r in results])
        write_text_atomic(run_dir / "collectors.json", json.dumps(timing, indent=1))
        for name, result in zip(("MPO_agent1", "MPO_agent2"), results):
            rows += [dict(seed=seed, method=name, env=env, final_return=value) for env, value in result["final"].items()]
        opened = [LifelongReplayBuffer.open(path, read_only=True) for path in buffers]
        data: Any = merge_buffers(opened, starts=[0, first]) if setup == "copy" else LifelongBufferView(opened)
        check_shared(data, {0: first, 1: second, 2: second})
        log(f"seed {seed}: {data.size():,} transitions shared, per source {data.source_counts()}")
        distilled = []
        if distill_students:
            students = (("distilled", dict(beta=1.0)), ("distilled_indicator", dict(advantage_transform="indicator")))
            for method, kwargs in students:
                log(f"seed {seed}: distilling {config['distill_steps']:,} updates: {method}")
                limit = episode_limit(config.get("max_episode_steps"))
                eval_envs = stage_envs(config["env_id"], list(stages), NAMES, limit, append_params=True)
                callbacks = eval_callbacks(run_dir / method, eval_envs, config, source_q=True, offline=True, seed=seed)
                distill(data, CRR, total_updates=config["distill_steps"], callback=callbacks,
                        tensorboard_log=tensorboard_log, tb_log_name=f"{method}_s{seed}",
                        observation_space=opened[0].observation_space, action_space=opened[0].action_space,
                        **algo_kwargs(config, seed), **kwargs)  # fmt: skip
                final = final_returns(callbacks[0])
                rows += [dict(seed=seed, method=method, env=env, final_return=value) for env, value in final.items()]
                distilled.append(method)
        for buffer in opened:
            buffer.close()
        if setup == "copy":
            switch = f"{NAMES[0]} -> {NAMES[1]} (agent 1), {NAMES[2]} (agent 2)"
        else:  # agent 2 starts from scratch: its steps count from 0
            switch = f"agent 1: {NAMES[0]} -> {NAMES[1]}"
        write_layout(run_dir, NAMES, distilled, [first], [switch], stages=stages)
    return rows


def check_shared(data: Any, expected: dict[int, int]) -> None:
    """
    :param data: the merged buffers
    :param expected: the transitions collected in each environment (source)
    :raises RuntimeError: when a transition was lost or is there twice
    """
    counts = {source: int(n) for source, n in data.source_counts().items() if n}
    if counts != expected:
        raise RuntimeError(f"the shared buffer holds {counts} transitions per source; the collectors collected {expected}")
