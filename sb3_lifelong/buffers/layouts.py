"""
Where a row store's rows live: its layout. ``"memory"``: in this process only (the pending rows are the storage,
nothing is ever written); ``"single"`` (no capacity): one append-only file per field; ``"chunked"`` (with a
capacity): one file per flushed chunk, deleted once a committed manifest no longer lists it.

A layout creates, checks, writes and describes its data as segments of committed rows (which a reader of
``readers`` reads), keeps the directory's writer lock and writes its manifest; a layout without a directory
(``"memory"``) does none of it. It knows its store through a small :class:`LayoutState` (directory, fields, chunk
size, capacity) and the committed state the store passes to each call; only the store changes that state (the
commit protocol is :class:`~sb3_lifelong.buffers.rowstore.RowStore`'s).

The files a buffer directory owns (what ``mode="overwrite"`` may delete, what a lost manifest leaves) are here too.
"""

from __future__ import annotations

import math
import os
import sys
import zlib
from collections.abc import Mapping
from typing import IO, Any, Callable, NamedTuple, Optional, Protocol

import numpy as np

from sb3_lifelong.buffers import files
from sb3_lifelong.buffers.manifest import (
    CHUNK_FILE_PATTERN,
    DATA_FILE_PATTERN,
    LOCK_NAME,
    MANIFEST_NAME,
    BufferFormatError,
    chunk_file_name,
    committed_transitions,
    read_manifest,
    validate_fields,
)
from sb3_lifelong.core.atomic import write_json_atomic

if sys.platform == "win32":  # pragma: no cover: no flock; the writer lock goes through filelock (LockFileEx)
    fcntl = None
else:
    import fcntl


class _PortableLock:
    """
    The writer lock where ``fcntl`` does not exist (Windows): :mod:`filelock`'s OS lock on the same lock file, with the
    ``close()`` of the file object the POSIX lock keeps (closing releases it, as closing a flock'ed file does).
    """

    def __init__(self, lock_name: str) -> None:
        from filelock import FileLock, Timeout

        self._lock = FileLock(lock_name, timeout=0, thread_local=False)
        try:
            self._lock.acquire()
        except Timeout:
            raise BlockingIOError(f"{lock_name} is held") from None

    def close(self) -> None:
        self._lock.release()


#: what an error about a damaged chunk adds
SALVAGE_HINT = (
    "`python -m sb3_lifelong.buffers verify {path}` lists every damaged chunk, and `python -m sb3_lifelong.buffers "
    "salvage {path} NEW_DIRECTORY` copies the intact ones into a new buffer (neither writes to this directory)"
)

#: what the store gives a layout's ``write``: the bytes of a field's rows ``lo:hi``, counted from the first pending row
BlockSource = Callable[[str, int, int], memoryview]


class Segment(NamedTuple):
    """Committed rows ``start:start + rows`` (global numbers) stored contiguously: each field's rows at a byte
    offset of a data file."""

    start: int
    rows: int
    places: dict[str, tuple[str, int]]  # field name -> (data file, byte offset of the segment's first row)


class LayoutState:
    """
    What a layout knows of its store: the directory, the fields (dtype, row shape and bytes of each), the chunk size,
    the capacity, whether the store writes, and the directory's writer lock. The store sets the fields once it knows
    them (given, or read from the manifest) and the capacity when it reads another one (reopening with a new
    capacity, a reader's refresh).

    :param path: The buffer directory (None in memory)
    :param chunk_size: Rows per flushed chunk
    :param capacity: The number of most recent rows kept (None: every row)
    :param read_only: Whether the store only reads (another process may be writing)
    """

    def __init__(self, path: Optional[str], chunk_size: int, capacity: Optional[int], read_only: bool) -> None:
        self.path = path
        self.chunk_size = chunk_size
        self.capacity = capacity
        self.read_only = read_only
        self.fields: dict[str, tuple[str, tuple[int, ...]]] = {}
        self.dtypes: dict[str, np.dtype] = {}
        self.shapes: dict[str, tuple[int, ...]] = {}
        self.row_bytes: dict[str, int] = {}
        #: the directory's writer lock while this store holds it (kept here: a layout read from the manifest replaces
        #: the one the store started with, and the lock goes on)
        self.lock_file: Optional[IO[str]] = None

    def set_fields(self, fields: Mapping[str, tuple[str, tuple[int, ...]]]) -> None:
        """:param fields: field name -> (dtype string, row shape), validated"""
        self.fields = dict(fields)
        self.dtypes = {name: np.dtype(dt) for name, (dt, _) in self.fields.items()}
        self.shapes = {name: shape for name, (_, shape) in self.fields.items()}
        self.row_bytes = {name: self.dtypes[name].itemsize * math.prod(shape) for name, shape in self.shapes.items()}

    def field_offsets(self, rows: int) -> dict[str, int]:
        """Byte offset of each field's block in a chunk file of ``rows`` rows, and ``""`` -> the file size."""
        offsets, offset = {}, 0
        for name in self.fields:
            offsets[name] = offset
            offset += rows * self.row_bytes[name]
        offsets[""] = offset
        return offsets


