"""
Loading and validating offline data: d4rl-style dicts and ``.npz`` files, Minari datasets and SB3 replay buffers.

The canonical in-memory form is a *d4rl dict* of equal-length arrays:

- ``observations`` ``[N, *obs_shape]`` and ``next_observations`` ``[N, *obs_shape]``
- ``actions`` ``[N, action_dim]`` (or ``[N]``), in the units of the environment unless stated otherwise
- ``rewards`` ``[N]`` (or ``[N, 1]``)
- ``terminals`` ``[N]``: the episode ended in a terminal state (no bootstrapping)
- ``timeouts`` ``[N]`` (optional): the episode was cut by a time limit (bootstrapping continues)

It is turned into an in-memory :class:`~sb3_lifelong.buffers.LifelongReplayBuffer` (``from_d4rl``), the one
buffer every offline algorithm reads: it keeps each transition's source and chains consecutive rows into
trajectories, so it also gives the next action in the data (for SARSA targets).
"""

import os
import warnings
import zipfile
import zlib
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple, Optional, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import PyTorchObs

__all__ = [
    "OPTIONAL_KEYS",
    "REQUIRED_KEYS",
    "OfflineData",
    "OfflineDataError",
    "OfflineSamples",
    "import_minari",
    "infer_spaces",
    "load_d4rl",
    "minari_columns",
    "minari_to_d4rl",
    "normalize_actions",
    "read_npz",
    "record_transitions",
    "replay_buffer_to_d4rl",
    "validate_d4rl",
]

REQUIRED_KEYS = ("observations", "actions", "rewards", "next_observations", "terminals")
#: the largest source id a transition may have: the buffer's (``sb3_lifelong.buffers.manifest.MAX_SOURCE_ID``, a layer
#: above this module; equal, tested)
MAX_SOURCE_ID = 65534
OPTIONAL_KEYS = ("timeouts", "sources")

# What the offline entry points accept
OfflineData = Union[ReplayBuffer, Mapping[str, Any], str, os.PathLike, Any]


class OfflineDataError(ValueError):
    """Offline data that cannot be used as it is: missing keys, mismatched lengths, wrong dtypes, NaN."""


class OfflineSamples(NamedTuple):
    """``ReplayBufferSamples`` (or ``DictReplayBufferSamples``) plus the next action recorded in the data (for SARSA)."""

    observations: PyTorchObs
    actions: th.Tensor
    next_observations: PyTorchObs
    dones: th.Tensor
    rewards: th.Tensor
    discounts: Optional[th.Tensor] = None
    # action taken at next_observations in the data, normalised; zeros where unknown
    next_actions: Optional[th.Tensor] = None
    # 1.0 where next_actions is known, [batch, 1]
    next_action_mask: Optional[th.Tensor] = None


#: rows checked for NaN and infinite values at a time (bounds the memory the check takes on large data)
_CHECK_BLOCK = 1 << 16


def _as_array(data: Mapping[str, Any], key: str, where: str) -> np.ndarray:
    try:
        return np.asarray(data[key])
    except Exception as error:  # ragged lists, exotic objects
        raise OfflineDataError(f"{where} key {key!r} cannot be read as an array: {error}") from error


def _check_numeric(key: str, array: np.ndarray, allow_int: bool, where: str, allow_bool: bool = False) -> None:
    kind = array.dtype.kind
    allowed = ("fiu" if allow_int else "f") + ("b" if allow_bool else "")
    if kind not in allowed:
        expected = "a numeric (float or integer)" if allow_int else "a floating-point"
        expected += " or bool" if allow_bool else ""
        raise OfflineDataError(f"{where} key {key!r} must have {expected} dtype, got {array.dtype}")
    if kind != "f":
        return
    bad = np.zeros(0, dtype=np.int64)
    for start in range(0, len(array), _CHECK_BLOCK):
        block = array[start : start + _CHECK_BLOCK]
        bad = np.concatenate([bad, start + np.flatnonzero(~np.isfinite(block.reshape(len(block), -1)).all(axis=1))])
    if len(bad):
        raise OfflineDataError(
            f"{where} key {key!r} holds NaN or infinite values in {len(bad)} rows (first: row {int(bad[0])}): values "
            "that are not finite are refused"
        )


