"""
The format of a buffer directory: its files, the manifest (what it holds, reading and validating it, writing a new
one) and the format's constants (fields, dtypes, the flags of a row).

Directory format (versions 1 and 2), see ``docs/modules/buffer.md``::

    <path>/manifest.json     committed state (JSON, rewritten atomically after each flushed chunk)
    <path>/<field>.bin       layout "single" (no capacity): one append-only file per field, raw little-endian
                             C-order rows, no header
    <path>/chunk.<start>.bin layout "chunked" (with a capacity): one file per flushed chunk, each field's rows one
                             field after the other; deleted once no committed manifest lists it
    <path>/writer.lock       advisory lock held by the (single) writer process

Dict observations store one field per key, ``observations.<key>`` and ``next_observations.<key>`` (version 2;
plain buffers are still written as version 1).

A row ``i`` of field ``f`` lives at byte offset ``i * row_bytes(f)`` of ``f.bin``. Only the first
``num_transitions`` rows (sum of the chunk sizes listed in the manifest) are committed; bytes after
them are an unflushed tail of a crashed writer and are ignored by readers and cut off by the next writer.

Like every module of the row store, this one imports only numpy and the standard library (see ``files``).
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import uuid
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any, Optional

import numpy as np

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
# the buffer's identity: a random id written when the buffer is created, never changed (optional: older buffers have none)
ID_KEY = "buffer_id"
ID_PATTERN = re.compile(r"[0-9a-f]{32}")
LOCK_NAME = "writer.lock"
# bounds of what a manifest may make this code read or allocate (a manifest may be hostile: see read_manifest)
MAX_MANIFEST_BYTES = 256 * 1024 * 1024
MAX_ROW_ELEMENTS = 1 << 24
MAX_ROW_BYTES = 1 << 26  # one field of one row: 64 MiB (e.g. 2**24 float32 elements)
MAX_JSON_DEPTH = 32  # a valid manifest nests at most about 14 levels (metadata: 8 levels below its source)
MAX_NUMBER_CHARS = 100  # the longest number a manifest may hold (written ones have at most 20 digits or 25 characters)
#: the deepest a source's metadata (or the spaces' description) may nest: a value 9 levels below it is refused, by the
#: writer (at the add or set_source that gives it) and by the reader alike (see json_value)
MAX_METADATA_DEPTH = 8
MAX_SOURCE_ID = 65534
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
# bits of a row's flags: the episode ended there (done), by a time limit (timeout: not a terminal state)
FLAG_DONE = 1
FLAG_TIMEOUT = 2


class BufferFormatError(ValueError):
    """A manifest or a data file (field or chunk file) is not a valid buffer directory (corrupted, truncated or hostile)."""


def chunk_file_name(start: int) -> str:
    """
    :param start: First row of a chunk
    :return: The name of its file in the "chunked" layout
    """
    return f"chunk.{start:012d}.bin"


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


class MetadataError(ValueError):
    """A value of a source's metadata (or of the spaces' description) that a manifest cannot hold, or that the
    manifest's reader would refuse: the message names where it is (``['key'][0]``...) and the limit."""

    #: the message without what was (not) changed, for a caller that says it in its own terms
    core: str = ""


def _json_path(path: str) -> str:
    return path or "(the value itself)"


def _int_chars(value: int) -> int:
    """:return: the characters of ``str(value)`` (without making the string of a huge int)"""
    if value.bit_length() > 4 * MAX_NUMBER_CHARS:  # more than 1.2 * MAX_NUMBER_CHARS digits: the exact count is moot
        return 4 * MAX_NUMBER_CHARS
    return len(str(value))