class Layout(Protocol):
    """
    Where a store's rows live. ``chunks`` and ``num_committed`` are always the store's committed state (the
    manifest's chunks, the global row after the last committed row) unless said otherwise.
    """

    #: "memory", "single" or "chunked" (the manifest's ``layout``)
    name: str
    #: whether the rows are written to a directory (False: in memory, where ``flush()`` has nothing to do)
    persistent: bool
    #: how many rows the store's array of pending rows holds at first
    tail_rows: int
    #: the number of pending rows that makes the store write them as chunks (never, in memory)
    flush_at: int

    def create(self) -> None:
        """Make the data files of a new, empty buffer."""

    def open_existing(self, chunks: list[dict[str, Any]], num_committed: int, verify: str) -> tuple[int, list[str]]:
        """Check the data files against the manifest just read (sizes, checksums); a writer cleans up after a crash.
        :return: the bytes of unflushed rows discarded, the unreferenced chunk files removed"""

    def chunk_damage(self, chunk: dict[str, Any]) -> Optional[str]:
        """:return: None when the rows of a committed chunk are all in their files with their checksums (read in blocks),
        else what is wrong (a missing, short or unreadable file, a checksum mismatch), naming the file"""

    def segments(self, chunks: list[dict[str, Any]], num_committed: int) -> list[Segment]:
        """:return: the committed rows as segments (where each field's rows are)"""

    def write(self, chunks: list[dict[str, Any]], base: int, block: BlockSource) -> None:
        """Write and fsync the rows of new ``chunks`` (not committed yet: the manifest does not name them) and record
        their checksums; ``base`` is the global row of the first pending row, ``block`` gives the rows' bytes."""

    def discard(self, chunks: list[dict[str, Any]], num_committed: int) -> None:
        """Give back the space of written ``chunks`` that were not committed (best effort)."""

    def retain(
        self, chunks: list[dict[str, Any]], num_committed: int, committed_first: int
    ) -> tuple[list[dict[str, Any]], int, list[str]]:
        """:param chunks: the chunks of a commit up to global row ``num_committed``; ``committed_first``: the oldest
        row retained before it. :return: the chunks the commit keeps, its first retained row, the files it drops (to
        delete once synced)"""

    def lock(self, create: bool = False) -> Optional[str]:
        """Take the directory's writer lock, unless held already (``create``: make a missing directory first, else a
        missing directory is not locked). :return: the directory locked by this call, or None"""

    def unlock(self) -> Optional[str]:
        """Release the writer lock. :return: the directory unlocked, or None if no lock was held"""

    def remove_buffer(self) -> None:
        """Delete the buffer the directory holds (``mode="overwrite"``, under the lock)."""

    def has_manifest(self) -> bool:
        """Whether there is a buffer to open (a manifest)."""

    def read_manifest(self, consistent: bool = False) -> dict[str, Any]:
        """:return: the validated manifest (``consistent``: one whose chunk files all exist, for readers)"""

    def refuse_orphans(self) -> None:
        """Raise ``BufferFormatError`` if the directory holds data files but no manifest (creating would overwrite
        them)."""

    def write_manifest(self, manifest: dict[str, Any]) -> None:
        """Replace the manifest atomically (the commit)."""

    def committed_on_disk(self, num_committed: int) -> Optional[bool]:
        """Whether the manifest in place commits the rows up to global row ``num_committed`` (None: unknown)."""

    def delete(self, file_names: list[str]) -> list[str]:
        """Delete files of chunks dropped by synced commits. :return: those that could not be deleted (kept)"""


