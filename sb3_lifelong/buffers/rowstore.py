"""
The row store behind :class:`sb3_lifelong.buffers.LifelongReplayBuffer`: an append-only table of fixed-size rows,
in memory or in a crash-safe buffer directory, and its commit protocol.

The store's modules import only numpy, the standard library and one another (never torch), so that crash tests and
tools can load them in light subprocesses:

- ``files``: writing every byte, fsync, files never opened through a link, the atomic JSON write;
- ``manifest``: the directory format, reading, validating and making the manifest;
- ``layouts``: where the rows live (``"memory"``, ``"single"``, ``"chunked"``), the data files and the writer lock;
- ``readers``: how committed rows are read (``"mmap"``, ``"pread"``);
- ``writers``: the directories this process holds open for writing, and what a forked child may not do;
- ``rowstore`` (this module): :class:`RowStore`, the commit protocol over a layout and a reader.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, Optional

import numpy as np

from sb3_lifelong.buffers import files, writers
from sb3_lifelong.buffers.layouts import Layout, LayoutState, check_buffer_path, make_layout
from sb3_lifelong.buffers.manifest import (
    BufferFormatError,
    ManifestRecords,
    buffer_id_of,
    make_manifest,
    new_buffer_id,
    validate_fields,
    validated_fields,
)
from sb3_lifelong.buffers.readers import Reader, check_read_mode, make_reader
from sb3_lifelong.buffers.writers import ForkedWriterError

#: the most bytes a directory writer allocates for its pending rows when it opens (they grow up to a chunk as needed)
TAIL_PREALLOCATION = 64 * 1024 * 1024


class RowStore(ManifestRecords):
    """
    Append-only table of fixed-size rows (one array per field), in memory or in a buffer directory, optionally
    keeping only the most recent ``capacity`` rows.

    Rows have global numbers (0 for the first row ever appended); indices given to :meth:`gather` and
    :meth:`read_range` count from the oldest retained row (:attr:`first`).

    Rows are committed or pending. With a path, committed rows are read from the files (memory-mapped, or with
    positioned reads, see ``read_mode``) and the unflushed rows wait in a tail of ``chunk_size`` pending rows, written
    out (appended, fsync'd, manifest replaced atomically) when full or on ``flush()``. Without a capacity the
    directory has one append-only file per field (layout "single"); with one, a file per chunk (layout "chunked"),
    deleted once the committed manifest no longer lists it. In memory (``path=None``, layout "memory") nothing is
    ever committed: the pending rows are the storage, preallocated arrays that double when full (with a capacity,
    the evicted rows at their front are dropped by moving the retained ones down instead).

    The store keeps the commit protocol (pending rows, manifest, eviction, recovery); two small strategies do the
    rest: the layout (a :class:`~sb3_lifelong.buffers.layouts.Layout`) creates, checks, writes and describes the data
    files as segments of committed rows and keeps the directory's lock and manifest, and the read mode's reader (a
    :class:`~sb3_lifelong.buffers.readers.Reader`) reads rows from those segments.

    Besides the rows, the store owns what its manifest records about them (a
    :class:`~sb3_lifelong.buffers.manifest.ManifestRecords`): the stream ids (:meth:`reserve_streams`), the source
    table (:meth:`source`, :meth:`set_source`, :meth:`source_table`) and the description of the spaces
    (:meth:`describe_spaces`), saved with the next commit; :attr:`fields`, :attr:`dtypes`, :attr:`spaces` and
    :attr:`next_stream_id` are read-only.

    :param fields: field name -> (dtype string, row shape)
    :param path: Buffer directory, or None for an in-memory store
    :param read_only: Open an existing directory without writing (another process may be writing)
    :param chunk_size: Rows per flushed chunk
    :param verify: Checksums to verify when opening: "all", "last" (only the last chunk: corrupted bytes in an
        earlier chunk are not detected and are served as they are) or "none"
    :param max_resident_bytes: Replaced by ``read_mode="pread"``: a value other than None reads with positioned reads
        (``FutureWarning``), see :func:`~sb3_lifelong.buffers.readers.check_read_mode`
    :param capacity: Keep only the most recent ``capacity`` rows (None: keep everything). For an existing
        directory, None keeps its stored capacity
    :param read_mode: How committed rows are read: ``"mmap"`` (memory maps: fastest when the rows sampled are
        mapped already, but every page touched counts in this process's RSS) or ``"pread"`` (positioned reads
        into fresh arrays, one call per run of nearby rows: no file page is mapped, the RSS stays at the anonymous
        memory; one file descriptor per field file or chunk file, closed by :meth:`close`). No effect in memory
    :param overwrite: Writers: delete the buffer the directory holds first
        (:func:`~sb3_lifelong.buffers.layouts.remove_buffer_files`), once this store holds the directory's writer lock
        (a live writer makes this raise before anything is deleted); a directory whose manifest is not one of this
        package's buffers is refused (``BufferFormatError``)
    :param evict: Reopening a directory with a capacity smaller than the number of transitions it retains evicts the
        oldest of them at once: only with ``evict=True``; otherwise that raises ``ValueError`` and nothing changes
    :param allow_foreign_files: Writers: create a buffer in a directory that holds other files (no manifest) all the
        same; by default that raises ``FileExistsError`` naming some of them (see
        :func:`~sb3_lifelong.buffers.layouts.check_buffer_path`), and a ``path`` that is a file ``NotADirectoryError``,
        before anything is written
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
        allow_foreign_files: bool = False,
    ) -> None:
        read_mode = check_read_mode(read_mode, max_resident_bytes)
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
        if self.path is not None:  # before anything is written there (the writer lock is a file of the directory)
            check_buffer_path(self.path, allow_foreign_files, writing=not read_only)
        self.read_only = read_only
        self.chunk_size = chunk_size
        self._state = LayoutState(self.path, chunk_size, None if capacity is None else int(capacity), read_only)
        # the layout of a new store; an existing directory's is the one its manifest names
        self._layout: Layout = make_layout(
            "memory" if self.path is None else "single" if capacity is None else "chunked", self._state
        )
        super().__init__()  # the manifest's records: stream ids, sources, spaces
        self.chunks: list[dict[str, Any]] = []
        self.num_committed = 0  # global row after the last committed row
        self.committed_first = 0  # global row of the oldest retained committed row (the manifest's first_row)
        self.recovered = 0
        self.discarded_bytes = 0
        self.removed_files: list[str] = []  # chunk files found unreferenced (and deleted) when opening
        self._tail_start = 0  # global row of the tail's first row (the first pending row)
        self._closed = False
        # chunk files dropped by a commit whose directory fsync failed: deleted once a later manifest is synced (the
        # previous manifest, which lists them, may be the one a power loss leaves)
        self._undeleted: list[str] = []
        self.read_mode = read_mode
        #: the process that opened this writer: only it may write, commit or release the directory (see
        #: :class:`ForkedWriterError`); None for stores that never write a directory (in memory, read-only)
        self._owner_pid: Optional[int] = None if self.path is None or read_only else os.getpid()
        if not read_only:
            # the writer lock first, then everything else: a manifest read before taking it could be replaced by a
            # writer that commits and closes in between, and this writer would then cut that writer's rows off
            self._take_lock()
        try:
            if overwrite and not read_only:
                self._layout.remove_buffer()  # under the lock: a live writer was refused above
            self._open_or_create(fields, capacity, verify, evict)
        except BaseException:
            self.abandon()  # a store that failed to open writes nothing, now or when it is collected
            raise
        self._tail_start = self.num_committed
        rows = self._first_tail_rows()
        self._tail = {name: np.empty((rows, *shape), dtype=self._dtypes[name]) for name, (_, shape) in self._fields.items()}
        self.num_tail = 0
        self._reader_stale = False  # True while the maps (or read files) may not cover every committed row
        if self.layout == "chunked" and not read_only:
            try:
                self._commit(self.chunks, self.num_committed)  # a smaller capacity than the stored one evicts now; maps
            except BaseException:
                self.abandon()
                raise
        else:
            self._sync_maps()
        self.recovered = len(self)
        if self.discarded_bytes:
            removed = f" ({len(self.removed_files)} unreferenced chunk files removed)" if self.removed_files else ""
            warnings.warn(
                f"{self.path}: recovered {self.recovered} transitions; discarded {self.discarded_bytes} bytes of "
                f"unflushed rows left by a writer that did not close the buffer{removed}"
            )

    def _first_tail_rows(self) -> int:
        """
        How many pending rows the store's arrays hold at first: none for a reader (it never appends), a whole chunk for
        a directory writer when that takes at most :data:`TAIL_PREALLOCATION` bytes (else fewer: they grow up to a
        chunk as rows come, so that opening a directory never allocates more than that), the layout's default in memory.
        """
        if self.read_only:
            return 0
        rows = self._layout.tail_rows
        if self._layout.persistent:
            rows = min(rows, max(1, TAIL_PREALLOCATION // max(1, sum(self.row_bytes.values()))))
        return rows

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
        if self._layout.has_manifest():
            manifest = self._layout.read_manifest(consistent=self.read_only)
            stored = validate_fields(manifest["fields"])
            if fields is not None and dict(fields) != stored:
                raise ValueError(f"{self.path}: stored fields {stored} do not match the requested {fields}")
            layout = manifest.get("layout", "single")
            stored_capacity = manifest.get("capacity")
            if capacity is not None and capacity != stored_capacity:
                if layout == "single":
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
            self._state.capacity = stored_capacity if capacity is None else int(capacity)
            self._layout = make_layout(layout, self._state)
            self._load_manifest(manifest)
            self._set_row_format(stored)
            self.discarded_bytes, self.removed_files = self._layout.open_existing(self.chunks, self.num_committed, verify)
        else:
            self._layout.refuse_orphans()  # data files without a manifest would be overwritten
            if fields is None:
                raise FileNotFoundError(f"no buffer at {self.path!r} and no field specification to create one")
            if self.read_only:
                raise FileNotFoundError(f"no buffer at {self.path!r} to open read-only")
            self._set_row_format(validated_fields(fields))
            if self._take_lock(create=True):
                # the directory did not exist: it is created and locked now; look again (another writer may have
                # created the buffer meanwhile)
                self._open_or_create(fields, capacity, verify, evict)
                return
            self._layout.create()
            if self._layout.persistent:  # the new buffer's identity (a buffer created again here gets another)
                self._buffer_id = new_buffer_id()
            self._write_manifest()

    # ------------------------------------------------------------------ positions
    @property
    def end(self) -> int:
        """Global row after the last stored row (committed or not)."""
        return self._tail_start + self.num_tail

    @property
    def first(self) -> int:
        """Global row of the oldest retained row (index 0 of :meth:`gather` and :meth:`read_range`)."""
        # the oldest committed row if one is retained, else (always in memory, where none is) the first pending row
        low = self.committed_first if self.committed_first < self.num_committed else self._tail_start
        capacity = self._state.capacity
        if capacity is None:
            return low
        return max(low, self._tail_start + self.num_tail - capacity)

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

    @property
    def layout(self) -> str:
        """Where the rows live: ``"memory"``, ``"single"`` (one file per field) or ``"chunked"`` (one file per chunk)."""
        return self._layout.name

    @property
    def capacity(self) -> Optional[int]:
        """The number of most recent rows kept, or None when every row is kept."""
        return self._state.capacity

    # ------------------------------------------------------------------ opening / recovery
    def _set_row_format(self, fields: dict[str, tuple[str, tuple[int, ...]]]) -> None:
        """The fields (validated), their dtypes and row sizes, and the reader of the committed rows."""
        self._state.set_fields(fields)
        self._fields = self._state.fields
        self._dtypes = self._state.dtypes
        self.row_bytes = self._state.row_bytes
        self._reader: Reader = make_reader(self.read_mode, self._dtypes, self._state.shapes)

    def _load_manifest(self, manifest: dict[str, Any]) -> None:
        self.chunks = manifest["chunks"]
        self.num_committed = manifest["num_transitions"]
        self.committed_first = manifest.get("first_row", 0)
        self._load_records(manifest)

    def forked(self) -> bool:
        """Whether this is a writer's copy in a process other than the one that opened it (a child of ``os.fork()``):
        such a copy may read, never write (:class:`ForkedWriterError`)."""
        owner = getattr(self, "_owner_pid", None)
        return owner is not None and owner != os.getpid()

    def check_owner(self, action: str) -> None:
        """
        :param action: What is about to be done (``"add"``, ``"flush"``, ``"close"``, ``"commit"``...), for the message
        :raises ForkedWriterError: this writer was opened by another process (this one is a child of ``os.fork()``)
        """
        if self._owner_pid is not None and self._owner_pid != os.getpid():
            raise ForkedWriterError(
                f"{self.path}: {action}() refused in process {os.getpid()}: this buffer was opened for writing by "
                f"process {self._owner_pid}, and this process is a fork of it, holding a copy of its writer. Writes of a "
                "copy would be overwritten by the parent's next commit, and would commit the parent's pending rows: "
                "only the parent writes (and closes) this directory. Reading and sampling here work; to write from a "
                "child, let the parent close the buffer first and open it again in the child, or use another directory. "
                "Nothing was written"
            )

    def _take_lock(self, create: bool = False) -> bool:
        """Take the directory's writer lock (see ``Layout.lock``). :return: whether this call took it"""
        locked = self._layout.lock(create)
        if locked is None:
            return False
        writers.register(locked, self)
        return True

    def _release_lock(self) -> None:
        if self.forked():
            return  # a writer's lock is released only by the process that took it
        unlocked = self._layout.unlock()
        if unlocked is not None:
            writers.forget(unlocked, self)

    def refresh(self) -> int:
        """
        Read-only stores: re-read the manifest to see the rows a writer committed (and evicted) since.

        :return: The number of retained committed rows
        :raises BufferFormatError: the directory now holds another buffer (its manifest records another id: deleted and
            created again), or its rows or fields went back (buffers without an id: only these can be told)
        """
        if not self.read_only:
            return len(self)
        manifest = self._layout.read_manifest(consistent=True)
        found = buffer_id_of(manifest)
        if found != self._buffer_id:
            now, opened = found or "none recorded", self._buffer_id or "none recorded"
            raise BufferFormatError(
                f"{self.path} now holds another buffer (its id is {now}; this reader opened id {opened}): it was deleted "
                "and created again while open, so its rows are not the ones read so far. Refusing to refresh rather than "
                "serve old and new rows together; open it again to read the new buffer"
            )
        if validate_fields(manifest["fields"]) != self._fields or manifest.get("layout", "single") != self.layout:
            raise BufferFormatError(f"{self.path}: fields or layout changed while open")
        if manifest["num_transitions"] < self.num_committed or manifest.get("first_row", 0) < self.committed_first:
            raise BufferFormatError(
                f"{self.path}: committed rows went down from {self.num_committed} to {manifest['num_transitions']}: the "
                "buffer was replaced or cut back while open; open it again to read what it holds now"
            )
        changed = manifest["num_transitions"] != self.num_committed or manifest.get("first_row", 0) != self.committed_first
        self._state.capacity = manifest.get("capacity")
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
        self.check_owner("append")
        if self._closed:
            raise RuntimeError("buffer is closed (or was handed over to a buffer unpickled from it)")
        count = len(rows["rewards"])
        tail = self._tail
        stop = self.num_tail + count
        flush_at = self._layout.flush_at
        if stop <= len(tail["rewards"]) and stop < flush_at:
            # fast path of add(): no growth, no flush
            for name in self._fields:
                tail[name][self.num_tail : stop] = rows[name]
            self.num_tail = stop
            return
        if stop < flush_at:  # the rows stay pending (in memory, where they are the storage): make room for them
            self._extend_tail(rows, count)
            return
        keep = stop % self.chunk_size  # rows of this call left pending
        committed_before = self.num_committed
        try:
            self._write_chunks(rows, count - keep)
        except BaseException as error:
            if self.num_committed == committed_before:  # nothing of this call is stored
                if isinstance(error, OSError):
                    raise files.explained(
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
        if keep > len(self._tail["rewards"]):
            self._grow(min(max(keep, 2 * len(self._tail["rewards"])), self.chunk_size))
        for name in self._fields:
            self._tail[name][:keep] = rows[name][count - keep : count]
        self.num_tail = keep

    def _extend_tail(self, rows: dict[str, np.ndarray], count: int) -> None:
        """Append rows to the pending rows, growing (or compacting) their arrays as needed."""
        done = 0
        while done < count:
            if self.num_tail == len(self._tail["rewards"]):
                self._make_room(count - done)
            take = min(len(self._tail["rewards"]) - self.num_tail, count - done)
            for name in self._fields:
                self._tail[name][self.num_tail : self.num_tail + take] = rows[name][done : done + take]
            self.num_tail += take
            done += take

    def _make_room(self, need: int) -> None:
        """The arrays of pending rows are full: drop the evicted rows at their front (if that frees enough), else grow."""
        persistent = self._layout.persistent
        evicted = self.first - self._tail_start
        # in memory only: the pending rows of a directory start at the committed end, evicted or not, until the commit
        if not persistent and evicted > 0 and evicted >= len(self._tail["rewards"]) // 4:
            for name in self._fields:
                self._tail[name][: self.num_tail - evicted] = self._tail[name][evicted : self.num_tail]
            self._tail_start += evicted
            self.num_tail -= evicted
            return
        target = max(2 * self.num_tail, self.num_tail + need)
        if persistent:  # the pending rows of a directory never reach a chunk (the add that completes one writes it)
            target = max(min(target, self.chunk_size), self.num_tail + need)
        elif self.capacity is not None:  # twice the capacity is enough to compact rarely
            target = max(min(target, 2 * self.capacity), self.num_tail + min(need, self.capacity), self.num_tail + 1)
        self._grow(target)

    def _grow(self, rows: int) -> None:
        for name in self._fields:
            new = np.empty((rows, *self._tail[name].shape[1:]), dtype=self._tail[name].dtype)
            new[: self.num_tail] = self._tail[name][: self.num_tail]
            self._tail[name] = new

    def clear(self) -> None:
        """Forget every row of an in-memory store."""
        if self._layout.persistent:
            raise RuntimeError("a directory store cannot be cleared")
        self.num_tail = 0
        self._tail_start = 0

    def flush(self) -> None:
        """
        Write the pending rows as one chunk: the field files (layout "single": each cut back to its committed length
        first, then appended to) or the chunk file (layout "chunked") are written and fsync'd, then the manifest is
        replaced atomically, then the files of evicted chunks are deleted. In memory, there is nothing to write.

        Only once the new manifest is in place does this object count the rows as committed. If anything fails
        before (e.g. ``OSError`` ENOSPC, disk full), it raises with the committed state (on disk and in memory)
        unchanged and the rows still pending in memory, readable and sampled as before: calling ``flush()`` again
        (e.g. after freeing space) writes the same bytes to the same places and commits them. If only the fsync of
        the directory after the manifest's rename fails, it raises :class:`CommitNotDurableError` with the rows
        committed (the manifest is in place); calling ``flush()`` again writes and syncs the manifest again.
        """
        if self.read_only or not self._layout.persistent:
            return
        self.check_owner("flush")
        if self._closed:
            return
        if self.num_tail == 0:
            self._write_manifest()  # source names may have changed; a commit whose directory sync failed is synced
            self._delete_undeleted()
            return
        try:
            self._write_chunks()
        except files.CommitNotDurableError:
            raise
        except OSError as error:
            raise files.explained(
                error,
                f"{self.path}: flush() failed before the commit: the {self.num_tail:,} pending transitions stay in memory "
                "(read and sampled as before) and the manifest is unchanged. flush() again once the cause is fixed "
                "(e.g. space freed)",
            ) from error

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
        return block.data.cast("B")

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
        self.check_owner("commit")
        base, total = self.num_committed, self.num_tail + extra_rows
        bounds = [*range(0, total, self.chunk_size), total]
        chunks: list[dict[str, Any]] = [
            {"start": base + lo, "rows": hi - lo, "crc32": {}} for lo, hi in zip(bounds[:-1], bounds[1:])
        ]
        try:
            self._layout.write(chunks, base, lambda name, lo, hi: self._block(name, lo, hi, extra))
            self._commit([*self.chunks, *chunks], base + total)
        except BaseException:
            if self.num_committed == base and self._layout.committed_on_disk(base + total) is False:
                self._layout.discard(chunks, self.num_committed)  # not committed: give the space back (best effort)
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
        chunks, committed_first, dropped = self._layout.retain(chunks, num_committed, self.committed_first)
        try:
            self._write_manifest(chunks, num_committed, committed_first)
        except files.CommitNotDurableError:
            self._adopt_commit(chunks, committed_first, num_committed, dropped, synced=False)
            raise
        except BaseException:
            # e.g. KeyboardInterrupt during the directory's fsync: the new manifest may be in place all the same,
            # and then its rows are committed; the pending rows must not be discarded as if they were not
            if num_committed > self.num_committed and self._layout.committed_on_disk(num_committed):
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

    def _delete_undeleted(self) -> None:
        """Delete the files of chunks dropped by commits, once the manifest in place (which does not list them) is
        synced; those that cannot be deleted now (e.g. EIO) are tried again at the next commit."""
        self._undeleted = self._layout.delete(self._undeleted)

    def _sync_maps(self) -> None:
        """
        Let the reader follow the committed rows after a commit or a refresh: map the new segments (or, with
        ``read_mode="pread"``, open their files) and drop those no longer committed.
        """
        self._reader_stale = True
        self._reader.sync(self._layout.segments(self.chunks, self.num_committed), eager=not self._closed)
        self._reader_stale = False

    def _write_manifest(
        self,
        chunks: Optional[list[dict[str, Any]]] = None,
        num_committed: Optional[int] = None,
        committed_first: Optional[int] = None,
    ) -> None:
        """Atomically replace the manifest: the committed state of this object, or the one given."""
        self.check_owner("commit")
        manifest = make_manifest(
            self._fields,
            self.layout,
            self.capacity,
            num_transitions=self.num_committed if num_committed is None else num_committed,
            first_row=self.committed_first if committed_first is None else committed_first,
            chunks=self.chunks if chunks is None else chunks,
            sources=self._sources,
            next_stream_id=self._next_stream_id,
            spaces=self._spaces,
            buffer_id=self._buffer_id,
        )
        self._layout.write_manifest(manifest)

    def __getstate__(self) -> dict[str, Any]:
        if not self._layout.persistent:  # in memory: the rows themselves
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
            "read_mode": self.read_mode,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        if "_fields" in state:  # in memory
            self.__dict__.update(state)
            return
        previous = writers.writer_of(state["path"])
        if previous is not None and not state["read_only"] and not previous.forked():
            # e.g. SB3's load() built a buffer on this directory before load_replay_buffer(): hand it over
            previous.close()
        try:
            self._reopen(state)
        except RuntimeError:
            warnings.warn(f"{state['path']} is locked by another writer: the unpickled buffer is opened read-only")
            self._reopen(dict(state, read_only=True))

    def _reopen(self, state: dict[str, Any]) -> None:
        """Unpickling a directory store: open its directory (``state``: what :meth:`__getstate__` recorded)."""
        RowStore.__init__(
            self,
            path=state["path"],
            read_only=state["read_only"],
            chunk_size=state["chunk_size"],
            max_resident_bytes=state.get("max_resident_bytes"),  # pickled by earlier releases (None, or "pread")
            read_mode=state["read_mode"],
        )

    def __del__(self) -> None:
        if getattr(self, "_owner_pid", None) not in (None, os.getpid()):
            return  # a fork's copy of a writer: its exit (garbage collection, interpreter shutdown) writes nothing
        try:
            self.close()
        except Exception:  # pragma: no cover (interpreter shutdown)
            pass

    def close(self) -> None:
        """
        Flush, release the writer lock and close the read file descriptors (``read_mode="pread"``). Reading the
        committed rows keeps working (with ``"pread"`` it opens the files again, until the next ``close()``).

        In a child of ``os.fork()`` holding a copy of a writer, this flushes nothing and leaves the lock to the parent:
        the copy is marked closed and :class:`ForkedWriterError` is raised (once).
        """
        refuse = False
        if self.forked():
            refuse, self._closed = not self._closed, True  # nothing flushed, the lock left to the parent
        elif not getattr(self, "_closed", True):
            self.flush()
            self._closed = True
            self._release_lock()
        reader = getattr(self, "_reader", None)
        if reader is not None:
            reader.close()
        if refuse:
            self.check_owner("close")

    def abandon(self) -> None:
        """Close without writing anything (not even the manifest) and release the writer lock: what a constructor does
        when it refuses the directory it opened (pending rows, if any, are dropped)."""
        if not getattr(self, "_closed", True) and not self.forked():
            self._closed = True
            self._release_lock()
        self._closed = True
        reader = getattr(self, "_reader", None)
        if reader is not None:
            reader.close()

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
        if self.num_committed == 0 or (len(rows) and rows.min() >= committed):
            local = rows - committed if committed else rows
            return {name: self._tail[name][local] for name in names}
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
        if lo < committed:  # committed rows (never in memory, where every retained row is pending)
            pieces.extend(self._reader.pieces(name, lo, min(hi, committed)))
        if hi > committed:
            pieces.append(self._tail[name][max(lo, committed) - committed : hi - committed])
        if len(pieces) == 1:
            return pieces[0]
        if not pieces:
            return self._tail[name][:0]
        return np.concatenate(pieces)
