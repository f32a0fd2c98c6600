"""
What a loaded model does with the buffer directory its zip names: loading never writes, and ``learn`` reattaches
the very buffer the model was saved with.

A zip's ``replay_buffer_kwargs`` are plain data that anyone can edit, and ``load`` used to rebuild the buffer from
them: a zip naming another buffer's ``path`` with ``capacity`` and ``evict=True`` evicted that buffer's rows, and a
bare ``path`` created a buffer in a directory of the zip's choosing. Now, when ``load`` rebuilds a
``LifelongReplayBuffer`` directory from the kwargs saved in the zip (none given to ``load``), the saved path is only a
suggestion:

- At ``load``, the directory is opened **read-only** (nothing is created, locked, written, evicted or cut), and only
  if it holds the buffer the model was saved with: the identity (:attr:`LifelongReplayBuffer.buffer_id`) recorded in
  the zip's checkpoint record must be the directory's. Otherwise (no buffer there, another buffer, an unreadable one)
  the model gets an empty in-memory buffer, and a warning says why. Of the saved kwargs, only those that say how to
  read and sample it are used (:data:`REOPEN_KEYS`); ``capacity``, ``evict``, ``mode`` and ``read_only=False`` are
  never applied.
- At the first ``learn`` (online training resumes), the same buffer is reopened for writing (``mode="append"``,
  its stored capacity, never evicting or cutting committed rows), after checking again, under the directory's writer
  lock, that it is that buffer and that it holds at least the transitions the checkpoint committed; otherwise
  ``learn`` raises, naming what to pass to ``load`` instead. New transitions continue after those it holds (all of
  them, also those committed after the save), and training resumes at the timestep they reach (the checkpoint
  rule: one transition per timestep, ``docs/modules/buffer.md``). A writer of this process that still holds the
  directory (the saved model, still alive) is closed first, its pending transitions committed. As any writer, the
  reopened buffer discards the uncommitted bytes a crashed writer left after the committed rows.

A buffer created before buffers had an identity, or a zip saved before checkpoints recorded it, has an unknown
identity: then only the number of committed transitions is checked (and, as for any reopening, that the directory
holds a buffer of the model's observation and action spaces). ``replay_buffer_kwargs`` given to ``load`` (or in its
``custom_objects``) are the user's and are used as they are.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import Any, Optional

from sb3_lifelong.buffers import writers
from sb3_lifelong.buffers.lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers.manifest import ID_PATTERN, BufferFormatError, buffer_id_of, read_manifest

#: the saved ``replay_buffer_kwargs`` a loaded model reopens its buffer with (how it is read and sampled); every other
#: one (``capacity``, ``evict``, ``mode``, ``path``, ...) is left out: a zip never changes a buffer
REOPEN_KEYS = (
    "n_steps",
    "gamma",
    "handle_timeout_termination",
    "chunk_size",
    "verify",
    "source",
    "max_resident_bytes",
    "read_mode",
)


def checkpoint_record(record: Any) -> Optional[dict[str, Any]]:
    """
    The buffer record a zip holds (``_buffer_checkpoint``, written by ``save``), checked: plain data from a file.

    :param record: The record as loaded
    :return: ``{"path": str, "transitions": int, "buffer_id": str or None, "timesteps": int or None}`` (``timesteps``:
        the model's timestep those transitions reach; None in a zip saved before checkpoints recorded it), or None when
        it is not one
    """

    def count(value: Any) -> Optional[int]:
        return value if isinstance(value, int) and not isinstance(value, bool) and value >= 0 else None

    if not isinstance(record, dict) or not isinstance(record.get("path"), str):
        return None
    transitions = count(record.get("transitions"))
    if transitions is None:
        return None
    buffer_id = record.get("buffer_id")
    if not (isinstance(buffer_id, str) and ID_PATTERN.fullmatch(buffer_id)):
        buffer_id = None
    return {
        "path": record["path"],
        "transitions": transitions,
        "buffer_id": buffer_id,
        "timesteps": count(record.get("timesteps")),
    }


def identity_problem(path: str, buffer_id: Optional[str]) -> tuple[Optional[str], int]:
    """
    Whether ``path`` holds the buffer of identity ``buffer_id``, read from its manifest alone (nothing is opened for
    writing).

    :param path: The buffer directory
    :param buffer_id: The identity the model recorded (None: unknown, any buffer is accepted)
    :return: None when it does, else why not (no buffer there, an unreadable one, another one); and the number of
        transitions its manifest says were ever committed (0 when it cannot be read)
    """
    try:
        manifest = read_manifest(path)
    except FileNotFoundError:
        return f"there is no buffer at {path!r} (it was moved or deleted)", 0
    except (OSError, BufferFormatError) as error:
        return f"the buffer at {path!r} cannot be read ({error})", 0
    found = buffer_id_of(manifest)
    if buffer_id is not None and found != buffer_id:
        return (
            f"{path!r} holds another buffer (id {found or 'none recorded'}) than the one this model was saved with (id "
            f"{buffer_id}): it was deleted and created again, or replaced"
        ), 0
    return None, int(manifest["num_transitions"])


def lag_problem(path: str, held: int, committed: int) -> Optional[str]:
    """:return: why a buffer holding ``held`` transitions cannot continue a checkpoint that committed ``committed``"""
    if held >= committed:
        return None
    return (
        f"{path!r} holds {held:,} transitions, fewer than the {committed:,} committed when the model was saved (an "
        "older copy of the directory?)"
    )


@dataclass
class SavedBuffer:
    """
    The buffer directory a loaded model's zip names, until ``learn`` reattaches it for writing.

    :param path: The directory (the absolute path the checkpoint recorded, else the saved ``path``)
    :param buffer_class: The saved ``replay_buffer_class``
    :param kwargs: The saved kwargs of :data:`REOPEN_KEYS`
    :param read_only: The model's buffer was read-only (then ``learn`` does not reopen it for writing)
    :param buffer_id: The identity the checkpoint recorded (None: unknown)
    :param committed: The transitions the checkpoint committed (0 when it recorded none)
    :param placeholder: The buffer ``load`` gave the model (the directory, read-only, or an empty one in memory)
    :param problem: Why the directory was not opened at load (None: it was)
    """

    path: str
    buffer_class: type[LifelongReplayBuffer]
    kwargs: dict[str, Any]
    read_only: bool
    buffer_id: Optional[str]
    committed: int
    placeholder: Any = None
    problem: Optional[str] = None

    def how_to(self) -> str:
        """What to pass to ``load`` instead."""
        return (
            f"Pass replay_buffer_kwargs to load to choose: {{'path': {self.path!r}, 'mode': 'append'}} continues in "
            "that directory anyway, {'path': <another directory>} starts a new buffer, {} keeps one in memory"
        )


def plan(model: Any, buffer_class: Any, kwargs: Any, record: Any) -> Optional[SavedBuffer]:
    """
    At ``load`` (the zip's own ``replay_buffer_kwargs``): what to do with the buffer directory they name.

    :param model: The model being loaded
    :param buffer_class: Its saved ``replay_buffer_class``
    :param kwargs: Its saved ``replay_buffer_kwargs``
    :param record: Its saved ``_buffer_checkpoint``
    :return: The plan, or None when the kwargs name no directory of a ``LifelongReplayBuffer`` (then SB3 builds the
        buffer as usual: in memory)
    """
    if not (isinstance(buffer_class, type) and issubclass(buffer_class, LifelongReplayBuffer)):
        return None
    if not isinstance(kwargs, dict) or kwargs.get("path") is None:
        return None
    checked = checkpoint_record(record)
    path = checked["path"] if checked is not None else kwargs["path"]
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"the saved replay_buffer_kwargs name a buffer path that is not a path: {path!r}")
    return SavedBuffer(
        path=os.path.abspath(os.fspath(path)),
        buffer_class=buffer_class,
        kwargs={key: kwargs[key] for key in REOPEN_KEYS if key in kwargs},
        read_only=kwargs.get("read_only") is True,
        buffer_id=None if checked is None else checked["buffer_id"],
        committed=0 if checked is None else checked["transitions"],
    )


def open_for_reading(model: Any, saved: SavedBuffer, where: str) -> LifelongReplayBuffer:
    """
    At ``load``: the buffer the model gets, without writing anything anywhere: ``saved.path`` read-only when it holds
    the model's buffer, else an empty buffer in memory (with a warning saying why).

    :param model: The model being loaded (its spaces, buffer size, device and number of envs)
    :param saved: The plan
    :param where: The zip, for the warning
    :return: The buffer (also ``saved.placeholder``)
    """
    common = dict(device=model.device, n_envs=model.n_envs, optimize_memory_usage=False)
    saved.problem = identity_problem(saved.path, saved.buffer_id)[0]
    buffer = None
    if saved.problem is None:
        try:
            buffer = saved.buffer_class(
                model.buffer_size,
                model.observation_space,
                model.action_space,
                path=saved.path,
                read_only=True,
                **common,
                **saved.kwargs,
            )
        except (OSError, ValueError, TypeError) as error:  # e.g. another buffer's spaces (ValueError), a corrupted chunk
            saved.problem = f"the buffer at {saved.path!r} cannot be reopened ({error})"
    if buffer is None:
        warnings.warn(
            f"{where}: the replay buffer this model was saved with is not attached: {saved.problem}. Nothing was written "
            "there; the model has an empty buffer in memory, and learn() refuses to start until you choose. " + saved.how_to(),
            stacklevel=4,
        )
        in_memory = {
            key: saved.kwargs[key] for key in ("n_steps", "gamma", "handle_timeout_termination") if key in saved.kwargs
        }
        buffer = saved.buffer_class(model.buffer_size, model.observation_space, model.action_space, **common, **in_memory)
    saved.placeholder = buffer
    return buffer


def _take_over(path: str) -> None:
    """
    Close the writer of ``path`` that this process holds, if any (e.g. the model that was saved, still alive beside
    the loaded one), as unpickling a buffer does: its pending transitions are committed first, and it refuses to add
    from then on. A writer in another process is left alone (reopening then raises ``RuntimeError``).
    """
    stale = writers.writer_of(path)  # writers of this process, by directory
    if stale is None or stale.read_only:
        return
    stale.close()  # flushes first: if that fails, the error goes through and nothing is taken over
    warnings.warn(
        f"{path} was open for writing by another buffer of this process (e.g. the model that was saved): it is closed "
        "(its pending transitions committed) and the loaded model continues the buffer",
        stacklevel=5,
    )


def open_for_writing(model: Any, saved: SavedBuffer) -> LifelongReplayBuffer:
    """
    At ``learn``: reopen the buffer ``load`` attached read-only for writing (``mode="append"``), after checking that it
    is still the model's buffer and that it holds the transitions the checkpoint committed; checked again once this
    process holds the directory's writer lock. Nothing is evicted or cut back (the stored capacity is kept). A writer
    of this process that holds the directory is closed first (:func:`_take_over`).

    :param model: The loaded model
    :param saved: The plan
    :return: The buffer, open for writing
    :raises FileNotFoundError: there is no buffer there
    :raises ValueError: another buffer, or fewer transitions than the checkpoint committed; or as the constructor
    :raises RuntimeError: a writer in another process has the directory open
    """
    problem, _ = identity_problem(saved.path, saved.buffer_id)
    if problem is None:
        _take_over(saved.path)
        problem, held = identity_problem(saved.path, saved.buffer_id)  # again: the writer closed may have committed rows
        problem = problem or lag_problem(saved.path, held, saved.committed)
    if problem is None:
        buffer = saved.buffer_class(
            model.buffer_size,
            model.observation_space,
            model.action_space,
            device=model.device,
            n_envs=model.n_envs,
            path=saved.path,
            mode="append",
            **saved.kwargs,
        )
        # under the writer lock now: what was checked above cannot have been replaced meanwhile unnoticed
        if saved.buffer_id is not None and buffer.buffer_id != saved.buffer_id:
            problem = f"{saved.path!r} holds another buffer (id {buffer.buffer_id or 'none recorded'}) than the model's"
        else:
            problem = lag_problem(saved.path, int(buffer.store.num_committed), saved.committed)
        if problem is None:
            return buffer
        buffer.close()
    error = FileNotFoundError if problem.startswith("there is no buffer") else ValueError
    raise error(f"learn() cannot resume the replay buffer this model was saved with: {problem}. {saved.how_to()}")