class MemoryLayout:
    """
    Layout "memory": the rows stay in the store's array of pending rows, which grows (with a capacity, the evicted
    rows at its front are dropped by moving the retained ones down instead); nothing is committed, written, locked or
    checked, and there are no segments to read.
    """

    name = "memory"
    persistent = False
    flush_at = sys.maxsize  # never

    def __init__(self, state: LayoutState) -> None:
        self.state = state
        self.tail_rows = 1024 if state.capacity is None else min(1024, state.capacity)

    def create(self) -> None:
        pass

    def open_existing(self, chunks: list[dict[str, Any]], num_committed: int, verify: str) -> tuple[int, list[str]]:
        return 0, []

    def chunk_damage(self, chunk: dict[str, Any]) -> Optional[str]:
        return None

    def segments(self, chunks: list[dict[str, Any]], num_committed: int) -> list[Segment]:
        return []

    def write(self, chunks: list[dict[str, Any]], base: int, block: BlockSource) -> None:
        raise RuntimeError("an in-memory store writes no chunk")

    def discard(self, chunks: list[dict[str, Any]], num_committed: int) -> None:
        pass

    def retain(
        self, chunks: list[dict[str, Any]], num_committed: int, committed_first: int
    ) -> tuple[list[dict[str, Any]], int, list[str]]:
        return chunks, committed_first, []

    def lock(self, create: bool = False) -> Optional[str]:
        return None

    def unlock(self) -> Optional[str]:
        return None

    def remove_buffer(self) -> None:
        pass

    def has_manifest(self) -> bool:
        return False

    def read_manifest(self, consistent: bool = False) -> dict[str, Any]:
        raise FileNotFoundError("an in-memory store has no manifest")

    def refuse_orphans(self) -> None:
        pass

    def write_manifest(self, manifest: dict[str, Any]) -> None:
        pass

    def committed_on_disk(self, num_committed: int) -> Optional[bool]:
        return None

    def delete(self, file_names: list[str]) -> list[str]:
        return []