def _check_flags(key: str, array: np.ndarray, where: str) -> np.ndarray:
    if array.dtype.kind == "b":
        return array.reshape(len(array))
    if array.dtype.kind not in "fiu":
        raise OfflineDataError(f"{where} key {key!r} must be boolean (or 0/1 numbers), got dtype {array.dtype}")
    if array.size and not np.isin(array, (0, 1)).all():
        raise OfflineDataError(f"{where} key {key!r} must hold only 0/1 (or booleans), got other values")
    return array.astype(bool).reshape(len(array))


def validate_d4rl(
    data: Mapping[str, Any], where: str = "offline data", cast_observations: bool = True, integer_actions: bool = False
) -> dict[str, np.ndarray]:
    """
    Check a d4rl-style dict and return a clean copy of its standard keys (other keys are dropped): the one validator
    of every way data comes in (``from_offline_data``, ``LifelongReplayBuffer.from_d4rl`` and ``from_minari``).

    :param data: mapping with ``observations``, ``actions``, ``rewards``, ``next_observations``, ``terminals`` and
        optionally ``timeouts`` and ``sources`` (the source id of each transition, as ``to_d4rl`` exports them)
    :param where: what the data is, at the start of the error messages (e.g. the file it was read from)
    :param cast_observations: cast float64 observations to float32 (False: keep their dtype, for a buffer whose
        observation space keeps it)
    :param integer_actions: also accept integer actions (discrete action spaces, which the buffer stores but the
        offline algorithms do not learn from), kept as they are
    :return: dict with the observations (float32 unless they were integers, or ``cast_observations=False``),
        ``actions`` ``[N, action_dim]`` (float32, or integers with ``integer_actions``) and ``rewards`` ``[N]``
        (float32), boolean ``terminals`` and ``timeouts``,
        and ``sources`` ``[N]`` (int64) when given
    :raises OfflineDataError: on missing keys, mismatched lengths or shapes, wrong dtypes, NaN or infinite values
        (checked in blocks of rows, so the check takes little memory on large data)
    """
    if not isinstance(data, Mapping):
        raise OfflineDataError(f"{where} must be a mapping of arrays, got {type(data).__name__}")
    missing = [key for key in REQUIRED_KEYS if key not in data]
    if missing:
        raise OfflineDataError(
            f"{where} is missing the key(s) {missing}; required: {list(REQUIRED_KEYS)}, optional: "
            f"{list(OPTIONAL_KEYS)}; found: {sorted(data.keys())}"
        )
    arrays = {key: _as_array(data, key, where) for key in REQUIRED_KEYS + OPTIONAL_KEYS if key in data}
    for key, array in arrays.items():
        if array.ndim == 0:
            raise OfflineDataError(f"{where} key {key!r} must be an array with one row per transition, got a scalar")
    lengths = {key: len(array) for key, array in arrays.items()}
    if len(set(lengths.values())) != 1:
        raise OfflineDataError(f"{where}: the arrays must all have the same length, got {lengths}")
    total = lengths["observations"]
    if total == 0:
        raise OfflineDataError(f"{where} is empty (0 transitions)")
    obs, next_obs = arrays["observations"], arrays["next_observations"]
    if obs.shape != next_obs.shape:
        raise OfflineDataError(
            f"{where}: observations {obs.shape} and next_observations {next_obs.shape} must have the same shape"
        )
    # bool observations too: what a buffer with a bool Box exports (to_d4rl) imports again
    _check_numeric("observations", obs, allow_int=True, where=where, allow_bool=True)
    _check_numeric("next_observations", next_obs, allow_int=True, where=where, allow_bool=True)
    actions = arrays["actions"]
    _check_numeric("actions", actions, allow_int=integer_actions, where=where)
    if actions.ndim == 1:
        actions = actions.reshape(total, 1)
    elif actions.ndim > 2:
        raise OfflineDataError(f"{where}: actions must be [N, action_dim] (or [N]), got shape {actions.shape}")
    rewards = arrays["rewards"]
    _check_numeric("rewards", rewards, allow_int=True, where=where)
    if rewards.ndim > 2 or (rewards.ndim == 2 and rewards.shape[1] != 1):
        raise OfflineDataError(f"{where}: rewards must be [N] (or [N, 1]), got shape {rewards.shape}")
    flags = {}
    for key in ("terminals", "timeouts"):
        if key in arrays:
            if arrays[key].ndim > 2 or arrays[key].size != total:
                raise OfflineDataError(f"{where}: {key} must be [N] (or [N, 1]), got shape {arrays[key].shape}")
            flags[key] = _check_flags(key, arrays[key], where)
        else:
            flags[key] = np.zeros(total, dtype=bool)

    def float_obs(array: np.ndarray) -> np.ndarray:
        return array.astype(np.float32) if cast_observations and array.dtype == np.float64 else array

    clean = {
        "observations": float_obs(obs),
        "next_observations": float_obs(next_obs),
        "actions": actions if actions.dtype.kind in "iu" else actions.astype(np.float32),
        "rewards": rewards.reshape(total).astype(np.float32),
        "terminals": flags["terminals"],
        "timeouts": flags["timeouts"],
    }
    if "sources" in arrays:
        sources = arrays["sources"]
        if sources.dtype.kind not in "iu" or sources.size != total or sources.ndim > 2:
            raise OfflineDataError(
                f"{where}: sources must be integer source ids, [N] (or [N, 1]), got {sources.dtype} {sources.shape}"
            )
        if sources.min() < 0 or sources.max() > MAX_SOURCE_ID:
            raise OfflineDataError(
                f"{where}: sources must be in [0, {MAX_SOURCE_ID}], got values in [{sources.min()}, {sources.max()}]"
            )
        clean["sources"] = sources.reshape(total).astype(np.int64)
    return clean


