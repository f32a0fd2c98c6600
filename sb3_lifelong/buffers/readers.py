"""
How a directory store reads its committed rows (``read_mode``): memory maps (``"mmap"``, the default) or positioned
reads (``"pread"``: ``os.pread`` / ``os.preadv`` on file descriptors kept open, so that no page of the files is ever
mapped into the process). A reader reads the segments of committed rows a layout describes (``layouts.Segment``).
"""

from __future__ import annotations

import math
import mmap
import os
import warnings
from collections.abc import Mapping
from typing import Any, Optional, Protocol, Union

import numpy as np

from sb3_lifelong.buffers.layouts import Segment
from sb3_lifelong.buffers.manifest import BufferFormatError

# how committed rows are read: memory maps, or positioned reads into this process's memory
READ_MODES = ("mmap", "pread")
# read_mode "pread": rows of a field at most this many bytes apart are read with one call, gap included (adjacent
# rows always are). Measured on 1M-2M rows of 240 bytes: 0 to 8 KiB within noise of each other, 16 KiB and more slower
PREAD_MERGE_GAP = 4096


def check_read_mode(read_mode: Any, max_resident_bytes: Optional[int] = None) -> str:
    """
    :param read_mode: How committed rows are read: ``"mmap"`` or ``"pread"``
    :param max_resident_bytes: The remap limit of earlier releases (``read_mode="mmap"`` only): replaced by
        ``read_mode="pread"``, the one way to bound the RSS; any value but None maps onto it, with a ``FutureWarning``
    :return: The read mode
    :raises ValueError: for another value, or for ``"pread"`` where the OS has no ``pread``
    """
    if not isinstance(read_mode, str) or read_mode not in READ_MODES:
        raise ValueError(f"read_mode must be one of {list(READ_MODES)}, got {read_mode!r}")
    if max_resident_bytes is not None:
        warnings.warn(
            f"max_resident_bytes={max_resident_bytes!r} is replaced by read_mode='pread', which reads rows with positioned "
            "reads and maps no file page, so the RSS stays at the process's own memory: reading with read_mode='pread'. "
            "Pass read_mode='pread' (and no max_resident_bytes) instead",
            FutureWarning,
            stacklevel=4,
        )
        read_mode = "pread"
    if read_mode == "pread" and not hasattr(os, "pread"):  # pragma: no cover (Windows)
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


class _RowFormat:
    """What a reader needs to know of the rows: dtype and shape of each field."""

    def __init__(self, dtypes: Mapping[str, np.dtype], shapes: Mapping[str, tuple[int, ...]]) -> None:
        self.dtypes = dict(dtypes)
        self.shapes = dict(shapes)
        self.row_bytes = {name: self.dtypes[name].itemsize * math.prod(shape) for name, shape in self.shapes.items()}

    def empty(self, names: tuple[str, ...], rows: int = 0) -> dict[str, np.ndarray]:
        return {name: np.empty((rows, *self.shapes[name]), dtype=self.dtypes[name]) for name in names}


class Reader(Protocol):
    """How a directory store reads its committed rows (``read_mode``): memory maps or positioned reads."""

    def sync(self, segments: list[Segment], fresh: bool = False, eager: bool = True) -> None:
        """Follow the committed segments after a commit, an eviction or a refresh."""

    def gather(self, names: tuple[str, ...], rows: np.ndarray) -> dict[str, np.ndarray]:
        """:return: the given global rows of the given fields (copies)"""

    def pieces(self, name: str, lo: int, hi: int) -> list[np.ndarray]:
        """:return: the global rows ``lo:hi`` of a field, one array per segment touched"""

    def close(self) -> None:
        """Release what the reader holds open (the next read opens it again)."""


class MappedReader(_RowFormat):
    """
    ``read_mode="mmap"``: each segment's data files are memory-mapped read-only, its fields are arrays over the
    maps. A sync maps the new segments and keeps the maps of those unchanged; ``fresh=True`` maps everything again.

    :param dtypes: field name -> dtype of its rows
    :param shapes: field name -> shape of its rows
    """

    def __init__(self, dtypes: Mapping[str, np.dtype], shapes: Mapping[str, tuple[int, ...]]) -> None:
        super().__init__(dtypes, shapes)
        self._segments: list[Segment] = []
        self._arrays: list[dict[str, np.ndarray]] = []  # one dict per segment: field -> its committed rows
        self._starts = np.zeros(0, dtype=np.int64)

    def sync(self, segments: list[Segment], fresh: bool = False, eager: bool = True) -> None:
        known = {} if fresh else {(s.start, s.rows): arrays for s, arrays in zip(self._segments, self._arrays)}
        self._arrays = [known.get((s.start, s.rows)) or self._map(s) for s in segments]
        self._segments = list(segments)
        self._starts = np.array([s.start for s in segments], dtype=np.int64)

    def _map(self, segment: Segment) -> dict[str, np.ndarray]:
        lengths: dict[str, int] = {}
        for name, (file_name, offset) in segment.places.items():
            lengths[file_name] = max(lengths.get(file_name, 0), offset + segment.rows * self.row_bytes[name])
        maps = {file_name: _map_file(file_name, length) for file_name, length in lengths.items()}
        arrays = {}
        for name, (file_name, offset) in segment.places.items():
            count = segment.rows * math.prod(self.shapes[name])
            array = np.frombuffer(maps[file_name], dtype=self.dtypes[name], count=count, offset=offset)
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


class PositionedReader(_RowFormat):
    """
    ``read_mode="pread"``: the data files of the committed segments are kept open and rows are read with
    positioned reads into fresh arrays (one call per run of nearby rows): no page of the files is mapped. Closing
    closes the files; the next read opens them again.
    """

    def __init__(self, dtypes: Mapping[str, np.dtype], shapes: Mapping[str, tuple[int, ...]]) -> None:
        super().__init__(dtypes, shapes)
        self.fds: dict[str, int] = {}  # open descriptors by file name
        self._segments: list[Segment] = []
        # per field: the descriptor and byte offset of each segment; None: closed (to open at the next read)
        self._table: Optional[dict[str, tuple[list[int], np.ndarray]]] = None
        self._starts = np.zeros(0, dtype=np.int64)

    def sync(self, segments: list[Segment], fresh: bool = False, eager: bool = True) -> None:
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
        view = out.reshape(-1).view(np.uint8).data
        for k, segment in enumerate(self._segments):
            a, b = max(lo, segment.start), min(hi, segment.start + segment.rows)
            if a < b:
                _read_into(fds[k], view[(a - lo) * size : (b - lo) * size], int(bases[k]) + (a - segment.start) * size)
        return [out]


def make_reader(
    read_mode: str,
    dtypes: Mapping[str, np.dtype],
    shapes: Mapping[str, tuple[int, ...]],
) -> Reader:
    """
    :param read_mode: ``"mmap"`` or ``"pread"`` (see :func:`check_read_mode`)
    :param dtypes: field name -> dtype of its rows
    :param shapes: field name -> shape of its rows
    :return: A reader of those fields, following no segment yet
    """
    if read_mode == "pread":
        return PositionedReader(dtypes, shapes)
    return MappedReader(dtypes, shapes)


def _map_file(file_name: str, length: int) -> Union[mmap.mmap, bytes]:
    """A read-only map of the first ``length`` bytes of a file (no bytes for none), advised for random reads."""
    if length == 0:  # (a segment has rows, and a row bytes: not in practice)
        return b""
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
