"""
Exact resumption: the random streams of training and of the environments' resets, captured at ``save`` and restored by
``load``, so that a loaded model continues as an uninterrupted run would (:class:`ExactResume`, a part of
:class:`~sb3_lifelong.common.base.LifelongOffPolicyAlgorithm`).
"""

import random
import warnings
from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import GymEnv

from sb3_lifelong.core.contract import reset_options


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
        return self.env.reset(seed=seed, **reset_options(options))

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


class ExactResume:
    """
    The part of the algorithms that replays the random streams after a ``load`` (mixed into
    :class:`~sb3_lifelong.common.base.LifelongOffPolicyAlgorithm` before SB3's ``OffPolicyAlgorithm``).
    """

    env: Any
    seed: Optional[int]
    action_space: spaces.Space
    num_timesteps: int
    _n_updates: int
    _last_obs: Any
    _last_episode_starts: Any
    _env_rng: Any  # the records of a load, until the env replays them

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
                else "the env is a VecEnv whose sub-envs are not wrapped in sb3_lifelong.common.resume.EpisodeRngRecorder"
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
        super().set_env(env, force_reset=force_reset)  # type: ignore[misc]
        self._replay_env_rng()

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
