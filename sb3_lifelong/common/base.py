"""
Base class of this package's off-policy algorithms: SB3's ``OffPolicyAlgorithm`` plus exact resumption (the random
streams of training and of the environment's resets are saved with the model and restored by ``load``).
"""

import contextvars
import inspect
import io
import pathlib
import random
import warnings
from collections.abc import Iterable, Sequence
from typing import Any, Optional, TypeVar, Union

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.common.vec_env import VecEnv

from sb3_lifelong.common.distillation import distill
from sb3_lifelong.common.losses import sum_of
from sb3_lifelong.core.contract import SYNC_TIMESTEP_METHOD
from sb3_lifelong.core.safe_load import safe_custom_objects, saved_data, saved_policy_class
from sb3_lifelong.numerics.compiling import CHECK_TOLERANCE, LOW_PRECISION_CHECK_TOLERANCE, LazyCompiled
from sb3_lifelong.numerics.fast_ops import HiddenLinear
from sb3_lifelong.numerics.hardware import SIMULATED_BFLOAT16, resolve_train_dtype
from sb3_lifelong.numerics.scoring import LowPrecisionCopy, resolve_scoring_dtype, runs_no_grad_pass

SelfLifelongAlgorithm = TypeVar("SelfLifelongAlgorithm", bound="LifelongOffPolicyAlgorithm")


def capture_rng_state(action_space: Optional[spaces.Space] = None) -> dict[str, Any]:
    """
    Snapshot of every random stream training draws from, in a JSON-serialisable form: torch's global generator (and
    CUDA's, once CUDA is in use), numpy's legacy global generator, Python's ``random``, and the action space's
    generator (warm-up actions).

    :param action_space: the algorithm's action space
    :return: the state, to be passed to :func:`restore_rng_state`
    """
    np_state = np.random.get_state()
    assert isinstance(np_state, tuple)  # the legacy form, get_state's default
    py_version, py_internal, py_gauss = random.getstate()
    state: dict[str, Any] = {
        "torch": th.get_rng_state().tolist(),
        "numpy": [np_state[0], np_state[1].tolist(), int(np_state[2]), int(np_state[3]), float(np_state[4])],
        "python": [py_version, list(py_internal), py_gauss],
    }
    if th.cuda.is_available() and th.cuda.is_initialized():
        state["cuda"] = [device_state.tolist() for device_state in th.cuda.get_rng_state_all()]
    if action_space is not None:
        state["action_space"] = action_space.np_random.bit_generator.state
    return state


def restore_rng_state(state: dict[str, Any], action_space: Optional[spaces.Space] = None) -> None:
    """
    Restore the random streams captured by :func:`capture_rng_state`.

    :param state: the captured state
    :param action_space: the algorithm's action space
    """
    th.set_rng_state(th.tensor(state["torch"], dtype=th.uint8))
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and th.cuda.is_available():
        th.cuda.set_rng_state_all([th.tensor(device_state, dtype=th.uint8) for device_state in state["cuda"]])
    if action_space is not None and "action_space" in state:
        action_space.np_random.bit_generator.state = state["action_space"]


