"""
On-disk / in-memory row store behind :class:`sb3_lifelong.buffers.LifelongReplayBuffer`.

This module only depends on numpy and the standard library (it can be loaded without torch), so that
crash tests and tools can use it in light subprocesses.

Directory format (versions 1 and 2), see ``docs/modules/buffer.md``::

    <path>/manifest.json     committed state (JSON, rewritten atomically after each flushed chunk)
    <path>/<field>.bin       layout "single" (no capacity): one append-only file per field, raw little-endian
                             C-order rows, no header
    <path>/chunk.<start>.bin layout "chunked" (with a capacity): one file per flushed chunk, each field's rows one
                             field after the other; deleted once no committed manifest lists it
    <path>/writer.lock       advisory lock held by the (single) writer process

Committed rows are read with memory maps (``read_mode="mmap"``, the default) or with positioned reads
(``read_mode="pread"``: ``os.pread`` / ``os.preadv`` on file descriptors kept open, so that no page of the files
is ever mapped into the process).

Dict observations store one field per key, ``observations.<key>`` and ``next_observations.<key>`` (version 2;
plain buffers are still written as version 1).

A row ``i`` of field ``f`` lives at byte offset ``i * row_bytes(f)`` of ``f.bin``. Only the first
``num_transitions`` rows (sum of the chunk sizes listed in the manifest) are committed; bytes after
them are an unflushed tail of a crashed writer and are ignored by readers and cut off by the next writer.
"""

from __future__ import annotations

import errno
import json
import math
import mmap
import os
import re
import warnings
import weakref
import zlib
from collections.abc import Callable, Mapping, Sequence
from types import MappingProxyType
from typing import Any, NamedTuple, Optional, Protocol

import numpy as np

try:  # POSIX only: the writer lock is advisory and simply skipped elsewhere
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

FORMAT_NAME = "sb3-lifelong-buffer"
FORMAT_VERSION = 2  # the newest version written (version 1 is still written when it can describe the buffer)
READABLE_VERSIONS = (1, 2)
# manifest keys added by version 2 (version 1 means layout "single", capacity null, first_row 0)
V2_KEYS = ("layout", "capacity", "first_row")
# "single": one append-only file per field, "<field>.bin", rows from 0 (every row kept);
# "chunked": one file per flushed chunk, "chunk.<start>.bin", holding each field's rows one field after the other
LAYOUTS = ("single", "chunked")
CHUNK_FILE_PATTERN = re.compile(r"chunk\.([0-9]{12,19})\.bin")
# the data files any buffer directory may hold (field files of layout "single", chunk files of layout "chunked")
DATA_FILE_PATTERN = re.compile(
    r"(?:(?:observations|next_observations)(?:\.[A-Za-z0-9_][A-Za-z0-9_-]{0,63})?|actions|rewards|flags|sources|streams"
    r"|widths)\.bin|chunk\.[0-9]{12,19}\.bin"
)
MANIFEST_NAME = "manifest.json"
LOCK_NAME = "writer.lock"
MAX_MANIFEST_BYTES = 256 * 1024 * 1024
MAX_ROW_ELEMENTS = 1 << 24
MAX_SOURCE_ID = 65534
# how committed rows are read: memory maps, or positioned reads into this process's memory
READ_MODES = ("mmap", "pread")
# read_mode "pread": rows of a field at most this many bytes apart are read with one call, gap included (adjacent
# rows always are). Measured on 1M-2M rows of 240 bytes: 0 to 8 KiB within noise of each other, 16 KiB and more slower
PREAD_MERGE_GAP = 4096

# dtypes a manifest may name (numpy ``dtype.str``), nothing else is accepted
ALLOWED_DTYPES = frozenset(["|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8"])
# fields every buffer stores, with the dtypes that are fixed by the format (None: chosen by the spaces)
FIELD_NAMES = ("observations", "next_observations", "actions", "rewards", "flags", "sources", "streams", "widths")
OBS_FIELDS = ("observations", "next_observations")
# keys of Dict observations name files (``observations.<key>.bin``): a conservative portable file-name pattern
OBS_KEY_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_-]{0,63}")
FIXED_FIELDS = {
    "rewards": ("<f4", ()),
    "flags": ("|u1", ()),
    "sources": ("<u2", ()),
    "streams": ("<u4", ()),
    "widths": ("<u2", ()),
}
FLAG_DONE = 1
FLAG_TIMEOUT = 2
# writer stores of this process by directory, so that unpickling can take a directory over from a stale object
_WRITERS: weakref.WeakValueDictionary[str, RowStore] = weakref.WeakValueDictionary()


class BufferFormatError(ValueError):
    """A manifest or a data file (field or chunk file) is not a valid buffer directory (corrupted, truncated or hostile)."""


# errno values of an fsync of a directory that mean "this filesystem cannot sync directories" (nothing to wait for)
_DIR_FSYNC_UNSUPPORTED = frozenset({errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP})


class CommitNotDurableError(OSError):
    """
    A buffer's new manifest was renamed into place, so its rows are committed and readable (by this object, by
    readers and by a reopen), but the fsync of the directory that follows the rename failed: the commit may not
    survive a power loss or an operating-system crash (it survives a crash of the process). Whichever manifest a
    power loss leaves, the directory stays consistent: no file that the previous manifest needs is deleted until a
    later manifest is synced. ``flush()`` (or ``close()``) writes and syncs the manifest again.
    """


def _explained(error: OSError, context: str) -> OSError:
    """An OSError of the same errno (so of the same class) and file name, whose message starts with ``context``."""
    if error.errno is None:
        return OSError(f"{context}: {error}")
    return OSError(error.errno, f"{context} ({error.strerror})", error.filename)


def _fsync_dir(path: str, strict: bool = False) -> None:
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


def _delete_file(path: str) -> None:
    """Delete a chunk file (a missing one is fine). A separate function so that tests can simulate a crash here."""
    try:
        os.remove(path)
    except FileNotFoundError:  # pragma: no cover (removed by hand)
        pass


def _write_all(fd: int, data: Any) -> None:
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


# never open a file of a buffer directory for writing through a symbolic link (POSIX; 0 where the OS has no such flag)
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def _open_for_writing(file_name: str, flags: int = 0) -> int:
    """
    Open a file of a buffer directory for writing, never through a symbolic link (``O_NOFOLLOW``: a link planted at
    ``file_name`` makes this fail with ``ELOOP`` instead of writing where it points).

    :param file_name: The file
    :param flags: Further ``os.O_*`` flags
    :return: The file descriptor
    """
    flags |= os.O_WRONLY | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    return os.open(file_name, flags, 0o666)


def _create_new_file(file_name: str) -> int:
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
    return _open_for_writing(file_name, os.O_CREAT | os.O_EXCL)


def _remove_quietly(file_name: str) -> None:
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
        fd = _create_new_file(tmp)  # a new file, never through a link planted at the temporary name
        try:
            _write_all(fd, payload)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        _remove_quietly(tmp)
        raise
    try:
        _fsync_dir(directory, strict=True)
    except OSError as error:
        raise CommitNotDurableError(
            error.errno,
            f"{path} was replaced, but the fsync of its directory failed ({error.strerror}): the new version may not "
            "survive a power loss or an operating-system crash",
        ) from error


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_json_value(value: Any, where: str, depth: int = 0) -> None:
    if depth > 8:
        raise BufferFormatError(f"{where}: metadata nested too deeply")
    if value is None or isinstance(value, (bool, int, float, str)):
        return
    if isinstance(value, list):
        for item in value:
            _check_json_value(item, where, depth + 1)
        return
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise BufferFormatError(f"{where}: metadata keys must be strings")
            _check_json_value(item, where, depth + 1)
        return
    raise BufferFormatError(f"{where}: unsupported metadata value of type {type(value).__name__}")


def check_obs_key(key: Any) -> str:
    """
    Check that a Dict observation key can name a field file (``observations.<key>.bin``).

    :param key: The key
    :return: The key
    :raises BufferFormatError: when it is not a string of 1-64 letters, digits, ``_`` or ``-`` (not starting with ``-``)
    """
    if not isinstance(key, str) or OBS_KEY_PATTERN.fullmatch(key) is None or key.lower() in ("con", "prn", "aux", "nul"):
        raise BufferFormatError(
            f"Dict observation key {key!r} cannot name a field file: keys must be 1 to 64 ASCII letters, digits, '_' "
            "or '-' (not starting with '-')"
        )
    return key


def obs_keys_of(names: Any) -> Optional[tuple[str, ...]]:
    """
    :param names: Field names
    :return: The sorted keys of Dict observations, or None when the observations are one field
    """
    keys = sorted(name.split(".", 1)[1] for name in names if isinstance(name, str) and name.startswith("observations."))
    return tuple(keys) if keys else None


def field_names(obs_keys: Optional[Sequence[str]] = None) -> tuple[str, ...]:
    """
    :param obs_keys: Keys of Dict observations (None: one observation field)
    :return: The fields of a buffer, in their canonical order
    """
    if obs_keys is None:
        return FIELD_NAMES
    keys = sorted(obs_keys)
    obs = tuple(f"{base}.{key}" for base in OBS_FIELDS for key in keys)
    return obs + FIELD_NAMES[2:]


