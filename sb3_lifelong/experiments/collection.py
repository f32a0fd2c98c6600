"""
The ``collect`` job: MPO through every stage of a preset into one lifetime buffer on disk, in parts when it is longer
than a session (a pause is a checkpoint that the next part continues; a part that stopped without pausing is cut back
to its pause, keeping everything it wrote beside it).
"""

import json
import os
import pathlib
import shutil
import time
from typing import Any, Callable, Optional

from sb3_lifelong.buffers import LifelongReplayBuffer, merge_buffers
from sb3_lifelong.core.atomic import write_json_atomic
from sb3_lifelong.experiments.jobs import (
    OWNED_MARKER,
    NotOwnedError,
    claim_directory,
    drop_rows_after,
    job_callbacks,
    make_env,
    model_kwargs,
    remove_unfinished,
    set_aside,
    tensorboard_dir,
)
from sb3_lifelong.experiments.presets import (
    Preset,
    describe_stage,
    stage_ends,
    switch_points,
)
from sb3_lifelong.mpo import MPO

#: a paused collection (``collect(..., until=...)``): its checkpoint (the model, which commits the lifetime buffer) and
#: what the pause recorded (timesteps, the buffer's transitions), in the ``collect`` directory
PAUSED_MODEL, PAUSED_RECORD = "paused.zip", "paused.json"


def paused_at(run_dir: pathlib.Path) -> int:
    """
    :param run_dir: a seed's directory
    :return: the timestep its collection paused at (``collect/paused.json``; 0: not started, or not paused)
    """
    record = run_dir / "collect" / PAUSED_RECORD
    return int(json.loads(record.read_text())["timesteps"]) if record.exists() else 0