class EpisodeRngRecorder(gym.Wrapper):
    """
    Records where the random draws of each ``reset`` come from (the seed it was given, or else the state of the
    environment's ``np_random`` just before), so that a saved model can replay the start of an episode exactly:
    :class:`LifelongOffPolicyAlgorithm` wraps every ``gym.Env`` it is given in it (for a ``VecEnv``, wrap the
    sub-envs yourself, e.g. ``make_vec_env(env_id, n_envs, wrapper_class=EpisodeRngRecorder)``).

    Only the generator ``env.np_random`` is recorded (the one Gymnasium environments, MuJoCo ones included, draw
    their initial states from); generators of their own in the environment or its wrappers are not.

    :param env: The environment
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self._start_record: Optional[dict[str, Any]] = None
        self._replay: Optional[dict[str, Any]] = None

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict[str, Any]] = None) -> tuple[Any, dict[str, Any]]:
        if self._replay is not None:  # the first reset after a load: replay the saved record, whatever seed is given
            record, self._replay = self._replay, None
            seed = record.get("seed")
            if seed is None:
                self.env.np_random.bit_generator.state = record["rng"]
        if seed is not None:
            self._start_record = {"seed": int(seed)}
        else:
            self._start_record = {"rng": self.env.np_random.bit_generator.state}
        return self.env.reset(seed=seed, options=options)

    def sb3_lifelong_rng_record(self, at_episode_start: Optional[bool]) -> Optional[dict[str, Any]]:
        """
        What to save so that a loaded model continues from here: at an episode start (no step since the reset), the
        record of that reset (replaying it gives the same initial state); in an episode, the generator's current
        state (the next reset starts a new episode from it); a replay still pending from a load, as it is.

        :param at_episode_start: Whether no step was taken since the last reset; None: the algorithm has not reset
            the env (only a pending replay is returned)
        :return: ``{"seed": int}`` or ``{"rng": bit generator state}``, or None
        """
        if self._replay is not None:
            return self._replay
        if at_episode_start is None:
            return None
        if at_episode_start:
            return self._start_record
        return {"rng": self.env.np_random.bit_generator.state}

    def sb3_lifelong_replay(self, record: dict[str, Any]) -> None:
        """
        Make the next ``reset`` replay ``record`` (from :meth:`sb3_lifelong_rng_record`), ignoring the seed it is
        given.

        :param record: The saved record
        """
        self._replay = record


#: True while ``load`` rebuilds a model whose replay buffer comes from the saved ``replay_buffer_kwargs``
_LOADING_SAVED_BUFFER_KWARGS: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "loading_saved_buffer_kwargs", default=False
)


def _describe(path: Union[str, pathlib.Path, io.BufferedIOBase]) -> str:
    """A saved model's path for messages (``the checkpoint`` for a file object)."""
    return str(path) if isinstance(path, (str, pathlib.Path)) else "the checkpoint"


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


def optimized_parameters(module: BaseModel) -> list[th.Tensor]:
    """
    :return: the parameters ``module.optimizer`` steps, in its order: a critic's own, without a features extractor it
        shares with the actor (SB3 leaves that one to the actor's optimizer), so that clipping a critic's gradients
        never counts, or scales, the gradients the actor's loss put into the shared extractor
    """
    return [parameter for group in module.optimizer.param_groups for parameter in group["params"]]


