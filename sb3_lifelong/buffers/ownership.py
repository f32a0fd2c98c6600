"""
The files a buffer directory owns: what ``mode="overwrite"`` may delete (``owned_buffer_files``,
``remove_buffer_files``), the data files a lost manifest leaves (``orphaned_data_files``), and a path a writer may
create a buffer at (``check_buffer_path``). Only what provably belongs to a buffer of this package is ever
deleted.

Like every module of the row store, this one imports only numpy, the standard library and the store's modules.
"""

from __future__ import annotations

import os

from sb3_lifelong.buffers import files
from sb3_lifelong.buffers.manifest import (
    CHUNK_FILE_PATTERN,
    DATA_FILE_PATTERN,
    LOCK_NAME,
    MANIFEST_NAME,
    BufferFormatError,
    chunk_file_name,
    read_manifest,
    validate_fields,
)


def owned_buffer_files(path: str) -> list[str]:
    """
    The files of the buffer in ``path`` that ``mode="overwrite"`` may delete: only what provably belongs to a buffer
    of this package. ``manifest.json`` must be a regular file (not a link) that this code parses and validates as
    its own format; the files are then the data files its manifest names (the listed chunk files of layout
    "chunked", the field files of layout "single"), the chunk files it does not list and the field files of its
    fields in layout "chunked" (what a writer deletes on opening anyway, left by a crash), the temporary
    ``manifest.json.tmp``, and the manifest itself, last. ``writer.lock`` and every other entry of the directory are
    kept.

    :param path: The directory
    :return: The names of those files (relative to ``path``) that exist, the manifest last; ``[]`` without a manifest
    :raises BufferFormatError: the manifest is not one of this package's buffers, or one of those names is a
        directory: nothing may be deleted
    """
    manifest_name = os.path.join(path, MANIFEST_NAME)
    if not os.path.lexists(manifest_name):
        return []
    refusal = (
        f"refusing to overwrite {path}: mode='overwrite' deletes only a buffer directory written by this package, and "
        "nothing was deleted"
    )
    if os.path.islink(manifest_name) or not os.path.isfile(manifest_name):
        raise BufferFormatError(f"{refusal}: its {MANIFEST_NAME} is a link or not a regular file. Choose another path")
    try:
        manifest = read_manifest(path)
    except (BufferFormatError, OSError) as error:
        raise BufferFormatError(
            f"{refusal}: its {MANIFEST_NAME} is not the manifest of such a buffer ({error}). Choose another path (or, if "
            "this directory holds nothing you need, delete it yourself)"
        ) from None
    listed = [chunk_file_name(c["start"]) for c in manifest["chunks"]] if manifest.get("layout") == "chunked" else []
    unlisted = sorted(e for e in os.listdir(path) if CHUNK_FILE_PATTERN.fullmatch(e) and e not in set(listed))
    named = listed + unlisted + [f"{name}.bin" for name in validate_fields(manifest["fields"])]
    names = [name for name in [*named, MANIFEST_NAME + ".tmp"] if os.path.lexists(os.path.join(path, name))]
    for name in names:
        file_name = os.path.join(path, name)
        if os.path.isdir(file_name) and not os.path.islink(file_name):
            raise BufferFormatError(f"{refusal}: {file_name} is a directory, not a file of the buffer")
    return [*names, MANIFEST_NAME]


def remove_buffer_files(path: str) -> list[str]:
    """
    Delete the buffer in ``path`` (``mode="overwrite"``): the files :func:`owned_buffer_files` lists, data files
    first and the manifest last (so that an interrupted deletion leaves a manifest that still names what is left,
    which the next overwrite deletes), then fsync the directory. Links are removed, never what they point to. The
    caller holds the directory's writer lock, so no live writer is affected.

    :param path: The directory
    :return: The names deleted
    :raises BufferFormatError: see :func:`owned_buffer_files` (then nothing is deleted)
    """
    names = owned_buffer_files(path)
    for name in names:
        try:
            os.unlink(os.path.join(path, name))
        except FileNotFoundError:  # pragma: no cover (removed meanwhile)
            pass
    if names:
        files.fsync_dir(path)
    return names


def orphaned_data_files(path: str) -> list[str]:
    """
    :param path: A directory with no manifest
    :return: The names of the buffer data files in it (field or chunk files) that are not empty or not regular files
        (a directory whose manifest was lost). Empty field files are what a writer killed while creating the
        directory leaves: nothing to lose
    """
    try:
        entries = sorted(os.listdir(path))
    except (FileNotFoundError, NotADirectoryError):
        return []
    found = []
    for entry in entries:
        if DATA_FILE_PATTERN.fullmatch(entry):
            file_name = os.path.join(path, entry)
            if os.path.islink(file_name) or not os.path.isfile(file_name) or os.path.getsize(file_name) > 0:
                found.append(entry)
    return found


def check_buffer_path(path: str, allow_foreign_files: bool = False, writing: bool = True) -> None:
    """
    Refuse, before anything is written there, a buffer path that is not a directory, and (writers) a directory that
    holds no buffer but files that are not a buffer's: creating a buffer among them would mix its files with someone
    else's (and ``mode="overwrite"`` of that buffer later would leave theirs in its directory).

    :param path: The buffer directory (absolute)
    :param allow_foreign_files: Create the buffer among other files all the same (they are never read, changed or
        deleted)
    :param writing: Whether the buffer is opened for writing (a reader only needs a directory)
    :raises NotADirectoryError: ``path`` is an existing file (or a link to one, or a dangling link)
    :raises FileExistsError: ``path`` is a directory without ``manifest.json`` that holds other files than a buffer's
        (``writer.lock``, ``manifest.json.tmp`` and data files, which :meth:`Layout.refuse_orphans` checks), naming
        a few of them, unless ``allow_foreign_files``
    """
    if not os.path.lexists(path):
        return
    if not os.path.isdir(path):
        kind = "a symbolic link to no directory" if os.path.islink(path) else "an existing file"
        raise NotADirectoryError(
            f"buffer path {path!r} is {kind}, not a directory: a buffer's path names a directory (a new one, or one that "
            "holds a buffer). Choose another path; nothing was written"
        )
    if not writing or allow_foreign_files or os.path.lexists(os.path.join(path, MANIFEST_NAME)):
        return
    buffer_names = {LOCK_NAME, MANIFEST_NAME + ".tmp"}
    foreign = sorted(e for e in os.listdir(path) if e not in buffer_names and DATA_FILE_PATTERN.fullmatch(e) is None)
    if foreign:
        listed = ", ".join(repr(name) for name in foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise FileExistsError(
            f"buffer path {path!r} is a directory that holds no buffer (no {MANIFEST_NAME}) but {len(foreign)} other "
            f"entries: {listed}. Refusing to create a buffer among them. Choose a new (or empty) directory, e.g. a "
            "subdirectory; or pass allow_foreign_files=True to create it there all the same (those entries are never "
            "read, changed or deleted); nothing was written"
        )
