"""
Base class of this package's off-policy algorithms: SB3's ``OffPolicyAlgorithm`` plus exact resumption (the random
streams of training and of the environment's resets are saved with the model and restored by ``load``).
"""

import contextvars
import dataclasses
import inspect
import io
import pathlib
import warnings
from collections.abc import Iterable, Mapping
from typing import Any, ClassVar, Optional, TypeVar, Union, cast

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.logger import HumanOutputFormat
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_lifelong.buffers.lifelong import LifelongReplayBuffer
from sb3_lifelong.common import reattach
from sb3_lifelong.common.distillation import distill
from sb3_lifelong.common.resume import EpisodeRngRecorder, ExactResume, capture_rng_state, restore_rng_state
from sb3_lifelong.common.updates import UpdateMechanics
from sb3_lifelong.core.atomic import atomic_write
from sb3_lifelong.core.contract import SYNC_TIMESTEP_METHOD
from sb3_lifelong.core.safe_load import safe_custom_objects, saved_data, saved_policy_class
from sb3_lifelong.core.settings import Settings

SelfLifelongAlgorithm = TypeVar("SelfLifelongAlgorithm", bound="LifelongOffPolicyAlgorithm")


#: While ``load`` rebuilds a model whose replay buffer comes from the saved ``replay_buffer_kwargs``: the zip, for
#: messages (None otherwise)
_LOADING_SAVED_BUFFER_KWARGS: contextvars.ContextVar[Optional[str]] = contextvars.ContextVar(
    "loading_saved_buffer_kwargs", default=None
)


def _describe(path: Union[str, pathlib.Path, io.BufferedIOBase]) -> str:
    """A saved model's path for messages (``the checkpoint`` for a file object)."""
    return str(path) if isinstance(path, (str, pathlib.Path)) else "the checkpoint"


def _with_suffix(path: Union[str, pathlib.Path], suffix: str) -> pathlib.Path:
    """The file SB3's ``save`` writes for ``path``: ``<path>.<suffix>`` when ``path`` has no suffix."""
    path = pathlib.Path(path)
    return pathlib.Path(f"{path}.{suffix}") if path.suffix == "" else path


def _algorithms(base: type) -> list[type]:
    """Every algorithm class derived from ``base`` (those imported), ``base`` included."""
    found = [base]
    subclass: type
    for subclass in base.__subclasses__():
        found.extend(_algorithms(subclass))
    return found


def _check_saved_algorithm(
    cls: type, path: Union[str, pathlib.Path, io.BufferedIOBase], data: Optional[dict[str, Any]]
) -> None:
    """
    Refuse, before anything is built, a zip saved by another of this package's algorithms (its policy class is one
    of that algorithm's, not of ``cls``), naming both classes.

    :param cls: The class whose ``load`` was called
    :param path: The saved model, for the message
    :param data: Its ``data`` (see :func:`~sb3_lifelong.core.safe_load.saved_data`), or None
    :raises ValueError: e.g. ``CRR.load`` of an MPO zip
    """
    saved = None if data is None else saved_policy_class(data)
    if saved is None:
        return

    def policies(algorithm: type) -> set[tuple[str, str]]:
        aliases = getattr(algorithm, "policy_aliases", {}) or {}
        return {(policy.__module__, policy.__qualname__) for policy in aliases.values()}

    if saved in policies(cls):
        return
    owners = [a.__name__ for a in _algorithms(LifelongOffPolicyAlgorithm) if a is not cls and saved in policies(a)]
    if owners:
        raise ValueError(
            f"{_describe(path)} was saved by {owners[0]} (its policy is {saved[0]}.{saved[1]}), not by {cls.__name__}: "
            f"load it with {owners[0]}.load"
        )


