"""
Lifelong replay buffer: every transition of a robot's life, in memory or in a crash-safe directory.

See ``docs/modules/buffer.md`` for the directory format, the crash guarantees and examples.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from typing import Any, Optional, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, ReplayBufferSamples
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import VecNormalize

from sb3_lifelong.buffers import interop
from sb3_lifelong.buffers.interop import raise_if_not_finite
from sb3_lifelong.buffers.storage import (
    FLAG_DONE,
    FLAG_TIMEOUT,
    MANIFEST_NAME,
    MAX_SOURCE_ID,
    OBS_FIELDS,
    BufferFormatError,
    CommitNotDurableError,
    RowStore,
    check_obs_key,
    obs_keys_of,
    owned_buffer_files,
)
from sb3_lifelong.core.contract import DYNAMICS_PARAMS_KEY, STAGE_KEY
from sb3_lifelong.core.datasets import OfflineSamples

__all__ = ["BufferFormatError", "CommitNotDurableError", "LifelongReplayBuffer"]

_Samples = Union[ReplayBufferSamples, DictReplayBufferSamples]


_vdot = np.vdot
_isfinite = math.isfinite


def _conform(label: str, value: np.ndarray, target: tuple[int, ...], what: str = "") -> np.ndarray:
    """
    ``value`` as an array of shape ``target`` where numpy's assignment rules (as used by SB3's ``ReplayBuffer.add``)
    accept it: leading dimensions of size 1 dropped, then broadcasting. Otherwise a ValueError naming the field.
    """
    shape = value.shape
    while len(shape) > len(target) and shape[0] == 1:
        shape = shape[1:]
    try:
        return np.broadcast_to(value.reshape(shape), target)
    except ValueError:
        where = f"; {what}" if what else ""
        raise ValueError(
            f"add(): {label} have shape {value.shape}, expected {target} ({target[0]} envs, the length of rewards{where})"
        ) from None


def _env_vector(label: str, value: np.ndarray) -> np.ndarray:
    """Rewards given as a scalar (one env) or with leading dimensions of size 1, as a vector (n_envs,)."""
    shape = value.shape
    while len(shape) > 1 and shape[0] == 1:
        shape = shape[1:]
    if len(shape) > 1:
        raise ValueError(f"add(): {label} have shape {value.shape}, expected (n_envs,): one value per env")
    return value.reshape(shape or (1,))


def _space_to_json(space: spaces.Space) -> dict[str, Any]:
    if isinstance(space, spaces.Dict):
        return {"type": "Dict", "spaces": {key: _space_to_json(sub) for key, sub in space.spaces.items()}}
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


def _space_from_json(data: dict[str, Any], dtype: str, shape: tuple[int, ...]) -> spaces.Space:
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
    return spaces.Box(low.reshape(shape), high.reshape(shape), shape=shape, dtype=np_dtype)  # type: ignore[arg-type]


def _observation_space_from_store(store: RowStore) -> spaces.Space:
    """The observation space described by a store's manifest (a Dict space when the observations have keys)."""
    data = store.spaces.get("observation", {})
    data = data if isinstance(data, dict) else {}
    keys = obs_keys_of(store.fields)
    if keys is None:
        return _space_from_json(data, *store.fields["observations"])
    described = data["spaces"] if isinstance(data.get("spaces"), dict) else {}
    subspaces = {}
    for key in keys:
        sub = described.get(key)
        subspaces[key] = _space_from_json(sub if isinstance(sub, dict) else {}, *store.fields[f"observations.{key}"])
    return spaces.Dict(subspaces)


def _observation_fields(observation_space: spaces.Space) -> dict[str, tuple[str, tuple[int, ...]]]:
    """The observation and next-observation fields of a store for an observation space (one pair per Dict key)."""

    def spec(space: spaces.Space) -> tuple[str, tuple[int, ...]]:
        shape: tuple[int, ...] = tuple(get_obs_shape(space))  # type: ignore[arg-type]
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


