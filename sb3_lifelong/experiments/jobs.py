"""
A job of a study, the same for every job of a seed: its directory from start to finish, and what every job is built
with. A job claims a new directory (``start_job``), runs while it holds its lock (:func:`job_lock`), may pause and
resume (a student's checkpoint and the record that names it: ``StudentPauses``, ``paused_student``; a pause's logs
cut back to it, everything cut kept beside it: ``aside_name``, ``drop_rows_after``, ``cut_logs_back``), and is done
once its ``done.json`` is written (``finish_job``). Every job acts in the robot through its stages and its drift
(``make_env``), is evaluated in one copy of it per stage (``eval_envs``), builds its models with the preset's network
and device (``model_kwargs``), logs through the same callbacks (``job_callbacks``, ``tensorboard_dir``), and a bounded
critic has its value support (:func:`value_support`). What the jobs run and what their pauses record are
``collection`` (the ``collect`` job) and :mod:`~sb3_lifelong.experiments.protocol` (the students, the online
baselines, one seed).

What a job may delete: only what it wrote itself. A job that creates its directory writes a marker of its own into it
(:data:`OWNED_MARKER`, naming the job and, for the collection, the buffer directories it creates beside it) and
removes the marker when it has finished (once its ``done.json`` is written). A later attempt deletes an unfinished
attempt's directory only when that marker is there; a directory without it (a finished job whose ``done.json`` was
lost, files put there by hand, a directory of an older version of this package) is refused with a message saying
what was found, and nothing is deleted. ``done.json`` only says that a job can be skipped: it never decides a deletion.
"""

import contextlib
import csv
import json
import os
import pathlib
import re
import shutil
import time
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Callable, Optional

import gymnasium as gym
from filelock import FileLock, Timeout
from stable_baselines3.common.callbacks import BaseCallback

from sb3_lifelong.core.atomic import atomic_write, write_json_atomic
from sb3_lifelong.envs import DynamicsSchedule, LinearRamp, stage_envs
from sb3_lifelong.evaluation.callbacks import EVAL_SEED_OFFSET, MultiEnvEvalCallback, SourceQCallback, TrainLogCallback
from sb3_lifelong.experiments import costs
from sb3_lifelong.experiments.presets import Preset, evaluation_stages

# ------------------------------------------------------------------------------------------------- a job's directory
#: the marker of a directory that a job created and has not finished: everything in it is the job's to delete
OWNED_MARKER = ".sb3_lifelong_owned.json"


class NotOwnedError(FileExistsError):
    """A job would have deleted a directory it did not write (or a finished one): nothing was deleted."""


def claim_directory(directory: pathlib.Path, job: str, beside: Sequence[str] = ()) -> None:
    """
    Create a job's directory with its marker, before the job writes anything.

    :param directory: the job's directory (it must not exist, or be empty)
    :param job: the job's name, for the record
    :param beside: names of directories beside ``directory`` that the job creates too (the collection's buffers):
        an unfinished attempt's are deleted with it
    :raises FileExistsError: ``directory`` holds files
    :raises NotOwnedError: a directory of ``beside`` is there already: no attempt of this job wrote it (a claim names
        only what the job is about to create), so claiming it would let a later attempt delete it; nothing was written
    """
    for name in beside:
        path = directory.parent / name
        if path.exists() or path.is_symlink():
            raise NotOwnedError(
                f"{path} is there already, but the {job} job that would create it has not started ({directory} holds no "
                f"claim): nothing was deleted or written. Move {path} away to run the {job} job"
            )
    directory.mkdir(parents=True, exist_ok=True)
    if any(directory.iterdir()):
        raise FileExistsError(f"{directory} is not empty: a job starts in a new directory")
    record = dict(job=job, beside=list(beside), pid=os.getpid(), started=time.strftime("%Y-%m-%d %H:%M:%S %Z"))
    write_json_atomic(directory / OWNED_MARKER, record)


