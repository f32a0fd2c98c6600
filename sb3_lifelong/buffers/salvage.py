"""
Checking a buffer directory chunk by chunk, and copying the intact chunks of a damaged one into a new directory.

Opening a directory is strict: one damaged chunk (a checksum mismatch, a truncated or missing file) makes it raise
``BufferFormatError`` (with ``verify="all"``; ``verify="last"``, the default, checks only the last chunk's checksums).
:func:`check_buffer` reads every chunk and reports each damaged one, and :func:`salvage_buffer` copies the rows of the
intact ones into a new buffer directory. Neither ever writes to the directory it checks (no lock file, no manifest,
no deletion): the damaged original stays as it is, for other tools or a backup.

From a shell: ``python -m sb3_lifelong.buffers verify PATH`` and ``python -m sb3_lifelong.buffers salvage PATH NEW``.

Like the row store's modules, this one imports only numpy, the standard library and the row store.
"""

from __future__ import annotations

import os
import zlib
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from sb3_lifelong.buffers.layouts import Layout, LayoutState, make_layout
from sb3_lifelong.buffers.manifest import MANIFEST_NAME, BufferFormatError, read_manifest, validate_fields
from sb3_lifelong.buffers.rowstore import RowStore

__all__ = ["BufferCheck", "ChunkCheck", "check_buffer", "salvage_buffer"]


@dataclass
class ChunkCheck:
    """One committed chunk of a buffer directory, checked."""

    #: global row of its first row
    start: int
    #: its rows
    rows: int
    #: its rows still retained (a capacity evicts the oldest rows of the first chunk)
    retained: int
    #: None when intact, else what is wrong (naming the file)
    damage: Optional[str] = None


@dataclass
class BufferCheck:
    """What :func:`check_buffer` (or :func:`salvage_buffer`) found in a buffer directory."""

    #: the directory checked
    path: str
    #: its layout, "single" or "chunked"
    layout: str
    #: every committed chunk, oldest first
    chunks: list[ChunkCheck] = field(default_factory=list)
    #: salvage only: the new directory, and the transitions copied into it
    destination: Optional[str] = None
    copied: int = 0

    @property
    def damaged(self) -> list[ChunkCheck]:
        """The damaged chunks."""
        return [chunk for chunk in self.chunks if chunk.damage is not None]

    @property
    def intact_transitions(self) -> int:
        """Retained transitions in intact chunks."""
        return sum(chunk.retained for chunk in self.chunks if chunk.damage is None)

    @property
    def lost_transitions(self) -> int:
        """Retained transitions in damaged chunks."""
        return sum(chunk.retained for chunk in self.damaged)

    def summary(self) -> str:
        """:return: a report for people: one line per damaged chunk, then the counts"""
        lines = [
            f"chunk of rows {c.start:,} to {c.start + c.rows - 1:,} ({c.retained:,} retained): {c.damage}"
            for c in self.damaged
        ]
        lines.append(
            f"{self.path}: {len(self.chunks)} chunks ({self.layout} layout), {len(self.damaged)} damaged; "
            f"{self.intact_transitions:,} transitions intact, {self.lost_transitions:,} in damaged chunks"
        )
        if self.destination is not None:
            lines.append(f"copied {self.copied:,} transitions to {self.destination}")
        return "\n".join(lines)


def _source(path: str) -> tuple[dict[str, Any], Layout, LayoutState]:
    """The validated manifest of ``path`` and a read-only layout over its files (nothing is opened for writing)."""
    path = os.path.abspath(os.fspath(path))
    if not os.path.isdir(path):
        raise FileNotFoundError(f"no buffer directory at {path!r}")
    try:
        manifest = read_manifest(path)
    except BufferFormatError as error:
        raise BufferFormatError(
            f"{error}. Without a valid {MANIFEST_NAME} the rows cannot be located: there is nothing to check or salvage"
        ) from None
    state = LayoutState(path, 1, manifest.get("capacity"), read_only=True)
    state.set_fields(validate_fields(manifest["fields"]))
    return manifest, make_layout(manifest.get("layout", "single"), state), state


def _checks(manifest: dict[str, Any]) -> list[ChunkCheck]:
    first = manifest.get("first_row", 0)
    return [
        ChunkCheck(chunk["start"], chunk["rows"], chunk["start"] + chunk["rows"] - max(first, chunk["start"]))
        for chunk in manifest["chunks"]
    ]


def check_buffer(path: str) -> BufferCheck:
    """
    Check every committed chunk of a buffer directory: its files exist with the sizes the manifest gives, and every
    field's bytes have their checksum (reads the whole buffer once, in blocks). Nothing is written to the directory.

    :param path: The buffer directory
    :return: The report (``report.damaged`` is empty when the buffer is intact)
    :raises BufferFormatError: its ``manifest.json`` is not a valid manifest (then nothing can be located)
    :raises FileNotFoundError: no directory, or no manifest in it
    """
    manifest, layout, _ = _source(path)
    report = BufferCheck(os.path.abspath(os.fspath(path)), manifest.get("layout", "single"), _checks(manifest))
    for check, chunk in zip(report.chunks, manifest["chunks"]):
        check.damage = layout.chunk_damage(chunk)
    return report


