"""
Parallel data sharing (the paper's appendix) on the protocol's runner: two robots at the same time, each collecting
into its own lifetime buffer, their buffers then merged into one for the students (``Preset.sharing``).

A sharing study's seed has two collection jobs and a merge beside the protocol's ``collect``:

* ``collect``: the first agent learns Env-A, then Env-B (:func:`~sb3_lifelong.experiments.collection.collect`, over
  :attr:`Preset.collector_steps`). The runner runs it in two parts when the second agent is its copy: up to the
  switch, then on, so that the copy starts at the switch and the two robots collect side by side.
* ``collect_agent2`` (:func:`collect_agent2`): the second agent learns Env-C into ``buffer_agent2``: the first agent
  at the switch, copied (its weights and its Stage-1 buffer, ``"copy"``), or a new agent (``"independent"``).
* ``share`` (:func:`share`): the two lifetime buffers merged into ``buffer_shared`` (the copy's Env-A once), checked
  to hold every transition collected exactly once; the students distill it.

Layout of ``<output>/seed_<k>/`` beside the protocol's::

    collect_agent2/          the second agent's evaluations (eval.csv, q_sources.csv, train.csv) and final.zip
    buffer_agent2/           its lifetime buffer (large: never commit it)
    share/done.json          the rows of each environment in the merged buffer
    buffer_shared/           the merged buffer the students distill (large)
"""

import pathlib
from collections.abc import Mapping
from typing import Any, Callable

import numpy as np

from sb3_lifelong.buffers import LifelongReplayBuffer, merge_buffers
from sb3_lifelong.experiments.collection import name_sources, new_collector
from sb3_lifelong.experiments.jobs import job_callbacks, make_env, start_job, tensorboard_dir
from sb3_lifelong.experiments.presets import AGENT2_SEED_OFFSET, SHARED_BUFFER, Preset
from sb3_lifelong.mpo import MPO

__all__ = ["AGENT2_BUFFER", "check_shared", "collect_agent2", "share"]

#: the second collector's lifetime buffer, in a seed's directory
AGENT2_BUFFER = "buffer_agent2"


def collect_agent2(
    preset: Preset, seed: int, run_dir: pathlib.Path, progress_bar: bool = False, log: Callable[[str], None] = print
) -> None:
    """
    The ``collect_agent2`` job of a sharing study: the second robot learns Env-C for ``stage_steps[2]`` steps into
    its own lifetime buffer (``buffer_agent2``), evaluated on every environment as the first is. An unfinished
    attempt's directory and buffer are deleted first (only what it wrote: anything else is refused).

    ``"copy"``: the first agent at the switch (``collect/stage1.zip``) with a copy of its Stage-1 buffer, its clock
    going on from the switch; ``"independent"``: a new agent (seed ``seed + AGENT2_SEED_OFFSET``) from timestep 0.

    :param preset: the study's settings (``Preset.sharing`` set)
    :param seed: the seed
    :param run_dir: the seed's directory
    :param progress_bar: show a progress bar
    :param log: where a deletion is reported
    :raises FileNotFoundError: (``"copy"``) the first agent has not reached the switch yet
    """
    if preset.sharing is None:
        raise ValueError("collect_agent2 is a sharing study's job: the preset has no sharing set-up")
    directory = run_dir / "collect_agent2"
    stage1, stage1_buffer = run_dir / "collect" / "stage1.zip", run_dir / "buffer_stage1"
    if preset.sharing == "copy" and not (stage1.is_file() and (stage1_buffer / "manifest.json").is_file()):
        raise FileNotFoundError(
            f"{stage1} and {stage1_buffer} are not there: the second agent of the copy set-up starts from the first at "
            "the switch, so the collect job runs to the switch first (the runner does)"
        )
    start_job(directory, directory.name, log, beside=(AGENT2_BUFFER,))
    env = make_env(preset)
    env.set_stage(2, immediate=True)  # Env-C for its whole life
    agent_seed = seed + AGENT2_SEED_OFFSET
    if preset.sharing == "copy":
        with LifelongReplayBuffer.open(stage1_buffer, read_only=True) as ancestor:
            merge_buffers([ancestor], path=run_dir / AGENT2_BUFFER).close()
        # the agent only (its saved buffer settings point at the first agent's buffer), then its own copy, extended
        model = MPO.load(
            stage1,
            env=env,
            device=preset.device,
            custom_objects={"replay_buffer_kwargs": {}},
            tensorboard_log=tensorboard_dir(directory),
        )
        model.replay_buffer = LifelongReplayBuffer.open(run_dir / AGENT2_BUFFER)
        model.set_random_seed(agent_seed)
        model.learning_starts = 0  # it has learnt: the copy acts by its policy from its first step
        name_sources(model.replay_buffer, preset)
    else:
        model = new_collector(preset, env, agent_seed, run_dir / AGENT2_BUFFER, directory)
    buffer: Any = model.replay_buffer
    callbacks = job_callbacks(preset, directory, preset.eval_freq, seed)
    model.learn(preset.stage_steps[2], callback=callbacks, reset_num_timesteps=preset.sharing != "copy",
                progress_bar=progress_bar)  # fmt: skip
    model.save(directory / "final.zip")  # commits the buffer first
    buffer.close()