def owner_record(directory: pathlib.Path) -> Optional[dict[str, Any]]:
    """:return: the marker of an unfinished job in ``directory`` (None when there is none, or it is unreadable)"""
    try:
        record = json.loads((directory / OWNED_MARKER).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def release_directory(directory: pathlib.Path) -> None:
    """A job has finished (its ``done.json`` is written): its directory is no longer deleted by a later attempt."""
    (directory / OWNED_MARKER).unlink(missing_ok=True)


def _listing(directory: pathlib.Path, limit: int = 5) -> str:
    """:return: a few of the entries of ``directory``, for messages"""
    names = sorted(path.name for path in directory.iterdir())
    shown = ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")
    return shown or "nothing"


def remove_unfinished(
    directory: pathlib.Path, job: str, log: Callable[[str], None] = print, finished: Sequence[str] = ("done.json",)
) -> None:
    """
    Delete an unfinished attempt of ``job`` before it starts again: ``directory`` (and the directories its marker
    names beside it) when the attempt's marker is there. A missing directory, or an empty one, is fine; a symbolic
    link is unlinked (what it points to is not touched).

    :param directory: the job's directory
    :param job: the job's name, for messages
    :param log: where the deletion is reported
    :param finished: files whose presence means the job has finished: such a directory is never deleted
    :raises NotOwnedError: ``directory`` holds a finished job (a file of ``finished``), or files without the marker
        (not written by an unfinished attempt of this job); nothing was deleted
    """
    if directory.is_symlink():
        directory.unlink()
        log(f"  {job}: removed the link {directory} (an unfinished attempt's; what it pointed to is untouched)")
        return
    if not directory.exists():
        return
    if not directory.is_dir():
        raise NotOwnedError(f"{directory} is a file, not the directory of job {job}: nothing was deleted; move it away")
    done = [name for name in finished if (directory / name).exists()]
    if done:
        raise NotOwnedError(
            f"{directory} holds a finished {job} job ({', '.join(done)}): nothing was deleted. Move the directory away "
            "to run the job again"
        )
    if not any(directory.iterdir()):
        directory.rmdir()
        return
    record = owner_record(directory)
    if record is None:
        raise NotOwnedError(
            f"{directory} holds files ({_listing(directory)}) but no record that an unfinished attempt of this job wrote "
            f"them ({OWNED_MARKER}): a finished job whose done.json was lost, files put there by hand, or a directory of "
            f"an older version of sb3_lifelong. Nothing was deleted: move {directory} away (or delete it) to run the "
            f"{job} job again"
        )
    beside = [directory.parent / name for name in record.get("beside", []) if isinstance(name, str) and name]
    for path in beside:
        if path.parent != directory.parent:  # a marker names directories beside its own only
            raise NotOwnedError(f"{directory / OWNED_MARKER} names {path}, which is not beside it: nothing was deleted")
    for path in beside:
        if path.is_symlink():
            path.unlink()
        elif path.exists():
            shutil.rmtree(path)
    shutil.rmtree(directory)
    removed = ", ".join(str(path) for path in [directory, *beside])
    log(f"  {job}: removed the unfinished attempt started {record.get('started', '?')} ({removed}) to start again")


def start_job(directory: pathlib.Path, job: str, log: Callable[[str], None] = print, beside: Sequence[str] = ()) -> None:
    """
    Start a job anew in ``directory``: an unfinished attempt's directory is deleted first (:func:`remove_unfinished`:
    only one this job wrote; anything else is refused), then the directory is claimed (:func:`claim_directory`).

    :param directory: the job's directory
    :param job: the job's name, for the record and messages
    :param log: where a deletion is reported
    :param beside: directories beside ``directory`` that the job creates too (see :func:`claim_directory`)
    """
    remove_unfinished(directory, job, log)
    claim_directory(directory, job, beside=beside)


def finish_job(directory: pathlib.Path, done: Mapping[str, Any]) -> None:
    """
    A job has finished: its ``done.json`` (written atomically: never a half-written "done"), then its marker goes, so
    that no later attempt deletes the directory.

    :param directory: the job's directory
    :param done: what ``done.json`` records
    """
    write_json_atomic(directory / "done.json", dict(done))
    release_directory(directory)


@contextlib.contextmanager
def job_lock(run_dir: pathlib.Path, job: str) -> Iterator[bool]:
    """
    Hold a seed's job for this process, so that two commands of the same seed (two terminals, a runner beside a
    command) never run one job at once: the second would delete the first one's directory and mix their files.

    :param run_dir: the seed's directory
    :param job: the job's name
    :return: (as a context manager) True if this process holds the job, False if another process does
    """
    # filelock: an OS lock (flock on POSIX, LockFileEx on Windows) on a file beside the job's directory, which a job
    # deletes first; the OS releases it when the process ends, however it ends
    lock = FileLock(run_dir / f".{job}.lock", timeout=0, thread_local=False)
    try:
        lock.acquire()
    except Timeout:
        yield False
        return
    try:
        yield True
    finally:
        lock.release()


# ------------------------------------------------------------------------------------------------- pause and resume
def aside_name(path: pathlib.Path, paused: int) -> pathlib.Path:
    """:return: ``<stem>.after_pause_<paused>[.k]<suffix>`` beside ``path``, the first such name that is free"""
    for attempt in range(1000):
        tag = f".after_pause_{paused}" + (f".{attempt}" if attempt else "")
        aside = path.with_name(f"{path.stem}{tag}{path.suffix}")
        if not aside.exists():
            return aside
    raise FileExistsError(f"no free name to set {path} aside")


def set_aside(path: pathlib.Path, paused: int) -> pathlib.Path:
    """Rename ``path`` to :func:`aside_name`'s name and return it."""
    aside = aside_name(path, paused)
    os.replace(path, aside)
    return aside


def drop_rows_after(path: pathlib.Path, timesteps: int) -> Optional[tuple[int, pathlib.Path]]:
    """
    Keep the rows of a job's CSV log (a ``timesteps`` column) up to ``timesteps``; the file is replaced atomically,
    and the whole log is kept beside it first (``<stem>.after_pause_<timesteps>[.k].csv``). A row cut short (a stop
    in the middle of writing it: too few fields, or a ``timesteps`` that is not a number) is past the pause.

    :return: how many rows were cut and where the whole log is kept; None when nothing was cut (or ``path`` is not a
        log with a ``timesteps`` column)
    """
    if not path.is_file():
        return None
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    if not rows or "timesteps" not in rows[0]:
        return None
    column = rows[0].index("timesteps")

    def before_pause(row: list[str]) -> bool:
        try:
            return len(row) == len(rows[0]) and float(row[column]) <= timesteps
        except ValueError:
            return False

    kept = [rows[0], *(row for row in rows[1:] if before_pause(row))]
    if len(kept) == len(rows):
        return None
    aside = aside_name(path, timesteps)
    shutil.copy2(path, aside)  # the whole log first: a stop in between leaves it twice, never lost
    with atomic_write(path, "w", newline="") as rewritten:
        csv.writer(rewritten).writerows(kept)
    return len(rows) - len(kept), aside


def cut_logs_back(directory: pathlib.Path, updates: int, log: Callable[[str], None]) -> None:
    """
    Cut the logs (``*.csv`` with a ``timesteps`` column) of a paused student back to the rows of its first
    ``updates`` updates (:func:`drop_rows_after`): rows past the pause were written by a part that stopped without
    pausing again. Nothing is deleted: a log that had such rows is kept whole beside it as
    ``<stem>.after_pause_<updates>[.k].csv``.
    """
    for path in sorted(directory.glob("*.csv")):
        if ".after_pause_" in path.name:
            continue
        cut = drop_rows_after(path, updates)
        if cut is not None:
            log(f"  {path.name}: {cut[0]} rows past the pause at {updates:,} updates (all kept in {cut[1].name})")


#: a paused student (``distill_student(..., pause_every=...)``), in the student's directory: what the pause recorded
#: (updates, the student's settings, its checkpoint ``paused_<updates>.zip``, which holds the random streams too)
PAUSED_STUDENT_RECORD = "paused.json"


def paused_student(directory: pathlib.Path, settings: Mapping[str, Any]) -> Optional[dict[str, Any]]:
    """
    :return: the pause record of the student in ``directory``, or None when it has none (a new student)
    :raises ValueError: the pause was recorded for other settings (the directory is left as it is)
    :raises FileNotFoundError: the checkpoint the record names is missing (the directory is left as it is)
    """
    record_path = directory / PAUSED_STUDENT_RECORD
    if not record_path.exists() or (directory / "done.json").exists():
        return None
    record = json.loads(record_path.read_text())
    recorded, expected = record.get("settings"), json.loads(json.dumps(settings))
    if isinstance(recorded, dict) and "preset" not in recorded:  # recorded before the preset was
        expected.pop("preset", None)
    if recorded != expected:
        raise ValueError(
            f"{directory} holds a student checkpoint at {record.get('updates', 0):,} updates with other settings "
            f"({recorded}) than these ({dict(settings)}): move it away to train this one"
        )
    if not (directory / record["model"]).exists():
        raise FileNotFoundError(
            f"{directory / PAUSED_STUDENT_RECORD} records a pause at {record.get('updates', 0):,} updates whose "
            f"checkpoint {record['model']} is missing: move the directory away to train this student anew"
        )
    return record


def pause_checkpoints(directory: pathlib.Path) -> list[pathlib.Path]:
    """:return: the checkpoints that pauses of a student wrote in ``directory`` (``paused_<updates>.zip``)"""
    return [path for path in directory.glob("paused_*.zip") if re.fullmatch(r"paused_\d+\.zip", path.name)]


class StudentPauses(BaseCallback):
    """
    Pause a student every ``every`` updates before its last: its checkpoint ``paused_<updates>.zip``, then the record
    that names it (:data:`PAUSED_STUDENT_RECORD`), then the older checkpoints go. Called after the student's other
    callbacks, so that the pause's evaluation is in its logs.

    :param directory: the student's directory
    :param every: the pause period, in updates (None: never)
    :param total: the student's updates in all
    :param settings: what the record must match to be continued
    :param paused: the record continued from (None: a new student)
    :param log: where each pause is reported
    """

    def __init__(
        self,
        directory: pathlib.Path,
        every: Optional[int],
        total: int,
        settings: Mapping[str, Any],
        paused: Optional[Mapping[str, Any]],
        log: Callable[[str], None] = print,
    ) -> None:
        super().__init__()
        self.directory, self.every, self.total, self.settings, self.log = directory, every, total, settings, log
        self.earlier = 0.0 if paused is None else float(paused.get("seconds", 0.0))
        self.start = time.perf_counter()

    def seconds(self) -> float:
        """:return: the student's training seconds so far, its earlier parts' included"""
        return self.earlier + time.perf_counter() - self.start

    def record(self, updates: int, checkpoint: str) -> float:
        """Write the record of a pause at ``updates`` whose checkpoint is ``checkpoint``. :return: the seconds so far"""
        seconds = self.seconds()
        forward = getattr(self.model, "_forward", None)
        compiled = forward is not None and forward.compiled is not None  # continued compiled too, as if never stopped
        record = dict(updates=updates, model=checkpoint, settings=self.settings, seconds=seconds, compiled=compiled)
        write_json_atomic(self.directory / PAUSED_STUDENT_RECORD, record)
        return seconds

    def _on_step(self) -> bool:
        updates = self.model.num_timesteps
        if self.every is None or updates % self.every or updates >= self.total:
            return True
        checkpoint = f"paused_{updates}.zip"
        self.model.save(self.directory / checkpoint)
        seconds = self.record(updates, checkpoint)
        for older in pause_checkpoints(self.directory):
            if older.name != checkpoint:
                older.unlink()
        self.log(
            f"  {self.directory.name}: checkpoint at {updates:,} of {self.total:,} updates ({costs.minutes(seconds)} so far); "
            "a stopped run continues from here"
        )
        return True


# ------------------------------------------------------------------------------------------------- environments
def make_env(preset: Preset, switch_at: Optional[Sequence[int]] = None, start_timestep: int = 0) -> DynamicsSchedule:
    """
    The robot through its stages and its drift, with the true physical parameters appended to the observation (as the
    paper).

    :param preset: the study's settings: each parameter of its ``drift`` ramps linearly
        (:class:`~sb3_lifelong.envs.LinearRamp`) from its start at timestep 0 to its end at the end of the life, the sum
        of ``stage_steps``
    :param switch_at: the timesteps at which the stages after the first take effect (None: the first stage only)
    :param start_timestep: the global timestep of the env's first step
    :return: the env
    :raises ValueError: naming the parameter, when the robot does not have a drifting parameter, or its range is
        outside the robot's own
    """
    lifetime = sum(preset.stage_steps)
    ramps = {name: LinearRamp(start, end, begin=0, finish=lifetime) for name, (start, end) in (preset.drift or {}).items()}
    return DynamicsSchedule(
        gym.make(preset.env_id, **preset.env_kwargs),
        stages=list(preset.stages),
        switch_at=switch_at,
        schedules=ramps or None,
        append_params=True,
        start_timestep=start_timestep,
    )


def eval_envs(preset: Preset) -> dict[str, DynamicsSchedule]:
    """
    :param preset: the study's settings
    :return: one copy of the robot per stage, pinned to it and named by ``env_names``
        (:func:`~sb3_lifelong.envs.stage_envs`), observing what the collector's robot does (a drifting parameter is
        at its nominal value there, or where ``drift_eval_at`` places it:
        :func:`~sb3_lifelong.experiments.presets.evaluation_stages`)
    """
    return stage_envs(
        preset.env_id,
        evaluation_stages(preset.stages, preset.drift, preset.drift_eval_at),
        preset.env_names,
        preset.env_kwargs,
        append_params=True,
        observed_params=preset.observed_params,
    )


# ---------------------------------------------------------------------------------------------- what every job is built with
def tensorboard_dir(directory: pathlib.Path) -> Optional[str]:
    """
    :param directory: a job's directory
    :return: the ``tensorboard_log`` of the job's model, ``<directory>/tb`` (SB3 writes each run into a folder
        ``<tb_log_name>_<k>`` there), or None when tensorboard is not installed (the CSV files only)
    """
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401  (SB3 writes its event files with it)
    except ImportError:
        return None
    return str(directory / "tb")


def model_kwargs(preset: Preset, seed: int) -> dict[str, Any]:
    """
    What every model of a study is built with: the preset's network (``net_arch``, ``layer_norm``), the seed, and the
    preset's device (``--device``). Models that continue a paused job load onto that device too, so that a run in
    parts computes what an uninterrupted one does.

    :param preset: the study's preset
    :param seed: the model's seed
    :return: ``policy_kwargs``, ``seed`` and ``device``, as constructor arguments
    """
    return dict(
        policy_kwargs=dict(net_arch=list(preset.net_arch), layer_norm=preset.layer_norm), seed=seed, device=preset.device
    )


def value_support(reward_range: tuple[float, float], gamma: float, scales: Sequence[float] = ()) -> dict[str, float]:
    """
    The support of a categorical critic that holds every return of the data: no value outside it can be learnt, so
    the critic cannot diverge (the paper's critic is distributional).

    :param reward_range: the smallest and largest stored reward (:meth:`LifelongReplayBuffer.reward_range`)
    :param gamma: the discount factor
    :param scales: per-source reward scales applied at sampling time (the bounds cover each of them)
    :return: ``v_min`` and ``v_max`` (policy kwargs)
    """
    if not 0 <= gamma < 1:
        raise ValueError(f"a bounded value support needs 0 <= gamma < 1, got {gamma}")
    factors = [1.0, *scales]
    low = min(0.0, *(reward_range[0] * f for f in factors), *(reward_range[1] * f for f in factors))
    high = max(0.0, *(reward_range[0] * f for f in factors), *(reward_range[1] * f for f in factors))
    if low == high:
        high = low + 1.0  # all rewards 0: any non-empty support
    return dict(v_min=low / (1 - gamma), v_max=high / (1 - gamma))


def job_callbacks(
    preset: Preset,
    directory: pathlib.Path,
    eval_freq: int,
    seed: int,
    data: Optional[Any] = None,
    q: bool = True,
    reward_scale: Optional[dict[int, float]] = None,
    **eval_kwargs: Any,
) -> list[Any]:
    """
    The callbacks of one job: its ``train/`` values (``train.csv``), its evaluations in one copy of the robot per
    stage (:func:`eval_envs`, ``eval.csv``, the same episodes at every evaluation, seeded from
    ``EVAL_SEED_OFFSET + seed``) and, with a
    critic, its average Q per source (``q_sources.csv``).

    :param preset: the protocol's settings
    :param directory: the job's directory
    :param eval_freq: the evaluation period (environment steps, or updates for a student)
    :param seed: the seed of the evaluations
    :param data: the transitions the Q-values are measured on (None: the model's replay buffer)
    :param q: measure the average Q per source
    :param reward_scale: per-source reward scales the model trains with, for the Monte-Carlo returns
    :param eval_kwargs: further arguments of :class:`~sb3_lifelong.evaluation.callbacks.MultiEnvEvalCallback`
    :return: the callbacks
    """
    # the train/ values first: the evaluation dumps the logger, which clears them
    callbacks: list[Any] = [
        TrainLogCallback(directory / "train.csv", log_freq=eval_freq),
        MultiEnvEvalCallback(
            eval_envs(preset),
            eval_freq,
            preset.eval_episodes,
            log_path=directory / "eval.csv",
            seed=EVAL_SEED_OFFSET + seed,
            same_episodes=True,
            **eval_kwargs,
        ),
    ]
    if q:
        q_log = directory / "q_sources.csv"
        callbacks.append(SourceQCallback(log_freq=eval_freq, log_path=q_log, data=data, reward_scale=reward_scale))
    return callbacks