def _read_chunk(layout: Layout, state: LayoutState, chunk: dict[str, Any]) -> tuple[Optional[dict[str, np.ndarray]], str]:
    """:return: every field's rows of ``chunk`` (each checked against its checksum, as read), or None and the damage"""
    rows: dict[str, np.ndarray] = {}
    offsets = state.field_offsets(chunk["rows"])
    for name in state.fields:
        size = chunk["rows"] * state.row_bytes[name]
        if layout.name == "single":
            file_name, offset = os.path.join(state.path or "", name + ".bin"), chunk["start"] * state.row_bytes[name]
        else:
            file_name, offset = layout.segments([chunk], 0)[0].places[name][0], offsets[name]
        try:
            if os.path.islink(file_name):
                raise OSError(f"{file_name} is a symbolic link")
            with open(file_name, "rb") as file:
                file.seek(offset)
                data = file.read(size)
        except OSError:
            data = b""
        if len(data) != size or zlib.crc32(data) != chunk["crc32"][name]:
            return None, layout.chunk_damage(chunk) or f"{file_name}: changed while it was read"
        rows[name] = np.frombuffer(data, dtype=state.dtypes[name]).reshape(chunk["rows"], *state.shapes[name])
    return rows, ""


def salvage_buffer(path: str, destination: str, chunk_size: int = 10_000) -> BufferCheck:
    """
    Copy the retained rows of every intact chunk of a buffer directory (a damaged one, typically) into a new buffer
    directory, with the same fields, capacity, sources and spaces. The rows of damaged chunks are left out; nothing
    is written to ``path``.

    Rows keep their order. N-step returns and next actions never chain across a left-out chunk: the rows after each
    gap get new stream ids (those before the first gap keep theirs).

    :param path: The buffer directory to copy from
    :param destination: A new directory (or an empty one) for the copy
    :param chunk_size: Transitions per chunk of the copy
    :return: The report of the check, with the number of transitions copied
    :raises BufferFormatError: ``path``'s manifest is not valid (nothing can be located)
    :raises FileExistsError: ``destination`` is ``path``, lies inside it (even through a symbolic link) or holds
        files; nothing is written
    :raises ValueError: ``chunk_size`` is not a positive int (checked before anything else)
    """
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"salvage: chunk_size must be a positive int (transitions per chunk of the copy), got {chunk_size!r}")
    manifest, layout, state = _source(path)
    source = os.path.abspath(os.fspath(path))
    destination = os.path.abspath(os.fspath(destination))
    if os.path.exists(destination) and (
        not os.path.isdir(destination) or os.listdir(destination) or os.path.samefile(source, destination)
    ):
        raise FileExistsError(f"salvage writes a new buffer: {destination!r} exists and is not an empty directory")
    real_source, real_destination = os.path.realpath(source), os.path.realpath(destination)
    if os.path.commonpath([real_source, real_destination]) == real_source:
        raise FileExistsError(
            f"salvage never writes into the directory it copies from: {destination!r} lies inside {source!r} (resolved: "
            f"{real_destination!r}). Choose a destination outside it; nothing was written"
        )
    report = BufferCheck(source, manifest.get("layout", "single"), _checks(manifest), destination=destination)
    fields = state.fields
    copy = RowStore(dict(fields), path=destination, chunk_size=chunk_size, capacity=manifest.get("capacity"))
    try:
        for source_id, entry in manifest["sources"].items():
            copy.set_source(int(source_id), entry["name"], entry["metadata"])
        copy.describe_spaces(manifest["spaces"])
        copy.reserve_streams(manifest["next_stream_id"])  # every original id stays taken: new ones come after
        first_row, gap = manifest.get("first_row", 0), False
        renumber: Optional[dict[int, int]] = None  # old stream id -> new, from the first gap on
        for check, chunk in zip(report.chunks, manifest["chunks"]):
            rows, damage = _read_chunk(layout, state, chunk)
            if rows is None:
                check.damage, gap = damage, True
                continue
            if gap:  # the first intact chunk after a left-out one: its streams start again, with new ids
                renumber, gap = {}, False
            skip = max(first_row - chunk["start"], 0)
            rows = {name: values[skip:] for name, values in rows.items()}
            if renumber is not None:
                rows["streams"] = _renumbered(rows["streams"], renumber, copy)
            copy.append(rows)
            report.copied += len(rows["rewards"])
        copy.flush()
    finally:
        copy.close()
    return report


def _renumbered(streams: np.ndarray, renumber: dict[int, int], copy: RowStore) -> np.ndarray:
    """Stream ids mapped to new ones (the same old id to the same new id within a run of intact chunks)."""
    unique, inverse = np.unique(streams, return_inverse=True)
    for stream in unique.tolist():
        if stream not in renumber:
            renumber[stream] = copy.reserve_streams(1)
    if copy.next_stream_id >= 2**32:
        raise OverflowError("salvage: the copy needs more stream ids than a buffer holds (2**32)")
    return np.array([renumber[s] for s in unique.tolist()], dtype=np.uint32)[inverse.reshape(-1)]