def json_value(value: Any, convert: bool = True, path: str = "", depth: int = 0) -> Any:
    """
    The one check of what a manifest's metadata (and its description of the spaces) may hold, used by the writer
    (:meth:`ManifestRecords.set_source`, before anything is stored) and by the reader (:func:`validate_manifest`):
    JSON's own values (None, bool, int, float, str, lists, objects with string keys), finite floats, numbers of at
    most :data:`MAX_NUMBER_CHARS` characters, at most :data:`MAX_METADATA_DEPTH` levels of nesting.

    :param value: The value
    :param convert: Writers: return a new copy in which what converts exactly is converted (numpy scalars and arrays
        of bool, integers and floats to Python ``bool``, ``int``, ``float`` and lists, tuples to lists, ``str`` and
        ``int`` subclasses to ``str`` and ``int``); False (readers): only check a decoded document
    :param path: Where ``value`` is, for the message (``['gains'][2]``)
    :param depth: Its nesting level (0: the metadata object itself)
    :return: The value, converted (``convert=True``), or ``value`` as it is
    :raises MetadataError: naming where the value is and the limit it is beyond
    """
    if depth > MAX_METADATA_DEPTH:
        raise MetadataError(
            f"{_json_path(path)}: nested {depth} levels deep, more than the {MAX_METADATA_DEPTH} a buffer's manifest "
            "accepts (MAX_METADATA_DEPTH)"
        )
    if value is None or (isinstance(value, str) and (type(value) is str or not convert)):
        return value
    if isinstance(value, (bool, np.bool_)):
        return bool(value) if convert else value
    if convert and isinstance(value, np.ndarray):
        if value.dtype.kind not in "biuf":
            raise MetadataError(f"{_json_path(path)}: an array of dtype {value.dtype}: only arrays of real numbers convert")
        if value.ndim == 0:
            return json_value(value[()], convert, path, depth)
        return [json_value(item, convert, f"{path}[{i}]", depth + 1) for i, item in enumerate(value)]
    if isinstance(value, (int, np.integer)):
        number = int(value)
        chars = _int_chars(number)
        if chars > MAX_NUMBER_CHARS:
            size = f"{chars}" if chars < 4 * MAX_NUMBER_CHARS else f"over {chars}"
            raise MetadataError(
                f"{_json_path(path)}: an int of {size} characters, more than the {MAX_NUMBER_CHARS} a number of a buffer's "
                "manifest may have (MAX_NUMBER_CHARS)"
            )
        return number if convert else value
    if isinstance(value, (float, np.floating)):
        real = float(value)
        if not math.isfinite(real):
            raise MetadataError(
                f"{_json_path(path)}: {value!r} is not finite: JSON holds only finite numbers (a buffer's manifest "
                "refuses NaN and infinities)"
            )
        if convert and not isinstance(value, float) and np.asarray(real, dtype=np.asarray(value).dtype) != value:
            raise MetadataError(f"{_json_path(path)}: {value!r} ({type(value).__name__}) has no exact float64 value")
        return real if convert else value
    if isinstance(value, str):  # a subclass (e.g. numpy.str_)
        return str(value)
    if isinstance(value, (list, tuple) if convert else list):
        return [json_value(item, convert, f"{path}[{i}]", depth + 1) for i, item in enumerate(value)]
    if isinstance(value, dict):
        result = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise MetadataError(
                    f"{_json_path(path)}: the key {key!r} is a {type(key).__name__}: keys of JSON objects are strings (it "
                    f"would be read back as {json.dumps(str(key))})"
                )
            result[str(key)] = json_value(item, convert, f"{path}[{key!r}]", depth + 1)
        return result if convert else value
    raise MetadataError(
        f"{_json_path(path)}: a value of type {type(value).__name__} ({value!r:.60}): JSON holds None, bool, int, float, "
        "str, lists and objects with string keys (numpy scalars and arrays of numbers are converted)"
    )


def _check_json_value(value: Any, where: str) -> None:
    """Readers: raise ``BufferFormatError`` naming ``where`` if a decoded value is not what :func:`json_value` accepts."""
    try:
        json_value(value, convert=False)
    except MetadataError as error:
        raise BufferFormatError(f"{where}: {error}") from None


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
        if math.prod(shape) * int(dtype[2:]) > MAX_ROW_BYTES:  # the item size is the digits of the dtype string
            raise BufferFormatError(
                f"manifest field {name!r}: a row of {math.prod(shape):,} elements of {dtype} takes "
                f"{math.prod(shape) * int(dtype[2:]):,} bytes, more than the {MAX_ROW_BYTES:,} a field's row may hold"
            )
        if name in FIXED_FIELDS and (dtype, tuple(shape)) != FIXED_FIELDS[name]:
            raise BufferFormatError(f"manifest field {name!r} must have dtype/shape {FIXED_FIELDS[name]}, got {dtype, shape}")
        result[name] = (dtype, tuple(shape))
    for suffix in [""] if obs_keys is None else [f".{key}" for key in obs_keys]:
        if result["observations" + suffix] != result["next_observations" + suffix]:
            raise BufferFormatError(
                f"manifest: observations{suffix} and next_observations{suffix} must have the same dtype and shape"
            )
    return result