def record_transitions(env: Any, act: Callable[[Any], Any], steps: int, seed: Optional[int] = None) -> dict[str, np.ndarray]:
    """
    Run a policy in an env and keep what it did as d4rl columns: a dataset for :meth:`CRR.from_offline_data` or
    :func:`~sb3_lifelong.buffers.from_d4rl`, recorded with any policy (an SB3 model's ``predict``, a script, random).

    The env is reset with ``seed`` once, then without a seed after each episode's end, so one seed gives one dataset.

    :param env: a Gymnasium env
    :param act: the policy: an observation in, an action (in the env's units) out, e.g.
        ``lambda obs: model.predict(obs, deterministic=False)[0]``
    :param steps: transitions to record (an unfinished last episode is kept, not flagged)
    :param seed: the seed of the first reset
    :return: ``observations``, ``actions``, ``rewards``, ``next_observations``, ``terminals``, ``timeouts``
    """
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    keys = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")
    columns: dict[str, list] = {key: [] for key in keys}
    obs, _ = env.reset(seed=seed)
    for _ in range(int(steps)):
        action = act(obs)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for key, value in zip(columns, (obs, action, reward, next_obs, terminated, truncated)):
            columns[key].append(value)
        obs = env.reset()[0] if terminated or truncated else next_obs
    return {key: np.asarray(value) for key, value in columns.items()}


def load_d4rl(data: Union[Mapping[str, Any], str, os.PathLike]) -> dict[str, np.ndarray]:
    """
    Read and validate a d4rl-style dict or ``.npz`` file (read without pickle).

    :param data: the dict, or the path of a ``.npz`` file
    :return: the validated dict (see :func:`validate_d4rl`)
    """
    return validate_d4rl(read_npz(data) if isinstance(data, (str, os.PathLike)) else data)


