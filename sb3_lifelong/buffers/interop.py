"""
The lifelong buffer's exchange formats: d4rl-style dicts (and ``.npz`` files of them) and Minari datasets, in and out.

:class:`~sb3_lifelong.buffers.LifelongReplayBuffer`'s ``from_d4rl``, ``from_minari``, ``to_d4rl``, ``to_minari`` and
``save_npz`` are thin methods over these functions. They use only what a buffer offers anyone (:class:`Exportable`,
:class:`Importing`), and of the buffer's modules they import only the row store's (its format and ``RowStore``):
``sampling`` and ``lifelong`` import this one.
"""

from __future__ import annotations

import inspect
import os
import warnings
from typing import Any, Callable, Optional, Protocol, TypeVar, Union

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_action_dim

from sb3_lifelong.buffers.manifest import FLAG_DONE, FLAG_TIMEOUT, MAX_SOURCE_ID, check_source_id
from sb3_lifelong.buffers.rowstore import RowStore
from sb3_lifelong.core.datasets import import_minari, minari_columns, normalize_actions, read_npz, validate_d4rl

# Minari interop: per-step source ids (in the episodes' infos) and source names / metadata (in the dataset metadata)
MINARI_SOURCE_INFO = "sb3_lifelong_source"
MINARI_SOURCES_METADATA = "sb3_lifelong_sources"
#: source metadata key of the environment spec (gymnasium's JSON) of data imported from Minari, written again by
#: ``to_minari`` so that the dataset's ``recover_environment()`` works
ENV_SPEC_METADATA = "env_spec"


class Exportable(Protocol):
    """What the exports read of a buffer or a view (a :class:`~sb3_lifelong.buffers.sampling.LifelongSampler`)."""

    observation_space: spaces.Space
    action_space: spaces.Space

    @property
    def sources(self) -> dict[int, dict[str, Any]]: ...

    def size(self) -> int: ...

    def read_range(self, name: str, start: int, stop: int) -> np.ndarray: ...


class Importing(Protocol):
    """What the imports write to a new buffer (a :class:`~sb3_lifelong.buffers.LifelongReplayBuffer`)."""

    store: RowStore
    obs_shape: tuple[int, ...]
    action_dim: int

    def name_source(self, source: int, name: Optional[str] = None, metadata: Optional[dict[str, Any]] = None) -> None: ...

    def append_rows(self, rows: dict[str, np.ndarray]) -> None: ...

    def flush(self) -> None: ...


BufferT = TypeVar("BufferT", bound=Importing)


def _check_exportable(buffer: Exportable, what: str) -> None:
    if isinstance(buffer.observation_space, spaces.Dict):
        raise NotImplementedError(
            f"{what} of Dict observations is not supported (d4rl and Minari exports need one observation array)"
        )


def _to_env_units(actions: np.ndarray, action_space: spaces.Space) -> np.ndarray:
    """
    Exports: map the normalised ``[-1, 1]`` actions SB3 stores to the action space's bounds (the inverse of
    :func:`~sb3_lifelong.core.datasets.normalize_actions`, which every import uses). Unbounded spaces, spaces
    that already are ``[-1, 1]``, and integer (or bool) Box spaces, whose actions are stored in the env's units, leave
    the actions untouched (bit for bit).
    """
    if not isinstance(action_space, spaces.Box) or not _is_float_box(action_space) or not action_space.is_bounded():
        return actions
    low, high = action_space.low.astype(np.float64), action_space.high.astype(np.float64)
    if np.all(low == -1.0) and np.all(high == 1.0):
        return actions
    return (low + 0.5 * (actions.astype(np.float64) + 1.0) * (high - low)).astype(actions.dtype)


def _is_float_box(space: spaces.Space) -> bool:
    """:return: whether ``space`` is a Box of floats (whose actions SB3 stores normalised; an integer Box's are not)"""
    return isinstance(space, spaces.Box) and np.dtype(space.dtype).kind == "f"


