"""
File operations of a buffer directory: writing every byte, fsync of files and directories, files that are never
opened through a symbolic link. The manifest's commit is ``sb3_lifelong.core.atomic.write_json_atomic``, whose
:class:`CommitNotDurableError` this module re-exports.

The modules of the row store (``files``, ``manifest``, ``layouts``, ``readers``, ``rowstore``) import only numpy,
the standard library, ``core/atomic.py`` (the standard library only) and one another, never torch: crash tests and
tools can load them in light subprocesses.
"""

from __future__ import annotations

import os

from sb3_lifelong.core.atomic import DIR_FSYNC_UNSUPPORTED as _DIR_FSYNC_UNSUPPORTED
from sb3_lifelong.core.atomic import (
    CommitNotDurableError,  # noqa: F401 (raised by the manifest's commit)
    write_all,  # noqa: F401 (the data files' writes; core's manifest commit uses it too)
)

# never open a file of a buffer directory for writing through a symbolic link (POSIX; 0 where the OS has no such flag)
NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def explained(error: OSError, context: str) -> OSError:
    """An OSError of the same errno (so of the same class) and file name, whose message starts with ``context``."""
    if error.errno is None:
        return OSError(f"{context}: {error}")
    return OSError(error.errno, f"{context} ({error.strerror})", error.filename)


def fsync_dir(path: str, strict: bool = False) -> None:
    """
    fsync a directory, so that the entries created, renamed or deleted in it survive a power loss.

    :param path: The directory
    :param strict: Raise the ``OSError`` of a failed fsync (commits); otherwise it is ignored (deletions, which the
        next writer redoes). A filesystem that cannot sync directories (EINVAL, ENOTSUP) or a platform that cannot
        open them is not a failure
    """
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover (e.g. Windows)
        return
    try:
        os.fsync(fd)
    except OSError as error:
        if strict and error.errno not in _DIR_FSYNC_UNSUPPORTED:
            raise
    finally:
        os.close(fd)


def delete_file(path: str) -> None:
    """Delete a chunk file (a missing one is fine). A separate function so that tests can simulate a crash here
    (callers look it up in this module at each call: ``files.delete_file``)."""
    try:
        os.remove(path)
    except FileNotFoundError:  # pragma: no cover (removed by hand)
        pass


def open_for_writing(file_name: str, flags: int = 0) -> int:
    """
    Open a file of a buffer directory for writing, never through a symbolic link (``O_NOFOLLOW``: a link planted at
    ``file_name`` makes this fail with ``ELOOP`` instead of writing where it points).

    :param file_name: The file
    :param flags: Further ``os.O_*`` flags
    :return: The file descriptor
    """
    flags |= os.O_WRONLY | NOFOLLOW | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    return os.open(file_name, flags, 0o666)


def create_new_file(file_name: str) -> int:
    """
    Create ``file_name`` as a new, empty regular file and open it for writing. Whatever has that name already (a
    temporary file or an unflushed chunk file left by a crash, or a symbolic link planted there) is unlinked first:
    ``unlink`` removes a link itself, never what it points to. The file is then created with ``O_CREAT | O_EXCL |
    O_NOFOLLOW``, so that no byte is ever written outside the directory, even if a link is planted again meanwhile.

    :param file_name: The file to create
    :return: The file descriptor
    :raises OSError: e.g. ``EISDIR`` (a directory has that name) or ``EEXIST`` (an entry appeared again between the
        unlink and the creation)
    """
    try:
        os.unlink(file_name)
    except FileNotFoundError:
        pass
    return open_for_writing(file_name, os.O_CREAT | os.O_EXCL)


def remove_quietly(file_name: str) -> None:
    """Delete a file that a failed write left behind (nothing refers to it); never raises."""
    try:
        os.remove(file_name)
    except OSError:
        pass