class LifelongOffPolicyAlgorithm(ExactResume, UpdateMechanics, OffPolicyAlgorithm):
    """
    SB3's ``OffPolicyAlgorithm`` whose ``save``/``load`` also carry the random streams, so that ``load`` (with an
    environment, or ``set_env`` after it) + the replay buffer (the ``LifelongReplayBuffer`` directory the model was
    saved with, which ``learn`` reattaches, or ``load_replay_buffer``) + ``learn(..., reset_num_timesteps=False)``
    continues exactly as an uninterrupted run would when the model was saved at an episode start of every env.

    Saved: torch's, numpy's and Python's global generators, the action space's, and for each env wrapped in
    :class:`EpisodeRngRecorder` (every ``gym.Env`` given to the algorithm is), what its pending episode start was
    drawn from. ``load`` restores them, and the first reset after it replays that episode start instead of
    re-seeding the env from ``seed`` (SB3's ``load`` re-seeds every generator from ``seed``, which replays the
    random numbers, and the first episode start, of the start of training). An env that was in the middle of an
    episode starts a new episode from its generator's saved state. The state of the environment itself (e.g.
    a dynamics schedule's step counter) is not saved; a dynamics schedule follows the model's ``num_timesteps``,
    which ``learn`` tells it (:mod:`sb3_lifelong.core.contract`). It also holds what the algorithms' training steps
    share: an optimizer step, the target networks' update, the critics' scoring copies, the check of the losses.
    """

    #: the algorithm's grouped settings: argument -> their class (e.g. MPO's ``policy_loss`` and ``compute``)
    settings_groups: ClassVar[dict[str, type[Settings]]] = {}

    def _setup_model(self) -> None:
        # a load may pass grouped settings as dicts (merged into the saved ones, see load), and a zip saved before
        # they were grouped holds them as attributes of their own
        for name, group in self.settings_groups.items():
            setattr(self, name, group.settled(self.__dict__, name))
        loading = _LOADING_SAVED_BUFFER_KWARGS.get()
        saved = None
        if loading is not None and self.replay_buffer is None:
            # load() rebuilds the buffer from the zip's replay_buffer_kwargs: plain data anyone can edit. A directory
            # they name is only opened read-only, if it holds the model's buffer; learn() reattaches it for writing
            # (sb3_lifelong.common.reattach). capacity, evict, mode, ... of the zip are never applied
            saved = reattach.plan(
                self, self.replay_buffer_class, self.replay_buffer_kwargs, self.__dict__.get("_buffer_checkpoint")
            )
        # A buffer class that computes n-step returns itself (e.g. LifelongReplayBuffer) gets the algorithm's
        # n_steps and gamma. SB3 warns that n_steps "is ignored" whenever a replay_buffer_class is given; that is
        # false when the buffer computes n-step returns of the same length (forwarded here, or saved with the
        # model, which SB3's load passes again), so that warning, and only it, is dropped then.
        honoured = False
        if self.n_steps > 1 and self.replay_buffer_class is not None and self.replay_buffer is None:
            parameters = inspect.signature(self.replay_buffer_class.__init__).parameters
            if "n_steps" in parameters:
                if "n_steps" not in self.replay_buffer_kwargs:
                    self.replay_buffer_kwargs.update({"n_steps": self.n_steps, "gamma": self.gamma})
                honoured = self.replay_buffer_kwargs["n_steps"] == self.n_steps
        if saved is not None:
            assert loading is not None
            saved.kwargs.update({k: v for k, v in self.replay_buffer_kwargs.items() if k in ("n_steps", "gamma")})
            self.replay_buffer = reattach.open_for_reading(self, saved, loading)
            self.__dict__["_saved_buffer"] = saved
        with warnings.catch_warnings():
            if honoured:
                warnings.filterwarnings("ignore", message=rf"`n_steps={self.n_steps}` is ignored because a custom")
            super()._setup_model()

    @staticmethod
    def _wrap_env(env: GymEnv, verbose: int = 0, monitor_wrapper: bool = True) -> VecEnv:
        if isinstance(env, gym.Env) and not is_wrapped(env, EpisodeRngRecorder):
            env = EpisodeRngRecorder(env)  # so that save() can record what the pending episode start was drawn from
        return OffPolicyAlgorithm._wrap_env(env, verbose, monitor_wrapper)

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: Union[np.ndarray, dict[str, np.ndarray]],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        try:
            super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        except BaseException:
            # add() failed (e.g. disk full): the env has stepped but SB3 kept the observation before the step, so a
            # learn() that goes on would store it with the next step's outcome. Reset the env at the next learn()
            # instead, and start new streams in the buffer (n-step returns must not chain into the new episode)
            self._last_obs = None
            end_streams = getattr(replay_buffer, "end_streams", None)
            if callable(end_streams):
                end_streams()
            raise
        # SB3's off-policy loop does not track it: the envs whose next observation starts an episode (for save())
        self._last_episode_starts = dones
        self._stored_timesteps = self.num_timesteps  # the timestep the stored transitions reach (for save())

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "_scoring_copies",
            "_resume_rng",
            "_forward",
            "_saved_buffer",
            "_stored_timesteps",
            "_resume_timesteps",
        ]

    def distill(self, student_class: type, **kwargs: Any) -> Any:
        """
        Distil this model's whole replay buffer into a fresh policy, offline (the Offline Distillation Pipeline):
        ``model.distill(CRR, beta=1.0, eval_env={"Env-A": env_a, "Env-B": env_b})``. The same as
        :func:`sb3_lifelong.distill.distill` with this model as the source: the student uses the buffer as it is (no
        copy), and logs beside the model's own logs.

        :param student_class: the offline algorithm (:class:`~sb3_lifelong.CRR`; :class:`~sb3_lifelong.BC` for
            behaviour cloning)
        :param kwargs: the arguments of :func:`sb3_lifelong.distill.distill`, by name and with its defaults
            (``total_updates``, ``eval_env``, ``beta``, ``batch_size``, ...; any other argument of the student's
            constructor)
        :return: the trained student, ready for ``predict`` and ``save``
        """
        return distill(self, student_class, **kwargs)

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        self._reattach_saved_buffer()
        self._restore_loaded_rng()
        self._continue_buffer_timesteps(reset_num_timesteps)
        self._sync_env_timestep(0 if reset_num_timesteps else self.num_timesteps)
        self._sample_on_model_device()
        setup = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        self._stored_timesteps = self.num_timesteps
        self._quiet_stdout()
        return setup

    def _continue_buffer_timesteps(self, reset_num_timesteps: bool) -> None:
        """
        The checkpoint rule, at the first ``learn`` after a ``load`` that continues the buffer directory the checkpoint
        committed: training resumes at the timestep its buffer reaches, so that the buffer holds one transition per
        timestep. Transitions committed after the save (the run went on, then stopped) are kept and count as collected
        (a warning says how many); a step in flight at the save (a callback's ``save`` runs before SB3 stores the step's
        transition) was not stored, and is collected again.

        :param reset_num_timesteps: As given to ``learn`` (True: the timesteps start again from 0, nothing to do)
        """
        pending = self.__dict__.pop("_resume_timesteps", None)
        buffer = self.replay_buffer
        if pending is None or reset_num_timesteps or not isinstance(buffer, LifelongReplayBuffer):
            return
        record, at_load = pending
        same = buffer.path == record["path"] and record["buffer_id"] in (None, buffer.buffer_id)
        if not same or buffer.store.read_only or self.num_timesteps != at_load:
            return  # another buffer, one only read, or trained since the load: not the checkpoint's buffer continued
        held = int(buffer.store.num_committed)
        after = held - record["transitions"]
        if after < 0:
            return  # the buffer lags the checkpoint: refused by learn, or warned at load
        timesteps = record["timesteps"] + after
        if after > 0:
            warnings.warn(
                f"{buffer.path} holds {after:,} transitions committed after this checkpoint was saved (the run went on, "
                f"then stopped): they are kept and count as collected, so training resumes at timestep {timesteps:,}, "
                f"not {self.num_timesteps:,} (the updates the stopped run made after its checkpoint are lost)",
                stacklevel=5,
            )
        self.num_timesteps = timesteps

    def _quiet_stdout(self) -> None:
        """
        ``verbose=1`` prints what happens (the device, the log folder, the evaluations: about one line each), not SB3's
        table of every logged value at every dump (hundreds of lines in a short run): those tables are ``verbose=2``.
        They still go to the other outputs (tensorboard, CSV); a logger given with ``set_logger`` is left as it is.
        """
        if self.verbose >= 2 or self._custom_logger or self._logger is None:
            return
        self._logger.output_formats = [
            output
            for output in self._logger.output_formats
            if not (isinstance(output, HumanOutputFormat) and not getattr(output, "own_file", True))
        ]

    def _pending_saved_buffer(self) -> Optional[reattach.SavedBuffer]:
        """The buffer directory the loaded zip names, while the model still has the buffer ``load`` gave it."""
        saved = self.__dict__.get("_saved_buffer")
        if saved is not None and self.replay_buffer is not saved.placeholder:
            del self.__dict__["_saved_buffer"]  # replaced since (load_replay_buffer, set_offline_data, ...): not ours
            return None
        return saved

    def _reattach_saved_buffer(self) -> None:
        """
        Online training resumes: a model loaded with its zip's ``replay_buffer_kwargs`` reopens the buffer directory it
        was saved with for writing (``mode="append"``), once it is checked to be that buffer, holding at least the
        transitions the checkpoint committed (see :mod:`sb3_lifelong.common.reattach`); otherwise this raises and
        nothing is written.
        """
        saved = self._pending_saved_buffer()
        if saved is None or saved.read_only:
            return
        buffer = reattach.open_for_writing(self, saved)
        placeholder = saved.placeholder
        self.replay_buffer = buffer
        del self.__dict__["_saved_buffer"]
        if isinstance(placeholder, LifelongReplayBuffer):
            placeholder.close()

    def _sample_on_model_device(self) -> None:
        """
        Have the replay buffer sample onto the model's device, as SB3's ``load_replay_buffer`` does: a buffer built or
        opened on another device (e.g. on the CPU, for a model on a GPU), or shared with a model on another device
        (``distill``'s teacher), gives its batches where this model's networks are. Called before each training run.
        """
        if self.replay_buffer is not None and self.replay_buffer.device != self.device:
            self.replay_buffer.device = self.device

    def _sync_env_timestep(self, timestep: int) -> None:
        """
        Tell the envs that follow the model's timestep (e.g. a ``DynamicsSchedule``) the timestep of the next step
        and the number of envs, before SB3's ``_setup_learn`` resets them (see :mod:`sb3_lifelong.core.contract`).

        :param timestep: ``num_timesteps`` at the start of this ``learn``
        """
        env = self.env
        if env is not None and env.has_attr(SYNC_TIMESTEP_METHOD):
            env.env_method(SYNC_TIMESTEP_METHOD, timestep=timestep, n_envs=env.num_envs)

    def _checkpoint_buffer(self) -> Optional[dict[str, Any]]:
        """
        Commit the replay buffer for a checkpoint, when it can (a ``LifelongReplayBuffer`` directory: its pending
        transitions are flushed), and say what the checkpoint records of it.

        :return: ``{"path", "transitions", "buffer_id"}`` (the transitions the buffer has committed, its identity), or
            None. A model loaded and not trained since records what its zip recorded, as it was
        """
        if self.replay_buffer is None or self._pending_saved_buffer() is not None:
            # loaded without its buffer, or not trained since load: what the loaded checkpoint recorded, as it was
            return self.__dict__.get("_buffer_checkpoint")
        checkpoint = getattr(self.replay_buffer, "checkpoint", None)
        if not callable(checkpoint):
            return None
        record = checkpoint()
        if record is not None:
            # the timestep its committed transitions reach: a save from a callback runs while a step is in flight
            # (SB3 counts the step before the callbacks, and stores its transition after them)
            in_flight = self.num_timesteps - self.__dict__.get("_stored_timesteps", self.num_timesteps)
            record["timesteps"] = self.num_timesteps - max(in_flight, 0)
        return record

    def _check_buffer_checkpoint(self, checkpoint: str = "the checkpoint") -> None:
        """Warn when the replay buffer holds fewer transitions than the loaded checkpoint recorded as committed."""
        record = self.__dict__.get("_buffer_checkpoint")
        check = getattr(self.replay_buffer, "check_checkpoint", None)
        if isinstance(record, dict) and callable(check):
            check(record, checkpoint)

    def load_replay_buffer(self, path: Union[str, pathlib.Path, io.BufferedIOBase], truncate_last_traj: bool = True) -> None:
        """
        SB3's ``load_replay_buffer`` (a pickle: load only files you trust, it can run code), then, for a
        ``LifelongReplayBuffer`` directory, a warning if it holds fewer transitions than the model's checkpoint
        recorded as committed.

        :param path: The pickled buffer
        :param truncate_last_traj: As for SB3 (HER buffers)
        """
        saved = self._pending_saved_buffer()
        super().load_replay_buffer(path, truncate_last_traj)
        if saved is not None and isinstance(saved.placeholder, LifelongReplayBuffer):
            saved.placeholder.close()  # the buffer load attached (read-only, or in memory) is replaced
        self._pending_saved_buffer()
        self._check_buffer_checkpoint()

    def save_replay_buffer(self, path: Union[str, pathlib.Path, io.BufferedIOBase]) -> None:
        """
        SB3's ``save_replay_buffer`` (a pickle), written atomically: a save that fails leaves the previous file as it
        was and raises :class:`~sb3_lifelong.core.atomic.AtomicWriteError` naming it.

        :param path: The file (``.pkl`` added if missing; missing parent directories are created) or a file object
        """
        if isinstance(path, (str, pathlib.Path)):
            target = _with_suffix(path, "pkl")
            target.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(target) as handle:
                super().save_replay_buffer(cast(io.BufferedIOBase, handle))
        else:
            super().save_replay_buffer(path)

    def save(
        self,
        path: Union[str, pathlib.Path, io.BufferedIOBase],
        exclude: Optional[Iterable[str]] = None,
        include: Optional[Iterable[str]] = None,
    ) -> None:
        """
        SB3's ``save``, plus what exact resumption needs (random streams, episode starts). A checkpoint commits the
        replay buffer: a ``LifelongReplayBuffer`` directory is flushed first (if that fails, the ``OSError`` goes
        through and no file is written), and the number of transitions it has committed is recorded in the zip, so
        that ``load`` can warn when the buffer on disk lags the checkpoint.

        The zip is written atomically (:mod:`sb3_lifelong.core.atomic`): into a temporary file beside ``path``,
        synced, then renamed over it. A save that fails (e.g. a full disk) raises
        :class:`~sb3_lifelong.core.atomic.AtomicWriteError` naming the file and leaves the previous checkpoint
        there as it was, loadable; a ``path`` that is a directory raises ``IsADirectoryError`` (SB3 would write
        ``<path>_2`` instead).

        :param path: The file (``.zip`` added if missing; missing parent directories are created) or a file object
        :param exclude: As for SB3
        :param include: As for SB3
        """
        # the buffer first: a checkpoint whose buffer cannot be committed is not written
        self._buffer_checkpoint = self._checkpoint_buffer()
        # loaded and not trained since: the streams and records to continue from are those that were loaded
        self._rng_state = self._pending_rng_state() or capture_rng_state(self.action_space)
        pending = self.__dict__.get("_env_rng")  # loaded without an env: saved again as it was
        records = self._env_rng_records()
        if records is not None:
            self._env_rng = records
        # grouped settings (MPO's policy_loss, compute) are saved as plain dicts: readable in the zip, loadable with
        # safe=True, and made settings again by the algorithm's setup
        grouped = {name: getattr(self, name) for name in self.settings_groups}
        self.__dict__.update({name: dataclasses.asdict(value) for name, value in grouped.items()})
        try:
            if isinstance(path, (str, pathlib.Path)):
                target = _with_suffix(path, "zip")
                target.parent.mkdir(parents=True, exist_ok=True)
                with atomic_write(target) as handle:  # the zip replaces the previous file only once it is complete
                    super().save(cast(io.BufferedIOBase, handle), exclude=exclude, include=include)
            else:
                super().save(path, exclude=exclude, include=include)
        finally:
            self.__dict__.update(grouped)
            del self._rng_state
            if pending is None:
                self.__dict__.pop("_env_rng", None)
            else:
                self._env_rng = pending

    @classmethod
    def load(
        cls: type[SelfLifelongAlgorithm],
        path: Union[str, pathlib.Path, io.BufferedIOBase],
        env: Optional[GymEnv] = None,
        device: Union[th.device, str] = "auto",
        custom_objects: Optional[dict[str, Any]] = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        safe: bool = False,
        **kwargs,
    ) -> SelfLifelongAlgorithm:
        """
        SB3's ``load``, plus exact resumption (random streams, episode starts) and clear errors: a zip saved by another
        of this package's algorithms is refused with a ``ValueError`` naming both classes, and a ``LifelongReplayBuffer``
        directory that holds fewer transitions than the checkpoint recorded as committed gives a warning.

        **Loading never writes to a buffer because of what the zip says.** When no ``replay_buffer_kwargs`` are given
        (here or in ``custom_objects``), a ``LifelongReplayBuffer`` directory named by the zip is opened read-only, and
        only if it is the buffer the model was saved with (same :attr:`~LifelongReplayBuffer.buffer_id`); else the model
        gets an empty buffer in memory, with a warning. The zip's ``capacity``, ``evict`` and ``mode`` are never
        applied. The first ``learn`` reattaches that buffer for writing (``mode="append"``: it continues after the
        transitions it holds, none evicted) once it is checked to hold at least the transitions the checkpoint
        committed, or raises saying what to pass instead (see :mod:`sb3_lifelong.common.reattach`). So
        ``load(zip, env=env)`` + ``learn(..., reset_num_timesteps=False)`` resumes a run as in SB3, with no extra
        argument. ``replay_buffer_kwargs`` given to ``load`` are used as they are.

        By default, loading unpickles the Python objects of the zip's ``data`` (spaces, schedules, classes) with
        cloudpickle, as SB3 does: **a tampered zip runs code**. Load only files you trust, or pass ``safe=True``.

        :param path: The saved model (``.zip`` added if missing) or a file object
        :param env: As for SB3
        :param device: As for SB3
        :param custom_objects: As for SB3 (entries given here are not unpickled, also with ``safe=True``)
        :param print_system_info: As for SB3
        :param force_reset: As for SB3
        :param safe: Unpickle nothing but what a model of this package saves: arrays, spaces, random generators,
            schedules, and references to policy, buffer, module and optimizer classes; anything else (a function
            pickled by value, any other global) raises ``pickle.UnpicklingError`` naming the entry and the global,
            before it runs (see :mod:`sb3_lifelong.core.safe_load`)
        :param kwargs: As for SB3 (e.g. ``replay_buffer_kwargs``); a grouped setting given as a dict (e.g.
            ``compute=dict(compile_losses=False)``) changes the settings it names and keeps the saved others
        :return: The model
        """
        data = saved_data(path)
        _check_saved_algorithm(cls, path, data)
        for name in cls.settings_groups:  # a dict of some settings changes those, the saved ones stay
            saved_settings = (data or {}).get(name)
            if isinstance(kwargs.get(name), Mapping) and isinstance(saved_settings, dict):
                kwargs[name] = {**saved_settings, **kwargs[name]}
        given = "replay_buffer_kwargs" in kwargs or "replay_buffer_kwargs" in (custom_objects or {})
        if safe:
            if data is None:
                raise ValueError(f"{_describe(path)}: safe=True needs a zip whose 'data' can be read as JSON")
            custom_objects = safe_custom_objects(data, custom_objects or {}, _describe(path))
        # the saved replay_buffer_kwargs never write to a buffer (see sb3_lifelong.common.reattach); those given here,
        # or in custom_objects, are the caller's and are used as they are
        reopening = _LOADING_SAVED_BUFFER_KWARGS.set(None if given else _describe(path))
        try:
            model = super().load(
                path,
                env=env,
                device=device,
                custom_objects=custom_objects,
                print_system_info=print_system_info,
                force_reset=force_reset,
                **kwargs,
            )
        except KeyError as error:  # e.g. a state dict this class saves that the zip does not hold
            raise ValueError(
                f"{_describe(path)} does not hold what {cls.__name__} saves (missing {error}): was it saved by another "
                "algorithm? Load it with the class that saved it"
            ) from error
        finally:
            _LOADING_SAVED_BUFFER_KWARGS.reset(reopening)
        model._check_buffer_checkpoint(_describe(path))
        record = reattach.checkpoint_record(model.__dict__.get("_buffer_checkpoint"))
        if record is not None and record["timesteps"] is not None:
            model.__dict__["_resume_timesteps"] = (record, model.num_timesteps)  # the checkpoint rule, at the first learn
        rng_state = model.__dict__.pop("_rng_state", None)
        if rng_state is not None:
            restore_rng_state(rng_state, model.action_space)
            model.__dict__["_resume_rng"] = (rng_state, model.num_timesteps, model._n_updates)  # restored again by learn()
        model._replay_env_rng()
        return model
