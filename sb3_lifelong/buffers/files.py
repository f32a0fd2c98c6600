"""
File operations of a buffer directory: writing every byte, fsync of files and directories, files that are never
opened through a symbolic link, and the atomic replacement of a JSON document (the manifest's commit).

The modules of the row store (``files``, ``manifest``, ``layouts``, ``readers``, ``rowstore``) import only numpy,
the standard library and one another, never torch: crash tests and tools can load them in light subprocesses.
"""

from __future__ import annotations

import errno
import json
import os
from typing import Any


class CommitNotDurableError(OSError):
    """
    A buffer's new manifest was renamed into place, so its rows are committed and readable (by this object, by
    readers and by a reopen), but the fsync of the directory that follows the rename failed: the commit may not
    survive a power loss or an operating-system crash (it survives a crash of the process). Whichever manifest a
    power loss leaves, the directory stays consistent: no file that the previous manifest needs is deleted until a
    later manifest is synced. ``flush()`` (or ``close()``) writes and syncs the manifest again.
    """


# errno values of an fsync of a directory that mean "this filesystem cannot sync directories" (nothing to wait for)
_DIR_FSYNC_UNSUPPORTED = frozenset({errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP})
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


def write_all(fd: int, data: Any) -> None:
    """
    Write every byte of ``data`` at the file offset of ``fd`` (``os.write`` may write fewer bytes than asked).

    :raises OSError: as ``os.write`` does, e.g. ENOSPC when the disk is full (after a short write)
    """
    view = memoryview(data).cast("B")
    while len(view):
        written = os.write(fd, view)
        if written <= 0:  # pragma: no cover (regular files do not do this)
            raise OSError(errno.EIO, "write() wrote nothing")
        view = view[written:]


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


def write_json_atomic(path: str, data: dict[str, Any]) -> None:
    """
    Write a JSON document atomically: temporary file, fsync, rename over the target, fsync of the directory.

    :param path: Target file
    :param data: JSON-serialisable document
    :raises OSError: (e.g. disk full) the target is unchanged and the temporary file removed
    :raises CommitNotDurableError: only the fsync of the directory after the rename failed: the target is replaced
        by the new document, which may not survive a power loss
    """
    directory = os.path.dirname(os.path.abspath(path))
    tmp = path + ".tmp"
    payload = json.dumps(data, indent=1, sort_keys=True, allow_nan=False).encode("utf-8")
    try:
        fd = create_new_file(tmp)  # a new file, never through a link planted at the temporary name
        try:
            write_all(fd, payload)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        remove_quietly(tmp)
        raise
    try:
        fsync_dir(directory, strict=True)
    except OSError as error:
        raise CommitNotDurableError(
            error.errno,
            f"{path} was replaced, but the fsync of its directory failed ({error.strerror}): the new version may not "
            "survive a power loss or an operating-system crash",
        ) from error