def collect_in_parts(
    preset: Preset, seed: int, run_dir: pathlib.Path, stop: int, part: int, log: Callable[[str], None] = print
) -> bool:
    """
    Collect to ``stop`` environment steps in parts of ``part``: each part ends with a checkpoint (:func:`collect` with
    ``until``) that the next continues, so a command killed loses at most one part, and the same call continues.

    :param preset: the protocol's settings
    :param seed: the seed
    :param run_dir: the seed's directory
    :param stop: the step to collect to (the end of the collection, or a switch: a Stage-1 alone)
    :param part: the environment steps of a part (at least 1)
    :param log: where the one-line messages go (one per part, with its seconds)
    :return: True when the collection finished (its last step reached), False when it stopped at ``stop`` before that
    :raises ValueError: ``part`` is below 1
    """
    if part < 1:
        raise ValueError(f"part must be at least 1 environment step, got {part}")
    done = paused_at(run_dir)
    while done < stop:
        start = time.perf_counter()
        until = min(stop, (done // part + 1) * part)
        finished = collect(preset, seed, run_dir, log=log, until=until)
        log(f"{run_dir}: to step {until:,} in {time.perf_counter() - start:.0f} s")
        if finished:
            return True
        done = paused_at(run_dir)
    return False


def collect(
    preset: Preset,
    seed: int,
    run_dir: pathlib.Path,
    progress_bar: bool = False,
    log: Callable = print,
    until: Optional[int] = None,
) -> bool:
    """
    MPO through both stages into one lifetime buffer on disk; keeps the Stage-1 agent and buffer.

    A collection longer than a session runs in parts: with ``until``, it stops cleanly after that many environment
    steps (a checkpoint, ``collect/paused.zip``, which commits the buffer), and the next call continues from there
    (the loaded model starts a new episode, as any resumed SB3 model). An attempt that neither finished nor paused is
    started again. One that had continued from a pause (killed, say) continues from that pause: its buffer is cut
    back to the transitions the pause recorded, and the directory with the later ones is kept beside it
    (:func:`_rewind_to_pause`).

    :param until: stop after this many environment steps of the whole collection (None: collect to the end)
    :return: True when the collection is finished, False when it paused at ``until``
    """
    directory = run_dir / "collect"
    if (directory / PAUSED_MODEL).exists():
        model = _resume_collection(preset, run_dir, log)
    else:
        model = _new_collection(preset, seed, run_dir, log)
    buffer: Any = model.replay_buffer
    callbacks = job_callbacks(preset, directory, preset.eval_freq, seed)
    ends = stage_ends(preset.collector_steps)
    for stage, end in enumerate(ends):
        stop = end if until is None else min(end, until)
        if model.num_timesteps < stop:
            log(f"  stage {stage + 1}/{len(ends)}: {preset.env_names[stage]}, to step {stop:,} of {end:,} (MPO)")
            model.learn(stop - model.num_timesteps, callback=callbacks, reset_num_timesteps=model.num_timesteps == 0,
                        progress_bar=progress_bar)  # fmt: skip
        if model.num_timesteps < end:  # paused inside this stage
            break
        if stage == 0 and not (directory / "stage1.zip").exists():
            model.save(directory / "stage1.zip")
            merge_buffers([buffer], path=run_dir / "buffer_stage1").close()
    if model.num_timesteps < ends[-1]:
        model.save(directory / PAUSED_MODEL)  # commits the buffer first
        record = dict(timesteps=int(model.num_timesteps), transitions=int(buffer.size()))
        write_json_atomic(str(directory / PAUSED_RECORD), record)
        buffer.close()
        return False
    model.save(directory / "final.zip")
    buffer.close()
    for name in (PAUSED_MODEL, PAUSED_RECORD):
        (directory / name).unlink(missing_ok=True)
    return True


def _resume_collection(preset: Preset, run_dir: pathlib.Path, log: Callable) -> MPO:
    """The paused collection's model, with its lifetime buffer reopened to append, when the two still agree."""
    directory = run_dir / "collect"
    record = json.loads((directory / PAUSED_RECORD).read_text()) if (directory / PAUSED_RECORD).exists() else None
    _finish_rewind(run_dir)
    if record is not None and record["timesteps"] < stage_ends(preset.stage_steps)[0]:
        # paused before the switch: a Stage-1 agent or buffer here was made by a part that passed the switch and
        # stopped without pausing, so it is not this collection's (the resumed one makes them again)
        for stage1 in (directory / "stage1.zip", run_dir / "buffer_stage1"):
            if stage1.exists() and not stage1.is_symlink():
                set_aside(stage1, record["transitions"])
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as held:
        transitions = held.size()
    if record is not None and transitions > record["transitions"] and not (run_dir / "buffer").is_symlink():
        _rewind_to_pause(run_dir, record["transitions"], transitions, log)
        transitions = record["transitions"]
    if record is None or transitions != record["transitions"]:
        if record is None:
            why = "the record of the pause is missing"
        elif transitions < record["transitions"]:
            why = f"fewer than the {record['transitions']:,} the pause committed (an older copy of the directory?)"
        else:
            why = f"more than the {record['transitions']:,} at the pause, in a linked buffer, which is not cut back here"
        raise RuntimeError(
            f"{run_dir}: the collection paused at {directory / PAUSED_MODEL}, but its buffer holds {transitions:,} "
            f"transitions: {why}. Nothing was deleted; to collect this seed again from the start, remove {directory}, "
            f"{run_dir / 'buffer'} and {run_dir / 'buffer_stage1'}"
        )
    for name in ("eval.csv", "q_sources.csv", "train.csv"):  # a killed part may have logged past the pause
        drop_rows_after(directory / name, record["timesteps"])
    log(f"  continuing the paused collection at step {record['timesteps']:,}")
    return MPO.load(
        directory / PAUSED_MODEL,
        env=make_env(preset, switch_at=switch_points(preset)),
        device=preset.device,
        replay_buffer_kwargs=dict(path=run_dir / "buffer", mode="append"),
    )


REWIND_STAGING = "buffer.rewinding"
#: beside the copy of a rewind (:data:`REWIND_STAGING`) while it is made: a copy without it is not deleted
REWIND_MARKER = ".buffer.rewinding.owned.json"


def _rewind_to_pause(run_dir: pathlib.Path, paused: int, held: int, log: Callable) -> None:
    """
    Cut a paused collection's buffer back to the ``paused`` transitions its pause recorded, when a later part
    committed more (``held``) and stopped without pausing again. Nothing is deleted: the first ``paused`` transitions
    are copied into a new directory, which then takes the buffer's place; the old directory, with all ``held``, is
    kept beside it as ``buffer.after_pause_<paused>``. A stop in between is finished by :func:`_finish_rewind`.
    """
    buffer, staging, marker = run_dir / "buffer", run_dir / REWIND_STAGING, run_dir / REWIND_MARKER
    if staging.exists() or staging.is_symlink():  # a copy of an earlier attempt that stopped while copying
        if not marker.is_file():
            raise NotOwnedError(
                f"{staging} exists, but no rewind of this collection made it (no {marker}): nothing was deleted. Move it "
                "away and run again"
            )
        shutil.rmtree(staging)  # only ever a partial copy: the rewind that made it did not get to its renames
    # opened as its writer: a process still writing to it holds the lock, and the open refuses
    with LifelongReplayBuffer.open(buffer) as whole:
        if whole.capacity is not None:  # its indices are not the transitions collected: a pause's count is not one
            raise RuntimeError(
                f"{buffer} holds {held:,} transitions, more than the {paused:,} its pause recorded, and it evicts "
                f"(capacity {whole.capacity:,}): it cannot be cut back to the pause. Nothing was deleted"
            )
        write_json_atomic(marker, dict(staging=REWIND_STAGING, paused=paused, held=held))  # the copy is ours to delete
        merge_buffers([whole], path=staging, stops=[paused]).close()
    aside = set_aside(buffer, paused)
    os.replace(staging, buffer)
    marker.unlink(missing_ok=True)
    log(
        f"  the buffer held {held:,} transitions, {held - paused:,} past the pause (a part that stopped without "
        f"pausing): continuing from the pause with its first {paused:,}; all {held:,} are kept in {aside}"
    )


def _finish_rewind(run_dir: pathlib.Path) -> None:
    """Complete a :func:`_rewind_to_pause` that stopped between its two renames (the copy is then complete)."""
    buffer, staging = run_dir / "buffer", run_dir / REWIND_STAGING
    if not buffer.exists() and staging.exists():
        os.replace(staging, buffer)
        (run_dir / REWIND_MARKER).unlink(missing_ok=True)


#: the directories of a seed that its collection creates beside ``collect`` (the lifetime and the Stage-1 buffers)
COLLECTED_BUFFERS = ("buffer", "buffer_stage1")


def finished_collection(preset: Preset, run_dir: pathlib.Path) -> list[str]:
    """
    What says that the collection in ``run_dir`` has finished, whatever its ``done.json`` says: the collector's final
    checkpoint, or a lifetime buffer (not a link) whose manifest holds every step of the collection.

    :param preset: the collection's settings
    :param run_dir: the seed's directory
    :return: one description per piece of evidence (empty: none)
    """
    found = []
    final = run_dir / "collect" / "final.zip"
    if final.is_file():
        found.append(f"{final} (the collector's final checkpoint, saved after the last step)")
    buffer, total = run_dir / "buffer", sum(preset.collector_steps)
    if not buffer.is_symlink() and (buffer / "manifest.json").is_file():
        try:
            with LifelongReplayBuffer.open(buffer, read_only=True) as held:
                transitions = held.size()
        except Exception:  # a buffer that cannot be opened is not a verified one
            transitions = -1
        if transitions >= total:
            found.append(f"{buffer}, whose manifest holds {transitions:,} transitions (every one of the {total:,} steps)")
    return found


def remove_unfinished_collection(preset: Preset, run_dir: pathlib.Path, log: Callable = print) -> None:
    """
    Delete what an unfinished collection attempt of ``run_dir`` wrote (``collect`` and the buffers beside it, which
    its marker names, :mod:`~sb3_lifelong.experiments.jobs`), so that a new attempt starts from nothing. Links
    to another study's buffers (an unfinished :func:`~sb3_lifelong.experiments.protocol.adopt_collection`) are
    unlinked, never followed.

    :raises NotOwnedError: the collection has finished (:func:`finished_collection`) although its ``done.json`` is
        missing, or ``run_dir`` holds a ``collect`` directory or buffers that no unfinished attempt wrote. Nothing is
        deleted then
    """
    directory = run_dir / "collect"
    found = finished_collection(preset, run_dir)
    if found:
        raise NotOwnedError(
            f"{run_dir}: the collect job has no {directory / 'done.json'}, but a finished collection is there: "
            f"{'; '.join(found)}. Nothing was deleted. If it is this study's collection, its done.json was lost: restore "
            f'it (from a backup, or write {{"job": "collect"}} into it) and run again; to collect this seed again '
            f"instead, move {directory}, {run_dir / 'buffer'} and {run_dir / 'buffer_stage1'} away first"
        )
    remove_unfinished(directory, "collect", log)
    for name in COLLECTED_BUFFERS:
        path = run_dir / name
        if path.is_symlink():  # a link to another study's buffer: unlinked, what it points to is not touched
            path.unlink()
        elif path.exists():
            raise NotOwnedError(
                f"{path} exists but no unfinished collection of {run_dir} wrote it (no {directory / OWNED_MARKER} naming "
                f"it): nothing was deleted. Move it away to collect this seed again"
            )


def _new_collection(preset: Preset, seed: int, run_dir: pathlib.Path, log: Callable = print) -> MPO:
    """A fresh collector and its lifetime buffer (an unfinished attempt's directories are removed first)."""
    directory = run_dir / "collect"
    remove_unfinished_collection(preset, run_dir, log)
    claim_directory(directory, "collect", beside=COLLECTED_BUFFERS)  # before the buffer is created
    return new_collector(preset, make_env(preset, switch_at=switch_points(preset)), seed, run_dir / "buffer", directory)


def new_collector(preset: Preset, env: Any, seed: int, buffer_path: pathlib.Path, directory: pathlib.Path) -> MPO:
    """
    :return: a new MPO collector of the preset's settings in ``env``, its lifetime buffer created at ``buffer_path``
        with the stages' names as its sources', logging to ``directory``'s tensorboard
    """
    model = MPO(
        "MlpPolicy",
        env,
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=buffer_path),
        learning_starts=preset.learning_starts,
        num_samples=preset.num_samples,
        batch_size=preset.batch_size,
        learning_rate=preset.learning_rate,
        tensorboard_log=tensorboard_dir(directory),
        **model_kwargs(preset, seed),
    )
    name_sources(model.replay_buffer, preset)
    return model


def name_sources(buffer: Any, preset: Preset) -> None:
    """Name a lifetime buffer's sources after the preset's environments (in its manifest; transitions carry their stage)."""
    for index in reversed(range(len(preset.env_names))):
        buffer.set_source(index, name=preset.env_names[index], metadata=dict(setting=describe_stage(preset.stages[index])))
