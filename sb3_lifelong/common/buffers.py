"""
Lifelong replay buffer: every transition of a robot's life, in memory or in a crash-safe directory.

See ``docs/modules/buffer.md`` for the directory format, the crash guarantees and examples.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, Optional, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import VecNormalize

from sb3_lifelong.common.buffer_storage import (
    FIELD_NAMES,
    FLAG_DONE,
    FLAG_TIMEOUT,
    MAX_SOURCE_ID,
    BufferFormatError,
    RowStore,
)

__all__ = ["BufferFormatError", "LifelongBufferView", "LifelongReplayBuffer", "merge_buffers"]

_COPY_BLOCK = 1 << 16


def _space_to_json(space: spaces.Space) -> dict[str, Any]:
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
    return spaces.Box(low.reshape(shape), high.reshape(shape), shape=shape, dtype=np_dtype)  # type: ignore[arg-type]


class _RunIndex:
    """Run-length index of the source ids (start row and source of each run), for per-source sampling."""

    def __init__(self) -> None:
        self.starts = np.zeros(64, dtype=np.int64)
        self.sources = np.zeros(64, dtype=np.int64)
        self.count = 0
        self.total = 0

    def extend(self, sources: np.ndarray) -> None:
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

    def runs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        starts = self.starts[: self.count]
        lengths = np.diff(np.append(starts, self.total))
        return starts, lengths, self.sources[: self.count]


class _LifelongSampler(ReplayBuffer):
    """
    Sampling shared by :class:`LifelongReplayBuffer` and :class:`LifelongBufferView` (uniform or per-source
    weighted indices, n-step returns, per-source reward scales). Subclasses provide the rows.
    """

    n_steps: int
    gamma: float
    last_sampled_sources: Optional[np.ndarray]

    def _init_sampler(self, n_steps: int, gamma: float) -> None:
        if n_steps < 1:
            raise ValueError(f"n_steps must be >= 1, got {n_steps}")
        self.n_steps = int(n_steps)
        self.gamma = float(gamma)
        self._sampling_weights: dict[int, float] = {}
        self._reward_scale: dict[int, float] = {}
        self.last_sampled_sources = None

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

    # ------------------------------------------------------------------ SB3 attributes
    @property  # type: ignore[override]
    def pos(self) -> int:
        """Number of stored transitions (the write position of an append-only buffer)."""
        return self.size()

    @pos.setter
    def pos(self, value: int) -> None:
        raise AttributeError("the position of a lifelong buffer is its size and cannot be set")

    @property  # type: ignore[override]
    def full(self) -> bool:
        """Always False: the buffer never wraps around and never overwrites."""
        return False

    @full.setter
    def full(self, value: bool) -> None:
        if value:
            raise AttributeError("a lifelong buffer is never full")

    # ------------------------------------------------------------------ per-source options
    def source_counts(self) -> dict[int, int]:
        """
        :return: Number of stored transitions per source id
        """
        _, lengths, run_sources = self._source_runs()
        counts = np.bincount(run_sources, weights=lengths, minlength=1) if len(run_sources) else np.zeros(0)
        return {int(s): int(c) for s, c in enumerate(counts) if c > 0}

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
        self, batch_size: int, env: Optional[VecNormalize] = None, return_sources: bool = False
    ) -> Union[ReplayBufferSamples, tuple[ReplayBufferSamples, th.Tensor]]:
        """
        Sample transitions uniformly (or with the per-source weights) over everything stored.

        :param batch_size: Number of transitions
        :param env: VecNormalize to normalise observations and rewards with
        :param return_sources: Also return the source ids of the batch (a long tensor)
        :return: The samples (``discounts`` is set when ``n_steps > 1``, like SB3's ``NStepReplayBuffer``),
            and the source ids if asked. The source ids of the last batch are also in ``last_sampled_sources``.
        """
        samples = self._get_samples(self._sample_indices(batch_size), env=env)
        if return_sources:
            assert self.last_sampled_sources is not None
            return samples, th.as_tensor(self.last_sampled_sources.astype(np.int64), device=self.device)
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

    def _get_samples(self, batch_inds: np.ndarray, env: Optional[VecNormalize] = None) -> ReplayBufferSamples:
        batch_inds = np.asarray(batch_inds, dtype=np.int64)
        if self.n_steps > 1:
            return self._get_n_step_samples(batch_inds, env)
        rows = self._gather(("observations", "actions", "next_observations", "rewards", "flags", "sources"), batch_inds)
        self.last_sampled_sources = rows["sources"]
        flags = rows["flags"]
        dones = ((flags & FLAG_DONE) != 0) & ((flags & FLAG_TIMEOUT) == 0)
        rewards = self._scaled(rows["rewards"], rows["sources"])
        return ReplayBufferSamples(
            observations=self._tensor(self._normalize_obs(rows["observations"], env)),  # type: ignore[arg-type]
            actions=self._tensor(rows["actions"]),
            next_observations=self._tensor(self._normalize_obs(rows["next_observations"], env)),  # type: ignore[arg-type]
            dones=self._tensor(dones.astype(np.float32).reshape(-1, 1)),
            rewards=self._tensor(self._normalize_reward(rewards.reshape(-1, 1), env).astype(np.float32, copy=False)),
        )

    def _get_n_step_samples(self, batch_inds: np.ndarray, env: Optional[VecNormalize]) -> ReplayBufferSamples:
        total = self.size()
        first = self._gather(("observations", "actions", "rewards", "flags", "sources", "streams", "widths"), batch_inds)
        self.last_sampled_sources = first["sources"]
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
        next_obs = self._gather(("next_observations",), last)["next_observations"]
        return ReplayBufferSamples(
            observations=self._tensor(self._normalize_obs(first["observations"], env)),  # type: ignore[arg-type]
            actions=self._tensor(first["actions"]),
            next_observations=self._tensor(self._normalize_obs(next_obs, env)),  # type: ignore[arg-type]
            dones=self._tensor(final_dones.astype(np.float32).reshape(-1, 1)),
            rewards=self._tensor(returns),
            discounts=self._tensor(discounts),
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
        total = self.size()
        data = {name: np.asarray(self._read_range(name, 0, total)) for name in FIELD_NAMES}
        flags = data["flags"]
        timeouts = (flags & FLAG_TIMEOUT) != 0
        terminals = ((flags & FLAG_DONE) != 0) & ~timeouts
        order = np.arange(total)
        if by_episode and total:
            streams = data["streams"].astype(np.int64)
            order = np.argsort(streams, kind="stable")
            sorted_streams = streams[order]
            last_of_stream = np.append(sorted_streams[1:] != sorted_streams[:-1], True)
            timeouts = timeouts[order] | (last_of_stream & ~terminals[order])
            terminals = terminals[order]
        actions = data["actions"][order]
        if not normalized_actions:
            actions = _rescale_actions(actions, self.action_space, to_env_units=True)
        return {
            "observations": data["observations"][order],
            "actions": actions,
            "rewards": data["rewards"][order],
            "next_observations": data["next_observations"][order],
            "terminals": terminals,
            "timeouts": timeouts,
            "sources": data["sources"][order].astype(np.int64),
        }

    def save_npz(self, file: Union[str, os.PathLike]) -> None:
        """
        Write :meth:`to_d4rl` to a ``.npz`` file (no pickle inside).

        :param file: Target file
        """
        np.savez(file, **self.to_d4rl())  # type: ignore[arg-type]


class LifelongReplayBuffer(_LifelongSampler):
    """
    Replay buffer that keeps every transition, tagged with its source (stage), in memory or in a crash-safe
    directory of append-only files that is memory-mapped for reading.

    Drop-in ``replay_buffer_class`` for SB3 off-policy algorithms: ``buffer_size`` is recorded but never
    evicts anything, and ``add()`` accepts any number of envs (each env of each ``add`` width is its own stream).

    :param buffer_size: SB3's buffer size: informational only, nothing is ever overwritten or evicted
    :param observation_space: Observation space (Box or Discrete; optional when opening an existing ``path``)
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
    :param verify: Checksums verified when opening a path: "last" chunk (default), "all" or "none"
    :param source: Initial source id of transitions whose ``info`` has no ``"stage"``
    :param max_resident_bytes: With a path: remap the files after random reads may have made about this many
        bytes of them resident, to bound the RSS of sampling a buffer larger than RAM (None: never)
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
    ) -> None:
        # BaseBuffer.__init__ is not called: it would allocate and assign attributes that are properties here
        if optimize_memory_usage:
            raise ValueError("LifelongReplayBuffer stores next observations: optimize_memory_usage is not supported")
        if isinstance(observation_space, spaces.Dict) or isinstance(action_space, spaces.Dict):
            raise NotImplementedError("LifelongReplayBuffer supports Box and Discrete spaces, not Dict spaces")
        path_str = None if path is None else os.fspath(path)
        fields: Optional[dict[str, tuple[str, tuple[int, ...]]]] = None
        if observation_space is not None and action_space is not None:
            obs_shape = get_obs_shape(observation_space)
            action_dtype = self._maybe_cast_dtype(action_space.dtype)
            fields = {
                "observations": (np.dtype(observation_space.dtype).str, tuple(obs_shape)),  # type: ignore[arg-type,misc]
                "next_observations": (np.dtype(observation_space.dtype).str, tuple(obs_shape)),  # type: ignore[arg-type,misc]
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
        )
        if not self.store.spaces and observation_space is not None and action_space is not None and not read_only:
            self.store.spaces = {"observation": _space_to_json(observation_space), "action": _space_to_json(action_space)}
        if observation_space is None or action_space is None:
            obs_dtype, obs_shape_stored = self.store.fields["observations"]
            act_dtype, act_shape = self.store.fields["actions"]
            observation_space = _space_from_json(self.store.spaces.get("observation", {}), obs_dtype, obs_shape_stored)
            action_space = _space_from_json(self.store.spaces.get("action", {}), act_dtype, act_shape)
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
        self._runs = _RunIndex()
        for start in range(0, len(self.store), 1 << 20):
            self._runs.extend(self.store.read_range("sources", start, min(len(self.store), start + (1 << 20))))

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def open(
        cls, path: Union[str, os.PathLike], read_only: bool = False, device: Union[th.device, str] = "auto", **kwargs: Any
    ) -> LifelongReplayBuffer:
        """
        Open an existing buffer directory (the spaces are read from its manifest).

        :param path: Buffer directory
        :param read_only: Do not write (another process may be writing; call :meth:`refresh` to see its new data)
        :param device: PyTorch device of the sampled tensors
        :param kwargs: Further constructor arguments (``n_steps``, ``gamma``, ``verify``, ...)
        :return: The buffer
        """
        if not os.path.isdir(os.fspath(path)):
            raise FileNotFoundError(f"no buffer directory at {os.fspath(path)!r}")
        return cls(path=path, read_only=read_only, device=device, **kwargs)

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
        if not isinstance(data, dict):
            with np.load(os.fspath(data), allow_pickle=False) as npz:
                data = {key: npz[key] for key in npz.files}
        for key in ("observations", "actions", "rewards", "next_observations", "terminals"):
            if key not in data:
                raise KeyError(f"d4rl data has no {key!r}")
        obs = np.asarray(data["observations"])
        actions = np.asarray(data["actions"])
        total = len(obs)
        for key, value in data.items():
            if key in ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts", "sources"):
                if len(value) != total:
                    raise ValueError(f"d4rl key {key!r} has {len(value)} rows, observations have {total}")
        if actions.ndim == 1:
            actions = actions.reshape(-1, 1)
        if observation_space is None:
            observation_space = spaces.Box(-np.inf, np.inf, shape=obs.shape[1:], dtype=obs.dtype)  # type: ignore[arg-type]
        if action_space is None:
            action_space = spaces.Box(-np.inf, np.inf, shape=actions.shape[1:], dtype=actions.dtype)  # type: ignore[arg-type]
        buffer = cls(total, observation_space, action_space, source=source, **kwargs)
        terminals = np.asarray(data["terminals"]).astype(bool).reshape(-1)
        timeouts = np.asarray(data.get("timeouts", np.zeros(total, dtype=bool))).astype(bool).reshape(-1)
        next_obs = np.asarray(data["next_observations"])
        sources = np.asarray(data["sources"]).reshape(-1) if "sources" in data else np.full(total, source)
        if total and (sources.min() < 0 or sources.max() > MAX_SOURCE_ID):
            raise ValueError(f"source ids must be in [0, {MAX_SOURCE_ID}]")
        ended = terminals | timeouts
        chained = np.zeros(total, dtype=bool)
        if total > 1:
            same = (next_obs[:-1] == obs[1:]).reshape(total - 1, -1).all(axis=1)
            chained[1:] = same & ~ended[:-1]
        streams = buffer.store.next_stream_id + np.cumsum(~chained) - 1
        buffer.store.next_stream_id = int(streams[-1]) + 1 if total else buffer.store.next_stream_id
        if not normalized_actions:
            actions = _rescale_actions(actions, action_space, to_env_units=False)
        rows = {
            "observations": obs,
            "next_observations": next_obs,
            "actions": actions,
            "rewards": np.asarray(data["rewards"], dtype=np.float32).reshape(-1),
            "flags": ((terminals | timeouts) * FLAG_DONE + timeouts * FLAG_TIMEOUT).astype(np.uint8),
            "sources": sources.astype(np.uint16),
            "streams": streams.astype(np.uint32),
            "widths": np.ones(total, dtype=np.uint16),
        }
        for source_id in np.unique(sources):
            buffer._ensure_source(int(source_id))
        buffer._append_rows(rows)
        buffer.flush()
        return buffer

    # ------------------------------------------------------------------ sources
    @staticmethod
    def _check_source(source: int) -> int:
        if not isinstance(source, (int, np.integer)) or isinstance(source, bool) or not 0 <= source <= MAX_SOURCE_ID:
            raise ValueError(f"source ids are ints in [0, {MAX_SOURCE_ID}], got {source!r}")
        return int(source)

    def _ensure_source(self, source: int, name: Optional[str] = None, metadata: Optional[dict[str, Any]] = None) -> None:
        known = self.store.sources.get(source)
        if known is None:
            self.store.sources[source] = {"name": name or f"source_{source}", "metadata": dict(metadata or {})}
        elif name is not None or metadata is not None:
            self.store.sources[source] = {
                "name": name or known["name"],
                "metadata": dict(metadata) if metadata is not None else known["metadata"],
            }

    @property
    def sources(self) -> dict[int, dict[str, Any]]:
        """Source id -> ``{"name": str, "metadata": dict}`` (e.g. the dynamics parameters of a stage)."""
        return {k: {"name": v["name"], "metadata": dict(v["metadata"])} for k, v in self.store.sources.items()}

    def set_source(self, source: int, name: Optional[str] = None, metadata: Optional[dict[str, Any]] = None) -> None:
        """
        Source of the next transitions whose ``info`` carries no ``"stage"``, with an optional name and metadata.

        :param source: Source id in [0, 65534]
        :param name: Name (default ``"source_<id>"``)
        :param metadata: JSON-serialisable dict (e.g. the physical parameters of this environment variant)
        """
        self._source = self._check_source(source)
        self._ensure_source(self._source, name, metadata)

    def _source_of(self, info: dict[str, Any]) -> int:
        stage = info.get("stage")
        if stage is None:
            return self._source
        source = int(stage)
        known = self.store.sources.get(source)
        if known is not None and known["name"] == f"stage_{source}":
            return source
        source = self._check_source(source)
        if known is None or known["name"] != f"stage_{source}":
            params = info.get("dynamics_params")
            metadata = {str(k): float(v) for k, v in params.items()} if isinstance(params, dict) else {}
            self.store.sources[source] = {"name": f"stage_{source}", "metadata": metadata}
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
        Append one transition per env (SB3 semantics). Any number of envs is accepted.

        :param obs: Observations, leading dimension n_envs
        :param next_obs: Next observations (the terminal observation where an episode ended)
        :param action: Actions
        :param reward: Rewards
        :param done: Episode ends (terminations and time-limit truncations)
        :param infos: One info dict per env (``"TimeLimit.truncated"``, ``"stage"``, ``"dynamics_params"``)
        """
        reward = np.asarray(reward, dtype=np.float32).reshape(-1)
        width = len(reward)
        if width != self._width or self._stream_base is None:
            self._stream_base = self.store.next_stream_id
            self.store.next_stream_id += width
            self._width = width
            self.n_envs = width
            self._stream_ids = np.arange(self._stream_base, self._stream_base + width, dtype=np.uint32)
            self._widths = np.full(width, width, dtype=np.uint16)
        if self._source not in self.store.sources:
            self._ensure_source(self._source)
        sources = np.empty(width, dtype=np.uint16)
        timeouts = np.zeros(width, dtype=np.uint8)
        for i, info in enumerate(infos):
            sources[i] = self._source if "stage" not in info else self._source_of(info)
            if self.handle_timeout_termination and info.get("TimeLimit.truncated", False):
                timeouts[i] = FLAG_TIMEOUT
        rows = {
            "observations": np.asarray(obs).reshape(width, *self.obs_shape),
            "next_observations": np.asarray(next_obs).reshape(width, *self.obs_shape),
            "actions": np.asarray(action).reshape(width, self.action_dim),
            "rewards": reward,
            "flags": np.asarray(done).reshape(width).astype(np.uint8) | timeouts,
            "sources": sources,
            "streams": self._stream_ids,
            "widths": self._widths,
        }
        self._append_rows(rows)

    def _append_rows(self, rows: dict[str, np.ndarray]) -> None:
        self.store.append(rows)
        self._runs.extend(rows["sources"])

    def flush(self) -> None:
        """Write the pending transitions to disk now (no-op in memory)."""
        self.store.flush()

    def close(self) -> None:
        """Flush and release the directory (its data stays readable from this object)."""
        self.store.close()

    def refresh(self) -> int:
        """
        Read-only buffers: see the transitions another process committed since opening.

        :return: The number of transitions
        """
        before = len(self.store)
        self.store.refresh()
        for start in range(before, len(self.store), 1 << 20):
            self._runs.extend(self.store.read_range("sources", start, min(len(self.store), start + (1 << 20))))
        return len(self.store)

    def reset(self) -> None:
        """Erase an in-memory buffer (a directory buffer refuses: its data is meant to be kept)."""
        if self.store.path is not None:
            raise RuntimeError("refusing to erase a persistent lifelong buffer; delete its directory instead")
        self.store.num_tail = 0
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
    def recovered(self) -> int:
        """Transitions found committed when the directory was opened."""
        return self.store.recovered

    @property  # type: ignore[override]
    def buffer_size(self) -> int:
        """The size SB3 asked for, or the number of stored transitions if larger (never a limit)."""
        return max(self.requested_buffer_size, self.size())

    @buffer_size.setter
    def buffer_size(self, value: int) -> None:
        self.requested_buffer_size = int(value)

    def size(self) -> int:
        """
        :return: The total number of stored transitions
        """
        return len(self.store)

    def _gather(self, names: tuple[str, ...], indices: np.ndarray) -> dict[str, np.ndarray]:
        return self.store.gather(names, indices)

    def _source_runs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._runs.runs()

    def _read_range(self, name: str, start: int, stop: int) -> np.ndarray:
        return self.store.read_range(name, start, stop)

    def __repr__(self) -> str:
        where = self.store.path or "memory"
        return f"LifelongReplayBuffer({self.size()} transitions, {len(self.store.sources)} sources, {where})"


class LifelongBufferView(_LifelongSampler):
    """
    Read-only concatenation of several lifelong buffers (parallel agents, earlier lifetimes) for offline
    training, without copying: indices run over the buffers one after the other, and the view sees what the
    buffers hold at each call. Source ids are shared (the same id means the same source in every buffer;
    names and metadata come from the first buffer that has the id).

    :param buffers: The buffers (same observation and action shapes and dtypes)
    :param device: PyTorch device of the sampled tensors (default: the first buffer's)
    :param n_steps: Length of n-step returns (never chaining across buffers)
    :param gamma: Discount of the n-step returns
    """

    def __init__(
        self,
        buffers: Sequence[LifelongReplayBuffer],
        device: Optional[Union[th.device, str]] = None,
        n_steps: int = 1,
        gamma: float = 0.99,
    ) -> None:
        if not buffers:
            raise ValueError("a view needs at least one buffer")
        first = buffers[0]
        for buffer in buffers[1:]:
            for name in ("observations", "actions"):
                if buffer.store.fields[name] != first.store.fields[name]:
                    raise ValueError(f"cannot combine buffers with different {name}: {buffer.store.fields[name]}")
        self.buffers = list(buffers)
        self.observation_space = first.observation_space
        self.action_space = first.action_space
        self.obs_shape = first.obs_shape
        self.action_dim = first.action_dim
        self.device = get_device(device) if device is not None else first.device
        self.n_envs = 1
        self.buffer_size = 0
        self.optimize_memory_usage = False
        self.handle_timeout_termination = True
        self._init_sampler(n_steps, gamma)

    @property
    def sources(self) -> dict[int, dict[str, Any]]:
        """Source id -> ``{"name": str, "metadata": dict}``, over all buffers."""
        merged: dict[int, dict[str, Any]] = {}
        for buffer in self.buffers:
            for key, value in buffer.sources.items():
                merged.setdefault(key, value)
        return merged

    def _offsets(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum([b.size() for b in self.buffers])]).astype(np.int64)

    def size(self) -> int:
        """
        :return: The total number of transitions of all buffers
        """
        return sum(b.size() for b in self.buffers)

    def add(self, *args: Any, **kwargs: Any) -> None:
        raise RuntimeError("a LifelongBufferView is read-only: add to one of its buffers")

    def _gather(self, names: tuple[str, ...], indices: np.ndarray) -> dict[str, np.ndarray]:
        offsets = self._offsets()
        owner = np.searchsorted(offsets, indices, side="right") - 1
        result: dict[str, np.ndarray] = {}
        for k in np.unique(owner):
            where = owner == k
            part = self.buffers[k].store.gather(names, indices[where] - offsets[k])
            for name, values in part.items():
                if name == "streams":  # keep streams of different buffers apart
                    values = values.astype(np.int64) + (int(k) << 32)
                if name not in result:
                    result[name] = np.empty((len(indices), *values.shape[1:]), dtype=values.dtype)
                result[name][where] = values
        return result

    def _source_runs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        offsets = self._offsets()
        parts = [b._source_runs() for b in self.buffers]
        starts = np.concatenate([p[0] + offsets[k] for k, p in enumerate(parts)])
        return starts, np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts])

    def _read_range(self, name: str, start: int, stop: int) -> np.ndarray:
        offsets = self._offsets()
        pieces = []
        for k, buffer in enumerate(self.buffers):
            lo, hi = max(start, offsets[k]), min(stop, offsets[k + 1])
            if lo < hi:
                piece = buffer.store.read_range(name, int(lo - offsets[k]), int(hi - offsets[k]))
                pieces.append(piece.astype(np.int64) + (k << 32) if name == "streams" else piece)
        return np.concatenate(pieces) if pieces else buffer.store.read_range(name, 0, 0)


def _rescale_actions(actions: np.ndarray, action_space: spaces.Space, to_env_units: bool) -> np.ndarray:
    """
    Map actions between the normalised ``[-1, 1]`` range SB3 stores and the action space's bounds. Unbounded
    spaces, and spaces that already are ``[-1, 1]``, leave the actions untouched (bit for bit).
    """
    if not isinstance(action_space, spaces.Box) or not action_space.is_bounded():
        return actions
    low, high = action_space.low.astype(np.float64), action_space.high.astype(np.float64)
    if np.all(low == -1.0) and np.all(high == 1.0):
        return actions
    values = actions.astype(np.float64)
    if to_env_units:
        values = low + 0.5 * (values + 1.0) * (high - low)
    else:
        values = 2.0 * (values - low) / (high - low) - 1.0
    return values.astype(actions.dtype)


def merge_buffers(
    buffers: Sequence[LifelongReplayBuffer],
    path: Optional[Union[str, os.PathLike]] = None,
    starts: Optional[Sequence[int]] = None,
    **kwargs: Any,
) -> LifelongReplayBuffer:
    """
    Materialise several buffers into a new one (copied in blocks, so it works for buffers larger than RAM
    when ``path`` is given). Stream ids are renumbered so n-step returns never chain across the inputs.

    :param buffers: The buffers to copy, in order
    :param path: Directory of the new buffer (None: in memory)
    :param starts: For each buffer, the index of its first transition to copy (default 0: all of it). For
        agents copied from a common ancestor (buffer included), pass the ancestor's size for the copies so that
        the shared transitions are kept once.
    :param kwargs: Further constructor arguments of the new buffer (``chunk_size``, ``n_steps``, ...)
    :return: The merged buffer
    """
    if starts is None:
        starts = [0] * len(buffers)
    if len(starts) != len(buffers) or any(not 0 <= int(s) <= b.size() for s, b in zip(starts, buffers)):
        raise ValueError(
            f"starts must give one index in [0, size] per buffer: got {list(starts)} for sizes {[b.size() for b in buffers]}"
        )
    view = LifelongBufferView(buffers)
    first = buffers[0]
    total_size = sum(buffer.size() - int(start) for buffer, start in zip(buffers, starts))
    merged = LifelongReplayBuffer(total_size, first.observation_space, first.action_space, path=path, **kwargs)
    for source, info in view.sources.items():
        merged._ensure_source(source, info["name"], info["metadata"])
    for buffer, first_row in zip(buffers, starts):
        base = merged.store.next_stream_id
        total = buffer.size()
        for start in range(int(first_row), total, _COPY_BLOCK):
            stop = min(total, start + _COPY_BLOCK)
            rows = {name: np.asarray(buffer.store.read_range(name, start, stop)) for name in FIELD_NAMES}
            rows["streams"] = (rows["streams"].astype(np.int64) + base).astype(np.uint32)
            merged._append_rows(rows)
        merged.store.next_stream_id = base + buffer.store.next_stream_id
    merged.flush()
    return merged