def validate_fields(fields: Any) -> dict[str, tuple[str, tuple[int, ...]]]:
    """
    Validate the ``fields`` entry of a manifest.

    :param fields: The decoded JSON value
    :return: field name -> (dtype string, row shape), in the canonical order
    """
    if not isinstance(fields, dict):
        raise BufferFormatError("manifest 'fields' must be an object")
    obs_keys = obs_keys_of(fields)
    if obs_keys is not None:
        lowered = [key.lower() for key in obs_keys]
        if len(set(lowered)) != len(lowered):
            raise BufferFormatError(f"Dict observation keys {list(obs_keys)} differ only by case (they name files)")
        for key in obs_keys:
            check_obs_key(key)
    names = field_names(obs_keys)
    if set(fields) != set(names):
        raise BufferFormatError(f"manifest 'fields' must name exactly {sorted(names)}, got {sorted(map(str, fields))}")
    result: dict[str, tuple[str, tuple[int, ...]]] = {}
    for name in names:
        spec = fields[name]
        if not isinstance(spec, dict) or set(spec) != {"dtype", "shape"}:
            raise BufferFormatError(f"manifest field {name!r} must be an object with exactly 'dtype' and 'shape'")
        dtype, shape = spec["dtype"], spec["shape"]
        if not isinstance(dtype, str) or dtype not in ALLOWED_DTYPES:
            raise BufferFormatError(f"manifest field {name!r}: dtype {dtype!r} is not one of {sorted(ALLOWED_DTYPES)}")
        if not isinstance(shape, list) or len(shape) > 8 or not all(_is_int(d) and 0 < d <= MAX_ROW_ELEMENTS for d in shape):
            raise BufferFormatError(f"manifest field {name!r}: shape must be a list of at most 8 positive ints, got {shape!r}")
        if math.prod(shape) > MAX_ROW_ELEMENTS:
            raise BufferFormatError(f"manifest field {name!r}: row of {math.prod(shape)} elements is too large")
        if name in FIXED_FIELDS and (dtype, tuple(shape)) != FIXED_FIELDS[name]:
            raise BufferFormatError(f"manifest field {name!r} must have dtype/shape {FIXED_FIELDS[name]}, got {dtype, shape}")
        result[name] = (dtype, tuple(shape))
    for suffix in [""] if obs_keys is None else [f".{key}" for key in obs_keys]:
        if result["observations" + suffix] != result["next_observations" + suffix]:
            raise BufferFormatError(
                f"manifest: observations{suffix} and next_observations{suffix} must have the same dtype and shape"
            )
    return result


def _validated_fields(fields: Mapping[str, tuple[Any, Sequence[int]]]) -> dict[str, tuple[str, tuple[int, ...]]]:
    """
    :param fields: field name -> (dtype, row shape), as a caller gives them
    :return: The same in the manifest's form, validated (see :func:`validate_fields`)
    """
    given = {name: (np.dtype(dt).str, tuple(int(d) for d in shape)) for name, (dt, shape) in fields.items()}
    return validate_fields({name: {"dtype": dt, "shape": list(shape)} for name, (dt, shape) in given.items()})


def _validate_chunks(chunks: Any, names: Sequence[str], start: Optional[int] = 0) -> int:
    """
    :param chunks: The ``chunks`` entry of a manifest
    :param names: The buffer's fields
    :param start: Row where the first chunk must start (None: anywhere, for chunk files whose oldest were evicted)
    :return: The row after the last chunk (``start`` when there is none)
    """
    if not isinstance(chunks, list):
        raise BufferFormatError("manifest 'chunks' must be a list")
    first: Any = start
    if first is None:
        first = chunks[0].get("start") if chunks and isinstance(chunks[0], dict) else 0
        if not _is_int(first) or not 0 <= first < 2**62:
            raise BufferFormatError(f"manifest chunk 0: 'start' must be an int in [0, 2**62), got {first!r}")
    start = int(first)
    for k, chunk in enumerate(chunks):
        if not isinstance(chunk, dict) or set(chunk) != {"start", "rows", "crc32"}:
            raise BufferFormatError(f"manifest chunk {k} must be an object with exactly 'start', 'rows', 'crc32'")
        if not _is_int(chunk["start"]) or chunk["start"] != start:
            raise BufferFormatError(f"manifest chunk {k}: 'start' must be {start}, got {chunk['start']!r}")
        if not _is_int(chunk["rows"]) or chunk["rows"] <= 0:
            raise BufferFormatError(f"manifest chunk {k}: 'rows' must be a positive int, got {chunk['rows']!r}")
        crc = chunk["crc32"]
        if not isinstance(crc, dict) or set(crc) != set(names):
            raise BufferFormatError(f"manifest chunk {k}: 'crc32' must give one checksum per field")
        if not all(_is_int(v) and 0 <= v < 2**32 for v in crc.values()):
            raise BufferFormatError(f"manifest chunk {k}: checksums must be ints in [0, 2**32)")
        start += chunk["rows"]
    return start


def _validate_layout(manifest: dict[str, Any], names: list[str]) -> None:
    """Check the chunks of a manifest against its layout, capacity and first retained row."""
    num = manifest["num_transitions"]
    layout: Any = manifest.get("layout", "single")
    capacity: Any = manifest.get("capacity")
    first_row: Any = manifest.get("first_row", 0)
    if layout not in LAYOUTS:
        raise BufferFormatError(f"manifest 'layout' must be one of {list(LAYOUTS)}, got {layout!r}")
    if layout == "single" and (capacity is not None or first_row != 0):
        raise BufferFormatError("manifest: layout 'single' keeps every row: 'capacity' must be null and 'first_row' 0")
    if layout == "chunked" and (not _is_int(capacity) or not 1 <= capacity < 2**62):
        raise BufferFormatError(f"manifest 'capacity' must be a positive int with layout 'chunked', got {capacity!r}")
    end = _validate_chunks(manifest["chunks"], names, start=0 if layout == "single" else None)
    if end != num:
        raise BufferFormatError(f"manifest chunks hold rows up to {end} but 'num_transitions' is {num}")
    if not _is_int(first_row) or not 0 <= first_row <= num:
        raise BufferFormatError(f"manifest 'first_row' must be an int in [0, num_transitions], got {first_row!r}")
    chunks = manifest["chunks"]
    if layout == "chunked":
        if chunks and not chunks[0]["start"] <= first_row < chunks[0]["start"] + chunks[0]["rows"]:
            raise BufferFormatError(
                f"manifest 'first_row' {first_row} must lie in the first chunk (rows {chunks[0]['start']} to "
                f"{chunks[0]['start'] + chunks[0]['rows'] - 1}): chunks with no retained row are not listed"
            )
        if not chunks and first_row != num:
            raise BufferFormatError("manifest: with no chunk, 'first_row' must equal 'num_transitions'")
        if num - first_row > capacity:
            raise BufferFormatError(f"manifest: {num - first_row} retained rows exceed the capacity {capacity}")


def validate_manifest(manifest: Any) -> dict[str, Any]:
    """
    Check every entry of a decoded manifest (types, ranges, consistency). Never evaluates anything.

    :param manifest: The decoded JSON document
    :return: The same document
    :raises BufferFormatError: with a message naming the offending entry
    """
    if not isinstance(manifest, dict):
        raise BufferFormatError("manifest must be a JSON object")
    if manifest.get("format") != FORMAT_NAME:
        raise BufferFormatError(f"manifest 'format' must be {FORMAT_NAME!r}, got {manifest.get('format')!r}")
    version = manifest.get("version")
    if not _is_int(version) or version not in READABLE_VERSIONS:
        raise BufferFormatError(f"unsupported format version {version!r} (this code reads versions {list(READABLE_VERSIONS)})")
    expected = {"format", "version", "fields", "num_transitions", "chunks", "sources", "next_stream_id", "spaces"}
    if version >= 2:
        expected |= set(V2_KEYS)
    if set(manifest) != expected:
        raise BufferFormatError(f"manifest keys must be {sorted(expected)}, got {sorted(map(str, manifest))}")
    fields = validate_fields(manifest["fields"])
    if version == 1 and obs_keys_of(fields) is not None:
        raise BufferFormatError("manifest: Dict observation fields need format version 2")
    num = manifest["num_transitions"]
    if not _is_int(num) or not 0 <= num < 2**62:
        raise BufferFormatError(f"manifest 'num_transitions' must be a non-negative int, got {num!r}")
    _validate_layout(manifest, list(fields))
    sources = manifest["sources"]
    if not isinstance(sources, dict):
        raise BufferFormatError("manifest 'sources' must be an object")
    for key, value in sources.items():
        if not (isinstance(key, str) and key.isdigit() and int(key) <= MAX_SOURCE_ID):
            raise BufferFormatError(f"manifest source id {key!r} must be a decimal int in [0, {MAX_SOURCE_ID}]")
        if not isinstance(value, dict) or set(value) != {"name", "metadata"} or not isinstance(value["name"], str):
            raise BufferFormatError(f"manifest source {key}: must be an object with a string 'name' and a 'metadata' object")
        if not isinstance(value["metadata"], dict):
            raise BufferFormatError(f"manifest source {key}: 'metadata' must be an object")
        _check_json_value(value["metadata"], f"manifest source {key}")
    stream = manifest["next_stream_id"]
    if not _is_int(stream) or not 0 <= stream < 2**32:
        raise BufferFormatError(f"manifest 'next_stream_id' must be an int in [0, 2**32), got {stream!r}")
    if not isinstance(manifest["spaces"], dict):
        raise BufferFormatError("manifest 'spaces' must be an object")
    _check_json_value(manifest["spaces"], "manifest 'spaces'")
    return manifest


def read_manifest(path: str) -> dict[str, Any]:
    """
    Read and validate ``<path>/manifest.json``.

    :param path: Buffer directory
    :return: The validated manifest
    """
    file_name = os.path.join(path, MANIFEST_NAME)
    if not os.path.isfile(file_name):
        raise FileNotFoundError(f"{path!r} is not a buffer directory (no {MANIFEST_NAME})")
    size = os.path.getsize(file_name)
    if size > MAX_MANIFEST_BYTES:
        raise BufferFormatError(f"{file_name}: manifest of {size} bytes is larger than the {MAX_MANIFEST_BYTES} allowed")
    with open(file_name, "rb") as file:
        raw = file.read()

    def _no_constants(name: str) -> Any:
        raise BufferFormatError(f"{file_name}: non-standard JSON constant {name}")

    try:
        manifest = json.loads(raw.decode("utf-8"), parse_constant=_no_constants)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as error:
        raise BufferFormatError(f"{file_name}: not valid JSON ({error})") from error
    try:
        return validate_manifest(manifest)
    except BufferFormatError as error:
        raise BufferFormatError(f"{file_name}: {error}") from None