def read_npz(file: Union[str, os.PathLike]) -> dict[str, np.ndarray]:
    """
    The arrays of a ``.npz`` archive, read without pickle (no validation: see :func:`validate_d4rl`).

    :param file: the ``.npz`` file
    :return: its arrays by name
    :raises FileNotFoundError: if there is no such file
    :raises OfflineDataError: naming the file (and the array) for anything else than named arrays readable without
        pickle: a single ``np.save`` array, pickled content, object arrays, an archive (or a member) that is truncated
        or damaged
    """
    name = os.fspath(file)
    if not os.path.isfile(name):
        raise FileNotFoundError(f"no offline data file at {name!r}")
    try:
        loaded = np.load(name, allow_pickle=False)
    except ValueError as error:  # pickled content, or not a numpy file at all
        raise OfflineDataError(
            f"{name}: not a .npz archive of arrays that can be read without pickle (nothing pickled is loaded): {error}"
        ) from None
    except (zipfile.BadZipFile, EOFError) as error:  # an archive cut short (or damaged), an empty file
        raise OfflineDataError(
            f"{name}: not a readable .npz archive: it is truncated or damaged ({type(error).__name__}: {error}); nothing "
            "was read. Write it again (np.savez), or copy it again from where it came"
        ) from None
    if not hasattr(loaded, "files"):  # np.save wrote one array (a .npy file): no names
        raise OfflineDataError(
            f"{name}: holds a single array (written by np.save), not a .npz archive of named arrays: write the data with "
            "np.savez(file, observations=..., actions=..., rewards=..., next_observations=..., terminals=...)"
        )
    result = {}
    with loaded as npz:
        for key in npz.files:
            try:
                result[key] = npz[key]
            except (ValueError, zipfile.BadZipFile, EOFError, zlib.error) as error:
                if _stored_with_pickle(npz, key):  # object arrays need pickle
                    raise OfflineDataError(
                        f"{name}: array {key!r} is stored with pickle (object dtype), which is refused (arrays are read "
                        f"without pickle): {error}"
                    ) from None
                raise OfflineDataError(
                    f"{name}: array {key!r} cannot be read: the archive is truncated or damaged ({type(error).__name__}: "
                    f"{error}); nothing was read. Write it again (np.savez), or copy it again from where it came"
                ) from None
    return result


def _stored_with_pickle(npz: Any, key: str) -> bool:
    """Whether the member ``key`` of an open ``.npz`` has an intact ``.npy`` header naming a dtype with objects."""
    try:
        with npz.zip.open(f"{key}.npy") as member:
            version = np.lib.format.read_magic(member)
            if version == (1, 0):
                _, _, dtype = np.lib.format.read_array_header_1_0(member)
            else:
                _, _, dtype = np.lib.format.read_array_header_2_0(member)
    except Exception:  # a header cut short or damaged: not what pickle would need
        return False
    return bool(dtype.hasobject)


def import_minari(purpose: str) -> Any:
    """
    Import the optional package ``minari``.

    :param purpose: What needs it (for the error message)
    :return: The ``minari`` module
    :raises ImportError: telling how to install it
    """
    try:
        import minari
    except ImportError as error:
        raise ImportError(
            f"{purpose} needs the optional package minari (`pip install minari[hdf5]`, or `pip install sb3_lifelong[extra]`)"
        ) from error
    return minari


