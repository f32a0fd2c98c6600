"""
The ``collect`` job: MPO through every stage of a preset into one lifetime buffer on disk, in parts when it is longer
than a session (a pause is a checkpoint that the next part continues; a part that stopped without pausing is cut back
to its pause, keeping everything it wrote beside it).
"""

import csv
import json
import os
import pathlib
import shutil
import sys
from typing import Any, Callable, Optional

if sys.platform != "win32":  # POSIX: the job locks are advisory and simply skipped elsewhere
    pass


from sb3_lifelong.buffers import LifelongReplayBuffer, merge_buffers
from sb3_lifelong.buffers.files import write_json_atomic
from sb3_lifelong.experiments.jobs import _common, job_callbacks, make_env, tensorboard_dir
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
        model = _new_collection(preset, seed, run_dir)
    buffer: Any = model.replay_buffer
    callbacks = job_callbacks(preset, directory, preset.eval_freq, seed)
    ends = stage_ends(preset.stage_steps)
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
                _set_aside(stage1, record["transitions"])
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
        _drop_rows_after(directory / name, record["timesteps"])
    log(f"  continuing the paused collection at step {record['timesteps']:,}")
    return MPO.load(
        directory / PAUSED_MODEL,
        env=make_env(preset, switch_at=switch_points(preset)),
        device=preset.device,
        replay_buffer_kwargs=dict(path=run_dir / "buffer", mode="append"),
    )


REWIND_STAGING = "buffer.rewinding"


def _rewind_to_pause(run_dir: pathlib.Path, paused: int, held: int, log: Callable) -> None:
    """
    Cut a paused collection's buffer back to the ``paused`` transitions its pause recorded, when a later part
    committed more (``held``) and stopped without pausing again. Nothing is deleted: the first ``paused`` transitions
    are copied into a new directory, which then takes the buffer's place; the old directory, with all ``held``, is
    kept beside it as ``buffer.after_pause_<paused>``. A stop in between is finished by :func:`_finish_rewind`.
    """
    buffer, staging = run_dir / "buffer", run_dir / REWIND_STAGING
    if staging.exists():  # a copy of an earlier attempt that stopped while copying: only ever a partial copy
        shutil.rmtree(staging)
    # opened as its writer: a process still writing to it holds the lock, and the open refuses
    with LifelongReplayBuffer.open(buffer) as whole:
        if whole.capacity is not None:  # its indices are not the transitions collected: a pause's count is not one
            raise RuntimeError(
                f"{buffer} holds {held:,} transitions, more than the {paused:,} its pause recorded, and it evicts "
                f"(capacity {whole.capacity:,}): it cannot be cut back to the pause. Nothing was deleted"
            )
        merge_buffers([whole], path=staging, stops=[paused]).close()
    aside = _set_aside(buffer, paused)
    os.replace(staging, buffer)
    log(
        f"  the buffer held {held:,} transitions, {held - paused:,} past the pause (a part that stopped without "
        f"pausing): continuing from the pause with its first {paused:,}; all {held:,} are kept in {aside}"
    )


def _aside_name(path: pathlib.Path, paused: int) -> pathlib.Path:
    """:return: ``<stem>.after_pause_<paused>[.k]<suffix>`` beside ``path``, the first such name that is free"""
    for attempt in range(1000):
        tag = f".after_pause_{paused}" + (f".{attempt}" if attempt else "")
        aside = path.with_name(f"{path.stem}{tag}{path.suffix}")
        if not aside.exists():
            return aside
    raise FileExistsError(f"no free name to set {path} aside")


def _set_aside(path: pathlib.Path, paused: int) -> pathlib.Path:
    """Rename ``path`` to :func:`_aside_name`'s name and return it."""
    aside = _aside_name(path, paused)
    os.replace(path, aside)
    return aside


def _finish_rewind(run_dir: pathlib.Path) -> None:
    """Complete a :func:`_rewind_to_pause` that stopped between its two renames (the copy is then complete)."""
    buffer, staging = run_dir / "buffer", run_dir / REWIND_STAGING
    if not buffer.exists() and staging.exists():
        os.replace(staging, buffer)


def _drop_rows_after(path: pathlib.Path, timesteps: int) -> None:
    """Keep the rows of a job's CSV log (a ``timesteps`` column) up to ``timesteps``; the file is replaced atomically."""
    if not path.is_file():
        return
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    if not rows or "timesteps" not in rows[0]:
        return
    column = rows[0].index("timesteps")
    kept = [rows[0], *(row for row in rows[1:] if int(float(row[column])) <= timesteps)]
    if len(kept) < len(rows):
        staging = path.with_name(path.name + ".tmp")
        with open(staging, "w", newline="") as handle:
            csv.writer(handle).writerows(kept)
        os.replace(staging, path)


def _new_collection(preset: Preset, seed: int, run_dir: pathlib.Path) -> MPO:
    """A fresh collector and its lifetime buffer (an unfinished attempt's directories are removed first)."""
    directory = run_dir / "collect"
    for stale in (directory, run_dir / "buffer", run_dir / "buffer_stage1"):  # an unfinished attempt: start again
        if stale.is_symlink():  # a link to another study's buffer (an unfinished adopt_collection): not ours to delete
            stale.unlink()
        else:
            shutil.rmtree(stale, ignore_errors=True)
    directory.mkdir(parents=True)
    model = MPO(
        "MlpPolicy",
        make_env(preset, switch_at=switch_points(preset)),
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=run_dir / "buffer"),
        learning_starts=preset.learning_starts,
        num_samples=preset.num_samples,
        batch_size=preset.batch_size,
        learning_rate=preset.learning_rate,
        tensorboard_log=tensorboard_dir(directory),
        **_common(preset, seed),
    )
    buffer: Any = model.replay_buffer
    for index in reversed(range(len(preset.env_names))):  # names in the manifest; transitions carry their stage
        buffer.set_source(index, name=preset.env_names[index], metadata=dict(setting=describe_stage(preset.stages[index])))
    return model