def check_read_mode(read_mode: Any, max_resident_bytes: Optional[int] = None) -> str:
    """
    :param read_mode: How committed rows are read: ``"mmap"`` or ``"pread"``
    :param max_resident_bytes: The remap limit asked for with it (only meaningful with ``"mmap"``)
    :return: The read mode
    :raises ValueError: for another value, for ``"pread"`` with ``max_resident_bytes``, or for ``"pread"`` where the
        OS has no ``pread``
    """
    if not isinstance(read_mode, str) or read_mode not in READ_MODES:
        raise ValueError(f"read_mode must be one of {list(READ_MODES)}, got {read_mode!r}")
    if read_mode == "pread":
        if max_resident_bytes is not None:
            raise ValueError(
                "max_resident_bytes bounds the pages mapped by read_mode='mmap'; read_mode='pread' maps none: leave it None"
            )
        if not hasattr(os, "pread"):  # pragma: no cover (Windows)
            raise ValueError("read_mode='pread' needs os.pread, which this OS does not have: use read_mode='mmap'")
    return read_mode


def _read_into(fd: int, target: memoryview, offset: int) -> None:
    """
    Fill ``target`` with the bytes of ``fd`` from ``offset`` (positioned reads: the file offset is not used).

    :param fd: Open file descriptor
    :param target: Writable byte buffer
    :param offset: Byte offset in the file
    :raises BufferFormatError: when the file ends first (truncated or replaced while open)
    """
    done, size = 0, len(target)
    while done < size:
        if hasattr(os, "preadv"):
            count = os.preadv(fd, [target[done:]], offset + done)
        else:  # pragma: no cover (no preadv)
            part = os.pread(fd, size - done, offset + done)
            target[done : done + len(part)] = part
            count = len(part)
        if count == 0:
            raise BufferFormatError(
                f"a buffer file ended at byte {offset + done} but the manifest commits rows up to byte {offset + size}; "
                "it was truncated or replaced while open"
            )
        done += count