def validated_fields(fields: Mapping[str, tuple[Any, Sequence[int]]]) -> dict[str, tuple[str, tuple[int, ...]]]:
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
    if set(manifest) - {ID_KEY} != expected:
        raise BufferFormatError(
            f"manifest keys must be {sorted(expected)} (and optionally {ID_KEY!r}), got {sorted(map(str, manifest))}"
        )
    if ID_KEY in manifest and (not isinstance(manifest[ID_KEY], str) or ID_PATTERN.fullmatch(manifest[ID_KEY]) is None):
        raise BufferFormatError(f"manifest {ID_KEY!r} must be 32 lowercase hexadecimal digits, got {manifest[ID_KEY]!r}")
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


# every digit as "0", for a quick search of long runs of digits
_DIGITS_AS_ZERO = bytes(0x30 if 0x30 <= b <= 0x39 else b for b in range(256))
# every byte but the quotes and brackets of a JSON document, for bytes.translate to delete
_NOT_STRUCTURE = bytes(b for b in range(256) if b not in b'"[]{}')


def _json_depth(raw: bytes) -> int:
    """:return: how deeply the arrays and objects of a JSON document nest (strings ignored), without parsing it"""
    # escaped backslashes, then escaped quotes, go (pairing from the left, as JSON does): every quote left delimits a
    # string; then only quotes and brackets are kept (C-speed byte operations; a few bytes per chunk remain)
    kept = raw.replace(b"\\\\", b"").replace(b'\\"', b"").translate(None, _NOT_STRUCTURE)
    data = np.frombuffer(kept, dtype=np.uint8)
    quotes = data == 0x22
    outside = (np.cumsum(quotes, dtype=np.int64) % 2 == 0) & ~quotes  # after an even number of quotes
    folded = data[outside] | 0x20  # "[" -> "{", "]" -> "}"
    if folded.size == 0:
        return 0
    levels = np.cumsum((folded == 0x7B).astype(np.int64) - (folded == 0x7D))
    return int(levels.max())


def parse_manifest(raw: bytes, file_name: str) -> Any:
    """
    Decode a manifest's bytes, bounded: nothing in a hostile document can make this recurse deeply, parse a huge
    number or hold an infinite or NaN value (``json.dumps`` of this package writes none).

    :param raw: The bytes (at most :data:`MAX_MANIFEST_BYTES`: the caller checks the file's size before reading it)
    :param file_name: The file, for messages
    :return: The decoded document (not validated: see :func:`validate_manifest`)
    :raises BufferFormatError: naming the file, for anything but a JSON document within the bounds
    """
    if len(raw) > MAX_MANIFEST_BYTES:
        raise BufferFormatError(f"{file_name}: manifest of {len(raw)} bytes is larger than the {MAX_MANIFEST_BYTES} allowed")
    depth = _json_depth(raw)
    if depth > MAX_JSON_DEPTH:
        raise BufferFormatError(
            f"{file_name}: not a manifest: its JSON nests {depth} levels deep, more than the {MAX_JSON_DEPTH} allowed"
        )

    def _no_constants(name: str) -> Any:
        raise BufferFormatError(f"{file_name}: non-standard JSON constant {name}")

    def _number(text: str) -> None:
        if len(text) > MAX_NUMBER_CHARS:
            raise BufferFormatError(
                f"{file_name}: not a manifest: a number of {len(text)} characters (more than {MAX_NUMBER_CHARS}): "
                f"{text[:20]}..."
            )

    def _int(text: str) -> int:
        _number(text)
        return int(text)

    def _float(text: str) -> float:
        _number(text)
        value = float(text)
        if not math.isfinite(value):
            raise BufferFormatError(f"{file_name}: not a manifest: the number {text} is out of the range of a float")
        return value

    # ints are parsed by json itself unless a run of more than MAX_NUMBER_CHARS digits is somewhere (in a string,
    # perhaps): only then is each int checked as it is parsed (a Python call per int)
    ints = _int if b"0" * (MAX_NUMBER_CHARS + 1) in raw.translate(_DIGITS_AS_ZERO) else int
    try:
        return json.loads(raw.decode("utf-8"), parse_constant=_no_constants, parse_int=ints, parse_float=_float)
    except (UnicodeDecodeError, ValueError, RecursionError, MemoryError) as error:
        if isinstance(error, BufferFormatError):
            raise
        raise BufferFormatError(f"{file_name}: not valid JSON ({type(error).__name__}: {error})") from None