def _stored_actions(
    actions: np.ndarray, action_space: spaces.Space, normalized_actions: bool, action_dim: int, where: str
) -> np.ndarray:
    """
    Imports: the actions as the buffer stores them, ``(N, action_dim)``: a float Box's normalised to ``[-1, 1]`` (with
    the one normaliser, :func:`~sb3_lifelong.core.datasets.normalize_actions`); the actions of an integer (or bool) Box
    and of Discrete, MultiDiscrete and MultiBinary spaces as they are (the env's units, ``normalized_actions`` has no
    effect), in the stored dtype, where it holds them exactly.

    :raises ValueError: naming ``where``, for an integer action its dtype does not hold exactly (out of range, fractional)
    """
    if _is_float_box(action_space) or not isinstance(
        action_space, (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)
    ):
        return normalize_actions(actions, action_space, normalized_actions).reshape(len(actions), action_dim)
    dtype = np.dtype(action_space.dtype)
    stored = actions.astype(dtype).reshape(len(actions), action_dim)
    if not np.array_equal(stored, np.asarray(actions).reshape(len(actions), action_dim)):
        raise ValueError(
            f"{where}: an action is not a value of the action space's dtype {dtype} ({action_space}: its actions are "
            "stored as they are, integers in the env's units): out of range or fractional"
        )
    return stored


def _minari_env_spec(dataset: Any) -> Optional[str]:
    """:return: the JSON of a Minari dataset's environment spec (what ``recover_environment`` makes), or None"""
    spec = getattr(getattr(dataset, "spec", None), "env_spec", None)
    try:
        return spec.to_json() if spec is not None else None
    except Exception:  # an env spec gymnasium cannot write as JSON (e.g. a callable entry point): not kept
        return None


def export_columns(buffer: Exportable, by_episode: bool, normalized_actions: bool) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """
    :param buffer: the buffer (or view) to export
    :param by_episode: see :meth:`LifelongReplayBuffer.to_d4rl`
    :param normalized_actions: see :meth:`LifelongReplayBuffer.to_d4rl`
    :return: The d4rl columns of ``to_d4rl`` plus ``streams``, and a mask of the rows marked as a timeout
        only because their stream stops there (the write head of an env, a reopen, an ``n_envs`` change)
    """
    _check_exportable(buffer, "d4rl export")
    total = buffer.size()
    names = ("observations", "next_observations", "actions", "rewards", "flags", "sources", "streams")
    data = {name: np.asarray(buffer.read_range(name, 0, total)) for name in names}
    flags = data["flags"]
    timeouts = (flags & FLAG_TIMEOUT) != 0
    terminals = ((flags & FLAG_DONE) != 0) & ~timeouts
    order = np.arange(total)
    open_end = np.zeros(total, dtype=bool)
    if by_episode and total:
        streams = data["streams"].astype(np.int64)
        order = np.argsort(streams, kind="stable")
        sorted_streams = streams[order]
        last_of_stream = np.append(sorted_streams[1:] != sorted_streams[:-1], True)
        terminals, timeouts = terminals[order], timeouts[order]
        open_end = last_of_stream & ~terminals & ~timeouts
        timeouts = timeouts | open_end
    actions = data["actions"][order]
    if not normalized_actions:
        actions = _to_env_units(actions, buffer.action_space)
    columns = {
        "observations": data["observations"][order],
        "actions": actions,
        "rewards": data["rewards"][order],
        "next_observations": data["next_observations"][order],
        "terminals": terminals,
        "timeouts": timeouts,
        "sources": data["sources"][order].astype(np.int64),
        "streams": data["streams"][order].astype(np.int64),
    }
    return columns, open_end


def to_d4rl(buffer: Exportable, by_episode: bool = True, normalized_actions: bool = False) -> dict[str, np.ndarray]:
    """``buffer`` as a d4rl-style dict (in memory): see :meth:`LifelongReplayBuffer.to_d4rl`."""
    columns, _ = export_columns(buffer, by_episode, normalized_actions)
    del columns["streams"]
    return columns