def owned_buffer_files(path: str) -> list[str]:
    """
    The files of the buffer in ``path`` that ``mode="overwrite"`` may delete: only what provably belongs to a buffer
    of this package. ``manifest.json`` must be a regular file (not a link) that this code parses and validates as
    its own format; the files are then the data files its manifest names (the field files of layout "single", the
    listed chunk files of layout "chunked"), the chunk files it does not list (layout "chunked": what a writer
    deletes on opening anyway, left by a crash), the temporary ``manifest.json.tmp``, and the manifest itself,
    last. ``writer.lock`` and every other entry of the directory are kept.

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
    if manifest.get("layout", "single") == "single":
        named = [f"{name}.bin" for name in validate_fields(manifest["fields"])]
    else:
        listed = [chunk_file_name(chunk["start"]) for chunk in manifest["chunks"]]
        unlisted = sorted(e for e in os.listdir(path) if CHUNK_FILE_PATTERN.fullmatch(e) and e not in set(listed))
        named = listed + unlisted
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
        _fsync_dir(path)
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


def chunk_file_name(start: int) -> str:
    """
    :param start: First row of a chunk
    :return: The name of its file in the "chunked" layout
    """
    return f"chunk.{start:012d}.bin"


class _Segment(NamedTuple):
    """Committed rows ``start:start + rows`` (global numbers) stored contiguously: each field's rows at a byte
    offset of a data file."""

    start: int
    rows: int
    places: dict[str, tuple[str, int]]  # field name -> (data file, byte offset of the segment's first row)


# ---------------------------------------------------------------------------------------------- layouts
class _Layout(Protocol):
    """
    Where a directory store's rows live on disk ("single" or "chunked"): every method takes the store, whose
    committed state (``chunks``, ``num_committed``, ...) it reads; only :class:`RowStore` changes that state.
    """

    def create(self, store: RowStore) -> None:
        """Make the data files of a new, empty buffer."""

    def open_existing(self, store: RowStore, verify: str) -> None:
        """Check the data files against the manifest just read (sizes, checksums); a writer cleans up after a crash."""

    def segments(self, store: RowStore) -> list[_Segment]:
        """:return: the committed rows as segments (where each field's rows are)"""

    def write(self, store: RowStore, chunks: list[dict[str, Any]], extra: Optional[dict[str, np.ndarray]]) -> None:
        """Write and fsync the rows of ``chunks`` (not committed yet: the manifest does not name them)."""

    def discard(self, store: RowStore, chunks: list[dict[str, Any]]) -> None:
        """Give back the space of written chunks that were not committed (best effort)."""

    def retain(
        self, store: RowStore, chunks: list[dict[str, Any]], num_committed: int
    ) -> tuple[list[dict[str, Any]], int, list[str]]:
        """:return: the chunks a commit keeps, its first retained row, the files it drops (to delete once synced)"""


class _SingleFileLayout:
    """
    Layout "single": one append-only file per field, ``<field>.bin``, row ``i`` at byte ``i * row_bytes``. Every
    row is kept (no capacity), so the committed rows are one segment. A flush cuts each file back to its committed
    length (bytes after it are left by a failed flush or a crash) and appends the new chunks to it.
    """

    @staticmethod
    def field_file(store: RowStore, name: str) -> str:
        assert store.path is not None
        return os.path.join(store.path, name + ".bin")

    def create(self, store: RowStore) -> None:
        for name in store._fields:  # empty field files left by an interrupted creation are reused (cut to 0 bytes)
            os.close(_open_for_writing(self.field_file(store, name), os.O_CREAT | os.O_TRUNC))

    def open_existing(self, store: RowStore, verify: str) -> None:
        for name in store._fields:
            file_name = self.field_file(store, name)
            if not os.path.isfile(file_name) or os.path.islink(file_name):
                raise BufferFormatError(f"{store.path}: field file {name}.bin is missing or not a regular file")
        for name in store._fields:
            file_name, need = self.field_file(store, name), store.num_committed * store.row_bytes[name]
            have = os.path.getsize(file_name)
            if have < need:
                raise BufferFormatError(
                    f"{file_name}: {have} bytes but the manifest commits {store.num_committed} rows ({need} bytes); "
                    "the file was truncated or replaced"
                )
            if have > need and not store.read_only:
                # an unflushed tail of a writer that died: cut it off so that appends continue at the committed end
                fd = _open_for_writing(file_name)
                try:
                    os.ftruncate(fd, need)
                    os.fsync(fd)
                finally:
                    os.close(fd)
                store.discarded_bytes += have - need
        for chunk in _checked_chunks(store.chunks, verify):
            for name in store._fields:
                with open(self.field_file(store, name), "rb") as file:
                    file.seek(chunk["start"] * store.row_bytes[name])
                    data = file.read(chunk["rows"] * store.row_bytes[name])
                if zlib.crc32(data) != chunk["crc32"][name]:
                    raise BufferFormatError(
                        f"{self.field_file(store, name)}: checksum mismatch in chunk starting at row {chunk['start']} "
                        "(corrupted data)"
                    )

    def segments(self, store: RowStore) -> list[_Segment]:
        if store.num_committed == 0:
            return []
        return [_Segment(0, store.num_committed, {name: (self.field_file(store, name), 0) for name in store._fields})]

    def write(self, store: RowStore, chunks: list[dict[str, Any]], extra: Optional[dict[str, np.ndarray]]) -> None:
        base = store.num_committed
        for name in store._fields:
            committed_bytes = base * store.row_bytes[name]
            fd = _open_for_writing(self.field_file(store, name))
            try:
                # bytes after the committed rows are left by a failed flush: cut them off so that this one writes the
                # same rows to the same place (the manifest's offsets)
                os.ftruncate(fd, committed_bytes)
                os.lseek(fd, committed_bytes, os.SEEK_SET)
                for chunk in chunks:
                    store._write_block(fd, name, chunk, chunk["start"] - base, extra)
                os.fsync(fd)
            finally:
                os.close(fd)

    def discard(self, store: RowStore, chunks: list[dict[str, Any]]) -> None:
        for name in store._fields:  # best effort: the bytes after the committed rows are ignored anyway
            try:
                fd = _open_for_writing(self.field_file(store, name))  # not os.truncate(path): it follows links
                try:
                    os.ftruncate(fd, store.num_committed * store.row_bytes[name])
                finally:
                    os.close(fd)
            except OSError:
                pass

    def retain(
        self, store: RowStore, chunks: list[dict[str, Any]], num_committed: int
    ) -> tuple[list[dict[str, Any]], int, list[str]]:
        return chunks, store.committed_first, []


class _ChunkFileLayout:
    """
    Layout "chunked": one file per flushed chunk, ``chunk.<start>.bin``, holding each field's rows one field after
    the other; each chunk is a segment. A commit keeps the last ``capacity`` committed rows: the files of the chunks
    with none of them are deleted once the manifest that drops them is synced.
    """

    @staticmethod
    def chunk_file(store: RowStore, chunk: dict[str, Any]) -> str:
        assert store.path is not None
        return os.path.join(store.path, chunk_file_name(chunk["start"]))

    def create(self, store: RowStore) -> None:
        self.remove_orphans(store)  # empty chunk files (non-empty ones without a manifest are refused before)

    def open_existing(self, store: RowStore, verify: str) -> None:
        for chunk in store.chunks:
            file_name = self.chunk_file(store, chunk)
            if not os.path.isfile(file_name) or os.path.islink(file_name):
                raise BufferFormatError(f"{file_name}: chunk file is missing or not a regular file")
            need = store._field_offsets(chunk["rows"])[""]
            have = os.path.getsize(file_name)
            if have != need:
                raise BufferFormatError(
                    f"{file_name}: {have} bytes but the manifest's chunk of {chunk['rows']} rows needs {need} bytes; "
                    "the file was truncated or replaced"
                )
        names = list(store._fields)
        for chunk in _checked_chunks(store.chunks, verify):
            offsets = store._field_offsets(chunk["rows"])
            with open(self.chunk_file(store, chunk), "rb") as file:
                data = file.read()
            for k, name in enumerate(names):
                stop = offsets[names[k + 1]] if k + 1 < len(names) else offsets[""]
                if zlib.crc32(data[offsets[name] : stop]) != chunk["crc32"][name]:
                    raise BufferFormatError(
                        f"{self.chunk_file(store, chunk)}: checksum mismatch in field {name!r} (corrupted data)"
                    )
        if not store.read_only:
            self.remove_orphans(store)

    def remove_orphans(self, store: RowStore) -> None:
        """Delete the chunk files the manifest does not list: evicted ones left by a crash after a commit, or the
        unflushed chunk of a crash before it (writer only)."""
        assert store.path is not None
        listed = {chunk_file_name(chunk["start"]) for chunk in store.chunks}
        removed = False
        for entry in sorted(os.listdir(store.path)):
            if CHUNK_FILE_PATTERN.fullmatch(entry) and entry not in listed:
                file_name = os.path.join(store.path, entry)
                if os.path.islink(file_name) or not os.path.isfile(file_name):
                    continue
                store.discarded_bytes += os.path.getsize(file_name)
                _delete_file(file_name)
                store.removed_files.append(entry)
                removed = True
        if removed:
            _fsync_dir(store.path)

    def segments(self, store: RowStore) -> list[_Segment]:
        segments = []
        for chunk in store.chunks:
            file_name, offsets = self.chunk_file(store, chunk), store._field_offsets(chunk["rows"])
            places = {name: (file_name, offsets[name]) for name in store._fields}
            segments.append(_Segment(chunk["start"], chunk["rows"], places))
        return segments

    def write(self, store: RowStore, chunks: list[dict[str, Any]], extra: Optional[dict[str, np.ndarray]]) -> None:
        assert store.path is not None
        base = store.num_committed
        for chunk in chunks:
            # a new file: an unflushed chunk file of a crash, or a link planted at this name, is unlinked first
            fd = _create_new_file(self.chunk_file(store, chunk))
            try:
                for name in store._fields:
                    store._write_block(fd, name, chunk, chunk["start"] - base, extra)
                os.fsync(fd)
            finally:
                os.close(fd)
        _fsync_dir(store.path, strict=True)  # the new files' entries are durable before a manifest names them

    def discard(self, store: RowStore, chunks: list[dict[str, Any]]) -> None:
        for chunk in chunks:  # not committed: nothing refers to these files
            _remove_quietly(self.chunk_file(store, chunk))

    def retain(
        self, store: RowStore, chunks: list[dict[str, Any]], num_committed: int
    ) -> tuple[list[dict[str, Any]], int, list[str]]:
        # the manifest keeps the last ``capacity`` committed rows (rows still pending do not evict on disk)
        committed_first = store.committed_first
        if store.capacity is not None:
            committed_first = max(committed_first, num_committed - store.capacity)
        dropped = [chunk for chunk in chunks if chunk["start"] + chunk["rows"] <= committed_first]
        return chunks[len(dropped) :], committed_first, [self.chunk_file(store, chunk) for chunk in dropped]


_LAYOUT_STRATEGIES: dict[str, _Layout] = {"single": _SingleFileLayout(), "chunked": _ChunkFileLayout()}


def _checked_chunks(chunks: list[dict[str, Any]], verify: str) -> list[dict[str, Any]]:
    """The chunks whose checksums ``verify`` ("all", "last" or "none") asks to check when opening."""
    return chunks if verify == "all" else chunks[-1:] if verify == "last" else []


# ---------------------------------------------------------------------------------------------- read modes
class _RowFormat:
    """What a reader needs to know of the rows: dtype and shape of each field."""

    def __init__(self, dtypes: Mapping[str, np.dtype], shapes: Mapping[str, tuple[int, ...]]) -> None:
        self.dtypes = dict(dtypes)
        self.shapes = dict(shapes)
        self.row_bytes = {name: self.dtypes[name].itemsize * math.prod(shape) for name, shape in self.shapes.items()}

    def empty(self, names: tuple[str, ...], rows: int = 0) -> dict[str, np.ndarray]:
        return {name: np.empty((rows, *self.shapes[name]), dtype=self.dtypes[name]) for name in names}


class _Reader(Protocol):
    """How a directory store reads its committed rows (``read_mode``): memory maps or positioned reads."""

    def sync(self, segments: list[_Segment], fresh: bool = False, eager: bool = True) -> None:
        """Follow the committed segments after a commit, an eviction or a refresh."""

    def gather(self, names: tuple[str, ...], rows: np.ndarray) -> dict[str, np.ndarray]:
        """:return: the given global rows of the given fields (copies)"""

    def pieces(self, name: str, lo: int, hi: int) -> list[np.ndarray]:
        """:return: the global rows ``lo:hi`` of a field, one array per segment touched"""

    def close(self) -> None:
        """Release what the reader holds open (the next read opens it again)."""


class _MappedReader(_RowFormat):
    """
    ``read_mode="mmap"``: each segment's data files are memory-mapped read-only, its fields are arrays over the
    maps. A sync maps the new segments and keeps the maps of those unchanged; ``fresh=True`` maps everything again,
    which drops the pages touched so far from this process's RSS.
    """

    def __init__(self, dtypes: Mapping[str, np.dtype], shapes: Mapping[str, tuple[int, ...]]) -> None:
        super().__init__(dtypes, shapes)
        self._segments: list[_Segment] = []
        self._arrays: list[dict[str, np.ndarray]] = []  # one dict per segment: field -> its committed rows
        self._starts = np.zeros(0, dtype=np.int64)

    def sync(self, segments: list[_Segment], fresh: bool = False, eager: bool = True) -> None:
        known = {} if fresh else {(s.start, s.rows): arrays for s, arrays in zip(self._segments, self._arrays)}
        self._arrays = [known.get((s.start, s.rows)) or self._map(s) for s in segments]
        self._segments = list(segments)
        self._starts = np.array([s.start for s in segments], dtype=np.int64)

    def _map(self, segment: _Segment) -> dict[str, np.ndarray]:
        lengths: dict[str, int] = {}
        for name, (file_name, offset) in segment.places.items():
            lengths[file_name] = max(lengths.get(file_name, 0), offset + segment.rows * self.row_bytes[name])
        maps = {file_name: _map_file(file_name, length) for file_name, length in lengths.items()}
        arrays = {}
        for name, (file_name, offset) in segment.places.items():
            count = segment.rows * math.prod(self.shapes[name])
            array = np.frombuffer(maps[file_name], dtype=self.dtypes[name], count=count, offset=offset)  # type: ignore[arg-type]
            arrays[name] = array.reshape(segment.rows, *self.shapes[name])
        return arrays

    def gather(self, names: tuple[str, ...], rows: np.ndarray) -> dict[str, np.ndarray]:
        if len(rows) == 0:
            return self.empty(names)
        if len(self._arrays) == 1:  # e.g. layout "single"
            start, arrays = int(self._starts[0]), self._arrays[0]
            local = rows - start if start else rows
            return {name: arrays[name][local] for name in names}
        owner = np.searchsorted(self._starts, rows, side="right") - 1
        if owner[0] == owner[-1] and (owner == owner[0]).all():  # one segment (e.g. a single row)
            k = int(owner[0])
            local = rows - self._starts[k]
            return {name: self._arrays[k][name][local] for name in names}
        order = np.argsort(owner, kind="stable")
        sorted_owner = owner[order]
        bounds = np.concatenate([[0], np.flatnonzero(sorted_owner[1:] != sorted_owner[:-1]) + 1, [len(rows)]]).tolist()
        result = self.empty(names, len(rows))
        if 4 * (len(bounds) - 1) > len(rows):
            # rows spread over many segments (random sampling): copying row by row is the fastest in numpy
            pairs = list(zip(owner.tolist(), (rows - self._starts[owner]).tolist()))
            for name in names:
                out, maps = result[name], [arrays[name] for arrays in self._arrays]
                for i, (k, j) in enumerate(pairs):
                    out[i] = maps[k][j]
            return result
        local = rows[order] - self._starts[sorted_owner]
        for name in names:  # one read per segment touched
            ordered = np.empty_like(result[name])
            for a, b in zip(bounds[:-1], bounds[1:]):
                ordered[a:b] = self._arrays[int(sorted_owner[a])][name][local[a:b]]
            result[name][order] = ordered
        return result

    def pieces(self, name: str, lo: int, hi: int) -> list[np.ndarray]:
        pieces = []
        for segment, arrays in zip(self._segments, self._arrays):
            a, b = max(lo, segment.start), min(hi, segment.start + segment.rows)
            if a < b:
                pieces.append(arrays[name][a - segment.start : b - segment.start])  # views of the maps
        return pieces

    def close(self) -> None:
        """Nothing to release: the maps stay readable after the store is closed."""


class _PositionedReader(_RowFormat):
    """
    ``read_mode="pread"``: the data files of the committed segments are kept open and rows are read with
    positioned reads into fresh arrays (one call per run of nearby rows): no page of the files is mapped. Closing
    closes the files; the next read opens them again.
    """

    def __init__(self, dtypes: Mapping[str, np.dtype], shapes: Mapping[str, tuple[int, ...]]) -> None:
        super().__init__(dtypes, shapes)
        self.fds: dict[str, int] = {}  # open descriptors by file name
        self._segments: list[_Segment] = []
        # per field: the descriptor and byte offset of each segment; None: closed (to open at the next read)
        self._table: Optional[dict[str, tuple[list[int], np.ndarray]]] = None
        self._starts = np.zeros(0, dtype=np.int64)

    def sync(self, segments: list[_Segment], fresh: bool = False, eager: bool = True) -> None:
        """
        :param segments: The committed segments
        :param fresh: Ignored (no map to drop)
        :param eager: Open the files now even if the reader is closed (else, when closed, at the next read)
        """
        self._segments = list(segments)
        if self._table is not None or eager:
            self._open()

    def _open(self) -> None:
        names = list(dict.fromkeys(file_name for s in self._segments for file_name, _ in s.places.values()))
        for name in names:  # first, so that a file that cannot be opened leaves the current table working
            if name not in self.fds:
                self.fds[name] = os.open(name, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
        self._table = {
            field: (
                [self.fds[s.places[field][0]] for s in self._segments],
                np.array([s.places[field][1] for s in self._segments], dtype=np.int64),
            )
            for field in self.shapes
        }
        self._starts = np.array([s.start for s in self._segments], dtype=np.int64)
        for name in set(self.fds) - set(names):  # segments evicted (their files may be deleted already)
            os.close(self.fds.pop(name))

    def close(self) -> None:
        while self.fds:
            os.close(self.fds.popitem()[1])
        self._table = None

    def _read_table(self) -> dict[str, tuple[list[int], np.ndarray]]:
        if self._table is None:  # closed: open the files again
            self._open()
            assert self._table is not None
        return self._table

    def gather(self, names: tuple[str, ...], rows: np.ndarray) -> dict[str, np.ndarray]:
        """Rows by global number (any order, repeats allowed): the distinct rows in file order, one call per run of
        rows of a field whose bytes are at most ``PREAD_MERGE_GAP`` apart."""
        if len(rows) == 0:
            return self.empty(names)
        table = self._read_table()
        unique, inverse = np.unique(rows, return_inverse=True)
        inverse = inverse.reshape(-1)
        starts = self._starts
        segment = np.searchsorted(starts, unique, side="right") - 1 if len(starts) > 1 else np.zeros(len(unique), np.int64)
        local = unique - starts[segment]
        new_segment = np.ones(len(unique), dtype=bool)
        new_segment[1:] = segment[1:] != segment[:-1]
        result = {}
        for name in names:
            fds, bases = table[name]
            size = self.row_bytes[name]
            offsets = bases[segment] + local * size
            new_read = new_segment.copy()
            new_read[1:] |= offsets[1:] - offsets[:-1] > size + PREAD_MERGE_GAP
            firsts = np.flatnonzero(new_read)
            low = offsets[firsts]
            sizes = offsets[np.append(firsts[1:], len(unique)) - 1] + size - low
            read_fds = [fds[k] for k in segment[firsts].tolist()]
            data = b"".join(map(os.pread, read_fds, sizes.tolist(), low.tolist()))
            if len(data) != int(sizes.sum()):  # short reads (a run past 2 GiB): read again, in full
                data = b"".join(map(_pread_exact, read_fds, sizes.tolist(), low.tolist()))
            run = np.cumsum(new_read) - 1
            position = ((np.cumsum(sizes) - sizes)[run] + offsets - low[run]) // size  # row of `data` of each row
            rows_read = np.frombuffer(data, dtype=self.dtypes[name]).reshape(-1, *self.shapes[name])
            result[name] = rows_read[position[inverse]]
        return result

    def pieces(self, name: str, lo: int, hi: int) -> list[np.ndarray]:
        out = np.empty((max(hi - lo, 0), *self.shapes[name]), dtype=self.dtypes[name])
        if hi <= lo:
            return [out]
        fds, bases = self._read_table()[name]
        size = self.row_bytes[name]
        view = memoryview(out.reshape(-1).view(np.uint8))  # type: ignore[arg-type]
        for k, segment in enumerate(self._segments):
            a, b = max(lo, segment.start), min(hi, segment.start + segment.rows)
            if a < b:
                _read_into(fds[k], view[(a - lo) * size : (b - lo) * size], int(bases[k]) + (a - segment.start) * size)
        return [out]


_READERS: dict[str, Callable[[Mapping[str, np.dtype], Mapping[str, tuple[int, ...]]], _Reader]] = {
    "mmap": _MappedReader,
    "pread": _PositionedReader,
}


def _map_file(file_name: str, length: int) -> Optional[mmap.mmap]:
    """A read-only map of the first ``length`` bytes of a file (None for none), advised for random reads."""
    if length == 0:
        return None
    with open(file_name, "rb") as file:
        mapped = mmap.mmap(file.fileno(), length, access=mmap.ACCESS_READ)
    if hasattr(mapped, "madvise") and hasattr(mmap, "MADV_RANDOM"):
        mapped.madvise(mmap.MADV_RANDOM)
    return mapped


def _pread_exact(fd: int, size: int, offset: int) -> bytes:
    """``size`` bytes at ``offset`` (a single read may return fewer, e.g. past 2 GiB on Linux)."""
    data = bytearray(size)
    _read_into(fd, memoryview(data), offset)
    return bytes(data)


#: RowStore attributes that pickles of in-memory stores written by earlier versions hold under these public names
_PUBLIC_BEFORE = frozenset({"fields", "dtypes", "sources", "spaces", "next_stream_id"})
#: and the (empty) reading state they held before the read modes became reader objects
_READER_BEFORE = frozenset(
    {"_maps", "_chunk_maps", "_chunk_starts", "_read_fds", "_pread_table", "_segment_starts", "_maps_stale"}
)


class RowStore:
    """
    Append-only table of fixed-size rows (one array per field), in memory or in a buffer directory, optionally
    keeping only the most recent ``capacity`` rows.

    Rows have global numbers (0 for the first row ever appended); indices given to :meth:`gather` and
    :meth:`read_range` count from the oldest retained row (:attr:`first`).

    In memory (``path=None``) the rows live in preallocated arrays that double when full (with a capacity, the
    evicted rows at their front are dropped by moving the retained ones down instead). With a path, committed rows
    are read from the files (memory-mapped, or with positioned reads, see ``read_mode``) and the unflushed rows wait
    in a tail of ``chunk_size`` rows, written out
    (appended, fsync'd, manifest replaced atomically) when full or on ``flush()``. Without a capacity the directory
    has one append-only file per field (layout "single"); with one, a file per chunk (layout "chunked"), deleted
    once the committed manifest no longer lists it.

    The store keeps the commit protocol (pending rows, manifest, eviction, recovery); two small strategies do the
    rest: the directory's layout (a ``_Layout``: ``_SingleFileLayout``, ``_ChunkFileLayout``) creates, checks, writes
    and describes the data files as segments of committed rows, and the read mode's reader (a ``_Reader``:
    ``_MappedReader``, ``_PositionedReader``) reads rows from those segments.

    Besides the rows, the store owns what its manifest records about them: the stream ids (:meth:`reserve_streams`),
    the source table (:meth:`source`, :meth:`set_source`, :meth:`source_table`) and the description of the spaces
    (:meth:`describe_spaces`), saved with the next commit; :attr:`fields`, :attr:`dtypes`, :attr:`spaces` and
    :attr:`next_stream_id` are read-only.

    :param fields: field name -> (dtype string, row shape)
    :param path: Buffer directory, or None for an in-memory store
    :param read_only: Open an existing directory without writing (another process may be writing)
    :param chunk_size: Rows per flushed chunk
    :param verify: Checksums to verify when opening: "all", "last" (only the last chunk: corrupted bytes in an
        earlier chunk are not detected and are served as they are) or "none"
    :param max_resident_bytes: Remap the files after random reads may have touched about this many bytes of
        pages, which drops them from this process's RSS (they stay in the OS page cache). None: never. Only with
        ``read_mode="mmap"``
    :param capacity: Keep only the most recent ``capacity`` rows (None: keep everything). For an existing
        directory, None keeps its stored capacity
    :param read_mode: How committed rows are read: ``"mmap"`` (memory maps: fastest when the rows sampled are
        mapped already, but every page touched counts in this process's RSS) or ``"pread"`` (positioned reads
        into fresh arrays, one call per run of nearby rows: no file page is mapped, the RSS stays at the anonymous
        memory; one file descriptor per field file or chunk file, closed by :meth:`close`). No effect in memory
    :param overwrite: Writers: delete the buffer the directory holds first (:func:`remove_buffer_files`), once this
        store holds the directory's writer lock (a live writer makes this raise before anything is deleted); a
        directory whose manifest is not one of this package's buffers is refused (``BufferFormatError``)
    :param evict: Reopening a directory with a capacity smaller than the number of transitions it retains evicts the
        oldest of them at once: only with ``evict=True``; otherwise that raises ``ValueError`` and nothing changes
    """

    def __init__(
        self,
        fields: Optional[dict[str, tuple[str, tuple[int, ...]]]] = None,
        path: Optional[str] = None,
        read_only: bool = False,
        chunk_size: int = 10_000,
        verify: str = "last",
        max_resident_bytes: Optional[int] = None,
        capacity: Optional[int] = None,
        read_mode: str = "mmap",
        overwrite: bool = False,
        evict: bool = False,
    ) -> None:
        check_read_mode(read_mode, max_resident_bytes)
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        if verify not in ("all", "last", "none"):
            raise ValueError(f"verify must be 'all', 'last' or 'none', got {verify!r}")
        if capacity is not None and (
            not isinstance(capacity, (int, np.integer)) or isinstance(capacity, bool) or capacity < 1
        ):
            raise ValueError(
                f"capacity must be a positive int (the number of most recent transitions kept) or None, got {capacity!r}"
            )
        self.path = None if path is None else os.path.abspath(os.fspath(path))
        self.read_only = read_only
        self.chunk_size = chunk_size
        self.capacity = None if capacity is None else int(capacity)
        self.layout = "memory" if self.path is None else "single" if capacity is None else "chunked"
        self._sources: dict[int, dict[str, Any]] = {}
        self._spaces: dict[str, Any] = {}
        self._next_stream_id = 0
        self.chunks: list[dict[str, Any]] = []
        self.num_committed = 0  # global row after the last committed row
        self.committed_first = 0  # global row of the oldest retained committed row (the manifest's first_row)
        self.recovered = 0
        self.discarded_bytes = 0
        self.removed_files: list[str] = []  # chunk files found unreferenced (and deleted) when opening
        self._tail_start = 0  # global row of the tail's first row
        self._lock_file: Any = None
        # the _Reader of a directory store's read mode (None in memory), set once the fields are known
        self._reader: Any = None
        self._closed = False
        # chunk files dropped by a commit whose directory fsync failed: deleted once a later manifest is synced (the
        # previous manifest, which lists them, may be the one a power loss leaves)
        self._undeleted: list[str] = []
        self.read_mode = read_mode
        self.max_resident_bytes = max_resident_bytes
        self.remaps = 0  # number of remaps done to bound the RSS
        self._baseline_file_bytes = 0
        if self.path is not None and not read_only and os.path.isdir(self.path):
            # the writer lock first, then everything else: a manifest read before taking it could be replaced by a
            # writer that commits and closes in between, and this writer would then cut that writer's rows off
            self._take_lock()
        try:
            if overwrite and self.path is not None and not read_only and os.path.isdir(self.path):
                remove_buffer_files(self.path)  # under the lock: a live writer was refused above
            self._open_or_create(fields, capacity, verify, evict)
        except BaseException:
            self._release_lock()
            raise
        self._tail_start = self.num_committed
        rows = self.chunk_size if self.path is not None else 1024 if self.capacity is None else min(1024, self.capacity)
        self._tail = {name: np.empty((rows, *shape), dtype=self._dtypes[name]) for name, (_, shape) in self._fields.items()}
        self.num_tail = 0
        self._reader_stale = False  # True while the maps (or read files) may not cover every committed row
        if self.path is not None and self.layout == "chunked" and not read_only:
            self._commit(self.chunks, self.num_committed)  # a smaller capacity than the stored one evicts now; maps
        elif self.path is not None:
            self._sync_maps()
        self.recovered = len(self)
        if self.max_resident_bytes is not None and self.path is not None:
            try:  # file-backed pages mapped before this store (python, numpy, torch libraries)
                with open("/proc/self/statm", "rb") as file:
                    self._baseline_file_bytes = int(file.read().split()[2]) * mmap.PAGESIZE
            except (OSError, ValueError, IndexError):  # pragma: no cover (not Linux)
                pass
        if self.discarded_bytes:
            removed = f" ({len(self.removed_files)} unreferenced chunk files removed)" if self.removed_files else ""
            warnings.warn(
                f"{self.path}: recovered {self.recovered} transitions; discarded {self.discarded_bytes} bytes of "
                f"unflushed rows left by a writer that did not close the buffer{removed}"
            )

    def _open_or_create(
        self,
        fields: Optional[dict[str, tuple[str, tuple[int, ...]]]],
        capacity: Optional[int],
        verify: str,
        evict: bool = False,
    ) -> None:
        """
        Read the committed state of the directory, or create the buffer. A writer holds the directory's lock
        before it reads anything there; one that creates the directory takes the lock, then looks again.

        :param fields: As for the constructor
        :param capacity: As for the constructor
        :param verify: As for the constructor
        :param evict: As for the constructor
        """
        if self.path is not None and os.path.isfile(os.path.join(self.path, MANIFEST_NAME)):
            manifest = self._read_consistent_manifest() if self.read_only else read_manifest(self.path)
            stored = validate_fields(manifest["fields"])
            if fields is not None and dict(fields) != stored:
                raise ValueError(f"{self.path}: stored fields {stored} do not match the requested {fields}")
            self._fields = stored
            self.layout = manifest.get("layout", "single")
            stored_capacity = manifest.get("capacity")
            if capacity is not None and capacity != stored_capacity:
                if self.layout == "single":
                    raise ValueError(
                        f"{self.path} keeps every transition in one file per field (it was created without a capacity) "
                        "and cannot evict: copy it into a new directory with a capacity, e.g. "
                        "merge_buffers([LifelongReplayBuffer.open(old, read_only=True)], path=new, capacity=N)"
                    )
                if self.read_only:
                    raise ValueError(f"{self.path} has capacity {stored_capacity}: a read-only buffer cannot change it")
                retained = manifest["num_transitions"] - manifest.get("first_row", 0)
                if capacity < retained and not evict:
                    raise ValueError(
                        f"{self.path} retains {retained:,} transitions (capacity {stored_capacity:,}): reopening it with "
                        f"capacity={capacity:,} would evict the oldest {retained - capacity:,} of them at once, for good. "
                        f"Pass evict=True to do that; or capacity=None (keeps {stored_capacity:,}) or a capacity >= "
                        f"{retained:,}. Nothing was changed"
                    )
            self.capacity = stored_capacity if capacity is None else int(capacity)
            self._load_manifest(manifest)
            self._set_row_format()
            self._layout.open_existing(self, verify)
        else:
            orphans = [] if self.path is None else orphaned_data_files(self.path)
            if orphans:
                assert self.path is not None
                listed = ", ".join(
                    (
                        f"{name} ({os.path.getsize(os.path.join(self.path, name))} bytes)"
                        if os.path.isfile(os.path.join(self.path, name))
                        else name
                    )
                    for name in orphans[:8]
                )
                more = f" and {len(orphans) - 8} more" if len(orphans) > 8 else ""
                raise BufferFormatError(
                    f"{self.path} has no {MANIFEST_NAME} but holds buffer data files: {listed}{more}. Its manifest was "
                    "lost (or removed), so these rows cannot be read, and creating a buffer there would overwrite them: "
                    "refusing. Move these files (or the whole directory) away, to keep them, or delete them if their data "
                    "is not needed, then create the buffer again; or pass another path"
                )
            if fields is None:
                raise FileNotFoundError(f"no buffer at {self.path!r} and no field specification to create one")
            if self.read_only:
                raise FileNotFoundError(f"no buffer at {self.path!r} to open read-only")
            self._fields = _validated_fields(fields)
            self._set_row_format()
            if self.path is not None and self._lock_file is None and fcntl is not None:
                # the directory did not exist: create it, lock it, and look again (another writer may have created
                # the buffer meanwhile)
                os.makedirs(self.path, exist_ok=True)
                self._take_lock()
                self._open_or_create(fields, capacity, verify, evict)
                return
            if self.path is not None:
                os.makedirs(self.path, exist_ok=True)
                self._layout.create(self)
                self._write_manifest()

    # ------------------------------------------------------------------ positions
    @property
    def end(self) -> int:
        """Global row after the last stored row (committed or not)."""
        return self._tail_start + self.num_tail

    @property
    def first(self) -> int:
        """Global row of the oldest retained row (index 0 of :meth:`gather` and :meth:`read_range`)."""
        low = self._tail_start if self.path is None else self.committed_first
        if self.capacity is None:
            return low
        return max(low, self._tail_start + self.num_tail - self.capacity)

    def __len__(self) -> int:
        return self.end - self.first

    # ------------------------------------------------------------------ what the rows are (read-only)
    @property
    def fields(self) -> Mapping[str, tuple[str, tuple[int, ...]]]:
        """Field name -> (dtype string, row shape), fixed when the store is created (a read-only view)."""
        return MappingProxyType(self._fields)

    @property
    def dtypes(self) -> Mapping[str, np.dtype]:
        """Field name -> numpy dtype of its rows (a read-only view)."""
        return MappingProxyType(self._dtypes)

    # ------------------------------------------------------------------ opening / recovery
    @property
    def _layout(self) -> _Layout:
        """The strategy of this directory's layout ("single" or "chunked"; not for in-memory stores)."""
        return _LAYOUT_STRATEGIES[self.layout]

    def _set_row_format(self) -> None:
        """Dtypes and row sizes of the fields, and the reader of a directory store's committed rows."""
        self._dtypes = {name: np.dtype(dt) for name, (dt, _) in self._fields.items()}
        self.row_bytes = {name: self._dtypes[name].itemsize * math.prod(shape) for name, (_, shape) in self._fields.items()}
        if self.path is not None:
            self._reader = _READERS[self.read_mode](self._dtypes, {name: shape for name, (_, shape) in self._fields.items()})

    def _load_manifest(self, manifest: dict[str, Any]) -> None:
        self.chunks = manifest["chunks"]
        self.num_committed = manifest["num_transitions"]
        self.committed_first = manifest.get("first_row", 0)
        self._sources = {int(k): v for k, v in manifest["sources"].items()}
        self._spaces = manifest["spaces"]
        self._next_stream_id = manifest["next_stream_id"]

    def _read_consistent_manifest(self) -> dict[str, Any]:
        """Read-only stores: a manifest whose chunk files all exist (a writer deletes evicted chunks after a commit)."""
        assert self.path is not None
        for _ in range(20):
            manifest = read_manifest(self.path)
            if manifest.get("layout") != "chunked":
                return manifest
            if all(os.path.isfile(os.path.join(self.path, chunk_file_name(c["start"]))) for c in manifest["chunks"]):
                return manifest
        return manifest  # opening it names the missing file

    def _take_lock(self) -> None:
        assert self.path is not None
        if fcntl is None:  # pragma: no cover
            return
        lock_name = os.path.join(self.path, LOCK_NAME)
        try:  # never through a symbolic link planted at its name (O_NOFOLLOW)
            self._lock_file = open(lock_name, "a+", opener=lambda name, flags: os.open(name, flags | _NOFOLLOW, 0o666))
        except OSError as error:
            if os.path.islink(lock_name):
                raise BufferFormatError(
                    f"{lock_name} is a symbolic link, not this buffer's lock file: refusing to open the directory for "
                    "writing (a lock must be a file of the directory itself). Remove the link, or open it with read_only=True"
                ) from None
            raise _explained(error, f"{self.path}: cannot open the writer lock {LOCK_NAME}") from error
        try:
            fcntl.flock(self._lock_file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._lock_file.close()
            self._lock_file = None
            raise RuntimeError(
                f"{self.path} is open for writing by another buffer (process or object); open it with read_only=True"
            ) from None
        _WRITERS[self.path] = self

    def _release_lock(self) -> None:
        if self._lock_file is not None:
            self._lock_file.close()
            self._lock_file = None
            if self.path is not None and _WRITERS.get(self.path) is self:
                del _WRITERS[self.path]

    def _field_offsets(self, rows: int) -> dict[str, int]:
        """Byte offset of each field's block in a chunk file of ``rows`` rows, and ``""`` -> the file size."""
        offsets, offset = {}, 0
        for name, (dtype, shape) in self._fields.items():
            offsets[name] = offset
            offset += rows * np.dtype(dtype).itemsize * math.prod(shape)
        offsets[""] = offset
        return offsets

    def refresh(self) -> int:
        """
        Read-only stores: re-read the manifest to see the rows a writer committed (and evicted) since.

        :return: The number of retained committed rows
        """
        if not self.read_only or self.path is None:
            return len(self)
        manifest = self._read_consistent_manifest()
        if validate_fields(manifest["fields"]) != self._fields or manifest.get("layout", "single") != self.layout:
            raise BufferFormatError(f"{self.path}: fields or layout changed while open")
        if manifest["num_transitions"] < self.num_committed or manifest.get("first_row", 0) < self.committed_first:
            raise BufferFormatError(f"{self.path}: committed rows went down from {self.num_committed}")
        changed = manifest["num_transitions"] != self.num_committed or manifest.get("first_row", 0) != self.committed_first
        self.capacity = manifest.get("capacity")
        self._load_manifest(manifest)
        self._tail_start = self.num_committed
        if changed:
            self._sync_maps()
        return len(self)

    # ------------------------------------------------------------------ writing
    def append(self, rows: dict[str, np.ndarray]) -> None:
        """
        Append rows (every field, same leading length). In a directory, once ``chunk_size`` rows are pending, the
        pending rows and the rows of this call that complete chunks of ``chunk_size`` rows are written and committed
        together, with one manifest; the rest of the call's rows stay pending.

        All or nothing: if writing fails (e.g. ``OSError``, disk full), this raises having stored none of the rows of
        this call, in this object or in the directory (its manifest is unchanged), whatever their number; the rows
        pending from earlier calls stay pending. The one exception is :class:`CommitNotDurableError`: the new
        manifest is in place and every row of this call is stored, but the commit may not survive a power loss.

        :param rows: field name -> array of shape (n, *row_shape)
        """
        if self.read_only:
            raise RuntimeError("buffer is open read-only")
        if self._closed:
            raise RuntimeError("buffer is closed (or was handed over to a buffer unpickled from it)")
        count = len(rows["rewards"])
        tail = self._tail
        if self.num_tail + count <= len(tail["rewards"]) and (self.path is None or self.num_tail + count < self.chunk_size):
            # fast path of add(): no growth, no flush
            start, stop = self.num_tail, self.num_tail + count
            for name in self._fields:
                tail[name][start:stop] = rows[name]
            self.num_tail = stop
            return
        if self.path is None:
            done = 0
            while done < count:
                if self.num_tail == len(self._tail["rewards"]):
                    self._make_room(count - done)
                take = min(len(self._tail["rewards"]) - self.num_tail, count - done)
                for name in self._fields:
                    self._tail[name][self.num_tail : self.num_tail + take] = rows[name][done : done + take]
                self.num_tail += take
                done += take
            return
        keep = (self.num_tail + count) % self.chunk_size  # rows of this call left pending
        committed_before = self.num_committed
        try:
            self._write_chunks(rows, count - keep)
        except BaseException as error:
            if self.num_committed == committed_before:  # nothing of this call is stored
                if isinstance(error, OSError):
                    raise _explained(
                        error,
                        f"{self.path}: writing failed before the commit, so none of the {count:,} transitions of this "
                        f"call was stored and the manifest is unchanged; the {self.num_tail:,} transitions pending before "
                        "it stay in memory. Repeat the call once the cause is fixed (e.g. space freed)",
                    ) from error
                raise
            # committed all the same (CommitNotDurableError; an interruption after the manifest's rename): the
            # call's last rows stay pending, as after a clean commit, so every row of the call is stored
            self._keep_pending(rows, count, keep)
            raise
        self._keep_pending(rows, count, keep)

    def _keep_pending(self, rows: dict[str, np.ndarray], count: int, keep: int) -> None:
        """After a commit, the last ``keep`` of the ``count`` rows of an append become the pending rows."""
        for name in self._fields:
            self._tail[name][:keep] = rows[name][count - keep : count]
        self.num_tail = keep

    def _make_room(self, need: int) -> None:
        """In memory, the arrays are full: drop the evicted rows at their front (if that frees enough), else grow."""
        evicted = self.first - self._tail_start
        if evicted > 0 and evicted >= len(self._tail["rewards"]) // 4:
            for name in self._fields:
                self._tail[name][: self.num_tail - evicted] = self._tail[name][evicted : self.num_tail]
            self._tail_start += evicted
            self.num_tail -= evicted
            return
        target = max(2 * self.num_tail, self.num_tail + need)
        if self.capacity is not None:  # twice the capacity is enough to compact rarely
            target = max(min(target, 2 * self.capacity), self.num_tail + min(need, self.capacity), self.num_tail + 1)
        self._grow(target)

    def _grow(self, rows: int) -> None:
        for name in self._fields:
            new = np.empty((rows, *self._tail[name].shape[1:]), dtype=self._tail[name].dtype)
            new[: self.num_tail] = self._tail[name][: self.num_tail]
            self._tail[name] = new

    def clear(self) -> None:
        """Forget every row of an in-memory store."""
        if self.path is not None:
            raise RuntimeError("a directory store cannot be cleared")
        self.num_tail = 0
        self._tail_start = 0

    def flush(self) -> None:
        """
        Write the pending rows as one chunk: the field files (layout "single": each cut back to its committed length
        first, then appended to) or the chunk file (layout "chunked") are written and fsync'd, then the manifest is
        replaced atomically, then the files of evicted chunks are deleted.

        Only once the new manifest is in place does this object count the rows as committed. If anything fails
        before (e.g. ``OSError`` ENOSPC, disk full), it raises with the committed state (on disk and in memory)
        unchanged and the rows still pending in memory, readable and sampled as before: calling ``flush()`` again
        (e.g. after freeing space) writes the same bytes to the same places and commits them. If only the fsync of
        the directory after the manifest's rename fails, it raises :class:`CommitNotDurableError` with the rows
        committed (the manifest is in place); calling ``flush()`` again writes and syncs the manifest again.
        """
        if self.path is None or self.read_only or self._closed:
            return
        if self.num_tail == 0:
            self._write_manifest()  # source names may have changed; a commit whose directory sync failed is synced
            self._delete_undeleted()
            return
        try:
            self._write_chunks()
        except CommitNotDurableError:
            raise
        except OSError as error:
            raise _explained(
                error,
                f"{self.path}: flush() failed before the commit: the {self.num_tail:,} pending transitions stay in memory "
                "(read and sampled as before) and the manifest is unchanged. flush() again once the cause is fixed "
                "(e.g. space freed)",
            ) from error

    def _write_block(self, fd: int, name: str, chunk: dict[str, Any], lo: int, extra: Optional[dict[str, np.ndarray]]) -> None:
        """Write field ``name`` of ``chunk`` (its rows from ``lo`` of the pending rows + ``extra``) and record its CRC."""
        data = self._block(name, lo, lo + chunk["rows"], extra)
        chunk["crc32"][name] = zlib.crc32(data)
        _write_all(fd, data)

    def _block(self, name: str, lo: int, hi: int, extra: Optional[dict[str, np.ndarray]]) -> memoryview:
        """Bytes of the rows ``lo:hi`` of field ``name`` of the pending rows followed by the rows of ``extra``."""
        pending = self.num_tail
        if hi <= pending:
            block = self._tail[name][lo:hi]  # contiguous: no copy
        else:
            assert extra is not None
            block = np.empty((hi - lo, *self._tail[name].shape[1:]), dtype=self._dtypes[name])
            split = max(pending - lo, 0)
            block[:split] = self._tail[name][lo:pending]
            block[split:] = extra[name][max(lo - pending, 0) : hi - pending]  # the tail's conversions (dtype, broadcast)
        return memoryview(block).cast("B")  # type: ignore[arg-type]

    def _write_chunks(self, extra: Optional[dict[str, np.ndarray]] = None, extra_rows: int = 0) -> None:
        """
        Write the pending rows followed by the first ``extra_rows`` rows of ``extra`` as chunks of at most
        ``chunk_size`` rows (appended to the field files, or one chunk file each, fsync'd), then commit them all with
        one manifest (:meth:`_commit`, which empties the tail).

        If anything fails before the manifest is in place, this raises with nothing changed: the committed state (in
        memory and on disk) and the pending rows are as before, and the bytes written are removed (best effort).

        :param extra: Rows to write after the pending ones (field name -> array), or None
        :param extra_rows: How many rows of ``extra`` to write
        """
        assert self.path is not None
        base, total = self.num_committed, self.num_tail + extra_rows
        bounds = [*range(0, total, self.chunk_size), total]
        chunks: list[dict[str, Any]] = [
            {"start": base + lo, "rows": hi - lo, "crc32": {}} for lo, hi in zip(bounds[:-1], bounds[1:])
        ]
        try:
            self._layout.write(self, chunks, extra)
            self._commit([*self.chunks, *chunks], base + total)
        except BaseException:
            if self.num_committed == base and self._committed_on_disk(base + total) is False:
                self._layout.discard(self, chunks)  # not committed: give the space back (best effort)
            raise

    def _commit(self, chunks: list[dict[str, Any]], num_committed: int) -> None:
        """
        Commit every pending row, up to global row ``num_committed`` (listed by ``chunks``; with a capacity, the
        chunks with no retained row are dropped): replace the manifest atomically, then, and only then, move this
        object's committed state (the tail is emptied), delete the files of the dropped chunks and map the committed
        rows. If the manifest cannot be written, this raises and nothing changed. If it was replaced but the
        directory's fsync failed, the state moves all the same (the manifest in place is the new one) but the files
        of the dropped chunks are kept until a later manifest is synced, and :class:`CommitNotDurableError` is raised.
        Any other exception after the rename (e.g. ``KeyboardInterrupt`` in that fsync) moves the state the same way
        before it goes through: the manifest on disk decides whether the rows are committed.

        :param chunks: The chunks of the new manifest
        :param num_committed: Global row after the last committed row
        """
        chunks, committed_first, dropped = self._layout.retain(self, chunks, num_committed)
        try:
            self._write_manifest(chunks, num_committed, committed_first)
        except CommitNotDurableError:
            self._adopt_commit(chunks, committed_first, num_committed, dropped, synced=False)
            raise
        except BaseException:
            # e.g. KeyboardInterrupt during the directory's fsync: the new manifest may be in place all the same,
            # and then its rows are committed; the pending rows must not be discarded as if they were not
            if num_committed > self.num_committed and self._committed_on_disk(num_committed):
                self._adopt_commit(chunks, committed_first, num_committed, dropped, synced=False)
            raise
        self._adopt_commit(chunks, committed_first, num_committed, dropped, synced=True)

    def _adopt_commit(
        self,
        chunks: list[dict[str, Any]],
        committed_first: int,
        num_committed: int,
        dropped: list[str],
        synced: bool,
    ) -> None:
        """
        The manifest in place is the new one: move this object's committed state to it (the tail is emptied), delete
        the files of the dropped chunks if the manifest is synced (else keep them until a later one is) and let the
        reader follow. A reader that cannot follow now (e.g. ENOMEM or EMFILE from ``mmap``/``open``) does not undo
        the commit: it stays marked stale and the next read tries again (and raises, if it still cannot).
        """
        # committed: from here on, no committed state refers to the dropped chunks
        self.chunks, self.committed_first = chunks, committed_first
        self.num_committed = self._tail_start = num_committed
        self.num_tail = 0
        self._reader_stale = True  # until the maps (or read files) follow: reads map again first
        self._undeleted.extend(dropped)
        if synced:
            self._delete_undeleted()
        try:
            self._sync_maps()
        except (OSError, MemoryError):
            pass

    def _committed_on_disk(self, num_committed: int) -> Optional[bool]:
        """
        Whether the manifest in place commits the rows up to global row ``num_committed`` (this writer holds the
        lock: no other writer replaces it). None when it cannot be read: then nothing may be discarded.
        """
        assert self.path is not None
        try:
            with open(os.path.join(self.path, MANIFEST_NAME), "rb") as file:
                return int(json.loads(file.read())["num_transitions"]) >= num_committed
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def _delete_undeleted(self) -> None:
        """Delete the files of chunks dropped by commits, once the manifest in place (which does not list them) is
        synced."""
        if self._undeleted:
            kept = []
            for file_name in self._undeleted:
                try:
                    _delete_file(file_name)
                except OSError:  # e.g. EIO: the rows are committed all the same; the next commit tries again
                    kept.append(file_name)
            self._undeleted = kept
            assert self.path is not None
            _fsync_dir(self.path)

    def _sync_maps(self, fresh: bool = False) -> None:
        """
        Let the reader follow the committed rows after a commit or a refresh: map the new segments (or, with
        ``read_mode="pread"``, open their files) and drop those no longer committed.

        :param fresh: Map every segment again (drops the pages touched so far from this process's RSS)
        """
        self._reader_stale = True
        self._reader.sync(self._layout.segments(self), fresh=fresh, eager=not self._closed)
        self._reader_stale = False

    def _write_manifest(
        self,
        chunks: Optional[list[dict[str, Any]]] = None,
        num_committed: Optional[int] = None,
        committed_first: Optional[int] = None,
    ) -> None:
        """Atomically replace the manifest: the committed state of this object, or the one given."""
        assert self.path is not None
        plain = self.layout == "single" and obs_keys_of(self._fields) is None
        manifest: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": 1 if plain else 2,
            "fields": {name: {"dtype": dt, "shape": list(shape)} for name, (dt, shape) in self._fields.items()},
            "num_transitions": self.num_committed if num_committed is None else num_committed,
            "chunks": self.chunks if chunks is None else chunks,
            "sources": {str(k): v for k, v in sorted(self._sources.items())},
            "next_stream_id": self._next_stream_id,
            "spaces": self._spaces,
        }
        if not plain:
            first = self.committed_first if committed_first is None else committed_first
            manifest.update(layout=self.layout, capacity=self.capacity, first_row=first)
        try:
            write_json_atomic(os.path.join(self.path, MANIFEST_NAME), manifest)
        except CommitNotDurableError as error:
            raise CommitNotDurableError(
                error.errno,
                f"{self.path}: the new {MANIFEST_NAME} is in place, so its {manifest['num_transitions']:,} transitions are "
                f"committed and readable, but the fsync of the directory failed ({error.strerror}): this commit may not "
                "survive a power loss or an operating-system crash (a crash of this process is fine). flush() (or "
                "close()) writes and syncs the manifest again; until then, files the previous manifest needs are kept",
            ) from error

    def __getstate__(self) -> dict[str, Any]:
        if self.path is None:
            state = dict(self.__dict__)
            skip = self.first - self._tail_start  # evicted rows are not pickled
            state["_tail"] = {name: array[skip : self.num_tail].copy() for name, array in self._tail.items()}
            state["_tail_start"] = self._tail_start + skip
            state["num_tail"] = self.num_tail - skip
            return state
        # a directory store pickles as a reference to its directory: flush, then reopen on unpickling
        self.flush()
        return {
            "path": self.path,
            "read_only": self.read_only,
            "chunk_size": self.chunk_size,
            "max_resident_bytes": self.max_resident_bytes,
            "read_mode": self.read_mode,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        if "_fields" in state or "fields" in state:
            # in memory; pickles of earlier versions have no read mode, and keep the attributes that are read-only
            # properties now under their public names
            self.__dict__.update(read_mode="mmap", _reader_stale=False)
            kept = {key: value for key, value in state.items() if key not in _READER_BEFORE}
            self.__dict__.update({f"_{key}" if key in _PUBLIC_BEFORE else key: value for key, value in kept.items()})
            self._reader = None  # an in-memory store reads no file
            return
        previous = _WRITERS.get(state["path"])
        if previous is not None and not state["read_only"]:
            # e.g. SB3's load() built a buffer on this directory before load_replay_buffer(): hand it over
            previous.close()
        try:
            self.__init__(**state)  # type: ignore[misc]
        except RuntimeError:
            warnings.warn(f"{state['path']} is locked by another writer: the unpickled buffer is opened read-only")
            self.__init__(**dict(state, read_only=True))  # type: ignore[misc]

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # pragma: no cover (interpreter shutdown)
            pass

    def close(self) -> None:
        """Flush, release the writer lock and close the read file descriptors (``read_mode="pread"``). Reading the
        committed rows keeps working (with ``"pread"`` it opens the files again, until the next ``close()``)."""
        if not getattr(self, "_closed", True):
            self.flush()
            self._closed = True
            self._release_lock()
        reader = getattr(self, "_reader", None)
        if reader is not None:
            reader.close()

    # ------------------------------------------------------------------ reading
    def _limit_resident(self) -> None:
        # random reads map file pages into this process (with the kernel's fault-around, 64 KiB per touched row);
        # they count in its RSS although the kernel can drop them at will. Past the limit, remap to unmap them.
        try:
            with open("/proc/self/statm", "rb") as file:
                mapped_file_pages = int(file.read().split()[2])
        except (OSError, ValueError, IndexError):  # pragma: no cover (not Linux)
            return
        assert self.max_resident_bytes is not None
        if mapped_file_pages * mmap.PAGESIZE > self.max_resident_bytes + self._baseline_file_bytes:
            self._sync_maps(fresh=True)
            self.remaps += 1

    # ------------------------------------------------------------------ streams, sources and spaces
    @property
    def next_stream_id(self) -> int:
        """The first stream id not reserved yet (every id below it is taken): see :meth:`reserve_streams`."""
        return self._next_stream_id

    @property
    def spaces(self) -> Mapping[str, Any]:
        """The JSON description of the observation and action spaces (``{}`` until :meth:`describe_spaces`), read-only."""
        return MappingProxyType(self._spaces)

    def reserve_streams(self, count: int) -> int:
        """
        Reserve ``count`` new stream ids (a stream is one env's chain of transitions: n-step returns and next
        actions never cross streams). Saved with the next commit.

        :param count: how many ids
        :return: the first of the ``count`` consecutive new ids
        """
        if count < 0:
            raise ValueError(f"count must be >= 0, got {count}")
        first = self._next_stream_id
        self._next_stream_id += int(count)
        return first

    def source(self, source: int) -> Optional[dict[str, Any]]:
        """:return: ``{"name": str, "metadata": dict}`` of a source id (a copy), or None if it is not known"""
        known = self._sources.get(source)
        return None if known is None else {"name": known["name"], "metadata": dict(known["metadata"])}

    def set_source(self, source: int, name: str, metadata: dict[str, Any]) -> None:
        """
        Name a source id and set its metadata (JSON-serialisable); saved with the next commit.

        :param source: source id in ``[0, MAX_SOURCE_ID]``
        :param name: its name
        :param metadata: its metadata (copied)
        """
        if not 0 <= int(source) <= MAX_SOURCE_ID:
            raise ValueError(f"source ids are ints in [0, {MAX_SOURCE_ID}], got {source!r}")
        self._sources[int(source)] = {"name": str(name), "metadata": dict(metadata)}

    def source_table(self) -> dict[int, dict[str, Any]]:
        """:return: every source id -> ``{"name": str, "metadata": dict}`` (copies)"""
        return {k: {"name": v["name"], "metadata": dict(v["metadata"])} for k, v in self._sources.items()}

    def describe_spaces(self, spaces: dict[str, Any]) -> None:
        """
        Record the JSON description of the observation and action spaces, once: a store that has one keeps it.

        :param spaces: ``{"observation": ..., "action": ...}``
        """
        if not self._spaces:
            self._spaces = dict(spaces)

    def gather(self, names: tuple[str, ...], indices: np.ndarray) -> dict[str, np.ndarray]:
        """
        Copy the rows ``indices`` (ints in [0, len(self)), counted from the oldest retained row) of several fields.

        :param names: Fields to read
        :param indices: Row indices
        :return: field name -> array of shape (len(indices), *row_shape)
        """
        if self._reader_stale:
            self._sync_maps()
        first = self.first
        rows = indices + first if first else indices
        committed = self._tail_start
        if self.path is None or self.num_committed == 0 or (len(rows) and rows.min() >= committed):
            local = rows - committed if committed else rows
            return {name: self._tail[name][local] for name in names}
        if self.max_resident_bytes is not None:
            self._limit_resident()
        if len(rows) == 0 or rows.max() < committed:
            return self._reader.gather(names, rows)
        in_tail = rows >= committed
        from_maps = self._reader.gather(names, rows[~in_tail])
        tail_idx = rows[in_tail] - committed
        result = {}
        for name in names:
            out = np.empty((len(rows), *self._tail[name].shape[1:]), dtype=self._tail[name].dtype)
            out[in_tail] = self._tail[name][tail_idx]
            out[~in_tail] = from_maps[name]
            result[name] = out
        return result

    def read_range(self, name: str, start: int, stop: int) -> np.ndarray:
        """
        Rows ``start:stop`` of a field, counted from the oldest retained row (a view of a map or of the tail where
        possible, a copy when the range spans several or is read with ``read_mode="pread"``).

        :param name: Field
        :param start: First row
        :param stop: One past the last row
        :return: Array of shape (stop - start, *row_shape)
        """
        if self._reader_stale:
            self._sync_maps()
        first = self.first
        lo, hi = start + first, max(start, stop) + first
        committed = self._tail_start
        pieces = []
        if lo < committed and self.path is not None:
            pieces.extend(self._reader.pieces(name, lo, min(hi, committed)))
        if hi > committed:
            pieces.append(self._tail[name][max(lo, committed) - committed : hi - committed])
        if len(pieces) == 1:
            return pieces[0]
        if not pieces:
            return self._tail[name][:0]
        return np.concatenate(pieces)
