"""
Lifelong replay buffer: every transition of a robot's life, in memory or in a crash-safe directory.

This module is the buffer's write side (construction, ``add`` and its checks, sources and streams, commits); the read
side it shares with :class:`~sb3_lifelong.buffers.LifelongBufferView` (sampling, n-step returns, next actions,
exports) is :class:`~sb3_lifelong.buffers.sampling.LifelongSampler`.

See ``docs/modules/buffer.md`` for the directory format, the crash guarantees and examples.
"""

from __future__ import annotations

import os
import warnings
from typing import Any, Optional, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape
from stable_baselines3.common.utils import get_device

from sb3_lifelong.buffers import interop
from sb3_lifelong.buffers.add_checks import AddChecks
from sb3_lifelong.buffers.files import CommitNotDurableError
from sb3_lifelong.buffers.layouts import owned_buffer_files
from sb3_lifelong.buffers.manifest import (
    FLAG_TIMEOUT,
    MANIFEST_NAME,
    BufferFormatError,
    MetadataError,
    check_source_id,
    committed_transitions,
    obs_keys_of,
)
from sb3_lifelong.buffers.rowstore import RowStore
from sb3_lifelong.buffers.salvage import BufferCheck, check_buffer, salvage_buffer
from sb3_lifelong.buffers.sampling import LifelongSampler, RunIndex
from sb3_lifelong.buffers.schema import (
    action_space_of,
    buffer_fields,
    check_spaces,
    describe_spaces,
    observation_space_of,
)
from sb3_lifelong.core.contract import DYNAMICS_PARAMS_KEY, STAGE_KEY, stage_name

__all__ = ["BufferFormatError", "CommitNotDurableError", "LifelongReplayBuffer"]


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
    held = committed_transitions(path)
    return -1 if held is None else held


