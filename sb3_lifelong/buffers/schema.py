"""
What a lifelong buffer's store holds for its spaces: the fields of the observations and actions (one pair of
observation fields per key of a Dict space), and the spaces' JSON description that the manifest keeps, so that a
directory opens again with its spaces, equal to the ones it was created with (bounds, dtype, ``nvec``, ``n``).

The spaces a buffer accepts (:data:`SUPPORTED_SPACES`) are checked at construction (:func:`check_spaces`): every
other space is refused there, before anything is written, as is a description the manifest cannot hold
(:data:`MAX_SPACES_JSON_CHARS`).

Arrays of a description (a Box's ``low`` and ``high``, a MultiDiscrete's ``nvec`` and ``start``) are written exactly:
a list of JSON numbers when they have at most :data:`MAX_LISTED_ELEMENTS` elements (``null`` for an unbounded
element), ``{"fill": value}`` when every element is the same, otherwise ``{"zlib": base64}`` (the little-endian bytes
of the array in the space's dtype, zlib-compressed; with an integer Box's unbounded elements as a packed bit mask in
``"unbounded"``).
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import zlib
from typing import Any, Optional

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape

from sb3_lifelong.buffers.manifest import (
    ALLOWED_DTYPES,
    FIXED_FIELDS,
    MAX_ROW_ELEMENTS,
    OBS_FIELDS,
    check_obs_key,
    json_value,
    obs_keys_of,
)
from sb3_lifelong.buffers.rowstore import RowStore

__all__ = [
    "MAX_LISTED_ELEMENTS",
    "MAX_SPACES_JSON_CHARS",
    "SUPPORTED_SPACES",
    "action_field_dtype",
    "action_space_of",
    "buffer_fields",
    "check_spaces",
    "describe_spaces",
    "observation_space_of",
    "space_from_json",
    "space_to_json",
]

#: what the constructor accepts (the message of every refused space lists it)
SUPPORTED_SPACES = (
    "observation spaces Box (bool, integer or float dtype of at most 64 bits), Discrete, MultiDiscrete (a 1-D nvec), "
    "MultiBinary, or a Dict of those; action spaces Box, Discrete, MultiDiscrete (a 1-D nvec) or MultiBinary (an int n)"
)
#: arrays of a description with at most this many elements are written as JSON lists (more: filled or compressed)
MAX_LISTED_ELEMENTS = 4096
#: the longest description of the spaces a buffer accepts (written in the manifest, which every commit writes again):
#: 16 MiB, reached only by Box bounds of millions of elements that are neither uniform nor compressible
MAX_SPACES_JSON_CHARS = 16 * 1024 * 1024


def action_field_dtype(dtype: Any) -> np.dtype:
    """:return: the dtype actions of ``dtype`` are stored as (SB3's ``_maybe_cast_dtype``: float64 as float32)"""
    dtype = np.dtype(dtype)
    return np.dtype(np.float32) if dtype == np.float64 else dtype


def _refuse(role: str, space: Any, why: str = "") -> NotImplementedError:
    because = f" ({why})" if why else ""
    return NotImplementedError(
        f"LifelongReplayBuffer does not support the {role} space {space}{because}: it supports {SUPPORTED_SPACES}"
    )


def _check_leaf(space: Any, role: str) -> None:
    """Raise (naming the space and listing the supported ones) unless a buffer stores and reopens ``space`` exactly."""
    if isinstance(space, spaces.Box):
        if np.dtype(space.dtype).str not in ALLOWED_DTYPES:
            raise _refuse(role, space, f"a Box of dtype {space.dtype}")
        if np.dtype(space.dtype).kind == "f" and (np.isposinf(space.low).any() or np.isneginf(space.high).any()):
            raise _refuse(role, space, "a Box with a low of +inf or a high of -inf holds no value")
        if role == "action" and not space.shape:
            raise _refuse(role, space, "a Box action space of shape ()")
    elif isinstance(space, spaces.MultiDiscrete):
        if space.nvec.ndim != 1:
            raise _refuse(role, space, f"a MultiDiscrete of nvec shape {space.nvec.shape}: only a 1-D nvec is stored")
        if np.dtype(space.dtype).str not in ALLOWED_DTYPES:
            raise _refuse(role, space, f"a MultiDiscrete of dtype {space.dtype}")
    elif isinstance(space, spaces.MultiBinary):
        if role == "action" and not isinstance(space.n, (int, np.integer)):
            raise _refuse(role, space, "a MultiBinary action space of several dimensions: flatten it")
    elif not isinstance(space, spaces.Discrete):
        raise _refuse(role, space)
    shape = get_obs_shape(space) if role != "action" else (get_action_dim(space),)
    if not isinstance(shape, tuple) or math.prod(shape) > MAX_ROW_ELEMENTS:
        raise _refuse(role, space, f"more than the {MAX_ROW_ELEMENTS:,} elements a row of a buffer may hold")


def check_spaces(observation_space: Optional[spaces.Space], action_space: Optional[spaces.Space]) -> None:
    """
    Refuse, at construction and before anything is written, a space a buffer would not reopen equal.

    :param observation_space: The observation space (None: not given)
    :param action_space: The action space (None: not given)
    :raises NotImplementedError: naming the space and listing :data:`SUPPORTED_SPACES`
    """
    if observation_space is not None:
        if isinstance(observation_space, spaces.Dict):
            for key, sub in observation_space.spaces.items():
                if isinstance(sub, (spaces.Dict, spaces.Tuple)):
                    raise _refuse(f"Dict observation key {key!r}: nested {type(sub).__name__} observation", sub)
                check_obs_key(key)
                _check_leaf(sub, f"Dict observation key {key!r}: observation")
        else:
            _check_leaf(observation_space, "observation")
    if action_space is not None:
        _check_leaf(action_space, "action")


# ---------------------------------------------------------------------------------------------- arrays, exactly
def _b64(data: bytes) -> str:
    return base64.b64encode(zlib.compress(data, 9)).decode("ascii")


def _unb64(text: Any, size: int, what: str) -> bytes:
    """:return: the ``size`` bytes a ``{"zlib": ...}`` string holds (a ValueError for anything else)"""
    if not isinstance(text, str):
        raise ValueError(f"{what}: expected a base64 string")
    try:
        packed = base64.b64decode(text.encode("ascii"), validate=True)
        inflate = zlib.decompressobj()
        raw = inflate.decompress(packed, size + 1)  # never more than one byte beyond what is expected
    except (binascii.Error, UnicodeEncodeError, zlib.error) as error:
        raise ValueError(f"{what}: not base64 of zlib data ({error})") from None
    if len(raw) != size or not inflate.eof or inflate.unconsumed_tail:
        raise ValueError(f"{what}: holds {len(raw):,} bytes or more, expected {size:,}")
    return raw


def _encode(values: np.ndarray, unbounded: Optional[np.ndarray] = None) -> Any:
    """
    :param values: An array of a space (its ``low``, ``high``, ``nvec`` or ``start``), in the space's dtype
    :param unbounded: Where the value stands for no bound (written as ``null``; None: nowhere)
    :return: Its exact JSON form (see the module's docstring)
    """
    flat = values.reshape(-1)
    mask = np.zeros(flat.shape, bool) if unbounded is None else unbounded.reshape(-1)
    if flat.size <= MAX_LISTED_ELEMENTS:
        return [None if hidden else value for value, hidden in zip(flat.tolist(), mask.tolist())]
    if np.all(flat == flat[0]) and np.all(mask == mask[0]):
        return {"fill": None if mask[0] else flat[:1].tolist()[0]}
    result = {"zlib": _b64(flat.astype(flat.dtype.newbyteorder("<")).tobytes())}
    if mask.any():
        result["unbounded"] = _b64(np.packbits(mask).tobytes())
    return result


def _decode(data: Any, dtype: np.dtype, size: int, what: str, infinity: float) -> tuple[np.ndarray, np.ndarray]:
    """
    :param data: What :func:`_encode` wrote
    :param dtype: The space's dtype
    :param size: The number of elements
    :param what: Where it is, for the message
    :param infinity: What ``null`` stands for (-inf for a lower bound, +inf for an upper one)
    :return: The values in ``dtype`` (``null``: ``infinity``, or the dtype's extreme for an integer dtype) and the mask
        of the unbounded ones
    :raises ValueError: for anything :func:`_encode` does not write, or a value ``dtype`` does not hold exactly
    """
    if isinstance(data, dict) and set(data) == {"fill"}:
        items: list[Any] = [data["fill"]]
    elif isinstance(data, dict) and "zlib" in data and set(data) <= {"zlib", "unbounded"}:
        raw = _unb64(data["zlib"], size * dtype.itemsize, what)
        values = np.frombuffer(raw, dtype=dtype.newbyteorder("<")).astype(dtype)
        mask = np.zeros(size, bool)
        if "unbounded" in data:
            mask = np.unpackbits(np.frombuffer(_unb64(data["unbounded"], (size + 7) // 8, what), np.uint8))[:size]
            mask = mask.astype(bool)
        if dtype.kind == "f":
            if np.isnan(values).any():
                raise ValueError(f"{what}: holds NaN")
            mask = values == infinity
        return values, mask
    elif isinstance(data, list) and len(data) == size:
        items = data
    else:
        raise ValueError(f"{what}: expected a list of {size:,} numbers, {{'fill': number}} or {{'zlib': base64}}")
    mask = np.array([item is None for item in items], bool)
    numbers = [0 if item is None else item for item in items]
    if not all(isinstance(n, (int, float)) for n in numbers):
        raise ValueError(f"{what}: holds a value that is not a number")
    if dtype.kind == "f":
        wide = np.array(numbers, np.float64)
        values = wide.astype(dtype)
        exact = np.array_equal(values.astype(np.float64), wide)
        values[mask] = infinity
    else:
        low, high = (0, 1) if dtype.kind == "b" else (int(np.iinfo(dtype).min), int(np.iinfo(dtype).max))
        exact = all(low <= n <= high and (isinstance(n, int) or float(n).is_integer()) for n in numbers)
        values = np.array([int(n) for n in numbers] if exact else [], dtype=object).astype(dtype)
        if exact:
            values[mask] = low if infinity < 0 else high
    if not exact:
        raise ValueError(f"{what}: holds a value that {dtype} does not hold exactly")
    if len(items) == 1:
        values, mask = np.repeat(values, size), np.repeat(mask, size)
    return values, mask


# ---------------------------------------------------------------------------------------------- spaces
def space_to_json(space: spaces.Space) -> dict[str, Any]:
    """
    :param space: A space :func:`check_spaces` accepts
    :return: The JSON description of ``space`` that a manifest keeps, from which :func:`space_from_json` makes it again
        exactly (bounds, dtype, ``nvec``, ``start``, ``n``)
    """
    if isinstance(space, spaces.Dict):
        return {"type": "Dict", "spaces": {key: space_to_json(sub) for key, sub in space.spaces.items()}}
    if isinstance(space, spaces.Discrete):
        return {"type": "Discrete", "n": int(space.n), "start": int(space.start)}
    dtype = np.dtype(space.dtype)
    if isinstance(space, spaces.MultiDiscrete):
        return {
            "type": "MultiDiscrete",
            "shape": list(space.shape),
            "dtype": dtype.str,
            "nvec": _encode(space.nvec),
            "start": _encode(space.start),
        }
    if isinstance(space, spaces.MultiBinary):
        n = space.n
        return {"type": "MultiBinary", "n": int(n) if isinstance(n, (int, np.integer)) else [int(d) for d in n]}
    assert isinstance(space, spaces.Box)  # check_spaces refuses the rest
    if dtype.kind == "f":  # the infinities (no bound) are written as null: -inf for low, +inf for high
        below, above = np.isneginf(space.low), np.isposinf(space.high)
    else:  # an integer Box's unbounded elements hold the dtype's extremes (gymnasium's bounded_below / bounded_above)
        below, above = ~np.asarray(space.bounded_below, bool), ~np.asarray(space.bounded_above, bool)
    return {
        "type": "Box",
        "shape": list(space.shape),
        "dtype": dtype.str,
        "low": _encode(space.low, below),
        "high": _encode(space.high, above),
    }


def describe_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> dict[str, Any]:
    """
    :param observation_space: The buffer's observation space (checked by :func:`check_spaces`)
    :param action_space: Its action space (checked by :func:`check_spaces`)
    :return: ``{"observation": ..., "action": ...}``, the description the manifest keeps, checked with the manifest
        reader's own limits
    :raises ValueError: the description is longer than :data:`MAX_SPACES_JSON_CHARS` (bounds of millions of elements
        that are neither uniform nor compressible), or beyond what the manifest's reader accepts
    """
    description = {"observation": space_to_json(observation_space), "action": space_to_json(action_space)}
    json_value(description, convert=False)  # the reader's limits (MetadataError, a ValueError)
    chars = len(json.dumps(description))
    if chars > MAX_SPACES_JSON_CHARS:
        raise ValueError(
            f"the description of the spaces ({observation_space}, {action_space}) takes {chars:,} characters of JSON, more "
            f"than the {MAX_SPACES_JSON_CHARS:,} a buffer's manifest keeps (MAX_SPACES_JSON_CHARS; the manifest is written "
            "again at every commit): give the Box uniform bounds (one low and one high), or bounds that compress"
        )
    return description


def _shape_of(data: dict[str, Any], size: int, what: str) -> Optional[tuple[int, ...]]:
    """The ``shape`` of a description (None: not written), checked to hold ``size`` elements."""
    shape = data.get("shape")
    if shape is None:
        return None
    if not (isinstance(shape, list) and len(shape) <= 8 and all(isinstance(d, int) and d >= 0 for d in shape)):
        raise ValueError(f"{what}: 'shape' must be a list of at most 8 non-negative ints, got {shape!r:.80}")
    if math.prod(shape) != size:
        raise ValueError(f"{what}: 'shape' {shape} does not hold the {size:,} elements of the stored field")
    return tuple(shape)


def space_from_json(data: dict[str, Any], dtype: str, shape: tuple[int, ...], role: str = "observation") -> spaces.Space:
    """
    :param data: A description written by :func:`space_to_json`; one written before the spaces were written exactly
        without bounds (a Box of more than 4096 elements, a MultiDiscrete or a MultiBinary): an unbounded Box
    :param dtype: The dtype of the field stored for the space
    :param shape: Its row shape
    :param role: ``"observation"`` or ``"action"`` (the field of an action space is ``(action_dim,)``, float64 is
        stored as float32)
    :return: The space
    :raises ValueError: the description does not describe a space of that field
    """
    what = f"the {role} space"
    field = np.dtype(dtype)
    size = math.prod(shape)
    kind = data.get("type")
    space: spaces.Space
    if kind == "Discrete" and isinstance(data.get("n"), int):
        start = data.get("start", 0)
        if not isinstance(start, int) or data["n"] < 1:
            raise ValueError(f"{what}: a Discrete needs an int n > 0 and an int start")
        space = spaces.Discrete(data["n"], start=start)
    elif kind == "MultiBinary" and "n" in data:
        n = data["n"]
        if not (isinstance(n, int) and n > 0) and not (
            isinstance(n, list) and 0 < len(n) <= 8 and all(isinstance(d, int) and d > 0 for d in n)
        ):
            raise ValueError(f"{what}: a MultiBinary needs an int n > 0 or a list of them, got {n!r:.80}")
        space = spaces.MultiBinary(n if isinstance(n, int) else tuple(n))
    elif kind == "MultiDiscrete" and "nvec" in data:
        described = np.dtype(data.get("dtype", dtype))
        if described.kind not in "iu":
            raise ValueError(f"{what}: a MultiDiscrete of dtype {described}")
        nvec, _ = _decode(data["nvec"], described, size, f"{what}'s nvec", np.inf)
        start, _ = _decode(data.get("start", {"fill": 0}), described, size, f"{what}'s start", np.inf)
        if (nvec < 1).any():
            raise ValueError(f"{what}: a MultiDiscrete's nvec must be positive")
        space = spaces.MultiDiscrete(nvec, dtype=described.type, start=start)
    else:
        # a Box (and what an older writer described without its bounds: an unbounded Box of the field)
        described = np.dtype(data["dtype"]) if isinstance(data.get("dtype"), str) else field
        if described.str not in ALLOWED_DTYPES:
            raise ValueError(f"{what}: a Box of dtype {described}")
        box_shape = _shape_of(data, size, what) or shape
        bounds = data.get("low"), data.get("high")
        unbounded = {"fill": None}
        low, below = _decode(bounds[0] if bounds[0] is not None else unbounded, described, size, f"{what}'s low", -np.inf)
        high, above = _decode(bounds[1] if bounds[1] is not None else unbounded, described, size, f"{what}'s high", np.inf)
        space = spaces.Box(low.reshape(box_shape), high.reshape(box_shape), shape=box_shape, dtype=described.type)
        if described.kind in "iu":  # no bound: the dtype's extreme, marked as gymnasium marks it
            space.bounded_below = ~below.reshape(box_shape)
            space.bounded_above = ~above.reshape(box_shape)
    expected: tuple[str, tuple[Any, ...]] = (field.str, tuple(shape))
    got: tuple[str, tuple[Any, ...]]
    if role == "action":
        got = (action_field_dtype(space.dtype).str, (get_action_dim(space),))
    else:
        got = (np.dtype(space.dtype).str, tuple(get_obs_shape(space)))  # type: ignore[arg-type]
    if got != expected:
        raise ValueError(f"{what} {space} is stored as {got}, but its field is {expected}")
    return space


def observation_space_of(store: RowStore) -> spaces.Space:
    """The observation space described by a store's manifest (a Dict space when the observations have keys)."""
    data = store.spaces.get("observation", {})
    data = data if isinstance(data, dict) else {}
    keys = obs_keys_of(store.fields)
    if keys is None:
        return space_from_json(data, *store.fields["observations"])
    described = data["spaces"] if isinstance(data.get("spaces"), dict) else {}
    subspaces = {}
    for key in keys:
        sub = described.get(key)
        subspaces[key] = space_from_json(sub if isinstance(sub, dict) else {}, *store.fields[f"observations.{key}"])
    return spaces.Dict(subspaces)


def action_space_of(store: RowStore) -> spaces.Space:
    """The action space described by a store's manifest."""
    data = store.spaces.get("action", {})
    return space_from_json(data if isinstance(data, dict) else {}, *store.fields["actions"], role="action")


def _observation_fields(observation_space: spaces.Space) -> dict[str, tuple[str, tuple[int, ...]]]:
    """The observation and next-observation fields of a store for an observation space (one pair per Dict key)."""

    def spec(space: spaces.Space) -> tuple[str, tuple[int, ...]]:
        shape = get_obs_shape(space)
        assert isinstance(shape, tuple)  # not a Dict space (refused below)
        return np.dtype(space.dtype).str, shape

    if not isinstance(observation_space, spaces.Dict):
        return {"observations": spec(observation_space), "next_observations": spec(observation_space)}
    check_spaces(observation_space, None)
    fields = {}
    for base in OBS_FIELDS:
        for key, sub in observation_space.spaces.items():
            fields[f"{base}.{key}"] = spec(sub)
    return fields


def buffer_fields(
    observation_space: spaces.Space, action_space: spaces.Space, action_dtype: Any
) -> dict[str, tuple[str, tuple[int, ...]]]:
    """
    :param observation_space: One of :data:`SUPPORTED_SPACES`
    :param action_space: One of :data:`SUPPORTED_SPACES`
    :param action_dtype: The dtype the actions are stored as
    :return: The fields of a buffer's store: field name -> (dtype string, row shape)
    """
    return {
        **_observation_fields(observation_space),
        "actions": (np.dtype(action_dtype).str, (get_action_dim(action_space),)),
        **FIXED_FIELDS,
    }