def share(preset: Preset, run_dir: pathlib.Path, log: Callable[[str], None] = print) -> dict[str, int]:
    """
    The ``share`` job of a sharing study: the two lifetime buffers merged into one (``buffer_shared``): the first
    agent's whole, then the second's after the Env-A part a copy shares with it.

    :param preset: the study's settings (``Preset.sharing`` set)
    :param run_dir: the seed's directory
    :param log: where a deletion is reported
    :return: the rows of each environment's data in the merged buffer, by its name
    :raises RuntimeError: the merged buffer does not hold exactly the transitions collected
    """
    if preset.sharing is None:
        raise ValueError("share is a sharing study's job: the preset has no sharing set-up")
    directory = run_dir / "share"
    start_job(directory, directory.name, log, beside=(SHARED_BUFFER,))
    copied: dict[int, int] = {}  # the copy's buffer starts with the first agent's Stage-1 buffer: shared once
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as agent1:
        with LifelongReplayBuffer.open(run_dir / AGENT2_BUFFER, read_only=True) as agent2:
            if preset.sharing == "copy":
                with LifelongReplayBuffer.open(run_dir / "buffer_stage1", read_only=True) as stage1:
                    check_copy(stage1, agent2, run_dir)
                    copied = {int(source): int(count) for source, count in stage1.source_counts().items()}
            expected = {source: int(agent1.source_counts().get(source, 0)) for source in range(len(preset.stages))}
            for source, count in agent2.source_counts().items():
                expected[int(source)] += int(count) - copied.get(int(source), 0)
            starts = [0, sum(copied.values())]
            merged = merge_buffers([agent1, agent2], starts=starts, path=run_dir / SHARED_BUFFER)
    try:
        check_shared(merged, {source: count for source, count in expected.items() if count})
        counts = {str(name): int(count) for name, count in merged.source_counts(by_name=True).items()}
    finally:
        merged.close()
    log(f"  {run_dir.name}: {sum(counts.values()):,} transitions shared, per environment {counts}")
    return counts


#: the fields whose rows say that two buffers hold the same transitions
COMPARED_FIELDS = ("observations", "actions", "rewards", "next_observations", "flags", "sources")
#: rows compared at a time
COMPARE_BLOCK = 1 << 14


def check_copy(stage1: Any, agent2: Any, run_dir: pathlib.Path) -> None:
    """
    :param stage1: the first agent's Stage-1 buffer
    :param agent2: the copy's lifetime buffer
    :param run_dir: the seed's directory, for the message
    :raises RuntimeError: the copy's buffer does not start with the Stage-1 buffer (a collection redone since the
        copy was made): the merge would pair another agent's Env-C with this Env-A
    """
    rows = stage1.size()
    same = agent2.size() >= rows
    for start in range(0, rows, COMPARE_BLOCK):
        stop = min(rows, start + COMPARE_BLOCK)
        for name in COMPARED_FIELDS:
            if not same:
                break
            same = bool(np.array_equal(stage1.read_range(name, start, stop), agent2.read_range(name, start, stop)))
    if not same:
        raise RuntimeError(
            f"{run_dir / AGENT2_BUFFER} does not start with the {rows:,} transitions of {run_dir / 'buffer_stage1'}: the "
            "second robot was copied from another Stage 1 (the collection was redone since). Nothing was merged; move "
            f"{run_dir / 'collect_agent2'} and {run_dir / AGENT2_BUFFER} away to collect the copy again"
        )


def check_shared(data: Any, expected: Mapping[int, int]) -> None:
    """
    :param data: the merged buffers
    :param expected: the transitions collected in each environment (source)
    :raises RuntimeError: when a transition was lost or is there twice
    """
    counts = {source: int(n) for source, n in data.source_counts().items() if n}
    if counts != dict(expected):
        raise RuntimeError(
            f"the shared buffer holds {counts} transitions per source; the collectors collected {dict(expected)}"
        )