def read_manifest(path: str) -> dict[str, Any]:
    """
    Read and validate ``<path>/manifest.json``, bounded (see :func:`parse_manifest`): its size is checked before it
    is read, its nesting before it is parsed, its numbers as they are parsed, and its fields' row sizes before
    anything is allocated for them.

    :param path: Buffer directory
    :return: The validated manifest
    :raises BufferFormatError: naming the file, for anything that is not a valid manifest within the bounds
    """
    file_name = os.path.join(path, MANIFEST_NAME)
    if not os.path.isfile(file_name):
        raise FileNotFoundError(f"{path!r} is not a buffer directory (no {MANIFEST_NAME})")
    size = os.path.getsize(file_name)
    if size > MAX_MANIFEST_BYTES:
        raise BufferFormatError(f"{file_name}: manifest of {size} bytes is larger than the {MAX_MANIFEST_BYTES} allowed")
    with open(file_name, "rb") as file:
        raw = file.read(MAX_MANIFEST_BYTES + 1)
    manifest = parse_manifest(raw, file_name)
    try:
        return validate_manifest(manifest)
    except BufferFormatError as error:
        raise BufferFormatError(f"{file_name}: {error}") from None
    except RecursionError:  # pragma: no cover (the depth is bounded before parsing)
        raise BufferFormatError(f"{file_name}: not a manifest: nested too deeply") from None


def make_manifest(
    fields: Mapping[str, tuple[str, tuple[int, ...]]],
    layout: str,
    capacity: Optional[int],
    num_transitions: int,
    first_row: int,
    chunks: list[dict[str, Any]],
    sources: Mapping[int, dict[str, Any]],
    next_stream_id: int,
    spaces: Mapping[str, Any],
    buffer_id: Optional[str] = None,
) -> dict[str, Any]:
    """
    The manifest of a committed state: version 1 when it can describe it (layout "single", one observation field),
    else version 2.

    :param fields: field name -> (dtype string, row shape)
    :param layout: "single" or "chunked"
    :param capacity: The number of most recent rows kept (None: every row, layout "single")
    :param num_transitions: Global row after the last committed row
    :param first_row: Global row of the oldest retained committed row
    :param chunks: The committed chunks (``start``, ``rows``, ``crc32`` per field)
    :param sources: source id -> ``{"name": str, "metadata": dict}``
    :param next_stream_id: The first stream id not reserved yet
    :param spaces: The JSON description of the observation and action spaces
    :param buffer_id: The buffer's identity (see :func:`new_buffer_id`); None: a buffer created without one
    :return: The document (see :func:`validate_manifest`)
    """
    plain = layout == "single" and obs_keys_of(fields) is None
    manifest: dict[str, Any] = {
        "format": FORMAT_NAME,
        "version": 1 if plain else 2,
        "fields": {name: {"dtype": dt, "shape": list(shape)} for name, (dt, shape) in fields.items()},
        "num_transitions": num_transitions,
        "chunks": chunks,
        "sources": {str(k): v for k, v in sorted(sources.items())},
        "next_stream_id": next_stream_id,
        "spaces": spaces,
    }
    if not plain:
        manifest.update(layout=layout, capacity=capacity, first_row=first_row)
    if buffer_id is not None:
        manifest[ID_KEY] = buffer_id
    return manifest


def new_buffer_id() -> str:
    """:return: a new buffer identity: 128 random bits as 32 hexadecimal digits, written in the manifest at creation"""
    return uuid.uuid4().hex


def buffer_id_of(manifest: Mapping[str, Any]) -> Optional[str]:
    """:return: the identity a validated manifest records, or None (a buffer created before buffers had one)"""
    return manifest.get(ID_KEY)


def committed_transitions(path: str) -> Optional[int]:
    """
    A quick look at a directory's manifest, not validated (a writer that holds the lock checks what it committed;
    a constructor checks whether the directory holds rows before opening it).

    :param path: Buffer directory
    :return: The manifest's ``num_transitions``, or None when there is no manifest or it cannot be read
    """
    file_name = os.path.join(path, MANIFEST_NAME)
    try:
        with open(file_name, "rb") as file:
            raw = file.read(MAX_MANIFEST_BYTES + 1)
        value = parse_manifest(raw, file_name)["num_transitions"]
        return value if _is_int(value) else None
    except (OSError, ValueError, KeyError, TypeError):  # BufferFormatError is a ValueError
        return None


