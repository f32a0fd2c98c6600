"""
Atomic file writes: a file is either its previous version or its new one, never a half-written mix.

Every write goes to a new temporary file in the target's directory (``.<name>.<random>.tmp``), which is flushed and
synced, then renamed over the target (``os.replace``, atomic on POSIX and Windows), and the directory is synced so
that the rename survives a power loss. If anything fails before the rename (a full disk, a file-size limit, an
exception of the code writing it), the temporary file is removed, the previous file is left as it was, and the
error says which file could not be written. If only the sync of the directory after the rename fails, the target
is already the new version, and :class:`CommitNotDurableError` says that it may not survive a power loss. A process
killed in the middle of a write leaves the previous file and, at worst, a hidden temporary file beside it (never a
truncated target).

- :func:`atomic_write`: a context manager that yields an open file whose contents replace the target on success;
- :func:`write_bytes_atomic`, :func:`write_text_atomic`, :func:`write_json_atomic`: whole documents at once (written
  with ``os.write``, every byte). The one writer of a file that holds its lock (a replay buffer's manifest) may ask
  for a fixed temporary name, ``<name>.tmp``, which it can then list among its files and clean up.

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
DIR_FSYNC_UNSUPPORTED = frozenset({errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP})


class AtomicWriteError(OSError):
    """
    A file could not be written (e.g. the disk is full): the previous version of the file, if any, is unchanged and
    no temporary file is left. Keeps the ``errno`` of the failure (``error.errno == errno.ENOSPC``) and the target's
    path in ``filename``.
    """


class CommitNotDurableError(OSError):
    """
    A file was replaced by its new version (readable at once, and after a crash of the process), but the fsync of its
    directory that follows the rename failed: the new version may not survive a power loss or an operating-system
    crash. Keeps the ``errno`` of the failed fsync. Writing the file again syncs it.

    A replay buffer (:class:`sb3_lifelong.buffers.CommitNotDurableError`) raises it for its manifest: the rows are
    committed and readable (by this object, by readers and by a reopen), but the commit may not survive a power loss.
    Whichever manifest a power loss leaves, the directory stays consistent: no file that the previous manifest needs is
    deleted until a later manifest is synced. ``flush()`` (or ``close()``) writes and syncs the manifest again.
    """


def temporary_name(path: PathLike) -> pathlib.Path:
    """:return: a fresh hidden name beside ``path`` for the temporary file of its next write"""
    target = pathlib.Path(path)
    return target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")


def fsync_directory(directory: PathLike) -> None:
    """
    Sync a directory, so that the entries renamed in it survive a power loss. A filesystem or platform that cannot
    sync directories (:data:`DIR_FSYNC_UNSUPPORTED`, or a directory that cannot be opened) is not a failure.

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
        if error.errno not in DIR_FSYNC_UNSUPPORTED:
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


@contextlib.contextmanager
def _new_version(path: PathLike, fixed_temporary: bool = False) -> Iterator[int]:
    """
    The machinery of every write of this module: yields the file descriptor of a new temporary file beside ``path``;
    when the block ends without an exception, the file is synced, closed and renamed over ``path``, then the directory
    synced. See :func:`atomic_write` and :func:`write_json_atomic` for the errors.
    """
    target = pathlib.Path(path)
    if target.is_dir():
        raise IsADirectoryError(errno.EISDIR, f"cannot write {target}: it is a directory", str(target))
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0)
    flags |= getattr(os, "O_CLOEXEC", 0)
    temporary = target.with_name(target.name + ".tmp") if fixed_temporary else temporary_name(target)
    try:
        if fixed_temporary:  # what has that name (a crash's leftover, a planted link) is unlinked, never followed
            with contextlib.suppress(FileNotFoundError):
                os.unlink(temporary)
        fd = os.open(temporary, flags, 0o666)  # a new file (the umask applies, as for open()), never through a link
    except OSError as error:
        raise _failed(target, error) from error
    try:
        try:
            try:
                yield fd
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(temporary, target)
        except BaseException:
            _remove_quietly(temporary)
            raise
    except OSError as error:
        if isinstance(error, AtomicWriteError):
            raise
        raise _failed(target, error) from error
    try:
        fsync_directory(target.parent)
    except OSError as error:
        raise CommitNotDurableError(
            error.errno,
            f"{os.fspath(path)} was replaced, but the fsync of its directory failed ({error.strerror}): the new version "
            "may not survive a power loss or an operating-system crash",
        ) from error


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
    :raises CommitNotDurableError: only the fsync of the directory after the rename failed: ``path`` is the new
        version, which may not survive a power loss
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write writes a whole new file: mode must be 'w' or 'wb', got {mode!r}")
    with _new_version(path) as fd:
        if mode == "wb":
            handle: IO[Any] = os.fdopen(fd, "wb", closefd=False)
        else:
            handle = os.fdopen(fd, "w", encoding=encoding or "utf-8", newline=newline, closefd=False)
        with handle:
            yield handle
            handle.flush()


def write_bytes_atomic(path: PathLike, data: bytes, fixed_temporary: bool = False) -> None:
    """
    Replace ``path`` by ``data`` atomically, written with ``os.write`` (every byte): temporary file, fsync, rename,
    fsync of the directory.

    :param path: the target file (its directory must exist)
    :param data: its new contents
    :param fixed_temporary: write through ``<path>.tmp``, unlinking first whatever has that name (a temporary file a
        crash left, or a symbolic link planted there), instead of a fresh hidden name: only for the one writer of
        ``path`` (it holds its lock), which can then list that name among its files. Two processes writing the same
        file this way at once could publish each other's half-written file
    :raises AtomicWriteError: ``path`` is unchanged and the temporary file removed (see :func:`atomic_write`)
    :raises CommitNotDurableError: only the fsync of the directory after the rename failed: ``path`` is the new
        version, which may not survive a power loss
    """
    with _new_version(path, fixed_temporary) as fd:
        write_all(fd, data)


def write_text_atomic(path: PathLike, text: str, encoding: str = "utf-8") -> None:
    """
    Replace ``path`` by ``text`` atomically (:func:`write_bytes_atomic`).

    :raises AtomicWriteError: ``path`` is unchanged (see :func:`atomic_write`)
    :raises CommitNotDurableError: ``path`` is the new version, which may not survive a power loss
    """
    write_bytes_atomic(path, text.encode(encoding))


def write_json_atomic(path: PathLike, data: Any, indent: Optional[int] = 1, fixed_temporary: bool = False) -> None:
    """
    Replace ``path`` by the JSON document ``data`` atomically (:func:`write_bytes_atomic`): temporary file, fsync,
    rename, fsync of the directory. The document is serialised first (keys sorted, UTF-8): a value JSON cannot hold
    (e.g. NaN) raises ``ValueError`` before anything is written.

    :param path: the target file (its directory must exist)
    :param data: a JSON-serialisable document
    :param indent: as for ``json.dumps``
    :param fixed_temporary: write through ``<path>.tmp`` (see :func:`write_bytes_atomic`), for the one writer of
        ``path``, e.g. a replay buffer's manifest
    :raises AtomicWriteError: (e.g. disk full) ``path`` is unchanged and the temporary file removed
    :raises CommitNotDurableError: only the fsync of the directory after the rename failed: ``path`` is the new
        document, which may not survive a power loss
    """
    payload = json.dumps(data, indent=indent, sort_keys=True, allow_nan=False).encode("utf-8")
    write_bytes_atomic(path, payload, fixed_temporary)