def minari_columns(dataset: Any, info_keys: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """
    Flatten the episodes of a Minari dataset into columns of transitions, as they are stored (no dtype conversion,
    no validation): ``observations[t]`` and ``observations[t + 1]`` of each episode become a transition.

    :param dataset: A dataset object with ``iterate_episodes()`` (a ``minari.MinariDataset`` or a duck-typed one)
    :param info_keys: Keys of the episodes' ``infos`` to return too, as ``info/<key>``: step ``t`` gets
        ``infos[key][t + 1]`` (Minari's ``infos`` start with the one of ``reset``). Returned only when every episode
        has the key with one entry per observation
    :return: ``observations``, ``next_observations``, ``actions``, ``rewards``, ``terminals``, ``timeouts`` (boolean),
        ``episode_lengths`` (one entry per episode) and the ``info/<key>`` columns found
    """
    columns: dict[str, list[np.ndarray]] = {key: [] for key in ("observations", "next_observations", "actions")}
    columns.update(rewards=[], terminals=[], timeouts=[], episode_lengths=[])
    infos: dict[str, list[np.ndarray]] = {key: [] for key in info_keys}
    for episode in dataset.iterate_episodes():
        observations = episode.observations
        if isinstance(observations, dict):
            raise OfflineDataError("Minari episodes with dict observations are not supported; flatten them first")
        observations = np.asarray(observations)
        steps = len(episode.actions)
        if len(observations) != steps + 1:
            raise OfflineDataError(
                f"Minari episode {getattr(episode, 'id', '?')}: expected {steps + 1} observations for {steps} actions, "
                f"got {len(observations)}"
            )
        columns["observations"].append(observations[:-1])
        columns["next_observations"].append(observations[1:])
        columns["actions"].append(np.asarray(episode.actions))
        columns["rewards"].append(np.asarray(episode.rewards))
        columns["terminals"].append(np.asarray(episode.terminations, dtype=bool))
        columns["timeouts"].append(np.asarray(episode.truncations, dtype=bool))
        columns["episode_lengths"].append(np.array([steps], dtype=np.int64))
        episode_infos = getattr(episode, "infos", None) or {}
        for key in list(infos):
            value = episode_infos.get(key) if isinstance(episode_infos, Mapping) else None
            if value is None or isinstance(value, Mapping) or len(value) != steps + 1:
                del infos[key]  # not usable: dropped for the whole dataset
            else:
                infos[key].append(np.asarray(value)[1:])
    if not columns["observations"]:
        raise OfflineDataError("the Minari dataset has no episodes")
    result = {key: np.concatenate(values) for key, values in columns.items()}
    result.update({f"info/{key}": np.concatenate(values) for key, values in infos.items()})
    return result


def minari_to_d4rl(dataset: Any) -> tuple[dict[str, np.ndarray], Optional[spaces.Space], Optional[spaces.Space]]:
    """
    Flatten a Minari dataset into a d4rl dict (``observations[t]``, ``observations[t + 1]`` of each episode become a
    transition; ``terminations`` and ``truncations`` become ``terminals`` and ``timeouts``).

    :param dataset: a Minari dataset id (loaded with ``minari.load_dataset``; needs ``minari`` installed) or a
        dataset object with ``iterate_episodes()``
    :return: the validated dict, and the dataset's observation and action spaces (None when it has none)
    """
    if isinstance(dataset, str):
        minari = import_minari(f"{dataset!r} is not a file, so it was taken as a Minari dataset id; loading it")
        dataset = minari.load_dataset(dataset)
    columns = minari_columns(dataset)
    data = validate_d4rl({key: columns[key] for key in (*REQUIRED_KEYS, "timeouts")})
    return data, getattr(dataset, "observation_space", None), getattr(dataset, "action_space", None)


def replay_buffer_to_d4rl(buffer: ReplayBuffer) -> dict[str, np.ndarray]:
    """
    Export an SB3 ``ReplayBuffer`` (or any buffer with a ``to_d4rl()`` method) as a d4rl dict, each env's
    transitions contiguous and in time order. Actions stay as stored, i.e. normalised to ``[-1, 1]`` for the
    buffers that SB3 algorithms with squashed policies fill.

    :param buffer: the buffer (not a ``DictReplayBuffer``; ``optimize_memory_usage`` is supported)
    :return: the validated dict
    """
    to_d4rl = getattr(buffer, "to_d4rl", None)
    if callable(to_d4rl):
        return validate_d4rl(to_d4rl())
    if isinstance(buffer.observations, dict):
        raise OfflineDataError("Dict-observation replay buffers cannot be exported to a d4rl dict")
    size = buffer.size()
    if size == 0:
        raise OfflineDataError("the replay buffer is empty")
    # rows in time order: a full circular buffer starts at pos
    order = (np.arange(size) + buffer.pos) % buffer.buffer_size if buffer.full else np.arange(size)
    columns: dict[str, list[np.ndarray]] = {key: [] for key in (*REQUIRED_KEYS, "timeouts")}
    for env_index in range(buffer.n_envs):
        if buffer.optimize_memory_usage:
            next_obs = buffer.observations[(order + 1) % buffer.buffer_size, env_index]
        else:
            next_obs = buffer.next_observations[order, env_index]
        dones = buffer.dones[order, env_index].astype(bool)
        timeouts = buffer.timeouts[order, env_index].astype(bool) & dones
        columns["observations"].append(buffer.observations[order, env_index])
        columns["next_observations"].append(next_obs)
        columns["actions"].append(buffer.actions[order, env_index])
        columns["rewards"].append(buffer.rewards[order, env_index])
        columns["terminals"].append(dones & ~timeouts)
        columns["timeouts"].append(timeouts)
    if buffer.optimize_memory_usage:  # the last row's next observation is not stored
        for key in columns:
            columns[key] = [value[:-1] for value in columns[key]]
    return validate_d4rl({key: np.concatenate(values) for key, values in columns.items()})


def _is_box_bounded(space: spaces.Space) -> bool:
    return isinstance(space, spaces.Box) and bool(np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high)))