def check_source_id(source: Any) -> int:
    """
    :param source: A source id
    :return: It, as an int
    :raises ValueError: unless it is an int (not a bool) in ``[0, MAX_SOURCE_ID]``
    """
    if not isinstance(source, (int, np.integer)) or isinstance(source, bool) or not 0 <= source <= MAX_SOURCE_ID:
        raise ValueError(f"source ids are ints in [0, {MAX_SOURCE_ID}], got {source!r}")
    return int(source)


class ManifestRecords:
    """
    What a buffer's manifest records besides its rows: the stream ids (:meth:`reserve_streams`), the source table
    (:meth:`source`, :meth:`set_source`, :meth:`source_table`) and the description of the spaces
    (:meth:`describe_spaces`), saved with the next commit; :attr:`next_stream_id` and :attr:`spaces` are read-only.
    :class:`~sb3_lifelong.buffers.rowstore.RowStore` keeps them so.
    """

    def __init__(self) -> None:
        self._sources: dict[int, dict[str, Any]] = {}
        self._spaces: dict[str, Any] = {}
        self._next_stream_id = 0
        self._buffer_id: Optional[str] = None

    def _load_records(self, manifest: dict[str, Any]) -> None:
        """Take the records of a manifest just read (validated)."""
        self._sources = {int(k): v for k, v in manifest["sources"].items()}
        self._spaces = manifest["spaces"]
        self._next_stream_id = manifest["next_stream_id"]
        self._buffer_id = buffer_id_of(manifest)

    @property
    def buffer_id(self) -> Optional[str]:
        """
        The buffer's identity: a random id written in its manifest when the directory's buffer was created and never
        changed, so that a reader, or a model that reattaches its buffer, can tell a buffer deleted and created again at
        the same path. None in memory and for a buffer created before buffers had one (identity unknown).
        """
        return self._buffer_id

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
        """:return: ``{"name": str, "metadata": dict}`` of a source id (a deep copy), or None if it is not known"""
        known = self._sources.get(source)
        return None if known is None else {"name": known["name"], "metadata": copy.deepcopy(known["metadata"])}

    def source_name(self, source: int) -> Optional[str]:
        """:return: the name of a source id, or None if it is not known (no copy of its metadata: ``add``'s test)"""
        known = self._sources.get(source)
        return None if known is None else known["name"]

    def set_source(self, source: int, name: str, metadata: Mapping[str, Any]) -> None:
        """
        Name a source id and set its metadata; saved with the next commit. The metadata is checked (and copied) first,
        with the reader's own limits (:func:`json_value`): numpy scalars and arrays of numbers are converted exactly to
        Python numbers and lists, tuples to lists; anything the manifest could not hold, or its reader would refuse
        (NaN or infinite floats, ints of more than :data:`MAX_NUMBER_CHARS` characters, more than
        :data:`MAX_METADATA_DEPTH` levels of nesting, keys that are not strings, other objects), is refused with
        nothing changed, so that every later commit can write the manifest.

        :param source: source id in ``[0, MAX_SOURCE_ID]``
        :param name: its name
        :param metadata: its metadata (a dict with string keys)
        :raises MetadataError: (a ``ValueError``) naming the source, the key and the limit; nothing was changed
        """
        source = check_source_id(source)
        if not isinstance(metadata, Mapping):
            raise MetadataError(f"source {source} ({name!r}): metadata must be a dict, got {type(metadata).__name__}")
        try:
            checked = json_value(dict(metadata))
        except MetadataError as error:
            refused = MetadataError(f"source {source} ({str(name)!r}): its metadata cannot be stored: metadata{error}")
            refused.core = str(refused)
            refused.args = (f"{refused.core}; nothing was changed",)
            raise refused from None
        self._sources[source] = {"name": str(name), "metadata": checked}

    def source_table(self) -> dict[int, dict[str, Any]]:
        """:return: every source id -> ``{"name": str, "metadata": dict}`` (deep copies)"""
        return {k: {"name": v["name"], "metadata": copy.deepcopy(v["metadata"])} for k, v in self._sources.items()}

    def describe_spaces(self, spaces: dict[str, Any]) -> None:
        """
        Record the JSON description of the observation and action spaces, once: a store that has one keeps it.

        :param spaces: ``{"observation": ..., "action": ...}``
        """
        if not self._spaces:
            self._spaces = dict(spaces)
