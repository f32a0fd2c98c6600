"""
The read side of the lifelong buffer: :class:`LifelongSampler`, what :class:`~sb3_lifelong.buffers.LifelongReplayBuffer`
and :class:`~sb3_lifelong.buffers.LifelongBufferView` share (uniform or per-source weighted indices, n-step returns,
per-source reward scales, the data's next actions for SARSA targets, exports), and the run index of the source ids
that per-source sampling reads.
"""

from __future__ import annotations

import os
from typing import Any, Literal, Optional, Union, overload

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize

from sb3_lifelong.buffers import interop
from sb3_lifelong.buffers.manifest import FLAG_DONE, FLAG_TIMEOUT, OBS_FIELDS
from sb3_lifelong.core.datasets import OfflineSamples

__all__ = ["LifelongSampler", "RunIndex"]

Samples = Union[ReplayBufferSamples, DictReplayBufferSamples]


class RunIndex:
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


class LifelongSampler(ReplayBuffer):
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

    def read_range(self, name: str, start: int, stop: int) -> np.ndarray:
        """
        Rows ``start:stop`` of a stored field (counted from the oldest retained transition), as stored: a view where
        possible (do not write to it), else a copy.

        :param name: A stored field: ``observations``, ``next_observations`` (``observations.<key>`` for Dict
            observations), ``actions``, ``rewards``, ``flags``, ``sources``, ``streams`` or ``widths``
        :param start: First row
        :param stop: One past the last row
        :return: Array of shape ``(stop - start, *row_shape)``
        """
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

    # ------------------------------------------------------------------ SB3 attributes
    @property
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

    @property
    def full(self) -> bool:
        """Whether the buffer holds ``capacity`` transitions (new ones evict the oldest); always False without one."""
        capacity = self.capacity
        return capacity is not None and self.size() >= capacity

    @full.setter
    def full(self, value: bool) -> None:
        if value != self.full:
            raise AttributeError("whether a lifelong buffer is full follows from its size and capacity and cannot be set")

    # ------------------------------------------------------------------ per-source options
    @overload
    def source_counts(self, by_name: Literal[False] = False) -> dict[int, int]: ...

    @overload
    def source_counts(self, by_name: Literal[True]) -> dict[str, int]: ...

    def source_counts(self, by_name: bool = False) -> Union[dict[int, int], dict[str, int]]:
        """
        :param by_name: key the counts by the sources' names (``Env-A``, ``Env-B``, ...: the names of the logs)
            instead of their ids
        :return: Number of stored transitions per source id (or name)
        """
        _, lengths, run_sources = self._source_runs()
        counts = np.bincount(run_sources, weights=lengths, minlength=1) if len(run_sources) else np.zeros(0)
        by_id = {int(s): int(c) for s, c in enumerate(counts) if c > 0}
        if not by_name:
            return by_id
        sources = self.sources
        named: dict[str, int] = {}
        ids: dict[str, int] = {}
        for source, count in by_id.items():
            name = sources.get(source, {}).get("name", f"source_{source}")
            if name in named:
                raise ValueError(f"sources {ids[name]} and {source} are both named {name!r}: use source_counts() (by id)")
            named[name], ids[name] = count, source
        return named

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
            rewards = np.asarray(self.read_range("rewards", start, min(total, start + block)))
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
    ) -> Union[Samples, tuple[Samples, th.Tensor]]:
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

    def _get_samples(self, batch_inds: np.ndarray, env: Optional[VecNormalize] = None) -> Samples:  # type: ignore[override]
        return self._get_samples_and_sources(batch_inds, env)[0]

    def _get_samples_and_sources(
        self, batch_inds: np.ndarray, env: Optional[VecNormalize], next_actions: bool = False
    ) -> tuple[Samples, np.ndarray]:
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
    ) -> tuple[Samples, np.ndarray]:
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

    def _with_next_actions(self, samples: Samples, last: np.ndarray, last_flags: np.ndarray) -> OfflineSamples:
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
            The buffer does not know who collected the data, with which code or algorithm: give them to record them
            (Minari's warnings that they are missing are not shown). Without ``env``, data imported from Minari keeps
            its environment spec. Image observations are stored losslessly (``jpeg_encoding=False``) unless asked
            otherwise
        :return: The ``minari.MinariDataset``
        """
        return interop.to_minari(self, dataset_id, normalized_actions, unfinished, description, **minari_kwargs)

    def save_npz(self, file: Union[str, os.PathLike]) -> None:
        """
        Write :meth:`to_d4rl` to a ``.npz`` file (no pickle inside).

        :param file: Target file
        """
        interop.save_npz(self, file)
