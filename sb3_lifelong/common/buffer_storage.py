"""
On-disk / in-memory row store behind :class:`sb3_lifelong.common.buffers.LifelongReplayBuffer`.

This module only depends on numpy and the standard library (it can be loaded without torch), so that
crash tests and tools can use it in light subprocesses.

Directory format (version 1), see ``docs/modules/buffer.md``::

    <path>/manifest.json     committed state (JSON, rewritten atomically after each flushed chunk)
    <path>/<field>.bin       one append-only file per field: raw little-endian C-order rows, no header
    <path>/writer.lock       advisory lock held by the (single) writer process

A row ``i`` of field ``f`` lives at byte offset ``i * row_bytes(f)`` of ``f.bin``. Only the first
``num_transitions`` rows (sum of the chunk sizes listed in the manifest) are committed; bytes after
them are an unflushed tail of a crashed writer and are ignored by readers and cut off by the next writer.
"""

from __future__ import annotations

import json
import math
import mmap
import os
import warnings
import weakref
import zlib
from typing import Any, Optional

import numpy as np

try:  # POSIX only: the writer lock is advisory and simply skipped elsewhere
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

FORMAT_NAME = "sb3-lifelong-buffer"
FORMAT_VERSION = 1
MANIFEST_NAME = "manifest.json"
LOCK_NAME = "writer.lock"
MAX_MANIFEST_BYTES = 256 * 1024 * 1024
MAX_ROW_ELEMENTS = 1 << 24
MAX_SOURCE_ID = 65534

# dtypes a manifest may name (numpy ``dtype.str``), nothing else is accepted
ALLOWED_DTYPES = frozenset(["|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8"])
# fields every buffer stores, with the dtypes that are fixed by the format (None: chosen by the spaces)
FIELD_NAMES = ("observations", "next_observations", "actions", "rewards", "flags", "sources", "streams", "widths")
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
    """A manifest or a chunk file is not a valid buffer directory (corrupted, truncated or hostile)."""