class _DirectoryLayout:
    """What the layouts of a directory share: its writer lock, its manifest, the deletion of dropped files."""

    persistent = True

    def __init__(self, state: LayoutState) -> None:
        if state.path is None:
            raise ValueError("a directory layout needs a path")
        self.state = state
        self.path: str = state.path
        self.tail_rows = self.flush_at = state.chunk_size

    def lock(self, create: bool = False) -> Optional[str]:
        if self.state.lock_file is not None:
            return None
        if create:
            os.makedirs(self.path, exist_ok=True)
        elif not os.path.isdir(self.path):
            return None
        lock_name = os.path.join(self.path, LOCK_NAME)
        if fcntl is None:
            if os.path.islink(lock_name):
                raise BufferFormatError(f"{lock_name} is a symbolic link, not this buffer's lock file: refusing to open it")
            try:
                self.state.lock_file = _PortableLock(lock_name)  # type: ignore[assignment]
            except BlockingIOError:
                raise RuntimeError(
                    f"{self.path} is open for writing by another buffer (process or object); open it with read_only=True"
                ) from None
            return self.path
        try:  # never through a symbolic link planted at its name (O_NOFOLLOW)
            lock_file = open(lock_name, "a+", opener=lambda name, flags: os.open(name, flags | files.NOFOLLOW, 0o666))
        except OSError as error:
            if os.path.islink(lock_name):
                raise BufferFormatError(
                    f"{lock_name} is a symbolic link, not this buffer's lock file: refusing to open the directory for "
                    "writing (a lock must be a file of the directory itself). Remove the link, or open it with read_only=True"
                ) from None
            raise files.explained(error, f"{self.path}: cannot open the writer lock {LOCK_NAME}") from error
        try:
            fcntl.flock(lock_file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock_file.close()
            raise RuntimeError(
                f"{self.path} is open for writing by another buffer (process or object); open it with read_only=True"
            ) from None
        self.state.lock_file = lock_file
        return self.path

    def unlock(self) -> Optional[str]:
        if self.state.lock_file is None:
            return None
        self.state.lock_file.close()
        self.state.lock_file = None
        return self.path

    def remove_buffer(self) -> None:
        if os.path.isdir(self.path):
            remove_buffer_files(self.path)

    def has_manifest(self) -> bool:
        return os.path.isfile(os.path.join(self.path, MANIFEST_NAME))

    def read_manifest(self, consistent: bool = False) -> dict[str, Any]:
        # readers: a manifest whose chunk files all exist (a writer deletes evicted chunks after a commit)
        for _ in range(20 if consistent else 1):
            manifest = read_manifest(self.path)
            if not consistent or manifest.get("layout") != "chunked":
                return manifest
            if all(os.path.isfile(os.path.join(self.path, chunk_file_name(c["start"]))) for c in manifest["chunks"]):
                return manifest
        return manifest  # opening it names the missing file

    def refuse_orphans(self) -> None:
        orphans = orphaned_data_files(self.path)
        if not orphans:
            return
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

    def write_manifest(self, manifest: dict[str, Any]) -> None:
        try:
            write_json_atomic(os.path.join(self.path, MANIFEST_NAME), manifest, fixed_temporary=True)
        except files.CommitNotDurableError as error:
            raise files.CommitNotDurableError(
                error.errno,
                f"{self.path}: the new {MANIFEST_NAME} is in place, so its {manifest['num_transitions']:,} transitions are "
                f"committed and readable, but the fsync of the directory failed ({error.strerror}): this commit may not "
                "survive a power loss or an operating-system crash (a crash of this process is fine). flush() (or "
                "close()) writes and syncs the manifest again; until then, files the previous manifest needs are kept",
            ) from error

    def committed_on_disk(self, num_committed: int) -> Optional[bool]:
        # this writer holds the lock: no other writer replaces the manifest
        committed = committed_transitions(self.path)
        return None if committed is None else committed >= num_committed

    def delete(self, file_names: list[str]) -> list[str]:
        if not file_names:
            return []
        kept = []
        for file_name in file_names:
            try:
                files.delete_file(file_name)
            except OSError:  # e.g. EIO: the rows are committed all the same; the next commit tries again
                kept.append(file_name)
        files.fsync_dir(self.path)
        return kept


class SingleFileLayout(_DirectoryLayout):
    """
    Layout "single": one append-only file per field, ``<field>.bin``, row ``i`` at byte ``i * row_bytes``. Every
    row is kept (no capacity), so the committed rows are one segment. A flush cuts each file back to its committed
    length (bytes after it are left by a failed flush or a crash) and appends the new chunks to it.
    """

    name = "single"

    def field_file(self, name: str) -> str:
        return os.path.join(self.path, name + ".bin")

    def create(self) -> None:
        os.makedirs(self.path, exist_ok=True)
        for name in self.state.fields:  # empty field files left by an interrupted creation are reused (cut to 0 bytes)
            os.close(files.open_for_writing(self.field_file(name), os.O_CREAT | os.O_TRUNC))

    def open_existing(self, chunks: list[dict[str, Any]], num_committed: int, verify: str) -> tuple[int, list[str]]:
        state, discarded = self.state, 0
        for name in state.fields:
            file_name = self.field_file(name)
            if not os.path.isfile(file_name) or os.path.islink(file_name):
                raise BufferFormatError(f"{self.path}: field file {name}.bin is missing or not a regular file")
        for name in state.fields:
            file_name, need = self.field_file(name), num_committed * state.row_bytes[name]
            have = os.path.getsize(file_name)
            if have < need:
                raise BufferFormatError(
                    f"{file_name}: {have} bytes but the manifest commits {num_committed} rows ({need} bytes); "
                    f"the file was truncated or replaced. {SALVAGE_HINT.format(path=self.path)}"
                )
            if have > need and not state.read_only:
                # an unflushed tail of a writer that died: cut it off so that appends continue at the committed end
                fd = files.open_for_writing(file_name)
                try:
                    os.ftruncate(fd, need)
                    os.fsync(fd)
                finally:
                    os.close(fd)
                discarded += have - need
        for chunk in checked_chunks(chunks, verify):
            damage = self.chunk_damage(chunk)
            if damage is not None:
                raise BufferFormatError(f"{damage} (corrupted data). {SALVAGE_HINT.format(path=self.path)}")
        return discarded, []

    def chunk_damage(self, chunk: dict[str, Any]) -> Optional[str]:
        """
        :param chunk: A chunk of the manifest
        :return: None when every field's rows of the chunk are in its file with their checksum, else what is wrong
        """
        for name in self.state.fields:
            file_name, size = self.field_file(name), chunk["rows"] * self.state.row_bytes[name]
            offset = chunk["start"] * self.state.row_bytes[name]
            try:
                if os.path.islink(file_name) or not os.path.isfile(file_name):
                    return f"{file_name}: field file is missing or not a regular file"
                crc = file_crc32(file_name, offset, size)
            except OSError as error:
                return f"{file_name}: cannot be read ({error.strerror or error})"
            if crc is None:
                return f"{file_name}: the file ends before the rows of the chunk starting at row {chunk['start']} (truncated)"
            if crc != chunk["crc32"][name]:
                return f"{file_name}: checksum mismatch in chunk starting at row {chunk['start']}"
        return None

    def segments(self, chunks: list[dict[str, Any]], num_committed: int) -> list[Segment]:
        if num_committed == 0:
            return []
        return [Segment(0, num_committed, {name: (self.field_file(name), 0) for name in self.state.fields})]

    def write(self, chunks: list[dict[str, Any]], base: int, block: BlockSource) -> None:
        for name in self.state.fields:
            committed_bytes = base * self.state.row_bytes[name]
            fd = files.open_for_writing(self.field_file(name))
            try:
                # bytes after the committed rows are left by a failed flush: cut them off so that this one writes the
                # same rows to the same place (the manifest's offsets)
                os.ftruncate(fd, committed_bytes)
                os.lseek(fd, committed_bytes, os.SEEK_SET)
                for chunk in chunks:
                    _write_field(fd, chunk, name, block(name, chunk["start"] - base, chunk["start"] - base + chunk["rows"]))
                os.fsync(fd)
            finally:
                os.close(fd)

    def discard(self, chunks: list[dict[str, Any]], num_committed: int) -> None:
        for name in self.state.fields:  # best effort: the bytes after the committed rows are ignored anyway
            try:
                fd = files.open_for_writing(self.field_file(name))  # not os.truncate(path): it follows links
                try:
                    os.ftruncate(fd, num_committed * self.state.row_bytes[name])
                finally:
                    os.close(fd)
            except OSError:
                pass

    def retain(
        self, chunks: list[dict[str, Any]], num_committed: int, committed_first: int
    ) -> tuple[list[dict[str, Any]], int, list[str]]:
        return chunks, committed_first, []


class ChunkFileLayout(_DirectoryLayout):
    """
    Layout "chunked": one file per flushed chunk, ``chunk.<start>.bin``, holding each field's rows one field after
    the other; each chunk is a segment. A commit keeps the last ``capacity`` committed rows: the files of the chunks
    with none of them are deleted once the manifest that drops them is synced.
    """

    name = "chunked"

    def chunk_file(self, chunk: dict[str, Any]) -> str:
        return os.path.join(self.path, chunk_file_name(chunk["start"]))

    def create(self) -> None:
        os.makedirs(self.path, exist_ok=True)
        self.remove_orphans([])  # empty chunk files (non-empty ones without a manifest are refused before)

    def open_existing(self, chunks: list[dict[str, Any]], num_committed: int, verify: str) -> tuple[int, list[str]]:
        for chunk in chunks:
            file_name = self.chunk_file(chunk)
            if not os.path.isfile(file_name) or os.path.islink(file_name):
                raise BufferFormatError(
                    f"{file_name}: chunk file is missing or not a regular file. {SALVAGE_HINT.format(path=self.path)}"
                )
            need = self.state.field_offsets(chunk["rows"])[""]
            have = os.path.getsize(file_name)
            if have != need:
                raise BufferFormatError(
                    f"{file_name}: {have} bytes but the manifest's chunk of {chunk['rows']} rows needs {need} bytes; "
                    f"the file was truncated or replaced. {SALVAGE_HINT.format(path=self.path)}"
                )
        for chunk in checked_chunks(chunks, verify):
            damage = self.chunk_damage(chunk)
            if damage is not None:
                raise BufferFormatError(f"{damage} (corrupted data). {SALVAGE_HINT.format(path=self.path)}")
        return (0, []) if self.state.read_only else self.remove_orphans(chunks)

    def chunk_damage(self, chunk: dict[str, Any]) -> Optional[str]:
        """
        :param chunk: A chunk of the manifest
        :return: None when its file holds every field's rows with their checksum (and nothing more), else what is wrong
        """
        file_name, offsets = self.chunk_file(chunk), self.state.field_offsets(chunk["rows"])
        try:
            if os.path.islink(file_name) or not os.path.isfile(file_name):
                return f"{file_name}: chunk file is missing or not a regular file"
            if os.path.getsize(file_name) != offsets[""]:
                return (
                    f"{file_name}: {os.path.getsize(file_name)} bytes but the manifest's chunk of {chunk['rows']} rows "
                    f"needs {offsets['']} bytes (truncated or replaced)"
                )
            names = list(self.state.fields)
            for k, name in enumerate(names):
                stop = offsets[names[k + 1]] if k + 1 < len(names) else offsets[""]
                if file_crc32(file_name, offsets[name], stop - offsets[name]) != chunk["crc32"][name]:
                    return f"{file_name}: checksum mismatch in field {name!r}"
        except OSError as error:
            return f"{file_name}: cannot be read ({error.strerror or error})"
        return None

    def remove_orphans(self, chunks: list[dict[str, Any]]) -> tuple[int, list[str]]:
        """Delete the chunk files the manifest does not list: evicted ones left by a crash after a commit, or the
        unflushed chunk of a crash before it (writer only). :return: the bytes and the names of the files deleted"""
        listed = {chunk_file_name(chunk["start"]) for chunk in chunks}
        discarded, removed = 0, []
        for entry in sorted(os.listdir(self.path)):
            if CHUNK_FILE_PATTERN.fullmatch(entry) and entry not in listed:
                file_name = os.path.join(self.path, entry)
                if os.path.islink(file_name) or not os.path.isfile(file_name):
                    continue
                discarded += os.path.getsize(file_name)
                files.delete_file(file_name)
                removed.append(entry)
        if removed:
            files.fsync_dir(self.path)
        return discarded, removed

    def segments(self, chunks: list[dict[str, Any]], num_committed: int) -> list[Segment]:
        segments = []
        for chunk in chunks:
            file_name, offsets = self.chunk_file(chunk), self.state.field_offsets(chunk["rows"])
            places = {name: (file_name, offsets[name]) for name in self.state.fields}
            segments.append(Segment(chunk["start"], chunk["rows"], places))
        return segments

    def write(self, chunks: list[dict[str, Any]], base: int, block: BlockSource) -> None:
        for chunk in chunks:
            # a new file: an unflushed chunk file of a crash, or a link planted at this name, is unlinked first
            fd = files.create_new_file(self.chunk_file(chunk))
            try:
                for name in self.state.fields:
                    _write_field(fd, chunk, name, block(name, chunk["start"] - base, chunk["start"] - base + chunk["rows"]))
                os.fsync(fd)
            finally:
                os.close(fd)
        files.fsync_dir(self.path, strict=True)  # the new files' entries are durable before a manifest names them

    def discard(self, chunks: list[dict[str, Any]], num_committed: int) -> None:
        for chunk in chunks:  # not committed: nothing refers to these files
            files.remove_quietly(self.chunk_file(chunk))

    def retain(
        self, chunks: list[dict[str, Any]], num_committed: int, committed_first: int
    ) -> tuple[list[dict[str, Any]], int, list[str]]:
        # the manifest keeps the last ``capacity`` committed rows (rows still pending do not evict on disk)
        if self.state.capacity is not None:
            committed_first = max(committed_first, num_committed - self.state.capacity)
        dropped = [chunk for chunk in chunks if chunk["start"] + chunk["rows"] <= committed_first]
        return chunks[len(dropped) :], committed_first, [self.chunk_file(chunk) for chunk in dropped]


_LAYOUTS: dict[str, Callable[[LayoutState], Layout]] = {
    "memory": MemoryLayout,
    "single": SingleFileLayout,
    "chunked": ChunkFileLayout,
}


def make_layout(name: str, state: LayoutState) -> Layout:
    """
    :param name: "memory", "single" or "chunked"
    :param state: What the layout knows of its store
    :return: The layout
    """
    return _LAYOUTS[name](state)


def _write_field(fd: int, chunk: dict[str, Any], name: str, data: memoryview) -> None:
    """Write the bytes of field ``name`` of ``chunk`` at the file offset of ``fd`` and record their CRC."""
    chunk["crc32"][name] = zlib.crc32(data)
    files.write_all(fd, data)


def file_crc32(file_name: str, offset: int, size: int, block: int = 1 << 22) -> Optional[int]:
    """
    :param file_name: A data file
    :param offset: The first byte
    :param size: How many bytes
    :param block: Bytes read at a time (the memory used, whatever ``size``)
    :return: The CRC-32 of the bytes ``offset:offset + size`` of the file, or None if it ends before
    """
    crc = 0
    with open(file_name, "rb") as file:
        file.seek(offset)
        left = size
        while left > 0:
            data = file.read(min(block, left))
            if not data:
                return None
            crc = zlib.crc32(data, crc)
            left -= len(data)
    return crc


def checked_chunks(chunks: list[dict[str, Any]], verify: str) -> list[dict[str, Any]]:
    """The chunks whose checksums ``verify`` ("all", "last" or "none") asks to check when opening."""
    return chunks if verify == "all" else chunks[-1:] if verify == "last" else []


# ---------------------------------------------------------------------------------------------- the files a directory owns


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
