"""
Atomic file writes: a file is either its previous version or its new one, never a half-written mix.

Every write goes to a new temporary file in the target's directory (``.<name>.<random>.tmp``), which is flushed and
synced, then renamed over the target (``os.replace``, atomic on POSIX and Windows), and the directory is synced so
that the rename survives a power loss. If anything fails before the rename (a full disk, a file-size limit, an
exception of the code writing it), the temporary file is removed, the previous file is left as it was, and the
error says which file could not be written. A process killed in the middle of a write leaves the previous file
and, at worst, a hidden temporary file beside it (never a truncated target).

- :func:`atomic_write`: a context manager that yields an open file whose contents replace the target on success;
- :func:`write_bytes_atomic`, :func:`write_text_atomic`, :func:`write_json_atomic`: whole documents at once.

Only the standard library is imported (the module can be used anywhere in the package).
"""

import contextlib
import errno
import json
import os
import pathlib
import secrets
from collections.abc import Iterator
from typing import IO, Any, Optional, Union

PathLike = Union[str, "os.PathLike[str]"]

# errno values of an fsync of a directory that mean "this filesystem cannot sync directories" (nothing to wait for)
_DIR_FSYNC_UNSUPPORTED = frozenset({errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EBADF})


class AtomicWriteError(OSError):
    """
    A file could not be written (e.g. the disk is full): the previous version of the file, if any, is unchanged and
    no temporary file is left. Keeps the ``errno`` of the failure (``error.errno == errno.ENOSPC``) and the target's
    path in ``filename``.
    """


def temporary_name(path: PathLike) -> pathlib.Path:
    """:return: a fresh hidden name beside ``path`` for the temporary file of its next write"""
    target = pathlib.Path(path)
    return target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")


def fsync_directory(directory: PathLike) -> None:
    """
    Sync a directory, so that the entries renamed in it survive a power loss. A filesystem or platform that cannot
    sync directories is not a failure.

    :param directory: the directory
    :raises OSError: the fsync itself failed (an I/O error)
    """
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # pragma: no cover (e.g. Windows, where directories cannot be opened)
        return
    try:
        os.fsync(fd)
    except OSError as error:
        if error.errno not in _DIR_FSYNC_UNSUPPORTED:
            raise
    finally:
        os.close(fd)


def _remove_quietly(path: pathlib.Path) -> None:
    try:
        os.remove(path)
    except OSError:
        pass


def _failed(target: pathlib.Path, error: OSError) -> AtomicWriteError:
    """:return: the error to raise for a failed write of ``target`` (same errno, the target's path in the message)"""
    reason = error.strerror or str(error)
    message = f"could not write {target} ({reason}): its previous version, if any, is unchanged"
    return AtomicWriteError(error.errno if error.errno is not None else errno.EIO, message, str(target))


@contextlib.contextmanager
def atomic_write(
    path: PathLike, mode: str = "wb", encoding: Optional[str] = None, newline: Optional[str] = None
) -> Iterator[IO[Any]]:
    """
    Write ``path`` atomically: yields a new temporary file beside it, opened with ``mode``; when the block ends
    without an exception, the file is flushed, synced and renamed over ``path``, and the directory synced.

    ``with atomic_write("scores.csv", "w", newline="") as handle: csv.writer(handle).writerows(rows)``

    :param path: the target file (its directory must exist)
    :param mode: ``"wb"`` (bytes) or ``"w"`` (text)
    :param encoding: the text encoding (text mode; default UTF-8)
    :param newline: as for ``open`` (text mode; ``""`` for the ``csv`` module)
    :return: (as a context manager) the open temporary file
    :raises AtomicWriteError: an ``OSError`` while writing, syncing or renaming (e.g. ``ENOSPC``): ``path`` is
        unchanged, the temporary file removed, and the message names ``path``. Any other exception of the block goes
        through as it is, with the same guarantees
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write writes a whole new file: mode must be 'w' or 'wb', got {mode!r}")
    target = pathlib.Path(path)
    if target.is_dir():
        raise IsADirectoryError(errno.EISDIR, f"cannot write {target}: it is a directory", str(target))
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0)
    temporary = temporary_name(target)
    try:
        fd = os.open(temporary, flags, 0o666)  # a new file (the umask applies, as for open()), never through a link
    except OSError as error:
        raise _failed(target, error) from error
    try:
        if mode == "wb":
            handle: IO[Any] = os.fdopen(fd, "wb")
        else:
            handle = os.fdopen(fd, "w", encoding=encoding or "utf-8", newline=newline)
    except BaseException:
        os.close(fd)
        _remove_quietly(temporary)
        raise
    try:
        try:
            with handle:
                yield handle
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(temporary, target)
        except BaseException:
            _remove_quietly(temporary)
            raise
        fsync_directory(target.parent)
    except OSError as error:
        if isinstance(error, AtomicWriteError):
            raise
        raise _failed(target, error) from error


def write_bytes_atomic(path: PathLike, data: bytes) -> None:
    """
    Replace ``path`` by ``data`` atomically (:func:`atomic_write`).

    :raises AtomicWriteError: ``path`` is unchanged (see :func:`atomic_write`)
    """
    with atomic_write(path, "wb") as handle:
        handle.write(data)


def write_text_atomic(path: PathLike, text: str, encoding: str = "utf-8") -> None:
    """
    Replace ``path`` by ``text`` atomically (:func:`atomic_write`).

    :raises AtomicWriteError: ``path`` is unchanged (see :func:`atomic_write`)
    """
    write_bytes_atomic(path, text.encode(encoding))


def write_json_atomic(path: PathLike, data: Any, indent: Optional[int] = 1) -> None:
    """
    Replace ``path`` by the JSON document ``data`` atomically (:func:`atomic_write`). The document is serialised
    first: a value JSON cannot hold (e.g. NaN) raises ``ValueError`` before anything is written.

    :raises AtomicWriteError: ``path`` is unchanged (see :func:`atomic_write`)
    """
    write_text_atomic(path, json.dumps(data, indent=indent, sort_keys=True, allow_nan=False))