class _RunIndex:
    """
    Run-length index of the source ids (start row and source of each run), for per-source sampling. Rows are the
    store's global row numbers, so that evicting the oldest rows only moves the point from which runs count.
    """

    def __init__(self, start: int = 0) -> None:
        self.starts = np.zeros(64, dtype=np.int64)
        self.sources = np.zeros(64, dtype=np.int64)
        self.count = 0
        self.total = start  # global row after the last indexed row

    def extend(self, sources: np.ndarray, at: Optional[int] = None) -> None:
        """
        :param sources: Source ids of the rows from ``at``
        :param at: Global row of ``sources[0]`` (default: right after the indexed rows). Rows skipped before it
            (evicted before they were indexed) are counted in the previous run, which only matters for evicted rows
        """
        if at is not None and at > self.total:
            self.total = at
        if len(sources) == 0:
            return
        if self.count and len(sources) == 1 and sources[0] == self.sources[self.count - 1]:
            self.total += 1  # the common case of add() with one env: the last run grows
            return
        breaks = np.flatnonzero(sources[1:] != sources[:-1]) + 1
        new = breaks if self.count and self.sources[self.count - 1] == sources[0] else np.concatenate([[0], breaks])
        if self.count + len(new) > len(self.starts):
            capacity = max(2 * len(self.starts), self.count + len(new))
            self.starts = np.resize(self.starts, capacity)
            self.sources = np.resize(self.sources, capacity)
        self.starts[self.count : self.count + len(new)] = new + self.total
        self.sources[self.count : self.count + len(new)] = sources[new]
        self.count += len(new)
        self.total += len(sources)

    def runs(self, first: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        :param first: Global row of the oldest retained row: runs are cut there
        :return: Start (counted from ``first``), length and source of each run of retained rows
        """
        skip = max(int(np.searchsorted(self.starts[: self.count], first, side="right")) - 1, 0) if first else 0
        if skip > 64 and skip > self.count // 2:  # forget runs of evicted rows for good
            self.starts[: self.count - skip] = self.starts[skip : self.count]
            self.sources[: self.count - skip] = self.sources[skip : self.count]
            self.count -= skip
            skip = 0
        starts = np.maximum(self.starts[skip : self.count], first)
        lengths = np.diff(np.append(starts, self.total))
        return starts - first, lengths, self.sources[skip : self.count]


class _LifelongSampler(ReplayBuffer):
    """
    Sampling shared by :class:`LifelongReplayBuffer` and :class:`LifelongBufferView` (uniform or per-source
    weighted indices, n-step returns, per-source reward scales). Subclasses provide the rows.
    """

    n_steps: int
    gamma: float
    # keys of Dict observations (fields ``observations.<key>``), None for Box / Discrete observations
    _obs_keys: Optional[tuple[str, ...]]

    def _init_sampler(self, n_steps: int, gamma: float) -> None:
        if n_steps < 1:
            raise ValueError(f"n_steps must be >= 1, got {n_steps}")
        self.n_steps = int(n_steps)
        self.gamma = float(gamma)
        self._sampling_weights: dict[int, float] = {}
        self._reward_scale: dict[int, float] = {}

    # ------------------------------------------------------------------ provided by subclasses
    def size(self) -> int:
        raise NotImplementedError

    def _gather(self, names: tuple[str, ...], indices: np.ndarray) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def _source_runs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _read_range(self, name: str, start: int, stop: int) -> np.ndarray:
        raise NotImplementedError

    @property
    def sources(self) -> dict[int, dict[str, Any]]:
        """Source id -> ``{"name": str, "metadata": dict}`` (e.g. the dynamics parameters of a stage)."""
        raise NotImplementedError

    def _field_names(self, names: tuple[str, ...]) -> tuple[str, ...]:
        """Stored fields of ``names``: ``observations`` / ``next_observations`` stand for one field per Dict key."""
        if self._obs_keys is None:
            return names
        result: list[str] = []
        for name in names:
            result.extend([f"{name}.{key}" for key in self._obs_keys] if name in OBS_FIELDS else [name])
        return tuple(result)

    def _gather_rows(self, names: tuple[str, ...], indices: np.ndarray) -> dict[str, Any]:
        """Like ``_gather``, with Dict observations regrouped as ``{key: array}`` under their base name."""
        rows: dict[str, Any] = self._gather(self._field_names(names), indices)
        if self._obs_keys is not None:
            for base in OBS_FIELDS:
                if base in names:
                    rows[base] = {key: rows.pop(f"{base}.{key}") for key in self._obs_keys}
        return rows

    def _check_exportable(self, what: str) -> None:
        if self._obs_keys is not None:
            raise NotImplementedError(
                f"{what} of Dict observations is not supported (d4rl and Minari exports need one observation array)"
            )

    # ------------------------------------------------------------------ SB3 attributes
    @property  # type: ignore[override]
    def pos(self) -> int:
        """Number of stored transitions (the write position of an append-only buffer)."""
        return self.size()

    @pos.setter
    def pos(self, value: int) -> None:
        raise AttributeError("the position of a lifelong buffer is its size and cannot be set")

    @property
    def capacity(self) -> Optional[int]:
        """The number of most recent transitions kept, or None when every transition is kept."""
        return None

    @property  # type: ignore[override]
    def full(self) -> bool:
        """Whether the buffer holds ``capacity`` transitions (new ones evict the oldest); always False without one."""
        capacity = self.capacity
        return capacity is not None and self.size() >= capacity

    @full.setter
    def full(self, value: bool) -> None:
        if value != self.full:
            raise AttributeError("whether a lifelong buffer is full follows from its size and capacity and cannot be set")

    # ------------------------------------------------------------------ per-source options
    def source_counts(self) -> dict[int, int]:
        """
        :return: Number of stored transitions per source id
        """
        _, lengths, run_sources = self._source_runs()
        counts = np.bincount(run_sources, weights=lengths, minlength=1) if len(run_sources) else np.zeros(0)
        return {int(s): int(c) for s, c in enumerate(counts) if c > 0}

    def reward_range(self, block: int = 1 << 20) -> tuple[float, float]:
        """
        The smallest and largest stored reward (as stored: per-source reward scales are not applied), read in blocks
        of rows. With the discount ``gamma``, every policy's return on this data lies in
        ``[min(0, low) / (1 - gamma), max(0, high) / (1 - gamma)]``: the support of a categorical critic that cannot
        diverge.

        :param block: rows read at a time (bounds the memory used)
        :return: ``(low, high)``
        :raises ValueError: the buffer is empty
        """
        total = self.size()
        if total == 0:
            raise ValueError("reward_range() of an empty buffer")
        low, high = np.inf, -np.inf
        for start in range(0, total, block):
            rewards = np.asarray(self._read_range("rewards", start, min(total, start + block)))
            low, high = min(low, float(rewards.min())), max(high, float(rewards.max()))
        return low, high

    def set_sampling_weights(self, weights: Optional[dict[int, float]]) -> None:
        """
        Per-source sampling weights. A transition of source ``s`` is drawn with a probability proportional
        to ``weights[s]`` (sources not listed weigh 1), so source ``s`` makes up a fraction
        ``w_s * N_s / sum_t(w_t * N_t)`` of the batches. ``None`` or ``{}``: uniform over all transitions.

        :param weights: source id -> non-negative weight
        """
        weights = dict(weights or {})
        for source, weight in weights.items():
            if not np.isfinite(weight) or weight < 0:
                raise ValueError(f"sampling weight of source {source} must be finite and >= 0, got {weight}")
        self._sampling_weights = {int(s): float(w) for s, w in weights.items()}

    def set_reward_scale(self, scales: Optional[dict[int, float]]) -> None:
        """
        Per-source reward scale applied at sampling time (stored rewards are unchanged).

        :param scales: source id -> factor (sources not listed: 1)
        """
        scales = dict(scales or {})
        for source, scale in scales.items():
            if not np.isfinite(scale):
                raise ValueError(f"reward scale of source {source} must be finite, got {scale}")
        self._reward_scale = {int(s): float(v) for s, v in scales.items()}

    # ------------------------------------------------------------------ sampling
    def _sample_indices(self, batch_size: int) -> np.ndarray:
        total = self.size()
        if total == 0:
            raise ValueError("cannot sample from an empty buffer")
        if not self._sampling_weights or all(w == 1.0 for w in self._sampling_weights.values()):
            return np.random.randint(0, total, size=batch_size)
        starts, lengths, run_sources = self._source_runs()
        counts = np.bincount(run_sources, weights=lengths)
        ids = np.flatnonzero(counts)
        mass = counts[ids] * np.array([self._sampling_weights.get(int(s), 1.0) for s in ids])
        if mass.sum() <= 0:
            raise ValueError("the sampling weights give zero probability to every stored transition")
        chosen = np.random.choice(len(ids), size=batch_size, p=mass / mass.sum())
        indices = np.empty(batch_size, dtype=np.int64)
        for k in np.unique(chosen):
            where = np.flatnonzero(chosen == k)
            runs = np.flatnonzero(run_sources == ids[k])
            cum = np.cumsum(lengths[runs])
            offset = np.random.randint(0, cum[-1], size=len(where))
            run = np.searchsorted(cum, offset, side="right")
            indices[where] = starts[runs][run] + offset - (cum[run] - lengths[runs][run])
        return indices

    def sample(  # type: ignore[override]
        self,
        batch_size: int,
        env: Optional[VecNormalize] = None,
        return_sources: bool = False,
        next_actions: bool = False,
    ) -> Union[_Samples, tuple[_Samples, th.Tensor]]:
        """
        Sample transitions uniformly (or with the per-source weights) over everything stored.

        :param batch_size: Number of transitions
        :param env: VecNormalize to normalise observations and rewards with
        :param return_sources: Also return the source ids of the batch (a long tensor)
        :param next_actions: Also return the action the data took at each sample's (last) next observation, for
            SARSA targets: ``OfflineSamples`` with ``next_actions`` (zeros where unknown) and ``next_action_mask``
            (1.0 where the same stream goes on after that transition without an episode end)
        :return: The samples (``discounts`` is set when ``n_steps > 1``, like SB3's ``NStepReplayBuffer``;
            ``DictReplayBufferSamples`` for Dict observations), and the source ids if asked.
        """
        samples, sources = self._get_samples_and_sources(self._sample_indices(batch_size), env, next_actions)
        if return_sources:
            return samples, th.as_tensor(sources.astype(np.int64), device=self.device)
        return samples

    def _scaled(self, rewards: np.ndarray, sources: np.ndarray) -> np.ndarray:
        if not self._reward_scale:
            return rewards
        table = np.ones(max(max(self._reward_scale), int(sources.max(initial=0))) + 1, dtype=np.float32)
        for source, scale in self._reward_scale.items():
            table[source] = scale
        return rewards * table[sources]

    def _tensor(self, array: np.ndarray) -> th.Tensor:
        # the gathered arrays are fresh copies: no second copy needed
        return th.as_tensor(array, device=self.device)

    def _obs_tensor(self, obs: Union[np.ndarray, dict[str, np.ndarray]], env: Optional[VecNormalize]) -> Any:
        obs = self._normalize_obs(obs, env)
        if isinstance(obs, dict):
            return {key: self._tensor(value) for key, value in obs.items()}
        return self._tensor(obs)

    def _samples(self, **kwargs: Any) -> Any:
        """``ReplayBufferSamples``, or ``DictReplayBufferSamples`` for Dict observations (as SB3's ``DictReplayBuffer``)."""
        return (ReplayBufferSamples if self._obs_keys is None else DictReplayBufferSamples)(**kwargs)

    def _get_samples(self, batch_inds: np.ndarray, env: Optional[VecNormalize] = None) -> _Samples:  # type: ignore[override]
        return self._get_samples_and_sources(batch_inds, env)[0]

    def _get_samples_and_sources(
        self, batch_inds: np.ndarray, env: Optional[VecNormalize], next_actions: bool = False
    ) -> tuple[_Samples, np.ndarray]:
        """:return: the samples of rows ``batch_inds`` (with the data's next actions if asked) and their source ids"""
        batch_inds = np.asarray(batch_inds, dtype=np.int64)
        if self.n_steps > 1:
            return self._get_n_step_samples(batch_inds, env, next_actions)
        rows = self._gather_rows(("observations", "actions", "next_observations", "rewards", "flags", "sources"), batch_inds)
        flags = rows["flags"]
        dones = ((flags & FLAG_DONE) != 0) & ((flags & FLAG_TIMEOUT) == 0)
        rewards = self._scaled(rows["rewards"], rows["sources"])
        samples = self._samples(
            observations=self._obs_tensor(rows["observations"], env),
            actions=self._tensor(rows["actions"]),
            next_observations=self._obs_tensor(rows["next_observations"], env),
            dones=self._tensor(dones.astype(np.float32).reshape(-1, 1)),
            rewards=self._tensor(self._normalize_reward(rewards.reshape(-1, 1), env).astype(np.float32, copy=False)),
        )
        if next_actions:
            samples = self._with_next_actions(samples, batch_inds, flags)
        return samples, rows["sources"]

    def _get_n_step_samples(
        self, batch_inds: np.ndarray, env: Optional[VecNormalize], next_actions: bool = False
    ) -> tuple[_Samples, np.ndarray]:
        total = self.size()
        first = self._gather_rows(("observations", "actions", "rewards", "flags", "sources", "streams", "widths"), batch_inds)
        steps = np.arange(1, self.n_steps)
        # the next transition of the same env stream is `widths` rows further (the n_envs of the add() that wrote it)
        succ = batch_inds[:, None] + steps[None, :] * first["widths"].astype(np.int64)[:, None]
        in_range = succ < total
        succ = np.where(in_range, succ, batch_inds[:, None])
        later = self._gather(("rewards", "flags", "sources", "streams"), succ.reshape(-1))
        shape = succ.shape
        linked = in_range & (later["streams"].reshape(shape) == first["streams"][:, None])
        flags = np.concatenate([first["flags"][:, None], later["flags"].reshape(shape)], axis=1)
        rewards = np.concatenate([first["rewards"][:, None], later["rewards"].reshape(shape)], axis=1)
        sources = np.concatenate([first["sources"][:, None], later["sources"].reshape(shape)], axis=1)
        indices = np.concatenate([batch_inds[:, None], succ], axis=1)
        # step k counts if steps 0..k-1 did not end an episode (done or timeout) and step k follows in the same stream
        step_ok = np.ones(indices.shape, dtype=bool)
        step_ok[:, 1:] = ((flags[:, :-1] & (FLAG_DONE | FLAG_TIMEOUT)) == 0) & linked
        mask = np.logical_and.accumulate(step_ok, axis=1)
        count = mask.sum(axis=1)
        rewards = self._normalize_reward(self._scaled(rewards, sources), env)
        powers = self.gamma ** np.arange(self.n_steps, dtype=np.float32)
        returns = (rewards * powers[None, :] * mask).sum(axis=1, keepdims=True).astype(np.float32)
        discounts = (self.gamma ** count.astype(np.float32)).reshape(-1, 1).astype(np.float32)
        rows = np.arange(len(batch_inds))
        last = indices[rows, count - 1]
        last_flags = flags[rows, count - 1]
        final_dones = ((last_flags & FLAG_DONE) != 0) & ((last_flags & FLAG_TIMEOUT) == 0)
        next_obs = self._gather_rows(("next_observations",), last)["next_observations"]
        samples = self._samples(
            observations=self._obs_tensor(first["observations"], env),
            actions=self._tensor(first["actions"]),
            next_observations=self._obs_tensor(next_obs, env),
            dones=self._tensor(final_dones.astype(np.float32).reshape(-1, 1)),
            rewards=self._tensor(returns),
            discounts=self._tensor(discounts),
        )
        if next_actions:
            samples = self._with_next_actions(samples, last, last_flags)
        return samples, first["sources"]

    def _with_next_actions(self, samples: _Samples, last: np.ndarray, last_flags: np.ndarray) -> OfflineSamples:
        """
        :param samples: the batch
        :param last: the row whose next observation each sample bootstraps from
        :param last_flags: the flags of those rows
        :return: the batch plus the action taken at that next observation, where the same stream goes on
        """
        total = self.size()
        own = self._gather(("streams", "widths"), last)
        successor = last + own["widths"].astype(np.int64)
        in_range = successor < total
        later = self._gather(("actions", "streams"), np.where(in_range, successor, last))
        known = in_range & (later["streams"] == own["streams"]) & ((last_flags & (FLAG_DONE | FLAG_TIMEOUT)) == 0)
        actions = np.where(known[:, None], later["actions"].reshape(len(last), -1), 0.0).astype(np.float32)
        return OfflineSamples(
            observations=samples.observations,
            actions=samples.actions,
            next_observations=samples.next_observations,
            dones=samples.dones,
            rewards=samples.rewards,
            discounts=samples.discounts,
            next_actions=self._tensor(actions.reshape(len(last), *later["actions"].shape[1:])),
            next_action_mask=self._tensor(known.astype(np.float32).reshape(-1, 1)),
        )

    # ------------------------------------------------------------------ export
    def to_d4rl(self, by_episode: bool = True, normalized_actions: bool = False) -> dict[str, np.ndarray]:
        """
        Materialise the whole buffer as a d4rl-style dict (in memory).

        :param by_episode: Order the rows stream by stream (each env's trajectory contiguous, as d4rl expects)
            and mark the last row of a stream that did not end an episode as a timeout. Otherwise keep the
            stored order (transitions of parallel envs interleaved).
        :param normalized_actions: Export the actions as stored (SB3 stores Box actions normalised to
            ``[-1, 1]``). By default they are rescaled to the action space's bounds (environment units, the d4rl
            convention), when the space is a bounded Box.
        :return: ``observations``, ``actions``, ``rewards``, ``next_observations``, ``terminals`` (done and not a
            timeout), ``timeouts`` (time-limit truncations) and ``sources`` (source id of each transition)
        """
        return interop.to_d4rl(self, by_episode, normalized_actions)

    def to_minari(
        self,
        dataset_id: str,
        normalized_actions: bool = False,
        unfinished: str = "truncate",
        description: Optional[str] = None,
        **minari_kwargs: Any,
    ) -> Any:
        """
        Write the buffer as a new local Minari dataset (under ``MINARI_DATASETS_PATH``, default ``~/.minari/datasets``).
        Needs the optional package ``minari`` (``pip install minari[hdf5]``). The data is materialised in memory.

        Episodes: the rows of each env stream (see :meth:`to_d4rl`), split after every episode end (done or
        time-limit truncation), and also where ``next_observations[t] != observations[t + 1]`` inside a stream
        (a Minari episode is one chain of observations: the cut is written as a truncation). The source id of step
        ``t`` is written to ``infos["sb3_lifelong_source"][t + 1]`` (``[0]`` repeats it for the reset), and the
        sources' names and metadata to the dataset metadata ``sb3_lifelong_sources``, so that :meth:`from_minari`
        restores them.

        :param dataset_id: Minari dataset id, ``(namespace/)(env_name/)dataset_name(-v<version>)``; must not exist
        :param normalized_actions: Write the actions as stored (normalised to ``[-1, 1]``, with a ``Box(-1, 1)``
            action space). By default they are in environment units (as :meth:`to_d4rl`) with the buffer's space
        :param unfinished: The last episode of a stream that has not ended yet (the write head of an env, or a stream
            cut by a reopen, an ``n_envs`` change or ``end_streams()``): ``"truncate"`` writes it with its last step
            marked as a truncation (as :meth:`to_d4rl` does), ``"drop"`` leaves it out
        :param description: Dataset description (default: says where it comes from)
        :param minari_kwargs: Further arguments of ``minari.create_dataset_from_buffers`` (``author``,
            ``author_email``, ``algorithm_name``, ``code_permalink``, ``env``, ``eval_env``, ``data_format``, ...).
            Image observations are stored losslessly (``jpeg_encoding=False``) unless asked otherwise
        :return: The ``minari.MinariDataset``
        """
        return interop.to_minari(self, dataset_id, normalized_actions, unfinished, description, **minari_kwargs)

    def save_npz(self, file: Union[str, os.PathLike]) -> None:
        """
        Write :meth:`to_d4rl` to a ``.npz`` file (no pickle inside).

        :param file: Target file
        """
        interop.save_npz(self, file)


BUFFER_MODES = ("new", "append", "overwrite")


def _prepare_directory(path: str, mode: str) -> int:
    """
    Check the constructor's ``mode`` against a buffer directory about to be opened for writing. ``"overwrite"`` only
    checks here that the directory holds one of this package's buffers (else ``BufferFormatError``, before anything
    is created there); the store deletes it once it holds the directory's writer lock.

    :return: the transitions it already holds (-1: a manifest that cannot be read; the store reports it)
    """
    if mode not in BUFFER_MODES:
        raise ValueError(f"mode must be one of {BUFFER_MODES}, got {mode!r}")
    manifest = os.path.join(path, MANIFEST_NAME)
    if mode == "overwrite":
        owned_buffer_files(path)  # refuses a directory that is not provably a buffer of this package
        return 0
    if not os.path.isfile(manifest):
        return 0
    try:
        with open(manifest) as handle:
            return int(json.load(handle).get("num_transitions", 0))
    except (OSError, ValueError, TypeError, AttributeError):
        return -1


class LifelongReplayBuffer(_LifelongSampler):
    """
    Replay buffer that keeps every transition (or the most recent ``capacity`` ones), tagged with its source
    (stage), in memory or in a crash-safe directory of append-only files, read with memory maps or positioned reads
    (``read_mode``).

    Drop-in ``replay_buffer_class`` for SB3 off-policy algorithms: ``buffer_size`` is recorded but never
    evicts anything (``capacity`` does), and ``add()`` accepts any number of envs (each env of each ``add`` width
    is its own stream).

    :param buffer_size: SB3's buffer size: informational only, nothing is evicted because of it (see ``capacity``)
    :param observation_space: Observation space (Box, Discrete, or Dict of those; optional when opening a ``path``)
    :param action_space: Action space (optional when opening an existing ``path``)
    :param device: PyTorch device of the sampled tensors
    :param n_envs: Number of parallel envs expected first (any number is accepted later)
    :param optimize_memory_usage: Not supported (must be False)
    :param handle_timeout_termination: Record ``info["TimeLimit.truncated"]`` so that time-limit ends are not
        treated as terminal states (as SB3's ``ReplayBuffer``)
    :param n_steps: Length of the n-step returns computed at sampling time (1: one-step, ``discounts`` is None)
    :param gamma: Discount of the n-step returns
    :param path: Buffer directory (created if missing, continued if it exists); None: in memory
    :param read_only: Open an existing ``path`` without writing (another process may be writing to it)
    :param chunk_size: Transitions per flushed chunk (at most this many are lost by a crash)
    :param verify: Checksums verified when opening an existing path: "last" (default): only those of the last
        committed chunk, so opening is fast whatever the size, but a corrupted byte in an earlier chunk (e.g. a bit
        flipped on disk) is NOT detected and is served as it is by sampling and reads; "all": every chunk (reads the
        whole buffer once when opening; raises ``BufferFormatError`` on a mismatch); "none": no checksum (file sizes
        are always checked)
    :param source: Initial source id of transitions whose ``info`` has no ``"stage"``
    :param max_resident_bytes: With a path and ``read_mode="mmap"``: remap the files after random reads may have
        made about this many bytes of them resident, to bound the RSS of sampling a buffer larger than RAM (None: never)
    :param capacity: Keep only the most recent ``capacity`` transitions (counted over all envs, like SB3's
        ``buffer_size``): adding to a full buffer evicts the oldest ones (FIFO). None (default): keep everything.
        A directory stores its chunks in separate files, deleted once every row of the chunk is evicted. When
        reopening a directory, None keeps its stored capacity; a directory created without one cannot get one
    :param read_mode: With a path, how stored transitions are read: ``"mmap"`` (default: memory maps; fastest, but
        every file page a read touches counts in the process's RSS) or ``"pread"`` (positioned reads into new arrays,
        about one system call per row and field: several times slower, but no file page is mapped, so the RSS stays
        at the process's own memory). Both give bit-identical samples. No effect in memory
    :param mode: With a path to write to, what to do when the directory already holds a buffer with transitions:
        ``"new"`` (default) opens it, but the first ``add`` raises an error that names the two choices, so that a
        re-run never mixes its data into an earlier run's silently (reading and sampling it, and SB3's ``load`` of a
        model whose buffer lives there, work as usual); ``"append"`` continues it (what :meth:`open` does: resuming
        after a crash or a stop); ``"overwrite"`` deletes that buffer and starts empty. Overwriting deletes only what
        provably belongs to a buffer of this package (a manifest this code parses and validates, the data files it
        names, unreferenced chunk files and its temporary file; other files of the directory are kept), and only
        once this buffer holds the directory's writer lock: a directory with a live writer is refused with the error a
        second writer gets (``RuntimeError``), one whose ``manifest.json`` is not such a buffer's with a
        ``BufferFormatError`` naming it, both before anything is deleted. Ignored with ``read_only=True``
    :param evict: Reopening a directory with a ``capacity`` smaller than the number of transitions it holds evicts
        the oldest of them at once: only with ``evict=True``; otherwise that raises a ``ValueError`` (nothing changes)
    """

    def __init__(
        self,
        buffer_size: int = 0,
        observation_space: Optional[spaces.Space] = None,
        action_space: Optional[spaces.Space] = None,
        device: Union[th.device, str] = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        n_steps: int = 1,
        gamma: float = 0.99,
        path: Optional[Union[str, os.PathLike]] = None,
        read_only: bool = False,
        chunk_size: int = 10_000,
        verify: str = "last",
        source: int = 0,
        max_resident_bytes: Optional[int] = None,
        capacity: Optional[int] = None,
        read_mode: str = "mmap",
        mode: str = "new",
        evict: bool = False,
    ) -> None:
        # BaseBuffer.__init__ is not called: it would allocate and assign attributes that are properties here
        if optimize_memory_usage:
            raise ValueError("LifelongReplayBuffer stores next observations: optimize_memory_usage is not supported")
        if isinstance(action_space, (spaces.Dict, spaces.Tuple)):
            raise NotImplementedError(f"LifelongReplayBuffer supports Box and Discrete action spaces, not {action_space}")
        if isinstance(observation_space, spaces.Tuple):
            raise NotImplementedError("LifelongReplayBuffer does not support Tuple observation spaces (Dict ones are)")
        path_str = None if path is None else os.fspath(path)
        held = _prepare_directory(path_str, mode) if path_str is not None and not read_only else 0
        #: a re-run must not add to an earlier run's data silently: without mode="append", adding to a directory that
        #: held transitions when it was opened is refused (reading, sampling and SB3's load of a model still work)
        self._refused_writes = f"{path_str!r} held {held:,} transitions when it was opened" if held and mode == "new" else ""
        fields: Optional[dict[str, tuple[str, tuple[int, ...]]]] = None
        if observation_space is not None and action_space is not None:
            action_dtype = self._maybe_cast_dtype(action_space.dtype)
            fields = {
                **_observation_fields(observation_space),
                "actions": (np.dtype(action_dtype).str, (get_action_dim(action_space),)),
                "rewards": ("<f4", ()),
                "flags": ("|u1", ()),
                "sources": ("<u2", ()),
                "streams": ("<u4", ()),
                "widths": ("<u2", ()),
            }
        elif path_str is None:
            raise ValueError("observation_space and action_space are required for a new buffer")
        self.store = RowStore(
            fields,
            path=path_str,
            read_only=read_only,
            chunk_size=chunk_size,
            verify=verify,
            max_resident_bytes=max_resident_bytes,
            capacity=capacity,
            read_mode=read_mode,
            overwrite=mode == "overwrite" and not read_only,
            evict=evict,
        )
        if not self.store.spaces and observation_space is not None and action_space is not None and not read_only:
            self.store.describe_spaces(
                {"observation": _space_to_json(observation_space), "action": _space_to_json(action_space)}
            )
        if observation_space is None or action_space is None:
            act_dtype, act_shape = self.store.fields["actions"]
            observation_space = _observation_space_from_store(self.store)
            action_space = _space_from_json(self.store.spaces.get("action", {}), act_dtype, act_shape)
        self._obs_keys = obs_keys_of(self.store.fields)
        self.observation_space = observation_space
        self.action_space = action_space
        self.obs_shape = get_obs_shape(observation_space)  # type: ignore[assignment]
        self.action_dim = get_action_dim(action_space)
        self.device = get_device(device)
        self.n_envs = n_envs
        self.requested_buffer_size = buffer_size
        self.optimize_memory_usage = False
        self.handle_timeout_termination = handle_timeout_termination
        self._init_sampler(n_steps, gamma)
        self._source = self._check_source(source)
        self._stream_base: Optional[int] = None
        self._width = 0
        self._runs = _RunIndex(self.store.first)
        self._index_sources(0)

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def open(
        cls,
        path: Union[str, os.PathLike],
        read_only: bool = False,
        device: Union[th.device, str] = "auto",
        read_mode: str = "mmap",
        **kwargs: Any,
    ) -> LifelongReplayBuffer:
        """
        Open an existing buffer directory (the spaces are read from its manifest).

        :param path: Buffer directory
        :param read_only: Do not write (another process may be writing; call :meth:`refresh` to see its new data)
        :param device: PyTorch device of the sampled tensors
        :param read_mode: ``"mmap"`` (memory maps) or ``"pread"`` (positioned reads, no file page mapped into the
            process), see the constructor
        :param kwargs: Further constructor arguments (``n_steps``, ``gamma``, ``verify``, ...)
        :return: The buffer
        """
        if not os.path.isdir(os.fspath(path)):
            raise FileNotFoundError(f"no buffer directory at {os.fspath(path)!r}")
        kwargs.setdefault("mode", "append")
        return cls(path=path, read_only=read_only, device=device, read_mode=read_mode, **kwargs)

    @classmethod
    def from_d4rl(
        cls,
        data: Union[dict[str, np.ndarray], str, os.PathLike],
        observation_space: Optional[spaces.Space] = None,
        action_space: Optional[spaces.Space] = None,
        source: int = 0,
        normalized_actions: bool = False,
        **kwargs: Any,
    ) -> LifelongReplayBuffer:
        """
        Build a buffer from a d4rl-style dict or ``.npz`` file (``observations``, ``actions``, ``rewards``,
        ``next_observations``, ``terminals``, optional ``timeouts`` and ``sources``). Consecutive rows are one
        trajectory unless an episode ends or ``next_observations[i] != observations[i + 1]``.

        :param data: The dict, or the path of a ``.npz`` (read without pickle)
        :param observation_space: Defaults to an unbounded Box of the observations' shape and dtype
        :param action_space: Defaults to an unbounded Box of the actions' shape and dtype
        :param source: Source id of every row when the data has no ``sources``
        :param normalized_actions: Whether the actions are already normalised to ``[-1, 1]`` (as SB3 stores
            them). By default they are in environment units (the d4rl convention) and are normalised with the
            bounds of ``action_space`` (left as they are when the space is unbounded).
        :param kwargs: Constructor arguments (``path``, ``device``, ``n_steps``, ...)
        :return: The buffer
        """
        return interop.from_d4rl(cls, data, observation_space, action_space, source, normalized_actions, **kwargs)

    @classmethod
    def from_minari(
        cls,
        dataset: Any,
        path: Optional[Union[str, os.PathLike]] = None,
        source: Optional[int] = None,
        source_name: Optional[str] = None,
        source_metadata: Optional[dict[str, Any]] = None,
        normalized_actions: bool = False,
        observation_space: Optional[spaces.Space] = None,
        action_space: Optional[spaces.Space] = None,
        **kwargs: Any,
    ) -> LifelongReplayBuffer:
        """
        Build a buffer from a Minari dataset (each episode becomes one env stream: n-step returns never cross
        episodes). Needs the optional package ``minari`` to load a dataset by id.

        :param dataset: A Minari dataset id (loaded with ``minari.load_dataset`` from ``MINARI_DATASETS_PATH``) or a
            dataset object (``minari.MinariDataset``, or anything with ``iterate_episodes()``)
        :param path: Buffer directory (None: in memory)
        :param source: Source id of every transition. None: the per-step source ids written by :meth:`to_minari`
            (with their names and metadata) when the dataset has them, else 0
        :param source_name: Name of ``source`` (default ``"minari:<dataset id>"``)
        :param source_metadata: Metadata of ``source``, added to ``minari_dataset_id``, ``minari_total_episodes``
            and ``minari_total_steps`` (restored sources get ``minari_dataset_id`` added to their metadata)
        :param normalized_actions: Whether the dataset's actions are already normalised to ``[-1, 1]``. By default
            they are in environment units (the Minari convention) and are normalised with the action space's bounds
        :param observation_space: Defaults to the dataset's
        :param action_space: Defaults to the dataset's
        :param kwargs: Further constructor arguments (``device``, ``n_steps``, ``chunk_size``, ...)
        :return: The buffer
        """
        return interop.from_minari(
            cls,
            dataset,
            path,
            source,
            source_name,
            source_metadata,
            normalized_actions,
            observation_space,
            action_space,
            **kwargs,
        )

    # ------------------------------------------------------------------ sources
    @staticmethod
    def _check_source(source: int) -> int:
        if not isinstance(source, (int, np.integer)) or isinstance(source, bool) or not 0 <= source <= MAX_SOURCE_ID:
            raise ValueError(f"source ids are ints in [0, {MAX_SOURCE_ID}], got {source!r}")
        return int(source)

    def _ensure_source(self, source: int, name: Optional[str] = None, metadata: Optional[dict[str, Any]] = None) -> None:
        known = self.store.source(source)
        if known is None:
            self.store.set_source(source, name or f"source_{source}", metadata or {})
        elif name is not None or metadata is not None:
            self.store.set_source(source, name or known["name"], metadata if metadata is not None else known["metadata"])

    @property
    def sources(self) -> dict[int, dict[str, Any]]:
        """Source id -> ``{"name": str, "metadata": dict}`` (e.g. the dynamics parameters of a stage)."""
        return self.store.source_table()

    def set_source(self, source: int, name: Optional[str] = None, metadata: Optional[dict[str, Any]] = None) -> None:
        """
        Source of the next transitions whose ``info`` carries no ``"stage"`` (``contract.STAGE_KEY``), with an optional
        name and metadata.

        :param source: Source id in [0, 65534]
        :param name: Name (default ``"source_<id>"``)
        :param metadata: JSON-serialisable dict (e.g. the physical parameters of this environment variant)
        """
        self._source = self._check_source(source)
        self._ensure_source(self._source, name, metadata)

    def _source_of(self, info: dict[str, Any]) -> int:
        stage = info.get(STAGE_KEY)
        if stage is None:
            return self._source
        source = int(stage)
        known = self.store.source(source)
        if known is not None and known["name"] != f"source_{source}":
            return source  # named already: by an earlier transition of this stage, or by set_source(name=...)
        source = self._check_source(source)
        params = info.get(DYNAMICS_PARAMS_KEY)
        metadata = {str(k): float(v) for k, v in params.items()} if isinstance(params, dict) else {}
        self.store.set_source(source, f"stage_{source}", metadata)
        return source

    # ------------------------------------------------------------------ writing
    def end_streams(self) -> None:
        """Start new env streams at the next ``add`` (n-step returns never chain across this point)."""
        self._stream_base = None

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """
        Append one transition per env (SB3 semantics). Any number of envs is accepted: ``n_envs`` is the length of
        ``reward``.

        Every argument is checked before anything is stored, and a ``ValueError`` naming the field, the expected and
        the received shape is raised for a shape SB3's ``ReplayBuffer.add`` would not accept for ``n_envs`` envs
        (observations: ``(n_envs, *obs_shape)`` or what numpy broadcasts to it, any array of ``n_envs`` elements for
        Discrete spaces; actions: ``(n_envs, action_dim)`` or ``(n_envs, *action_shape)``, unbatched for one env;
        rewards and dones: ``(n_envs,)``; ``len(infos) == n_envs``). Shapes are never reshaped across envs (a
        transposed array is refused, not scrambled). A NaN or infinite observation, next observation, action or
        reward (after conversion to the stored dtype) raises a ``ValueError`` naming the field and the env; nothing of
        that call is stored.

        In a directory, the add() that completes a chunk writes and commits it. If that fails (``OSError``, e.g. disk
        full), the error names the directory, none of the call's transitions is stored (in this object or on disk)
        and the transitions pending before it stay in memory: repeat the call once the cause is fixed. A
        ``CommitNotDurableError`` (an ``OSError``) means that the chunk was committed, with this call's
        transitions, but that the fsync of the directory after the manifest's rename failed, so the commit may not
        survive a power loss; ``flush()`` syncs it again.

        :param obs: Observations, leading dimension n_envs
        :param next_obs: Next observations (the terminal observation where an episode ended)
        :param action: Actions
        :param reward: Rewards
        :param done: Episode ends (terminations and time-limit truncations)
        :param infos: One info dict per env (``"TimeLimit.truncated"``, ``"stage"``, ``"dynamics_params"``)
        """
        if getattr(self, "_refused_writes", ""):  # (absent from pickles of earlier versions)
            raise FileExistsError(
                f"{self._refused_writes}: adding would mix this run's data into it. Pass mode='append' to continue it "
                "(as LifelongReplayBuffer.open does; in SB3: replay_buffer_kwargs={'path': ..., 'mode': 'append'}), "
                "mode='overwrite' to delete it and start again, or choose another path."
            )
        reward = np.asarray(reward, dtype=np.float32)
        if reward.ndim != 1:
            reward = _env_vector("rewards", reward)
        width = len(reward)
        if len(infos) != width:
            raise ValueError(
                f"add(): infos has {len(infos)} entries for {width} envs (the length of rewards): expected one info dict "
                "per env"
            )
        if width != self._add_width:
            self._set_add_shapes(width)
        flags = np.array(done, dtype=bool)  # a copy: stored as the flags (bit 0: done), timeouts set in place below
        if flags.shape != self._add_done:
            flags = np.array(_conform("dones", flags, self._add_done))
        actions = np.asarray(action)
        if actions.shape != self._add_actions:
            actions = self._conform_actions(actions, width)
        if actions.dtype != self._action_dtype and self._action_dtype.kind == "f":
            actions = actions.astype(self._action_dtype)  # stored as this: the finiteness check sees the stored values
        rows = self._checked_rows(obs, next_obs, actions, reward, width)
        # checked: nothing of this call was stored (or changed) before
        if width != self._width or self._stream_base is None:
            self._stream_base = self.store.reserve_streams(width)
            self._width = width
            self.n_envs = width
            self._stream_ids = np.arange(self._stream_base, self._stream_base + width, dtype=np.uint32)
            self._widths = np.full(width, width, dtype=np.uint16)
        source = self._source
        if self.store.source(source) is None:
            self._ensure_source(source)
        sources = self._source_rows
        if self._source_rows_of != source or len(sources) != width:
            sources = self._source_rows = np.full(width, source, dtype=np.uint16)  # append() copies it
            self._source_rows_of = source
        timeouts = self.handle_timeout_termination
        for i, info in enumerate(infos):
            if STAGE_KEY in info:
                if sources is self._source_rows:
                    sources = sources.copy()
                sources[i] = self._source_of(info)
            if timeouts and info.get("TimeLimit.truncated", False):
                flags = flags.view(np.uint8)
                flags[i] |= FLAG_TIMEOUT
        rows["actions"] = actions
        rows["rewards"] = reward
        rows["flags"] = flags
        rows["sources"] = sources
        rows["streams"] = self._stream_ids
        rows["widths"] = self._widths
        self._append_rows(rows)

    def _checked_rows(
        self, obs: Any, next_obs: Any, actions: np.ndarray, reward: np.ndarray, width: int
    ) -> dict[str, np.ndarray]:
        """add(): the observation rows, shaped (or a ValueError), and a ValueError if a float value is not finite."""
        if self._obs_keys is None:
            target, dtype = self._add_obs, self._obs_dtype
            observations = np.asarray(obs)
            if observations.shape != target:
                observations = self._conform_obs("observations", observations, target)
            next_observations = np.asarray(next_obs)
            if next_observations.shape != target:
                next_observations = self._conform_obs("next_observations", next_observations, target)
            if observations.dtype != dtype and dtype.kind == "f":
                observations = observations.astype(dtype)
            if next_observations.dtype != dtype and dtype.kind == "f":
                next_observations = next_observations.astype(dtype)
            # a cheap test of every value: a NaN or an infinity in x or y makes the dot product x.y NaN or infinite
            # (x * 0 is NaN for x infinite, and an infinite sum never comes back). Large finite values that overflow
            # do so too: then the exact check finds nothing
            total = float(reward[0]) if width == 1 else float(_vdot(reward, reward))
            if actions.dtype.kind == "f":
                total += float(_vdot(actions, actions))
            if dtype.kind == "f":  # both of the stored float dtype
                total += float(_vdot(observations, next_observations))
            else:
                if observations.dtype.kind == "f":
                    total += float(_vdot(observations, observations))
                if next_observations.dtype.kind == "f":
                    total += float(_vdot(next_observations, next_observations))
            if not _isfinite(total):
                self._check_finite({"observations": observations, "next_observations": next_observations}, actions, reward)
            rows = {"observations": observations, "next_observations": next_observations}
        else:
            rows = {
                **self._observation_rows("observations", obs, width),
                **self._observation_rows("next_observations", next_obs, width),
            }
            self._check_finite(rows, actions, reward)
        return rows

    # class defaults, so that buffers pickled by earlier versions compute them at their first add()
    _add_width = -1
    _source_rows = np.zeros(0, dtype=np.uint16)
    _source_rows_of = -1

    def _set_add_shapes(self, width: int) -> None:
        """The shapes add() expects for ``width`` envs, and the stored dtypes of its float fields."""
        self._add_width = width
        self._add_done = (width,)
        self._add_actions = (width, self.action_dim)
        action_shape = tuple(self.action_space.shape or ())
        accepted = {(width, self.action_dim), (width, *action_shape)}
        if width == 1:  # one env, unbatched: SB3 reshapes it too
            accepted |= {(self.action_dim,), action_shape}
        self._accepted_actions = accepted
        self._action_dtype = np.dtype(self.store.fields["actions"][0])
        if self._obs_keys is None:
            self._add_obs = (width, *self.obs_shape)  # type: ignore[misc]
            self._obs_dtype = np.dtype(self.store.fields["observations"][0])

    def _conform_actions(self, actions: np.ndarray, width: int) -> np.ndarray:
        if actions.shape not in self._accepted_actions:
            raise ValueError(
                f"add(): actions have shape {actions.shape}, expected {self._add_actions} ({width} envs, the length of "
                f"rewards; action space {self.action_space})"
            )
        return actions.reshape(self._add_actions)

    def _conform_obs(
        self, label: str, obs: np.ndarray, target: tuple[int, ...], space: Optional[spaces.Space] = None
    ) -> np.ndarray:
        """Observations of a shape other than ``target``: what SB3's ``ReplayBuffer.add`` accepts (reshaped Discrete
        observations, numpy broadcasting otherwise), or a ``ValueError``."""
        space = self.observation_space if space is None else space
        if isinstance(space, spaces.Discrete):
            if obs.size == target[0] and obs.ndim <= 2:
                return obs.reshape(target)
            raise ValueError(
                f"add(): {label} have shape {obs.shape}, expected {target} or {target[:1]} ({target[0]} envs, the length "
                f"of rewards; observation space {space})"
            )
        return _conform(label, obs, target, f"observation space {space}")

    def _observation_rows(self, base: str, obs: Union[np.ndarray, dict[str, np.ndarray]], width: int) -> dict[str, np.ndarray]:
        if not isinstance(obs, dict) or set(obs) != set(self._obs_keys or ()):
            got = sorted(obs) if isinstance(obs, dict) else type(obs).__name__
            raise ValueError(f"add(): {base}: expected a dict with the keys {list(self._obs_keys or ())}, got {got}")
        shapes: dict[str, tuple[int, ...]] = self.obs_shape  # type: ignore[assignment]
        subspaces = self.observation_space.spaces  # type: ignore[attr-defined]
        rows = {}
        for key in self._obs_keys or ():
            name, target = f"{base}.{key}", (width, *shapes[key])
            value = np.asarray(obs[key])
            if value.shape != target:
                value = self._conform_obs(f"{base}[{key!r}]", value, target, subspaces[key])
            dtype = self.store.dtypes[name]
            rows[name] = value.astype(dtype) if value.dtype != dtype and dtype.kind == "f" else value
        return rows

    def _check_finite(self, obs_rows: dict[str, np.ndarray], actions: np.ndarray, rewards: np.ndarray) -> None:
        """Raise a ValueError naming the field and the envs if a float value is NaN or infinite."""
        fields = {**obs_rows, "actions": actions, "rewards": rewards}
        for name, values in fields.items():
            if values.dtype.kind == "f":
                label = name if "." not in name else "{}[{!r}]".format(*name.split(".", 1))
                raise_if_not_finite(values, f"add(): {label} of env", "nothing of this add() was stored")

    def _append_rows(self, rows: dict[str, np.ndarray]) -> None:
        end = self.store.end
        try:
            self.store.append(rows)
        except BaseException:  # a failed flush (e.g. disk full) stores only the rows it committed before (usually none)
            stored = self.store.end - end
            if stored:
                self._runs.extend(rows["sources"][:stored])
            raise
        self._runs.extend(rows["sources"])

    def flush(self) -> None:
        """
        Write the pending transitions to disk now and commit them (no-op in memory).

        If it fails (``OSError``, e.g. disk full), nothing is committed: the pending transitions stay in memory, read
        and sampled as before, and calling ``flush()`` again commits them. ``CommitNotDurableError`` (an ``OSError``):
        they are committed, but the fsync of the directory after the manifest's rename failed, so the commit may not
        survive a power loss; calling ``flush()`` again syncs it.
        """
        self.store.flush()

    def close(self) -> None:
        """Flush and release the directory, and close the files opened by ``read_mode="pread"`` (its data stays
        readable from this object)."""
        self.store.close()

    def checkpoint(self) -> Optional[dict[str, Any]]:
        """
        Commit the buffer for a model checkpoint (what the ``save`` of this package's algorithms calls): flush the
        pending transitions, so that a crash right after the checkpoint loses none of them.

        :return: ``{"path": directory, "transitions": global number of transitions committed}`` (transitions ever
            committed, evicted ones included), recorded in the checkpoint; None in memory
        :raises OSError: the flush failed (then nothing new is committed, and the checkpoint must not be written)
        """
        if self.store.path is None:
            return None
        self.store.flush()  # no-op for a read-only buffer: it records what the writer committed
        return {"path": self.store.path, "transitions": int(self.store.num_committed)}

    def check_checkpoint(self, record: dict[str, Any], checkpoint: str = "the checkpoint") -> None:
        """
        Warn when this buffer holds fewer transitions than ``record`` (from :meth:`checkpoint`) says were committed
        when the model was saved: the directory lags the checkpoint (an older copy, or rows lost outside this
        package), and resuming would train on less data than the saved model had.

        :param record: What :meth:`checkpoint` returned when the model was saved
        :param checkpoint: The checkpoint, for the message
        """
        if self.store.path is None or not isinstance(record, dict) or not isinstance(record.get("transitions"), int):
            return
        held, recorded = int(self.store.end), record["transitions"]
        if held < recorded:
            where = "" if record.get("path") == self.store.path else f" (then at {record.get('path')})"
            warnings.warn(
                f"{self.store.path} holds {held:,} transitions, but {checkpoint} was saved when its buffer{where} had "
                f"committed {recorded:,}: the buffer on disk lags the model by {recorded - held:,} transitions (an older "
                "copy of the directory?). learn(..., reset_num_timesteps=False) would go on with fewer transitions than "
                "the saved model had; open the buffer directory the model was saved with",
                stacklevel=3,
            )

    def _index_sources(self, start: int) -> None:
        """Add the source ids of the retained rows from index ``start`` on to the run index."""
        first = self.store.first
        for block in range(start, len(self.store), 1 << 20):
            sources = self.store.read_range("sources", block, min(len(self.store), block + (1 << 20)))
            self._runs.extend(sources, at=first + block)

    def refresh(self) -> int:
        """
        Read-only buffers: see the transitions another process committed (and evicted) since opening.

        :return: The number of transitions
        """
        indexed = self._runs.total
        self.store.refresh()
        self._index_sources(max(indexed - self.store.first, 0))
        return len(self.store)

    def reset(self) -> None:
        """Erase an in-memory buffer (a directory buffer refuses: its data is meant to be kept)."""
        if self.store.path is not None:
            raise RuntimeError("refusing to erase a persistent lifelong buffer; delete its directory instead")
        self.store.clear()
        self._runs = _RunIndex()
        self._stream_base = None

    def __enter__(self) -> LifelongReplayBuffer:
        return self

    def __exit__(self, *args: Any) -> None:
        self.close()

    # ------------------------------------------------------------------ reading
    @property
    def path(self) -> Optional[str]:
        """The buffer directory, or None in memory."""
        return self.store.path

    @property
    def read_mode(self) -> str:
        """How stored transitions are read from the directory: ``"mmap"`` or ``"pread"``."""
        return self.store.read_mode

    @property
    def recovered(self) -> int:
        """Transitions found committed when the directory was opened."""
        return self.store.recovered

    @property
    def capacity(self) -> Optional[int]:
        """The number of most recent transitions kept (older ones are evicted), or None when every one is kept."""
        return self.store.capacity

    @property  # type: ignore[override]
    def buffer_size(self) -> int:
        """``capacity`` when set; otherwise the size SB3 asked for, or the number of stored transitions if larger
        (then never a limit)."""
        if self.store.capacity is not None:
            return self.store.capacity
        return max(self.requested_buffer_size, self.size())

    @buffer_size.setter
    def buffer_size(self, value: int) -> None:
        self.requested_buffer_size = int(value)

    def size(self) -> int:
        """
        :return: The number of stored (retained) transitions
        """
        return len(self.store)

    def _gather(self, names: tuple[str, ...], indices: np.ndarray) -> dict[str, np.ndarray]:
        return self.store.gather(names, indices)

    def _source_runs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._runs.runs(self.store.first)

    def _read_range(self, name: str, start: int, stop: int) -> np.ndarray:
        return self.store.read_range(name, start, stop)

    def __repr__(self) -> str:
        where = self.store.path or "memory"
        return f"LifelongReplayBuffer({self.size()} transitions, {len(self.store.source_table())} sources, {where})"