def save_npz(buffer: Exportable, file: Union[str, os.PathLike]) -> None:
    """Write :func:`to_d4rl` of ``buffer`` to a ``.npz`` file (no pickle inside): see :meth:`LifelongReplayBuffer.save_npz`."""
    columns: dict[str, Any] = to_d4rl(buffer)  # (typed Any: numpy's stubs would match the arrays to savez's flags)
    np.savez(file, **columns)


#: the optional fields of a Minari dataset whose absence Minari warns about (given to ``to_minari`` as keywords)
MINARI_OPTIONAL_FIELDS = ("author", "author_email", "algorithm_name", "code_permalink", "eval_env")


def to_minari(
    buffer: Exportable,
    dataset_id: str,
    normalized_actions: bool = False,
    unfinished: str = "truncate",
    description: Optional[str] = None,
    **minari_kwargs: Any,
) -> Any:
    """Write ``buffer`` as a new local Minari dataset: see :meth:`LifelongReplayBuffer.to_minari`."""
    if unfinished not in ("truncate", "drop"):
        raise ValueError(f"unfinished must be 'truncate' or 'drop', got {unfinished!r}")
    _check_exportable(buffer, "Minari export")
    minari = import_minari("LifelongReplayBuffer.to_minari")
    from minari.data_collector import EpisodeBuffer

    if buffer.size() == 0:
        raise ValueError("cannot export an empty buffer to Minari")
    data, open_end = export_columns(buffer, by_episode=True, normalized_actions=normalized_actions)
    obs, next_obs = data["observations"], data["next_observations"]
    terminals, timeouts = data["terminals"], data["timeouts"]
    total = len(obs)
    ends = terminals | timeouts
    if total > 1:  # a stream whose observations do not chain is cut into episodes there
        chained = (next_obs[:-1] == obs[1:]).reshape(total - 1, -1).all(axis=1)
        cut = np.append(~ends[:-1] & ~chained, False)
        timeouts = timeouts | cut
        ends = ends | cut
    stops = np.flatnonzero(ends) + 1
    starts = np.concatenate([[0], stops[:-1]])
    if unfinished == "drop":
        keep = ~open_end[stops - 1]
        starts, stops = starts[keep], stops[keep]
    if len(starts) == 0:
        raise ValueError("the buffer holds no finished episode to export (unfinished='drop')")
    obs_shape = tuple(buffer.observation_space.shape or ())
    action_space = buffer.action_space
    if normalized_actions and isinstance(action_space, spaces.Box) and _is_float_box(action_space):
        action_space = spaces.Box(-1.0, 1.0, shape=action_space.shape, dtype=action_space.dtype.type)
    action_shape = tuple(action_space.shape or ())
    sources = data["sources"].astype(np.int64)
    episodes = []
    for episode_id, (start, stop) in enumerate(zip(starts.tolist(), stops.tolist())):
        episode_obs = np.concatenate([obs[start:stop], next_obs[stop - 1 : stop]])
        episodes.append(
            EpisodeBuffer(
                id=episode_id,
                observations=episode_obs.reshape(stop - start + 1, *obs_shape),
                actions=data["actions"][start:stop].reshape(stop - start, *action_shape),
                rewards=data["rewards"][start:stop],
                terminations=terminals[start:stop],
                truncations=timeouts[start:stop],
                infos={MINARI_SOURCE_INFO: np.concatenate([sources[start : start + 1], sources[start:stop]])},
            )
        )
    if description is None:
        names = ", ".join(info["name"] for _, info in sorted(buffer.sources.items()))
        description = f"Exported from an sb3_lifelong LifelongReplayBuffer ({len(episodes)} episodes" + (
            f"; sources: {names})" if names else ")"
        )
    if "jpeg_encoding" in inspect.signature(minari.create_dataset_from_buffers).parameters:
        minari_kwargs.setdefault("jpeg_encoding", False)
    if minari_kwargs.get("env") is None:  # the env spec of data imported from Minari, when every source agrees on it
        specs = {info["metadata"].get(ENV_SPEC_METADATA) for info in buffer.sources.values()}
        if len(specs) == 1 and isinstance(next(iter(specs)), str):
            from gymnasium.envs.registration import EnvSpec

            minari_kwargs["env"] = EnvSpec.from_json(next(iter(specs)))
    with warnings.catch_warnings():
        # Minari reminds, one warning each, of every optional field left out (author, code_permalink, ...): the buffer
        # does not know them, and the caller may give them; its other warnings still show
        for field in MINARI_OPTIONAL_FIELDS:
            if minari_kwargs.get(field) is None:
                warnings.filterwarnings("ignore", message=f"`{field}` is set to None", category=UserWarning)
        if minari_kwargs.get("env") is None:
            warnings.filterwarnings("ignore", message="env_spec is None", category=UserWarning)
        dataset = minari.create_dataset_from_buffers(
            dataset_id,
            episodes,
            observation_space=buffer.observation_space,
            action_space=action_space,
            description=description,
            **minari_kwargs,
        )
    dataset.storage.update_metadata({MINARI_SOURCES_METADATA: {str(k): v for k, v in sorted(buffer.sources.items())}})
    return dataset


