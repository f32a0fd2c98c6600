"""Base class of this package's off-policy algorithms: SB3's ``OffPolicyAlgorithm`` plus exact resumption."""

import inspect
import io
import pathlib
import random
import warnings
from collections.abc import Iterable
from typing import Any, Optional, TypeVar, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv

from sb3_lifelong.common.utils import LowPrecisionCopy, resolve_scoring_dtype

SelfLifelongAlgorithm = TypeVar("SelfLifelongAlgorithm", bound="LifelongOffPolicyAlgorithm")


def capture_rng_state(action_space: Optional[spaces.Space] = None) -> dict[str, Any]:
    """
    Snapshot of every random stream training draws from, in a JSON-serialisable form: torch's global generator,
    numpy's legacy global generator, Python's ``random``, and the action space's generator (warm-up actions).

    :param action_space: the algorithm's action space
    :return: the state, to be passed to :func:`restore_rng_state`
    """
    np_state: tuple[Any, ...] = np.random.get_state()  # type: ignore[assignment]
    py_version, py_internal, py_gauss = random.getstate()
    state: dict[str, Any] = {
        "torch": th.get_rng_state().tolist(),
        "numpy": [np_state[0], np_state[1].tolist(), int(np_state[2]), int(np_state[3]), float(np_state[4])],
        "python": [py_version, list(py_internal), py_gauss],
    }
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
    if action_space is not None and "action_space" in state:
        action_space.np_random.bit_generator.state = state["action_space"]


class LifelongOffPolicyAlgorithm(OffPolicyAlgorithm):
    """
    SB3's ``OffPolicyAlgorithm`` whose ``save``/``load`` also carry the random streams, so that
    ``load`` + ``load_replay_buffer`` + ``learn(..., reset_num_timesteps=False)`` continues exactly as an
    uninterrupted run would (given an environment that is in the same state, e.g. at an episode boundary).

    SB3 itself re-seeds every generator from ``seed`` when a model is loaded, which replays the random numbers
    of the start of training instead of continuing them.
    """

    def _setup_model(self) -> None:
        # A buffer class that computes n-step returns itself (e.g. LifelongReplayBuffer) gets the algorithm's
        # n_steps and gamma, instead of SB3's warning that n_steps is ignored for custom buffer classes.
        forwarded = False
        if self.n_steps > 1 and self.replay_buffer_class is not None and self.replay_buffer is None:
            parameters = inspect.signature(self.replay_buffer_class.__init__).parameters
            if "n_steps" in parameters and "n_steps" not in self.replay_buffer_kwargs:
                self.replay_buffer_kwargs.update({"n_steps": self.n_steps, "gamma": self.gamma})
                forwarded = True
        with warnings.catch_warnings():
            if forwarded:
                warnings.filterwarnings("ignore", message=r"`n_steps=\d+` is ignored because a custom")
            super()._setup_model()

    def _make_scoring_copy(self, critic: th.nn.Module, scoring_dtype: str) -> Optional[LowPrecisionCopy]:
        """
        A low-precision copy of ``critic`` for the no-grad scoring passes, when ``scoring_dtype`` asks for one
        (see :func:`sb3_lifelong.common.utils.resolve_scoring_dtype`); it is synchronised by
        :meth:`_sync_scoring_copies` after loads and by the algorithm after its updates.

        :return: the copy, or None to score in the critic's own precision
        """
        dtype = resolve_scoring_dtype(scoring_dtype, critic, self.device)
        if dtype == th.float32:
            return None
        copy = LowPrecisionCopy(critic, dtype)  # type: ignore[arg-type]
        self.__dict__.setdefault("_scoring_copies", []).append(copy)
        return copy

    def _sync_scoring_copies(self) -> None:
        for copy in self.__dict__.get("_scoring_copies", []):
            copy.sync()

    def set_parameters(self, *args: Any, **kwargs: Any) -> None:
        super().set_parameters(*args, **kwargs)
        self._sync_scoring_copies()

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_scoring_copies"]

    def distill(self, student_class: Optional[type] = None, gradient_steps: int = 100_000, **kwargs: Any) -> Any:
        """
        Distil this model's whole replay buffer into a fresh policy, offline (the Offline Distillation Pipeline).
        See :func:`sb3_lifelong.common.distill.distill` for the arguments.

        :param student_class: the offline algorithm (default CRR; BC for behaviour cloning)
        :param gradient_steps: number of offline gradient updates
        :param kwargs: ``eval_env``, ``eval_freq``, ``progress_bar``, ... and the student's hyperparameters
            (``advantage_transform="exp"``, ``beta=1.0``, ...)
        :return: the trained student
        """
        from sb3_lifelong.common.distill import distill

        return distill(self, student_class=student_class, gradient_steps=gradient_steps, **kwargs)

    def save(
        self,
        path: Union[str, pathlib.Path, io.BufferedIOBase],
        exclude: Optional[Iterable[str]] = None,
        include: Optional[Iterable[str]] = None,
    ) -> None:
        self._rng_state = capture_rng_state(self.action_space)
        try:
            super().save(path, exclude=exclude, include=include)
        finally:
            del self._rng_state

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfLifelongAlgorithm],
        path: Union[str, pathlib.Path, io.BufferedIOBase],
        env: Optional[GymEnv] = None,
        device: Union[th.device, str] = "auto",
        custom_objects: Optional[dict[str, Any]] = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs,
    ) -> SelfLifelongAlgorithm:
        model = super().load(
            path,
            env=env,
            device=device,
            custom_objects=custom_objects,
            print_system_info=print_system_info,
            force_reset=force_reset,
            **kwargs,
        )
        rng_state = model.__dict__.pop("_rng_state", None)
        if rng_state is not None:
            restore_rng_state(rng_state, model.action_space)
        return model