def infer_spaces(
    data: Mapping[str, np.ndarray],
    observation_space: Optional[spaces.Space] = None,
    action_space: Optional[spaces.Space] = None,
    normalized_actions: bool = False,
) -> tuple[spaces.Space, spaces.Box]:
    """
    Observation and action spaces of a d4rl dict: the given ones (checked against the data), or inferred.

    Inference: an unbounded Box of the observations' shape; for actions ``Box(-1, 1)`` when they are normalised
    or all lie in ``[-1, 1]``, otherwise the per-dimension range of the data (with a warning: pass the
    environment's action space when you know it).

    :param data: a validated d4rl dict
    :param observation_space: observation space to use
    :param action_space: action space to use (a bounded Box)
    :param normalized_actions: whether the data's actions are already normalised to ``[-1, 1]``
    :return: the observation space and the action space
    """
    obs, actions = data["observations"], data["actions"]
    if observation_space is None:
        if obs.dtype == np.uint8:
            observation_space = spaces.Box(0, 255, shape=obs.shape[1:], dtype=np.uint8)
        else:
            observation_space = spaces.Box(-np.inf, np.inf, shape=obs.shape[1:], dtype=np.float32)
    elif observation_space.shape != obs.shape[1:]:
        raise OfflineDataError(
            f"observations have shape {obs.shape[1:]} per transition, the observation space {observation_space}"
        )
    if action_space is None:
        if normalized_actions or (np.abs(actions) <= 1.0).all():
            action_space = spaces.Box(-1.0, 1.0, shape=actions.shape[1:], dtype=np.float32)
        else:
            low, high = actions.min(axis=0), actions.max(axis=0)
            high = np.where(high > low, high, low + 1.0)
            warnings.warn(
                "The action space was inferred from the range of the data's actions "
                f"(low={low.tolist()}, high={high.tolist()}); pass action_space= (or env=) to use the true bounds",
                stacklevel=3,
            )
            action_space = spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
    if not isinstance(action_space, spaces.Box):
        raise OfflineDataError(f"offline learning here needs a continuous (Box) action space, got {action_space}")
    if not _is_box_bounded(action_space):
        raise OfflineDataError(
            f"the action space must have finite bounds (actions are normalised with them), got {action_space}"
        )
    if action_space.shape != actions.shape[1:]:
        raise OfflineDataError(f"actions have shape {actions.shape[1:]} per transition, the action space {action_space}")
    return observation_space, action_space


def normalize_actions(
    data: Union[Mapping[str, np.ndarray], np.ndarray], action_space: spaces.Space, normalized_actions: bool = False
) -> np.ndarray:
    """
    The data's actions normalised to ``[-1, 1]`` with the action space's bounds, as SB3 stores them for squashed
    policies: the one normaliser of every way data comes in (``from_offline_data``,
    ``LifelongReplayBuffer.from_d4rl`` and ``from_minari``). Computed in float64, returned as float32. Actions outside
    the bounds are clipped, with a warning. A space that is not a bounded Box (``from_d4rl`` without an action
    space), or whose bounds already are ``[-1, 1]``, leaves the values as they are (discrete actions keep their
    dtype).

    :param data: the actions ``[N, action_dim]``, or a validated d4rl dict holding them (see :func:`validate_d4rl`)
    :param action_space: the action space (a bounded Box for the actions to be rescaled)
    :param normalized_actions: whether the actions are already normalised to ``[-1, 1]`` (only checked and clipped)
    :return: the normalised actions, float32 (a discrete space's as they are)
    """
    actions = np.asarray(data["actions"] if isinstance(data, Mapping) else data)
    if not isinstance(action_space, spaces.Box):
        return actions
    bounded = isinstance(action_space, spaces.Box) and _is_box_bounded(action_space)
    if not bounded:
        return actions.astype(np.float32)
    assert isinstance(action_space, spaces.Box)
    low, high = action_space.low.astype(np.float64), action_space.high.astype(np.float64)
    if normalized_actions or (np.all(low == -1.0) and np.all(high == 1.0)):
        normalized = actions.astype(np.float32)
    else:
        normalized = (2.0 * (actions.astype(np.float64) - low) / (high - low) - 1.0).astype(np.float32)
    outside = np.abs(normalized) > 1.0 + 1e-5
    if outside.any():
        rows = int(outside.reshape(len(normalized), -1).any(axis=1).sum())
        warnings.warn(f"{rows} of {len(normalized)} actions lie outside the action space's bounds: clipped", stacklevel=3)
    return np.clip(normalized, -1.0, 1.0)