def from_d4rl(
    cls: Callable[..., BufferT],
    data: Union[dict[str, np.ndarray], str, os.PathLike],
    observation_space: Optional[spaces.Space] = None,
    action_space: Optional[spaces.Space] = None,
    source: int = 0,
    normalized_actions: bool = False,
    **kwargs: Any,
) -> BufferT:
    """Build a ``cls`` buffer from a d4rl-style dict or ``.npz`` file: see :meth:`LifelongReplayBuffer.from_d4rl`."""
    if isinstance(observation_space, spaces.Dict):
        raise NotImplementedError("from_d4rl: d4rl data has one observation array: Dict observation spaces are not supported")
    where = "from_d4rl"
    if not isinstance(data, dict):
        where = f"from_d4rl({os.fspath(data)})"
        data = read_npz(data)
    data = validate_d4rl(data, where=where, cast_observations=False, integer_actions=True)  # before anything is created
    obs, actions = data["observations"], data["actions"]
    total = len(obs)
    if observation_space is None:
        observation_space = spaces.Box(-np.inf, np.inf, shape=obs.shape[1:], dtype=obs.dtype.type)
    if action_space is None:
        action_space = spaces.Box(-np.inf, np.inf, shape=actions.shape[1:], dtype=actions.dtype.type)
    # the one normaliser (also checks bounds) for float Box actions; integer actions as they are, exactly
    actions = _stored_actions(actions, action_space, normalized_actions, get_action_dim(action_space), where)
    buffer = cls(total, observation_space, action_space, source=source, **kwargs)
    terminals, timeouts, next_obs = data["terminals"], data["timeouts"], data["next_observations"]
    sources = data["sources"] if "sources" in data else np.full(total, source)
    ended = terminals | timeouts
    chained = np.zeros(total, dtype=bool)
    if total > 1:
        same = (next_obs[:-1] == obs[1:]).reshape(total - 1, -1).all(axis=1)
        chained[1:] = same & ~ended[:-1]
    new_streams = np.cumsum(~chained) - 1
    streams = buffer.store.reserve_streams(int(new_streams[-1]) + 1 if total else 0) + new_streams
    rows = {
        "observations": obs,
        "next_observations": next_obs,
        "actions": actions,
        "rewards": data["rewards"],
        "flags": ((terminals | timeouts) * FLAG_DONE + timeouts * FLAG_TIMEOUT).astype(np.uint8),
        "sources": sources.astype(np.uint16),
        "streams": streams.astype(np.uint32),
        "widths": np.ones(total, dtype=np.uint16),
    }
    for source_id in np.unique(sources):
        buffer.name_source(int(source_id))
    buffer.append_rows(rows)
    buffer.flush()
    return buffer