def _fsync_dir(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover (e.g. Windows)
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def write_json_atomic(path: str, data: dict[str, Any]) -> None:
    """
    Write a JSON document atomically: temporary file, fsync, rename over the target, fsync of the directory.

    :param path: Target file
    :param data: JSON-serialisable document
    """
    directory = os.path.dirname(os.path.abspath(path))
    tmp = path + ".tmp"
    payload = json.dumps(data, indent=1, sort_keys=True, allow_nan=False).encode("utf-8")
    with open(tmp, "wb") as file:
        file.write(payload)
        file.flush()
        os.fsync(file.fileno())
    os.replace(tmp, path)
    _fsync_dir(directory)


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


def validate_fields(fields: Any) -> dict[str, tuple[str, tuple[int, ...]]]:
    """
    Validate the ``fields`` entry of a manifest.

    :param fields: The decoded JSON value
    :return: field name -> (dtype string, row shape)
    """
    if not isinstance(fields, dict):
        raise BufferFormatError("manifest 'fields' must be an object")
    if set(fields) != set(FIELD_NAMES):
        raise BufferFormatError(f"manifest 'fields' must name exactly {sorted(FIELD_NAMES)}, got {sorted(map(str, fields))}")
    result: dict[str, tuple[str, tuple[int, ...]]] = {}
    for name in FIELD_NAMES:
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
    if result["observations"] != result["next_observations"]:
        raise BufferFormatError("manifest: observations and next_observations must have the same dtype and shape")
    return result


def _validate_chunks(chunks: Any) -> int:
    """
    :param chunks: The ``chunks`` entry of a manifest
    :return: The number of rows they hold
    """
    if not isinstance(chunks, list):
        raise BufferFormatError("manifest 'chunks' must be a list")
    start = 0
    for k, chunk in enumerate(chunks):
        if not isinstance(chunk, dict) or set(chunk) != {"start", "rows", "crc32"}:
            raise BufferFormatError(f"manifest chunk {k} must be an object with exactly 'start', 'rows', 'crc32'")
        if not _is_int(chunk["start"]) or chunk["start"] != start:
            raise BufferFormatError(f"manifest chunk {k}: 'start' must be {start}, got {chunk['start']!r}")
        if not _is_int(chunk["rows"]) or chunk["rows"] <= 0:
            raise BufferFormatError(f"manifest chunk {k}: 'rows' must be a positive int, got {chunk['rows']!r}")
        crc = chunk["crc32"]
        if not isinstance(crc, dict) or set(crc) != set(FIELD_NAMES):
            raise BufferFormatError(f"manifest chunk {k}: 'crc32' must give one checksum per field")
        if not all(_is_int(v) and 0 <= v < 2**32 for v in crc.values()):
            raise BufferFormatError(f"manifest chunk {k}: checksums must be ints in [0, 2**32)")
        start += chunk["rows"]
    return start


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
    if manifest.get("version") != FORMAT_VERSION:
        raise BufferFormatError(f"unsupported format version {manifest.get('version')!r} (this code reads {FORMAT_VERSION})")
    expected = {"format", "version", "fields", "num_transitions", "chunks", "sources", "next_stream_id", "spaces"}
    if set(manifest) != expected:
        raise BufferFormatError(f"manifest keys must be {sorted(expected)}, got {sorted(map(str, manifest))}")
    validate_fields(manifest["fields"])
    num = manifest["num_transitions"]
    if not _is_int(num) or num < 0:
        raise BufferFormatError(f"manifest 'num_transitions' must be a non-negative int, got {num!r}")
    start = _validate_chunks(manifest["chunks"])
    if start != num:
        raise BufferFormatError(f"manifest chunks hold {start} rows but 'num_transitions' is {num}")
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


class RowStore:
    """
    Append-only table of fixed-size rows (one array per field), in memory or in a buffer directory.

    In memory (``path=None``) the rows live in preallocated arrays that double when full. With a path,
    committed rows are memory-mapped from the field files and the unflushed rows wait in a tail of
    ``chunk_size`` rows, written out (appended, fsync'd, manifest replaced atomically) when full or on ``flush()``.

    :param fields: field name -> (dtype string, row shape)
    :param path: Buffer directory, or None for an in-memory store
    :param read_only: Open an existing directory without writing (another process may be writing)
    :param chunk_size: Rows per flushed chunk
    :param verify: Checksums to verify when opening: "all", "last" (the last chunk) or "none"
    :param max_resident_bytes: Remap the files after random reads may have touched about this many bytes of
        pages, which drops them from this process's RSS (they stay in the OS page cache). None: never
    """

    def __init__(
        self,
        fields: Optional[dict[str, tuple[str, tuple[int, ...]]]] = None,
        path: Optional[str] = None,
        read_only: bool = False,
        chunk_size: int = 10_000,
        verify: str = "last",
        max_resident_bytes: Optional[int] = None,
    ) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        if verify not in ("all", "last", "none"):
            raise ValueError(f"verify must be 'all', 'last' or 'none', got {verify!r}")
        self.path = None if path is None else os.path.abspath(os.fspath(path))
        self.read_only = read_only
        self.chunk_size = chunk_size
        self.sources: dict[int, dict[str, Any]] = {}
        self.spaces: dict[str, Any] = {}
        self.next_stream_id = 0
        self.chunks: list[dict[str, Any]] = []
        self.num_committed = 0
        self.recovered = 0
        self.discarded_bytes = 0
        self._lock_file: Any = None
        self._maps: dict[str, np.ndarray] = {}
        self._closed = False
        self.max_resident_bytes = max_resident_bytes
        self.remaps = 0  # number of remaps done to bound the RSS
        self._baseline_file_bytes = 0
        if self.path is not None and os.path.isfile(os.path.join(self.path, MANIFEST_NAME)):
            manifest = read_manifest(self.path)
            stored = validate_fields(manifest["fields"])
            if fields is not None and dict(fields) != stored:
                raise ValueError(f"{self.path}: stored fields {stored} do not match the requested {fields}")
            self.fields = stored
            self.chunks = manifest["chunks"]
            self.num_committed = manifest["num_transitions"]
            self.sources = {int(k): v for k, v in manifest["sources"].items()}
            self.spaces = manifest["spaces"]
            self.next_stream_id = manifest["next_stream_id"]
            self._open_existing(verify)
        else:
            if fields is None:
                raise FileNotFoundError(f"no buffer at {self.path!r} and no field specification to create one")
            if read_only:
                raise FileNotFoundError(f"no buffer at {self.path!r} to open read-only")
            self.fields = {name: (np.dtype(dt).str, tuple(int(d) for d in shape)) for name, (dt, shape) in fields.items()}
            validate_fields({k: {"dtype": d, "shape": list(s)} for k, (d, s) in self.fields.items()})
            if self.path is not None:
                os.makedirs(self.path, exist_ok=True)
                self._take_lock()
                for name in FIELD_NAMES:
                    open(self._file(name), "wb").close()
                self._write_manifest()
        self.dtypes = {name: np.dtype(dt) for name, (dt, _) in self.fields.items()}
        self.row_bytes = {name: self.dtypes[name].itemsize * math.prod(shape) for name, (_, shape) in self.fields.items()}
        capacity = self.chunk_size if self.path is not None else 1024
        self._tail = {name: np.empty((capacity, *shape), dtype=self.dtypes[name]) for name, (_, shape) in self.fields.items()}
        self.num_tail = 0
        self._remap()
        if self.max_resident_bytes is not None and self.path is not None:
            try:  # file-backed pages mapped before this store (python, numpy, torch libraries)
                with open("/proc/self/statm", "rb") as file:
                    self._baseline_file_bytes = int(file.read().split()[2]) * mmap.PAGESIZE
            except (OSError, ValueError, IndexError):  # pragma: no cover (not Linux)
                pass

    # ------------------------------------------------------------------ opening / recovery
    def _file(self, name: str) -> str:
        assert self.path is not None
        return os.path.join(self.path, name + ".bin")

    def _take_lock(self) -> None:
        assert self.path is not None
        if fcntl is None:  # pragma: no cover
            return
        self._lock_file = open(os.path.join(self.path, LOCK_NAME), "a+")
        try:
            fcntl.flock(self._lock_file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._lock_file.close()
            self._lock_file = None
            raise RuntimeError(
                f"{self.path} is open for writing by another buffer (process or object); open it with read_only=True"
            ) from None
        _WRITERS[self.path] = self

    def _open_existing(self, verify: str) -> None:
        assert self.path is not None
        if not self.read_only:
            self._take_lock()
        for name in FIELD_NAMES:
            file_name = self._file(name)
            if not os.path.isfile(file_name) or os.path.islink(file_name):
                raise BufferFormatError(f"{self.path}: chunk file {name}.bin is missing or not a regular file")
        dtypes = {name: np.dtype(dt) for name, (dt, _) in self.fields.items()}
        sizes = {name: dtypes[name].itemsize * math.prod(shape) for name, (_, shape) in self.fields.items()}
        for name in FIELD_NAMES:
            have = os.path.getsize(self._file(name))
            need = self.num_committed * sizes[name]
            if have < need:
                raise BufferFormatError(
                    f"{self._file(name)}: {have} bytes but the manifest commits {self.num_committed} rows ({need} bytes); "
                    "the file was truncated or replaced"
                )
            if have > need and not self.read_only:
                # an unflushed tail of a writer that died: cut it off so that appends continue at the committed end
                with open(self._file(name), "r+b") as file:
                    file.truncate(need)
                    os.fsync(file.fileno())
                self.discarded_bytes += have - need
        checked = self.chunks if verify == "all" else self.chunks[-1:] if verify == "last" else []
        for chunk in checked:
            for name in FIELD_NAMES:
                with open(self._file(name), "rb") as file:
                    file.seek(chunk["start"] * sizes[name])
                    data = file.read(chunk["rows"] * sizes[name])
                if zlib.crc32(data) != chunk["crc32"][name]:
                    raise BufferFormatError(
                        f"{self._file(name)}: checksum mismatch in chunk starting at row {chunk['start']} (corrupted data)"
                    )
        self.recovered = self.num_committed
        if self.discarded_bytes:
            warnings.warn(
                f"{self.path}: recovered {self.num_committed} transitions; discarded {self.discarded_bytes} bytes of "
                "unflushed rows left by a writer that did not close the buffer"
            )

    def _remap(self) -> None:
        """(Re)create the read-only memory maps over the committed rows (drops their resident pages from this process)."""
        self._maps = {}
        if self.path is None or self.num_committed == 0:
            return
        for name, (_, shape) in self.fields.items():
            length = self.num_committed * self.row_bytes[name]
            with open(self._file(name), "rb") as file:
                mapped = mmap.mmap(file.fileno(), length, access=mmap.ACCESS_READ)
            if hasattr(mapped, "madvise") and hasattr(mmap, "MADV_RANDOM"):
                mapped.madvise(mmap.MADV_RANDOM)
            array = np.frombuffer(mapped, dtype=self.dtypes[name], count=self.num_committed * math.prod(shape))
            self._maps[name] = array.reshape(self.num_committed, *shape)

    def refresh(self) -> int:
        """
        Read-only stores: re-read the manifest to see the rows a writer committed since.

        :return: The number of committed rows
        """
        if not self.read_only or self.path is None:
            return self.num_committed
        manifest = read_manifest(self.path)
        if validate_fields(manifest["fields"]) != self.fields:
            raise BufferFormatError(f"{self.path}: fields changed while open")
        if manifest["num_transitions"] < self.num_committed:
            raise BufferFormatError(f"{self.path}: committed rows went down from {self.num_committed}")
        self.chunks = manifest["chunks"]
        self.sources = {int(k): v for k, v in manifest["sources"].items()}
        self.next_stream_id = manifest["next_stream_id"]
        if manifest["num_transitions"] != self.num_committed:
            self.num_committed = manifest["num_transitions"]
            self._remap()
        return self.num_committed

    # ------------------------------------------------------------------ writing
    def __len__(self) -> int:
        return self.num_committed + self.num_tail

    def append(self, rows: dict[str, np.ndarray]) -> None:
        """
        Append rows (every field, same leading length). Flushes a chunk each time ``chunk_size`` rows are pending.

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
            for name in FIELD_NAMES:
                tail[name][start:stop] = rows[name]
            self.num_tail = stop
            return
        done = 0
        while done < count:
            if self.path is None and self.num_tail == len(self._tail["rewards"]):
                self._grow(max(2 * self.num_tail, self.num_tail + count - done))
            free = len(self._tail["rewards"]) - self.num_tail
            take = min(free, count - done)
            for name in FIELD_NAMES:
                self._tail[name][self.num_tail : self.num_tail + take] = rows[name][done : done + take]
            self.num_tail += take
            done += take
            if self.path is not None and self.num_tail == self.chunk_size:
                self.flush()

    def _grow(self, capacity: int) -> None:
        for name in FIELD_NAMES:
            new = np.empty((capacity, *self._tail[name].shape[1:]), dtype=self._tail[name].dtype)
            new[: self.num_tail] = self._tail[name][: self.num_tail]
            self._tail[name] = new

    def flush(self) -> None:
        """Write the pending rows as one chunk (append + fsync each field file, then replace the manifest atomically)."""
        if self.path is None or self.read_only or self._closed:
            return
        if self.num_tail == 0:
            self._write_manifest()  # source names may have changed
            return
        count = self.num_tail
        crcs = {}
        for name in FIELD_NAMES:
            data = np.ascontiguousarray(self._tail[name][:count]).tobytes()
            crcs[name] = zlib.crc32(data)
            with open(self._file(name), "ab") as file:
                file.write(data)
                file.flush()
                os.fsync(file.fileno())
        self.chunks.append({"start": self.num_committed, "rows": count, "crc32": crcs})
        self.num_committed += count
        self.num_tail = 0
        self._write_manifest()
        self._remap()

    def _write_manifest(self) -> None:
        assert self.path is not None
        manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "fields": {name: {"dtype": dt, "shape": list(shape)} for name, (dt, shape) in self.fields.items()},
            "num_transitions": self.num_committed,
            "chunks": self.chunks,
            "sources": {str(k): v for k, v in sorted(self.sources.items())},
            "next_stream_id": self.next_stream_id,
            "spaces": self.spaces,
        }
        write_json_atomic(os.path.join(self.path, MANIFEST_NAME), manifest)

    def __getstate__(self) -> dict[str, Any]:
        if self.path is None:
            state = dict(self.__dict__)
            state["_tail"] = {name: array[: self.num_tail].copy() for name, array in self._tail.items()}
            return state
        # a directory store pickles as a reference to its directory: flush, then reopen on unpickling
        self.flush()
        return {
            "path": self.path,
            "read_only": self.read_only,
            "chunk_size": self.chunk_size,
            "max_resident_bytes": self.max_resident_bytes,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        if "fields" in state:
            self.__dict__.update(state)
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
        """Flush and release the writer lock. Reading the committed rows keeps working."""
        if getattr(self, "_closed", True):
            return
        self.flush()
        self._closed = True
        if self._lock_file is not None:
            self._lock_file.close()
            self._lock_file = None

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
            self._remap()
            self.remaps += 1

    def gather(self, names: tuple[str, ...], indices: np.ndarray) -> dict[str, np.ndarray]:
        """
        Copy the rows ``indices`` (ints in [0, len(self))) of several fields.

        :param names: Fields to read
        :param indices: Row indices
        :return: field name -> array of shape (len(indices), *row_shape)
        """
        committed = self.num_committed
        if committed == 0:
            return {name: self._tail[name][indices] for name in names}
        if self.max_resident_bytes is not None:
            self._limit_resident()
        if len(indices) == 0 or indices.max() < committed:
            return {name: self._maps[name][indices] for name in names}
        in_tail = indices >= committed
        tail_idx = indices[in_tail] - committed
        map_idx = indices[~in_tail]
        result = {}
        for name in names:
            out = np.empty((len(indices), *self._tail[name].shape[1:]), dtype=self._tail[name].dtype)
            out[in_tail] = self._tail[name][tail_idx]
            out[~in_tail] = self._maps[name][map_idx]
            result[name] = out
        return result

    def read_range(self, name: str, start: int, stop: int) -> np.ndarray:
        """
        Rows ``start:stop`` of a field (a view of the map or of the tail where possible, a copy when it straddles both).

        :param name: Field
        :param start: First row
        :param stop: One past the last row
        :return: Array of shape (stop - start, *row_shape)
        """
        committed = self.num_committed
        if stop <= committed and committed > 0:
            return self._maps[name][start:stop]
        if start >= committed:
            return self._tail[name][start - committed : stop - committed]
        return np.concatenate([self._maps[name][start:], self._tail[name][: stop - committed]])
