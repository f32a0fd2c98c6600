"""
What a job may delete: only what it wrote itself. A job that creates its directory writes a marker of its own into it
(:data:`OWNED_MARKER`, naming the job and, for the collection, the buffer directories it creates beside it) and
removes the marker when it has finished (once its ``done.json`` is written). A later attempt deletes an unfinished
attempt's directory only when that marker is there; a directory without it (a finished job whose ``done.json`` was
lost, files put there by hand, a directory of an older version of this package) is refused with a message saying
what was found, and nothing is deleted. ``done.json`` only says that a job can be skipped: it never decides a deletion.
"""

import json
import os
import pathlib
import shutil
import time
from collections.abc import Sequence
from typing import Any, Callable, Optional

from sb3_lifelong.core.atomic import write_json_atomic

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
    """
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