def from_minari(
    cls: Callable[..., BufferT],
    dataset: Any,
    path: Optional[Union[str, os.PathLike]] = None,
    source: Optional[int] = None,
    source_name: Optional[str] = None,
    source_metadata: Optional[dict[str, Any]] = None,
    normalized_actions: bool = False,
    observation_space: Optional[spaces.Space] = None,
    action_space: Optional[spaces.Space] = None,
    **kwargs: Any,
) -> BufferT:
    """Build a ``cls`` buffer from a Minari dataset: see :meth:`LifelongReplayBuffer.from_minari`."""
    if isinstance(dataset, (str, os.PathLike)):
        dataset = import_minari("LifelongReplayBuffer.from_minari").load_dataset(os.fspath(dataset))
    observation_space = observation_space if observation_space is not None else dataset.observation_space
    action_space = action_space if action_space is not None else dataset.action_space
    if observation_space is None or action_space is None:
        raise ValueError("the Minari dataset has no observation or action space: pass observation_space and action_space")
    if isinstance(observation_space, spaces.Dict) or isinstance(action_space, spaces.Dict):
        raise NotImplementedError("Minari import of Dict observation or action spaces is not supported")
    dataset_id = getattr(dataset, "id", None)
    columns = minari_columns(dataset, info_keys=(MINARI_SOURCE_INFO,))
    lengths = columns["episode_lengths"]
    total = int(lengths.sum())
    name_of = dataset_id if isinstance(dataset_id, str) else type(dataset).__name__
    valid = validate_d4rl(  # the one validator, before anything is created
        {key: columns[key] for key in ("observations", "next_observations", "actions", "rewards", "terminals", "timeouts")},
        where=f"from_minari({name_of})",
        cast_observations=False,
        integer_actions=True,
    )
    actions = _stored_actions(  # before anything is created
        valid["actions"], action_space, normalized_actions, get_action_dim(action_space), f"from_minari({name_of})"
    )
    buffer = cls(total, observation_space, action_space, path=path, **kwargs)
    common = {
        "minari_dataset_id": dataset_id if isinstance(dataset_id, str) else None,
        "minari_total_episodes": len(lengths),
        "minari_total_steps": total,
    }
    env_spec = _minari_env_spec(dataset)
    if env_spec is not None:  # kept, so that to_minari can write it again (recover_environment)
        common[ENV_SPEC_METADATA] = env_spec
    tags = columns.get(f"info/{MINARI_SOURCE_INFO}")
    if source is None and tags is not None:
        sources = tags.astype(np.int64).reshape(total)
        if total and (sources.min() < 0 or sources.max() > MAX_SOURCE_ID):
            raise ValueError(f"the dataset's source ids must be in [0, {MAX_SOURCE_ID}]")
        storage = getattr(dataset, "storage", None)
        stored = storage.metadata.get(MINARI_SOURCES_METADATA, {}) if storage is not None else {}
        for source_id in np.unique(sources).tolist():
            info = stored.get(str(source_id)) if isinstance(stored, dict) else None
            info = info if isinstance(info, dict) else {}
            name = info["name"] if isinstance(info.get("name"), str) else None
            extra: dict[str, Any] = info["metadata"] if isinstance(info.get("metadata"), dict) else {}
            spec = {ENV_SPEC_METADATA: env_spec} if env_spec is not None else {}
            buffer.name_source(source_id, name, {**extra, "minari_dataset_id": common["minari_dataset_id"], **spec})
    else:
        source = check_source_id(0 if source is None else source)
        sources = np.full(total, source, dtype=np.int64)
        name = source_name or f"minari:{dataset_id if isinstance(dataset_id, str) else 'dataset'}"
        buffer.name_source(source, name, {**common, **dict(source_metadata or {})})
    terminals, timeouts = valid["terminals"], valid["timeouts"]
    base = buffer.store.reserve_streams(len(lengths))
    rows = {
        "observations": columns["observations"].reshape(total, *buffer.obs_shape),
        "next_observations": columns["next_observations"].reshape(total, *buffer.obs_shape),
        "actions": actions,
        "rewards": valid["rewards"],
        "flags": ((terminals | timeouts) * FLAG_DONE + timeouts * FLAG_TIMEOUT).astype(np.uint8),
        "sources": sources.astype(np.uint16),
        "streams": np.repeat(np.arange(base, base + len(lengths), dtype=np.int64), lengths).astype(np.uint32),
        "widths": np.ones(total, dtype=np.uint16),
    }
    buffer.append_rows(rows)
    buffer.flush()
    return buffer
