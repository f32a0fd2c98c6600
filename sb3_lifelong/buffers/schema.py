"""
What a lifelong buffer's store holds for its spaces: the fields of the observations and actions (one pair of
observation fields per key of a Dict space), and the spaces' JSON description that the manifest keeps, so that a
directory opens again with its spaces.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape

from sb3_lifelong.buffers.manifest import FIXED_FIELDS, OBS_FIELDS, check_obs_key, obs_keys_of
from sb3_lifelong.buffers.rowstore import RowStore

__all__ = ["buffer_fields", "observation_space_of", "space_from_json", "space_to_json"]


def space_to_json(space: spaces.Space) -> dict[str, Any]:
    """:return: the JSON description of a space that a manifest keeps (a Box's bounds when it has at most 4096)"""
    if isinstance(space, spaces.Dict):
        return {"type": "Dict", "spaces": {key: space_to_json(sub) for key, sub in space.spaces.items()}}
    if isinstance(space, spaces.Discrete):
        return {"type": "Discrete", "n": int(space.n), "start": int(space.start)}
    if isinstance(space, spaces.Box):
        result: dict[str, Any] = {"type": "Box", "shape": list(space.shape), "dtype": np.dtype(space.dtype).str}
        if space.low.size <= 4096:
            # non-finite bounds are written as null (-inf for low, +inf for high)
            result["low"] = [float(v) if np.isfinite(v) else None for v in space.low.reshape(-1)]
            result["high"] = [float(v) if np.isfinite(v) else None for v in space.high.reshape(-1)]
        return result
    return {"type": type(space).__name__, "shape": list(space.shape or ()), "dtype": np.dtype(space.dtype).str}


def space_from_json(data: dict[str, Any], dtype: str, shape: tuple[int, ...]) -> spaces.Space:
    """
    :param data: A description written by :func:`space_to_json` (anything else: an unbounded Box)
    :param dtype: The dtype of the field stored for the space
    :param shape: Its row shape
    :return: The space (a Discrete or a Box)
    """
    if data.get("type") == "Discrete" and isinstance(data.get("n"), int):
        return spaces.Discrete(data["n"], start=int(data.get("start", 0)))
    size = int(np.prod(shape))
    low = np.full(size, -np.inf)
    high = np.full(size, np.inf)
    bounds = data.get("low"), data.get("high")
    if all(isinstance(b, list) and len(b) == size for b in bounds):
        low = np.array([-np.inf if v is None else float(v) for v in data["low"]])
        high = np.array([np.inf if v is None else float(v) for v in data["high"]])
    np_dtype = np.dtype(dtype)
    if np.issubdtype(np_dtype, np.integer):
        info = np.iinfo(np_dtype)
        low, high = np.clip(low, info.min, info.max), np.clip(high, info.min, info.max)
    elif np.issubdtype(np_dtype, np.floating):  # the bounds were written from values of this dtype: exact
        low, high = low.astype(np_dtype), high.astype(np_dtype)
    return spaces.Box(low.reshape(shape), high.reshape(shape), shape=shape, dtype=np_dtype.type)


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


def _observation_fields(observation_space: spaces.Space) -> dict[str, tuple[str, tuple[int, ...]]]:
    """The observation and next-observation fields of a store for an observation space (one pair per Dict key)."""

    def spec(space: spaces.Space) -> tuple[str, tuple[int, ...]]:
        shape = get_obs_shape(space)
        assert isinstance(shape, tuple)  # not a Dict space (refused below)
        return np.dtype(space.dtype).str, shape

    if not isinstance(observation_space, spaces.Dict):
        return {"observations": spec(observation_space), "next_observations": spec(observation_space)}
    fields = {}
    for base in OBS_FIELDS:
        for key, sub in observation_space.spaces.items():
            if isinstance(sub, (spaces.Dict, spaces.Tuple)):
                raise NotImplementedError(
                    f"Dict observation key {key!r}: nested {type(sub).__name__} spaces are not supported"
                )
            check_obs_key(key)
            fields[f"{base}.{key}"] = spec(sub)
    return fields


def buffer_fields(
    observation_space: spaces.Space, action_space: spaces.Space, action_dtype: Any
) -> dict[str, tuple[str, tuple[int, ...]]]:
    """
    :param observation_space: Box, Discrete, or Dict of those
    :param action_space: Box or Discrete
    :param action_dtype: The dtype the actions are stored as
    :return: The fields of a buffer's store: field name -> (dtype string, row shape)
    """
    return {
        **_observation_fields(observation_space),
        "actions": (np.dtype(action_dtype).str, (get_action_dim(action_space),)),
        **FIXED_FIELDS,
    }