class LifelongReplayBuffer(LifelongSampler):
    """
    Replay buffer that keeps every transition (or the most recent ``capacity`` ones), tagged with its source
    (stage), in memory or in a crash-safe directory of append-only files, read with memory maps or positioned reads
    (``read_mode``).

    Drop-in ``replay_buffer_class`` for SB3 off-policy algorithms: ``buffer_size`` is recorded but never
    evicts anything (``capacity`` does), and ``add()`` accepts any number of envs up to 65,535 (each env of each
    ``add`` width is its own stream).

    :param buffer_size: SB3's buffer size: informational only, nothing is evicted because of it (see ``capacity``)
    :param observation_space: Observation space (Box, Discrete, MultiDiscrete, MultiBinary, or a Dict of those;
        optional when opening a ``path``). A directory reopens with spaces equal to the ones it was created with (bounds,
        dtype, ``nvec``, ``start``, ``n``); any other space is refused here with a ``NotImplementedError`` that lists
        the supported ones (``sb3_lifelong.buffers.schema.SUPPORTED_SPACES``)
    :param action_space: Action space (Box, Discrete, MultiDiscrete or MultiBinary; optional when opening an existing
        ``path``). Box actions are stored as given to ``add``: SB3's off-policy algorithms give a float Box's actions
        normalised to ``[-1, 1]``; an integer Box's actions are stored (and exported) in the env's units, as integers
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
        are always checked). A damaged chunk makes opening raise in every mode: :meth:`check_directory` lists the
        damaged chunks and :meth:`salvage` copies the intact ones into a new directory
    :param source: Initial source id of transitions whose ``info`` has no ``"stage"``
    :param max_resident_bytes: Replaced by ``read_mode="pread"`` (the one way to bound the RSS): any value but None
        reads with ``read_mode="pread"`` and warns (``FutureWarning``); kept so that models saved with it still load
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
    :param allow_foreign_files: A ``path`` to write to that is a directory without a buffer (no ``manifest.json``) but
        with other files in it is refused by default, with a ``FileExistsError`` naming a few of them, before anything
        is written there: creating a buffer among them would mix its files with someone else's. True: create it there
        all the same (those files are never read, changed or deleted). A ``path`` that is an existing file always
        raises ``NotADirectoryError`` naming it
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
        allow_foreign_files: bool = False,
    ) -> None:
        # BaseBuffer.__init__ is not called: it would allocate and assign attributes that are properties here
        if optimize_memory_usage:
            raise ValueError("LifelongReplayBuffer stores next observations: optimize_memory_usage is not supported")
        # every space accepted reopens equal (schema.SUPPORTED_SPACES); the rest is refused before anything is written
        check_spaces(observation_space, action_space)
        description = None
        if observation_space is not None and action_space is not None and not read_only:
            description = describe_spaces(observation_space, action_space)
        path_str = None if path is None else os.fspath(path)
        held = _prepare_directory(path_str, mode) if path_str is not None and not read_only else 0
        #: a re-run must not add to an earlier run's data silently: without mode="append", adding to a directory that
        #: held transitions when it was opened is refused (reading, sampling and SB3's load of a model still work)
        self._refused_writes = f"{path_str!r} held {held:,} transitions when it was opened" if held and mode == "new" else ""
        fields: Optional[dict[str, tuple[str, tuple[int, ...]]]] = None
        if observation_space is not None and action_space is not None:
            fields = buffer_fields(observation_space, action_space, self._maybe_cast_dtype(action_space.dtype))
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
            allow_foreign_files=allow_foreign_files,
        )
        if not self.store.spaces and description is not None:
            self.store.describe_spaces(description)
        if observation_space is None or action_space is None:
            try:
                observation_space = observation_space_of(self.store)
                action_space = action_space_of(self.store)
            except (ValueError, TypeError, OverflowError, KeyError, AttributeError, AssertionError) as error:
                self.store.abandon()
                raise BufferFormatError(
                    f"{os.path.join(str(path_str), MANIFEST_NAME)}: its 'spaces' do not describe the observation and "
                    f"action spaces of its fields ({type(error).__name__}: {error})"
                ) from None
        self._obs_keys = obs_keys_of(self.store.fields)
        self._checks = AddChecks(observation_space, action_space, self.store.fields)
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
        self._source = check_source_id(source)
        self._stream_base: Optional[int] = None
        self._width = 0
        self._runs = RunIndex(self.store.first)
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

    @staticmethod
    def check_directory(path: Union[str, os.PathLike]) -> BufferCheck:
        """
        Check every chunk of a buffer directory (files, sizes and checksums: reads the whole buffer once), without
        opening it and without writing anything there. What ``verify="all"`` checks, reported chunk by chunk instead of
        raising at the first damaged one. From a shell: ``python -m sb3_lifelong.buffers verify PATH``.

        :param path: The buffer directory
        :return: The report: ``report.damaged`` lists the damaged chunks (empty: intact), ``report.summary()`` says it
        :raises BufferFormatError: its manifest is not valid (then no chunk can be located)
        """
        return check_buffer(os.fspath(path))

    @classmethod
    def salvage(
        cls, path: Union[str, os.PathLike], destination: Union[str, os.PathLike], chunk_size: int = 10_000, **kwargs: Any
    ) -> tuple[LifelongReplayBuffer, BufferCheck]:
        """
        Copy the intact chunks of a damaged buffer directory into a new directory and open the copy (``path`` is only
        read: the damaged original stays as it is). The rows of damaged chunks are left out; n-step returns never chain
        across them. From a shell: ``python -m sb3_lifelong.buffers salvage PATH NEW``.

        :param path: The damaged buffer directory
        :param destination: A new (or empty) directory
        :param chunk_size: Transitions per chunk of the copy
        :param kwargs: Arguments of :meth:`open` for the copy (``read_only``, ``device``, ``n_steps``, ...)
        :return: The copy, opened, and the report (``report.damaged``: the chunks left out; ``report.copied``)
        """
        report = salvage_buffer(os.fspath(path), os.fspath(destination), chunk_size=chunk_size)
        return cls.open(destination, **kwargs), report

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
    def name_source(self, source: int, name: Optional[str] = None, metadata: Optional[dict[str, Any]] = None) -> None:
        """
        Make a source id known, or rename it or replace its metadata, without making it the source of the next
        transitions (:meth:`set_source` does that too): what importers and :func:`merge_buffers` do before
        :meth:`append_rows`.

        :param source: Source id in [0, 65534]
        :param name: Name (default: the name it has, else ``"source_<id>"``)
        :param metadata: JSON-serialisable dict (default: the metadata it has, else ``{}``), checked with the manifest
            reader's own limits: numpy scalars and arrays of numbers are converted exactly to Python numbers and lists;
            NaN or infinite floats, ints of more than 100 characters, more than 8 levels of nesting, keys that are not
            strings and other objects raise a ``ValueError`` (``MetadataError``) naming the source and the key, with
            nothing changed
        """
        source = check_source_id(source)
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
        :param metadata: JSON-serialisable dict (e.g. the physical parameters of this environment variant), checked as
            by :meth:`name_source` (a refused one changes nothing, not even the source of the next transitions)
        """
        source = check_source_id(source)
        self.name_source(source, name, metadata)
        self._source = source

    def _source_of(self, info: dict[str, Any]) -> int:
        stage = info.get(STAGE_KEY)
        if stage is None:
            return self._source
        source = int(stage)
        known = self.store.source_name(source)
        if known is not None and known != f"source_{source}":
            return source  # named already: by an earlier transition of this stage, or by set_source(name=...)
        source = check_source_id(source)
        params = info.get(DYNAMICS_PARAMS_KEY)
        # checked (and numpy scalars converted exactly) by set_source, with the manifest reader's limits
        metadata = {str(k): v for k, v in params.items()} if isinstance(params, dict) else {}
        self.store.set_source(source, stage_name(source), metadata)  # Env-A, Env-B, ...: as stage_envs names them
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
        Append one transition per env (SB3 semantics). Any number of envs up to 65,535 is accepted: ``n_envs`` is the
        length of ``reward``.

        Every argument is checked before anything is stored, and a ``ValueError`` naming the field, the expected and
        the received shape is raised for a shape SB3's ``ReplayBuffer.add`` would not accept for ``n_envs`` envs
        (observations: ``(n_envs, *obs_shape)`` or what numpy broadcasts to it, any array of ``n_envs`` elements for
        Discrete spaces; actions: ``(n_envs, action_dim)`` or ``(n_envs, *action_shape)``, unbatched for one env;
        rewards and dones: ``(n_envs,)``; ``len(infos) == n_envs``). Shapes are never reshaped across envs (a
        transposed array is refused, not scrambled). A NaN or infinite observation, next observation, action or
        reward (after conversion to the stored dtype) raises a ``ValueError`` naming the field and the env; nothing of
        that call is stored. Only real numbers are stored (bool, integer and float arrays): complex, datetime,
        timedelta, string, bytes and object arrays raise a ``ValueError`` naming the field and the dtype, as does a
        call with more than 65,535 envs (``MAX_ENVS_PER_ADD``). Integer (and bool) fields store only what their dtype
        holds exactly, as float fields refuse what overflows: a value out of their range (300 or -1 in a uint8 image),
        fractional (0.7 for an integer action), NaN or infinite raises a ``ValueError`` naming the field and the env,
        instead of being wrapped around or truncated; ``done`` must be 0 or 1 (or a bool). The metadata a new
        stage's ``info["dynamics_params"]`` gives its source is checked as :meth:`name_source` checks it (numpy
        scalars converted exactly; NaN, infinities and what the manifest's reader would refuse raise a ``ValueError``
        naming the source and the key): a refused add stores nothing and every earlier transition stays committable.

        A directory writer writes only in the process that opened it: in a child of ``os.fork()``, ``add`` (and
        ``flush``, ``close``, ``checkpoint``) raise :class:`~sb3_lifelong.buffers.ForkedWriterError`.

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
        self.store.check_owner("add")
        self._refuse_mixing()
        rows = self._checks.rows(obs, next_obs, action, reward, done, infos)
        # checked: nothing of this call was stored (or changed) before
        width = len(infos)
        flags = rows["flags"]
        if width != self._width or self._stream_base is None:
            self._stream_base = self.store.reserve_streams(width)
            self._width = width
            self.n_envs = width
            self._stream_ids = np.arange(self._stream_base, self._stream_base + width, dtype=np.uint32)
            self._widths = np.full(width, width, dtype=np.uint16)
        source = self._source
        if self.store.source_name(source) is None:
            self.name_source(source)
        sources = self._source_rows
        if self._source_rows_of != source or len(sources) != width:
            sources = self._source_rows = np.full(width, source, dtype=np.uint16)  # append() copies it
            self._source_rows_of = source
        timeouts = self.handle_timeout_termination
        for i, info in enumerate(infos):
            if STAGE_KEY in info:
                if sources is self._source_rows:
                    sources = sources.copy()
                try:
                    sources[i] = self._source_of(info)
                except MetadataError as error:
                    raise MetadataError(
                        f"add(): info[{DYNAMICS_PARAMS_KEY!r}] of env {i}: {error.core or error}; nothing of this add() was "
                        "stored (every earlier transition stays committable)"
                    ) from None
            if timeouts and info.get("TimeLimit.truncated", False):
                flags = flags.view(np.uint8)
                flags[i] |= FLAG_TIMEOUT
        rows["flags"] = flags
        rows["sources"] = sources
        rows["streams"] = self._stream_ids
        rows["widths"] = self._widths
        self.append_rows(rows)

    # class defaults: add() makes its array of source ids at its first call, and again when the source or n_envs changes
    _source_rows = np.zeros(0, dtype=np.uint16)
    _source_rows_of = -1

    def _refuse_mixing(self) -> None:
        """Raise before the first write into a directory that held transitions when it was opened with mode="new"."""
        if self._refused_writes:
            raise FileExistsError(
                f"{self._refused_writes}: adding would mix this run's data into it. To continue the run that wrote it, "
                "load its saved model (MPO.load(zip, env=env), then learn(..., reset_num_timesteps=False): the model "
                "reattaches the buffer it was saved with), or pass mode='append' (as LifelongReplayBuffer.open does; in "
                "SB3: replay_buffer_kwargs={'path': ..., 'mode': 'append'}); pass mode='overwrite' to delete it and start "
                "again, or choose another path."
            )

    def append_rows(self, rows: dict[str, np.ndarray]) -> None:
        """
        Append transitions as the store keeps them, without the checks and conversions of :meth:`add`: what importers
        (``from_d4rl``, ``from_minari``) and :func:`merge_buffers` write. Each row must already hold what ``add`` would
        have stored: normalised actions, the ``flags`` (``FLAG_DONE``, ``FLAG_TIMEOUT``), known source ids
        (:meth:`name_source`), stream ids reserved with ``store.reserve_streams`` and the ``widths``. In a directory,
        a failed write stores none of the call's rows (see :meth:`add`).

        :param rows: every stored field (``buffer.store.fields``) -> array of shape ``(n, *row_shape)``
        """
        self.store.check_owner("append_rows")
        self._refuse_mixing()
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

        :return: ``{"path": directory, "transitions": global number of transitions committed, "buffer_id": its
            identity}`` (transitions ever committed, evicted ones included; ``buffer_id`` only for a buffer that has
            one, see :attr:`buffer_id`), recorded in the checkpoint; None in memory
        :raises OSError: the flush failed (then nothing new is committed, and the checkpoint must not be written)
        """
        if self.store.path is None:
            return None
        self.store.flush()  # no-op for a read-only buffer: it records what the writer committed
        record: dict[str, Any] = {"path": self.store.path, "transitions": int(self.store.num_committed)}
        if self.store.buffer_id is not None:
            record["buffer_id"] = self.store.buffer_id
        return record

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
        :raises BufferFormatError: the directory now holds another buffer (deleted and created again at the same path:
            its manifest records another :attr:`buffer_id`), or, for a buffer without an id, its committed rows went
            down; the buffer still reads what it read before
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
        self._runs = RunIndex()
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
    def buffer_id(self) -> Optional[str]:
        """
        The buffer's identity: a random id (32 hexadecimal digits) written in the directory's manifest when the buffer
        was created, kept by every writer after it (a copy of the directory keeps it too). A buffer deleted and created
        again at the same path gets another one. None in memory, and for a directory created before buffers had an id.
        """
        return self.store.buffer_id

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

    @property
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

    def read_range(self, name: str, start: int, stop: int) -> np.ndarray:
        """Rows ``start:stop`` of a stored field, as stored (see :meth:`LifelongSampler.read_range`)."""
        return self.store.read_range(name, start, stop)

    def __repr__(self) -> str:
        where = self.store.path or "memory"
        return f"LifelongReplayBuffer({self.size()} transitions, {len(self.store.source_table())} sources, {where})"
