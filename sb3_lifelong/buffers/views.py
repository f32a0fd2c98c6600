"""Several lifelong buffers as one: a read-only view without copying, and a merge into a new buffer."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, Optional, Union

import numpy as np
import torch as th
from stable_baselines3.common.utils import get_device

from sb3_lifelong.buffers.lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers.sampling import LifelongSampler

#: rows copied by merge_buffers at a time
COPY_BLOCK = 1 << 16


class LifelongBufferView(LifelongSampler):
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
            if buffer.store.fields != first.store.fields:
                differ = sorted(set(buffer.store.fields.items()) ^ set(first.store.fields.items()))
                raise ValueError(f"cannot combine buffers with different observation or action fields: {differ}")
        self.buffers = list(buffers)
        self._obs_keys = first._obs_keys
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

    def read_range(self, name: str, start: int, stop: int) -> np.ndarray:
        """Rows ``start:stop`` of a stored field over the buffers one after the other (streams kept apart)."""
        offsets = self._offsets()
        pieces = []
        for k, buffer in enumerate(self.buffers):
            lo, hi = max(start, offsets[k]), min(stop, offsets[k + 1])
            if lo < hi:
                piece = buffer.store.read_range(name, int(lo - offsets[k]), int(hi - offsets[k]))
                pieces.append(piece.astype(np.int64) + (k << 32) if name == "streams" else piece)
        return np.concatenate(pieces) if pieces else buffer.store.read_range(name, 0, 0)


def merge_buffers(
    buffers: Sequence[LifelongReplayBuffer],
    path: Optional[Union[str, os.PathLike]] = None,
    starts: Optional[Sequence[int]] = None,
    stops: Optional[Sequence[int]] = None,
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
    :param stops: For each buffer, the index after its last transition to copy (default: its size). E.g. the
        transitions a collection had committed when it was checkpointed: ``stops=[record["transitions"]]``.
    :param kwargs: Further constructor arguments of the new buffer (``chunk_size``, ``n_steps``, ``read_mode``, ...)
    :return: The merged buffer
    """
    if starts is None:
        starts = [0] * len(buffers)
    if len(starts) != len(buffers) or any(not 0 <= int(s) <= b.size() for s, b in zip(starts, buffers)):
        raise ValueError(
            f"starts must give one index in [0, size] per buffer: got {list(starts)} for sizes {[b.size() for b in buffers]}"
        )
    if stops is None:
        stops = [buffer.size() for buffer in buffers]
    if len(stops) != len(buffers) or any(not int(a) <= int(z) <= b.size() for a, z, b in zip(starts, stops, buffers)):
        raise ValueError(
            f"stops must give one index in [start, size] per buffer: got {list(stops)} for starts {list(starts)} and "
            f"sizes {[b.size() for b in buffers]}"
        )
    view = LifelongBufferView(buffers)
    first = buffers[0]
    total_size = sum(int(stop) - int(start) for start, stop in zip(starts, stops))
    merged = LifelongReplayBuffer(total_size, first.observation_space, first.action_space, path=path, **kwargs)
    try:
        merged._refuse_mixing()  # before the sources are named: a directory that holds transitions is left as it was
    except FileExistsError:
        merged.close()
        raise
    for source, info in view.sources.items():
        merged.name_source(source, info["name"], info["metadata"])
    for buffer, first_row, total in zip(buffers, starts, stops):
        base = merged.store.reserve_streams(buffer.store.next_stream_id)  # the copy's stream ids, shifted
        total = int(total)
        for start in range(int(first_row), total, COPY_BLOCK):
            stop = min(total, start + COPY_BLOCK)
            rows = {name: np.asarray(buffer.store.read_range(name, start, stop)) for name in merged.store.fields}
            rows["streams"] = (rows["streams"].astype(np.int64) + base).astype(np.uint32)
            merged.append_rows(rows)
    merged.flush()
    return merged