class LifelongOffPolicyAlgorithm(OffPolicyAlgorithm):
    """
    SB3's ``OffPolicyAlgorithm`` whose ``save``/``load`` also carry the random streams, so that ``load`` (with an
    environment, or ``set_env`` after it) + the replay buffer (``load_replay_buffer``, or a ``LifelongReplayBuffer``
    directory reopened with ``mode="append"``) + ``learn(..., reset_num_timesteps=False)`` continues exactly as an
    uninterrupted run would when the model was saved at an episode start of every env.

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

    # the networks of an algorithm with target networks (MPO, CRR), set by its _setup_model (SB3 declares ``actor``)
    critic: th.nn.Module
    critic_target: th.nn.Module
    actor_target: th.nn.Module
    #: the low-precision copy of ``critic_target`` that scores sampled actions (:meth:`_make_scoring_copy`), or None
    _target_scoring_copy: Optional[LowPrecisionCopy] = None
    #: the update's forward pass, compiled when ``compile_losses`` asks for it (:meth:`_compiles_now`); None for an
    #: algorithm without one
    _forward: Optional[LazyCompiled] = None
    compile_losses: Union[bool, str] = False

    def _setup_model(self) -> None:
        if _LOADING_SAVED_BUFFER_KWARGS.get() and (self.replay_buffer_kwargs or {}).get("mode") == "overwrite":
            # load() rebuilds the buffer from the saved replay_buffer_kwargs: a model created with mode="overwrite" must
            # not delete, when loaded, the very buffer it was trained and saved with (reopened as mode="new" instead)
            self.replay_buffer_kwargs = {**self.replay_buffer_kwargs, "mode": "new"}
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

    def _env_rng_records(self) -> Optional[list[Optional[dict[str, Any]]]]:
        """What each env's pending (or next) episode start is drawn from, or None (no env, or not all recorded)."""
        env = self.env
        if env is None or not all(env.env_is_wrapped(EpisodeRngRecorder)):
            return None
        starts: list[Optional[bool]] = [None] * env.num_envs
        if self._last_obs is not None and self._last_episode_starts is not None:
            starts = [bool(start) for start in self._last_episode_starts]
        records = [env.env_method("sb3_lifelong_rng_record", starts[i], indices=[i])[0] for i in range(env.num_envs)]
        return records if any(record is not None for record in records) else None

    def _replay_env_rng(self) -> None:
        """After a load: make the env's next reset replay the records saved with the model (once)."""
        records = self.__dict__.get("_env_rng")
        if records is None or self.env is None or self._last_obs is not None:
            return  # nothing saved, no env yet (set_env will do it), or the env is not reset before learning
        del self._env_rng
        env = self.env
        if len(records) != env.num_envs or not all(env.env_is_wrapped(EpisodeRngRecorder)):
            why = (
                f"{len(records)} envs were saved, {env.num_envs} given"
                if len(records) != env.num_envs
                else "the env is a VecEnv whose sub-envs are not wrapped in sb3_lifelong.common.base.EpisodeRngRecorder"
            )
            consequence = (
                f"the env is re-seeded from seed={self.seed} as by SB3's load, so its first episodes start as those of the "
                "start of training did"
                if self.seed is not None
                else "its episodes do not start as those of an uninterrupted run would"
            )
            warnings.warn(f"The environment's random state saved with the model is not restored ({why}): {consequence}")
            return
        for i, record in enumerate(records):
            if record is not None:
                env.env_method("sb3_lifelong_replay", record, indices=[i])

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        super().set_env(env, force_reset=force_reset)
        self._replay_env_rng()

    def _raise_if_not_finite(self, **values: th.Tensor) -> None:
        """
        Stop training, with an error naming the update, as soon as a loss or a dual variable is NaN or infinite (a NaN
        reward in a buffer that does not refuse it, e.g. SB3's ``ReplayBuffer``, would otherwise spread to every
        parameter). Cheap: one ``isfinite`` over the few values concatenated, one device synchronisation per update;
        the values are looked at one by one only to write the message.

        :param values: name -> tensor (a loss, or a dual's raw parameters)
        :raises FloatingPointError: naming the values that are not finite, the update and the timestep
        """
        if bool(th.isfinite(th.cat([value.detach().reshape(-1) for value in values.values()])).all()):
            return
        bad = {
            name: value.detach().reshape(-1).tolist()
            for name, value in values.items()
            if not bool(th.isfinite(value.detach()).all())
        }
        described = ", ".join(f"{name} = {v[0] if len(v) == 1 else v}" for name, v in bad.items())
        raise FloatingPointError(
            f"{type(self).__name__}: {described} at update {self._n_updates} (num_timesteps {self.num_timesteps}): not "
            "finite, training stopped. The parameters this update changed may hold NaN or inf now: go on from the last "
            "checkpoint. Usual causes: a NaN or infinite reward, observation or action in the data (SB3's ReplayBuffer "
            "stores them; LifelongReplayBuffer refuses them at add()), or a learning rate too high"
        )

    @staticmethod
    def _gradient_step(
        *parts: tuple[BaseModel, th.Tensor], max_grad_norm: Optional[float], also_step: Sequence[th.optim.Optimizer] = ()
    ) -> None:
        """
        One step of each module's optimizer down its loss, with one backward pass of the losses' sum: one part is the
        usual step; several are one backward through a compiled graph, with the same gradients when no loss reaches
        another part's module. Each module's gradients' norm is clipped over the parameters its optimizer steps
        (:func:`optimized_parameters`).

        :param parts: ``(module, loss)`` pairs
        :param max_grad_norm: the clip of each module's gradients' norm (None: not clipped)
        :param also_step: optimizers of parameters outside the modules (e.g. MPO's duals), zeroed and stepped with
            them, not clipped
        """
        optimizers = [module.optimizer for module, _ in parts] + list(also_step)
        for optimizer in optimizers:
            optimizer.zero_grad(set_to_none=True)
        sum_of(loss for _, loss in parts).backward()
        if max_grad_norm is not None:
            for module, _ in parts:
                th.nn.utils.clip_grad_norm_(optimized_parameters(module), max_grad_norm, foreach=True)
        for optimizer in optimizers:
            optimizer.step()

    def _compiles_now(self) -> bool:
        """:return: whether this ``train`` call runs the compiled forward pass (see the algorithm's ``compile_losses``)"""
        if self._forward is None or getattr(self, "train_dtype", None) == SIMULATED_BFLOAT16:
            return False  # a compiled graph fuses the simulation's roundings away (HiddenLinear)
        to_go = getattr(self, "_total_timesteps", 0) - self.num_timesteps
        return self._forward.wanted(self.compile_losses, to_go, self.device)

    def _update_targets(self) -> None:
        """
        Move the target networks towards the online ones (an algorithm with targets calls it every
        ``target_update_interval`` updates): Polyak averaging with ``tau`` (1: a copy), of the critic then of the actor,
        and the target critic's low-precision copy follows.
        """
        polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
        polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)
        if self._target_scoring_copy is not None:
            self._target_scoring_copy.sync()

    def _make_scoring_copy(self, critic: th.nn.Module, scoring_dtype: str) -> Optional[LowPrecisionCopy]:
        """
        A low-precision copy of ``critic`` for the no-grad scoring passes, when ``scoring_dtype`` asks for one
        (see :func:`sb3_lifelong.numerics.scoring.resolve_scoring_dtype`); it is synchronised by
        :meth:`_sync_scoring_copies` after loads and by the algorithm after its updates.

        :return: the copy, or None to score in the critic's own precision (always for a critic that the scoring
            engine does not run, :func:`~sb3_lifelong.numerics.scoring.runs_no_grad_pass`: it is scored by calling it)
        """
        dtype = resolve_scoring_dtype(scoring_dtype, critic, self.device)
        if dtype == th.float32 or not runs_no_grad_pass(critic):
            return None
        copy = LowPrecisionCopy(critic, dtype)
        self.__dict__.setdefault("_scoring_copies", []).append(copy)
        return copy

    def _refuse_compiled_simulation(self, train_dtype: str) -> None:
        """
        :param train_dtype: the algorithm's ``train_dtype``
        :raises ValueError: ``train_dtype="simulated_bfloat16"`` with ``compile_losses=True``: the simulation runs
            eagerly, because a compiled graph fuses its roundings away (``"auto"`` then stays eager)
        """
        if train_dtype == SIMULATED_BFLOAT16 and self.compile_losses is True:
            raise ValueError(
                f"train_dtype={train_dtype!r} runs eagerly (a compiled graph fuses its roundings away): pass "
                "compile_losses=False or 'auto' (which then stays eager)"
            )

    def _apply_train_dtype(self, train_dtype: str) -> None:
        """
        Set the precision of the policy's hidden-to-hidden products in the passes that record gradients
        (:class:`~sb3_lifelong.numerics.fast_ops.HiddenLinear`), from ``train_dtype`` (see
        :func:`~sb3_lifelong.numerics.hardware.resolve_train_dtype`). Called at every setup, loads included.

        :param train_dtype: the algorithm's ``train_dtype``
        :raises ValueError: what :meth:`_refuse_compiled_simulation` refuses (for a load with ``compile_losses=True``)
        """
        self._refuse_compiled_simulation(train_dtype)
        dtype = resolve_train_dtype(train_dtype, self.device)
        for module in self.policy.modules():
            if isinstance(module, HiddenLinear):
                module.compute_dtype = None if dtype == th.float32 else dtype
                module.simulated = train_dtype == SIMULATED_BFLOAT16

    def _compiled_check_tolerance(self) -> float:
        """
        :return: the relative tolerance of the compiled update's first-call check against the eager one
            (:class:`~sb3_lifelong.numerics.compiling.LazyCompiled`): wider where the gradient passes multiply in
            bfloat16 (:meth:`_apply_train_dtype` first), whose roundings the compiled graph places differently
        """
        low = any(isinstance(m, HiddenLinear) and m.compute_dtype is not None for m in self.policy.modules())
        return LOW_PRECISION_CHECK_TOLERANCE if low else CHECK_TOLERANCE

    def _compile_scoring_copies(self, compiled: bool) -> None:
        """
        Have the scoring copies run their LayerNorm and tanh as one compiled kernel in the ``train`` calls whose update
        is compiled (:attr:`~sb3_lifelong.numerics.scoring.LowPrecisionCopy.compile_layer_norm`), and eagerly in the others.

        :param compiled: whether this ``train`` call runs the compiled update (:meth:`_compiles_now`)
        """
        for copy in self.__dict__.get("_scoring_copies", []):
            copy.compile_layer_norm = compiled

    def _sync_scoring_copies(self) -> None:
        for copy in self.__dict__.get("_scoring_copies", []):
            copy.sync()

    def set_parameters(self, *args: Any, **kwargs: Any) -> None:
        super().set_parameters(*args, **kwargs)
        self._sync_scoring_copies()

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_scoring_copies", "_resume_rng", "_forward"]

    def distill(self, student_class: type, gradient_steps: int = 100_000, **kwargs: Any) -> Any:
        """
        Distil this model's whole replay buffer into a fresh policy, offline (the Offline Distillation Pipeline):
        ``model.distill(CRR, advantage_transform="exp", beta=1.0)``. See
        :func:`sb3_lifelong.common.distillation.distill` for the arguments.

        :param student_class: the offline algorithm (CRR; BC for behaviour cloning)
        :param gradient_steps: number of offline gradient updates
        :param kwargs: ``eval_env``, ``eval_freq``, ``progress_bar``, ... and the student's hyperparameters
            (``advantage_transform="exp"``, ``beta=1.0``, ...)
        :return: the trained student
        """
        return distill(self, student_class, gradient_steps, **kwargs)

    def _pending_rng_state(self) -> Optional[dict[str, Any]]:
        """The random state restored by the last ``load``, while no training happened since (else None)."""
        pending = self.__dict__.get("_resume_rng")
        if pending is None or (pending[1], pending[2]) != (self.num_timesteps, self._n_updates):
            return None
        return pending[0]

    def _restore_loaded_rng(self) -> None:
        """
        At the first training call after a load, restore the random streams saved with the model again: random numbers
        drawn between the load and now (e.g. by make_vec_env, or predict) do not change the run.
        """
        rng_state = self._pending_rng_state()
        self.__dict__.pop("_resume_rng", None)
        if rng_state is not None:
            restore_rng_state(rng_state, self.action_space)

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        self._restore_loaded_rng()
        self._sync_env_timestep(0 if reset_num_timesteps else self.num_timesteps)
        self._sample_on_model_device()
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

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

        :return: ``{"path", "transitions"}`` (the transitions the buffer has committed), or None
        """
        checkpoint = getattr(self.replay_buffer, "checkpoint", None)
        if callable(checkpoint):
            return checkpoint()
        if self.replay_buffer is None:  # loaded without its buffer: what the loaded checkpoint recorded, as it was
            return self.__dict__.get("_buffer_checkpoint")
        return None

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
        super().load_replay_buffer(path, truncate_last_traj)
        self._check_buffer_checkpoint()

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

        :param path: The file (``.zip`` added if missing) or a file object
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
        try:
            super().save(path, exclude=exclude, include=include)
        finally:
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
        directory (reopened from ``replay_buffer_kwargs``) that holds fewer transitions than the checkpoint recorded
        as committed gives a warning. The buffer is rebuilt from the saved ``replay_buffer_kwargs`` unless others are
        given; a saved ``mode="overwrite"`` reopens it as ``mode="new"`` (loading never deletes a buffer).

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
        :param kwargs: As for SB3 (e.g. ``replay_buffer_kwargs``)
        :return: The model
        """
        data = saved_data(path)
        _check_saved_algorithm(cls, path, data)
        if safe:
            if data is None:
                raise ValueError(f"{_describe(path)}: safe=True needs a zip whose 'data' can be read as JSON")
            custom_objects = safe_custom_objects(data, custom_objects or {}, _describe(path))
        # the saved replay_buffer_kwargs never overwrite a buffer; those given here are used as they are
        reopening = _LOADING_SAVED_BUFFER_KWARGS.set("replay_buffer_kwargs" not in kwargs)
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
        rng_state = model.__dict__.pop("_rng_state", None)
        if rng_state is not None:
            restore_rng_state(rng_state, model.action_space)
            model.__dict__["_resume_rng"] = (rng_state, model.num_timesteps, model._n_updates)  # restored again by learn()
        model._replay_env_rng()
        return model
