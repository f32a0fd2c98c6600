"""
:class:`DynamicsSchedule`: a Gymnasium wrapper that changes a MuJoCo robot's physics over its lifetime.

Two kinds of change, which can be combined:

* **stages** -- piecewise-constant settings that take effect at given *global* timesteps (``switch_at``);
* **schedules** -- one continuous :class:`Scheduler` per parameter (ramp, random walk, drift, cyclic, saw wave,
  uniform per episode) for changes without boundaries, e.g. a robot that wears gradually.

Global timesteps are SB3's ``model.num_timesteps``. This package's algorithms tell the wrapper the model's timestep
(and the VecEnv's ``n_envs``) at the start of every ``learn``, before the env is reset, through the method named
:data:`~sb3_lifelong.core.contract.SYNC_TIMESTEP_METHOD`; from there the wrapper counts ``n_envs`` per step, as
SB3 does, however many ``model.learn`` calls, resets or episodes there are. Outside such a ``learn`` (the env used
on its own, or by another library's algorithm) it counts ``timestep = start_timestep + n_envs * (steps taken by
this wrapper)`` from its constructor's arguments (or :meth:`DynamicsSchedule.set_timestep`).
The transition collected when ``model.num_timesteps == t`` uses the setting due at ``t``: stage ``i + 1`` is due
from ``t >= switch_at[i]``. By default a due change is applied at the next episode start; with
``mid_episode=True`` it is applied before the very next step.

The ``info`` keys written (``"stage"``, ``"dynamics_params"``) are defined in :mod:`sb3_lifelong.core.contract`,
which the replay buffer reads them by.
"""

import math
from typing import Any, Dict, List, Mapping, Optional, Sequence, SupportsFloat, Tuple, Union

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_lifelong.core.contract import DYNAMICS_PARAMS_KEY, STAGE_KEY, reset_options, stage_name
from sb3_lifelong.envs.perturbations import LIMB_PERTURBATIONS, PERTURBATIONS, PhysicsEditor, find_mujoco, stable_seed
from sb3_lifelong.envs.stages import NAMED_STAGES

StageLike = Union[str, Mapping[str, float]]


class Scheduler:
    """
    Base class of continuous parameter schedules.

    A scheduler gives the value of one parameter as a function of the global timestep (``per_episode=False``)
    or draws a new value at every episode start (``per_episode=True``). Random schedulers draw from their own
    seeded generator, so every copy of an env (every sub-env of a VecEnv) follows the same sequence.

    :param low: lower clipping bound; ``None`` means the parameter's physical lower limit
    :param high: upper clipping bound; ``None`` means the parameter's physical upper limit
    :param seed: seed of the random generator; ``None`` lets the wrapper derive one from its ``schedule_seed``
        and the parameter name
    """

    per_episode = False

    def __init__(self, low: Optional[float] = None, high: Optional[float] = None, seed: Optional[int] = None) -> None:
        self.low = low
        self.high = high
        self.seed = seed

    def bind(self, name: str, low: float, high: float, seed: int) -> None:
        """
        Complete missing bounds and seed and check the definition (called by the wrapper).

        :param name: parameter name, for messages
        :param low: physical lower limit of the parameter
        :param high: physical upper limit of the parameter
        :param seed: fallback seed
        """
        self.name = name
        self.lo: float = low if self.low is None else float(self.low)
        self.hi: float = high if self.high is None else float(self.high)
        self.low, self.high = self.lo, self.hi
        if not (low <= self.lo < self.hi <= high):
            raise ValueError(
                f"{type(self).__name__} for {name}: bounds [{self.low}, {self.high}] must satisfy "
                f"{low:.4g} <= low < high <= {high:.4g} (the parameter's physical range)"
            )
        if self.seed is None:
            self.seed = seed
        self._check()
        self.restart()

    def _check(self) -> None:
        """Validate the scheduler's own arguments (after :meth:`bind`)."""

    def _in_bounds(self, what: str, value: float) -> None:
        if not (self.lo <= value <= self.hi):
            raise ValueError(f"{type(self).__name__} for {self.name}: {what}={value} outside [{self.low}, {self.high}]")

    def restart(self) -> None:
        """Go back to the beginning of the schedule (fresh random generator)."""

    def clip(self, value: float) -> float:
        """
        Clip a value to the scheduler's bounds.

        :param value: value
        :return: clipped value
        """
        return float(min(max(value, self.lo), self.hi))

    def value(self, timestep: int) -> float:
        """
        Value at a global timestep.

        :param timestep: global timestep
        :return: parameter value
        """
        raise NotImplementedError

    def sample_episode(self, rng: np.random.Generator) -> float:
        """
        Value for a new episode (per-episode schedulers only).

        :param rng: the generator of the env copy that starts the episode
        :return: parameter value
        """
        raise NotImplementedError


class LinearRamp(Scheduler):
    """
    Linear change from ``start`` to ``end`` between global timesteps ``begin`` and ``finish``; constant outside.

    :param start: value up to ``begin``
    :param end: value from ``finish`` on
    :param begin: timestep at which the ramp starts
    :param finish: timestep at which the ramp ends
    """

    def __init__(self, start: float, end: float, begin: int, finish: int) -> None:
        super().__init__(min(start, end) if start != end else None, max(start, end) if start != end else None)
        self.start, self.end, self.begin, self.finish = float(start), float(end), int(begin), int(finish)

    def bind(self, name: str, low: float, high: float, seed: int) -> None:
        if self.start == self.end:
            self.low, self.high = low, high
        super().bind(name, low, high, seed)

    def _check(self) -> None:
        if not 0 <= self.begin < self.finish:
            raise ValueError(
                f"LinearRamp for {self.name}: need 0 <= begin < finish, got begin={self.begin}, finish={self.finish}"
            )
        self._in_bounds("start", self.start)  # a flat ramp's bounds are the parameter's range: its value must be in it

    def value(self, timestep: int) -> float:
        frac = min(max((timestep - self.begin) / (self.finish - self.begin), 0.0), 1.0)
        return self.start + frac * (self.end - self.start)


class _Incremental(Scheduler):
    """A value updated every ``period`` timesteps by a random increment, clipped to [low, high]."""

    def __init__(
        self,
        start: float,
        std: float,
        period: int = 1000,
        low: Optional[float] = None,
        high: Optional[float] = None,
        seed: Optional[int] = None,
    ) -> None:
        super().__init__(low, high, seed)
        self.start, self.std, self.period = float(start), float(std), int(period)

    def _check(self) -> None:
        if self.period < 1 or not self.std >= 0:
            raise ValueError(f"{type(self).__name__} for {self.name}: need period >= 1 and std >= 0")
        self._in_bounds("start", self.start)

    def restart(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._k = 0
        self._v = self.start

    def _next(self, v: float, delta: float) -> float:
        raise NotImplementedError

    def value(self, timestep: int) -> float:
        k = max(int(timestep), 0) // self.period
        if k < self._k:  # time went backwards (e.g. set_timestep): replay from the start
            self.restart()
        while self._k < k:
            self._v = self._next(self._v, float(self._rng.normal(0.0, self.std)))
            self._k += 1
        return self._v


class RandomWalk(_Incremental):
    """
    Gaussian random walk: every ``period`` timesteps ``v <- clip(v + N(0, std))``.

    :param start: initial value
    :param std: standard deviation of one increment
    :param period: timesteps between increments
    :param low: lower clipping bound (default: physical limit)
    :param high: upper clipping bound (default: physical limit)
    :param seed: generator seed (default: derived by the wrapper, same for all sub-envs)
    """

    def _next(self, v: float, delta: float) -> float:
        return self.clip(v + delta)


class Drift(_Incremental):
    """
    Monotone random drift: every ``period`` timesteps ``v <- clip(v + direction * |N(0, std)|)``; it stays at the
    bound once it reaches it.

    :param start: initial value
    :param std: standard deviation of one (absolute) increment
    :param direction: +1 drifts up, -1 drifts down
    :param period: timesteps between increments
    :param low: lower clipping bound (default: physical limit)
    :param high: upper clipping bound (default: physical limit)
    :param seed: generator seed
    """

    def __init__(
        self,
        start: float,
        std: float,
        direction: int = 1,
        period: int = 1000,
        low: Optional[float] = None,
        high: Optional[float] = None,
        seed: Optional[int] = None,
    ) -> None:
        super().__init__(start, std, period, low, high, seed)
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {direction}")
        self.direction = direction

    def _next(self, v: float, delta: float) -> float:
        return self.clip(v + self.direction * abs(delta))


class Cyclic(Drift):
    """
    Drift that starts over: like :class:`Drift`, but when the value reaches the bound it drifts towards
    (``high`` for ``direction=+1``, ``low`` for -1) it jumps back to ``start``. ``start`` must lie strictly
    inside the bounds, otherwise the cycle would be empty.

    :param start: initial value and value after each restart of the cycle
    :param std: standard deviation of one (absolute) increment
    :param direction: +1 cycles upwards, -1 downwards
    :param period: timesteps between increments
    :param low: lower bound
    :param high: upper bound
    :param seed: generator seed
    """

    def _check(self) -> None:
        super()._check()
        bound = self.hi if self.direction > 0 else self.lo
        if self.start == bound:
            raise ValueError(f"Cyclic for {self.name}: start must differ from the bound it drifts to ({bound})")

    def _next(self, v: float, delta: float) -> float:
        v = v + self.direction * abs(delta)
        if (self.direction > 0 and v >= self.hi) or (self.direction < 0 and v <= self.lo):
            return self.start
        return v


class SawWave(Scheduler):
    """
    Deterministic triangle wave between ``low`` and ``high``: from ``start`` it moves ``(high - low)`` every
    ``half_period`` timesteps, turning at the bounds.

    :param low: lower turning point
    :param high: upper turning point
    :param half_period: timesteps to go from one bound to the other
    :param start: value at timestep 0 (default ``low``); it first moves up
    """

    def __init__(self, low: float, high: float, half_period: int, start: Optional[float] = None) -> None:
        super().__init__(low, high)
        self.half_period = int(half_period)
        self.start = start
        self._start = 0.0

    def _check(self) -> None:
        if self.half_period < 1:
            raise ValueError(f"SawWave for {self.name}: half_period must be >= 1")
        self._start = self.lo if self.start is None else float(self.start)
        self._in_bounds("start", self._start)

    def value(self, timestep: int) -> float:
        span = self.hi - self.lo
        x = ((self._start - self.lo) / span + timestep / self.half_period) % 2.0
        return self.lo + span * (x if x <= 1.0 else 2.0 - x)


class UniformPerEpisode(Scheduler):
    """
    A new value drawn uniformly from ``[low, high]`` at every episode start.

    The draws come from the env copy's own generator, seeded from ``seed`` and, when ``reset(seed=...)`` is
    called, from that seed too (so SB3 sub-envs, seeded ``seed + i``, draw different values, and a seeded reset
    is reproducible).

    :param low: lower bound
    :param high: upper bound
    :param seed: generator seed
    """

    per_episode = True

    def __init__(self, low: float, high: float, seed: Optional[int] = None) -> None:
        super().__init__(low, high, seed)

    def sample_episode(self, rng: np.random.Generator) -> float:
        return float(rng.uniform(self.lo, self.hi))


class Constant(Scheduler):
    """
    A fixed value (handy to pin one parameter while stages change the others).

    :param value: the value
    """

    def __init__(self, value: float) -> None:
        super().__init__()
        self.constant = float(value)

    def _check(self) -> None:
        self._in_bounds("value", self.constant)

    def value(self, timestep: int) -> float:
        return self.constant


class DynamicsSchedule(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """
    Change the physics of a MuJoCo robot env over its lifetime, by global timestep.

    ``info`` of every ``reset`` and ``step`` carries ``info["stage"]`` (index of the stage in effect; stays the
    current stage under continuous schedules, 0 if there are no stages) and ``info["dynamics_params"]`` (the true
    value of every parameter of this robot, in its units; see :data:`sb3_lifelong.envs.PERTURBATIONS`).

    :param env: a MuJoCo env (Gymnasium's Walker2d/Hopper/HalfCheetah/Humanoid v5, ``sb3_lifelong/OP3Walk-v0``,
        ``sb3_lifelong/DMCWalker-v0`` or any env with a robot description)
    :param stages: list of settings ``{parameter: value}`` (missing parameters keep their nominal value) or names
        of named stages (see :data:`sb3_lifelong.envs.NAMED_STAGES`); default: one nominal stage
    :param switch_at: global timesteps at which stages 1, 2, ... take effect (``len(stages) - 1`` strictly
        increasing positive integers); ``None`` keeps stage 0 until :meth:`set_stage` is called
    :param schedules: continuous schedules ``{parameter: Scheduler}``; they override the stages' values of the same
        parameter
    :param n_envs: number of sub-envs of the VecEnv stepping this env, so that ``timestep`` equals SB3's
        ``num_timesteps``; 1 for a single env. Only needed outside this package's algorithms: their ``learn``
        sets it from the VecEnv (see :mod:`sb3_lifelong.core.contract`)
    :param mid_episode: apply due changes before the next step instead of at the next episode start
    :param append_params: append the observed parameters, normalised as ``(value - nominal) / obs_scale``, to the
        observation (and widen the observation space)
    :param observed_params: parameters appended by ``append_params``; default: those the stages or schedules vary
        (all whole-robot parameters, not the limb ones, if none vary)
    :param schedule_seed: seed from which the random schedulers without their own seed are seeded
    :param start_timestep: global timestep of the first step (to continue a schedule, e.g. after loading a model).
        Only needed outside this package's algorithms: their ``learn`` sets the model's ``num_timesteps``
    """

    def __init__(
        self,
        env: gym.Env,
        stages: Optional[Sequence[StageLike]] = None,
        switch_at: Optional[Sequence[int]] = None,
        schedules: Optional[Mapping[str, Scheduler]] = None,
        n_envs: int = 1,
        mid_episode: bool = False,
        append_params: bool = False,
        observed_params: Optional[Sequence[str]] = None,
        schedule_seed: int = 0,
        start_timestep: int = 0,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(
            self,
            stages=stages,
            switch_at=switch_at,
            schedules=schedules,
            n_envs=n_envs,
            mid_episode=mid_episode,
            append_params=append_params,
            observed_params=observed_params,
            schedule_seed=schedule_seed,
            start_timestep=start_timestep,
        )
        gym.Wrapper.__init__(self, env)
        self.editor = PhysicsEditor(find_mujoco(env))
        robot = self.editor.description.name
        if int(n_envs) < 1:
            raise ValueError(f"n_envs must be >= 1, got {n_envs}")
        self.n_envs = int(n_envs)
        self.mid_episode = bool(mid_episode)
        self._stages: List[Dict[str, float]] = [
            self._resolve_stage(s, f"stages[{i}]") for i, s in enumerate(stages if stages is not None else [{}])
        ]
        if len(self._stages) == 0:
            raise ValueError("stages must hold at least one setting (use [{}] for the nominal robot)")
        # no switch_at: stages are only switched by hand (set_stage)
        if switch_at is not None and len(switch_at) != len(self._stages) - 1:
            raise ValueError(
                f"switch_at needs one global timestep per stage after the first: {len(self._stages) - 1} values "
                f"for {len(self._stages)} stages, got {len(switch_at)} (or None to switch by hand with set_stage)"
            )
        switch_at = list(switch_at) if switch_at is not None else []
        previous = 0
        for i, t in enumerate(switch_at):
            if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t <= previous:
                raise ValueError(
                    f"switch_at must be strictly increasing positive integers (schedule out of order at index {i}: "
                    f"{t!r} after {previous}); got {switch_at}"
                )
            previous = int(t)
        self.switch_at: List[int] = [int(t) for t in switch_at]
        self.schedules: Dict[str, Scheduler] = dict(schedules or {})
        for name, scheduler in self.schedules.items():
            if name not in self.editor.supported:
                raise ValueError(
                    f"schedules: unknown dynamics parameter {name!r} for {robot}. Allowed: {self.editor.allowed_text()}"
                )
            if not isinstance(scheduler, Scheduler):
                raise TypeError(f"schedules[{name!r}] must be a Scheduler (LinearRamp, RandomWalk, ...), got {scheduler!r}")
            low, high = self.editor.valid_range(name)
            scheduler.bind(name, low, high, stable_seed(schedule_seed, name))
        self.schedule_seed = int(schedule_seed)
        self._episode_rng = np.random.default_rng(stable_seed(schedule_seed, "episode"))
        self._episode_values: Dict[str, float] = {
            name: sch.sample_episode(self._episode_rng) for name, sch in self.schedules.items() if sch.per_episode
        }

        varied = sorted({k for s in self._stages for k in s} | set(self.schedules))
        self.observed_params: List[str] = list(observed_params) if observed_params is not None else varied
        if not self.observed_params:  # the whole-robot ones (limb perturbations came later: the observation kept its size)
            self.observed_params = [name for name in self.editor.supported if name not in LIMB_PERTURBATIONS]
        self.editor.validate({k: self.editor.nominal_params.get(k, math.nan) for k in self.observed_params}, "observed_params")
        self.append_params = bool(append_params)
        if self.append_params:
            space = env.observation_space
            if not isinstance(space, spaces.Box) or len(space.shape) != 1:
                raise ValueError(f"append_params needs a flat Box observation space, got {space}")
            n = len(self.observed_params)
            self.observation_space = spaces.Box(
                low=np.concatenate([space.low, np.full(n, -np.inf)]).astype(space.dtype),
                high=np.concatenate([space.high, np.full(n, np.inf)]).astype(space.dtype),
                dtype=space.dtype,  # type: ignore[arg-type]
            )
            self._obs_nominal = np.array([self.editor.nominal_params[k] for k in self.observed_params])
            self._obs_scale = np.array([PERTURBATIONS[k].obs_scale for k in self.observed_params])

        self._local_steps = 0
        if isinstance(start_timestep, bool) or not isinstance(start_timestep, (int, np.integer)) or start_timestep < 0:
            raise ValueError(f"start_timestep must be a non-negative integer (a global timestep), got {start_timestep!r}")
        self._start = int(start_timestep)
        self._pinned: Optional[int] = None
        self._stage = -1  # stage applied to the physics; -1 until the first application
        self._applied: Dict[str, float] = {}
        self.episodes = 0
        self._apply(self._target(self.timestep), force=True)

    # ------------------------------------------------------------------ construction helpers
    def _resolve_stage(self, stage: StageLike, where: str) -> Dict[str, float]:
        if isinstance(stage, str):
            if stage not in NAMED_STAGES:
                raise ValueError(f"{where}: unknown named stage {stage!r}; the named stages are {sorted(NAMED_STAGES)}")
            stage = NAMED_STAGES[stage]
        if not isinstance(stage, Mapping):
            raise TypeError(f"{where} must be a dict of parameter values or a named stage, got {stage!r}")
        return self.editor.validate(stage, where)

    # ------------------------------------------------------------------ public state
    @property
    def timestep(self) -> int:
        """Global timestep of the next step (equals SB3's ``num_timesteps`` when ``n_envs`` is right)."""
        return self._start + self.n_envs * self._local_steps

    def set_timestep(self, timestep: int) -> None:
        """
        Make the next step count as global timestep ``timestep`` (e.g. ``model.num_timesteps`` after loading).

        :param timestep: global timestep
        """
        self._start = int(timestep) - self.n_envs * self._local_steps

    def sb3_lifelong_sync_timestep(self, timestep: int, n_envs: int) -> None:
        """
        Follow a model's timestep: the next step counts as ``timestep``, and every step as ``n_envs`` (called by
        this package's algorithms at the start of ``learn``; see :mod:`sb3_lifelong.core.contract`).

        :param timestep: the model's ``num_timesteps``
        :param n_envs: number of sub-envs of the VecEnv stepping this env
        """
        if int(n_envs) < 1:
            raise ValueError(f"n_envs must be >= 1, got {n_envs}")
        self.n_envs = int(n_envs)
        self.set_timestep(timestep)

    @property
    def stage(self) -> int:
        """Index of the stage whose setting the physics has now."""
        return self._stage

    @property
    def stages(self) -> List[Dict[str, float]]:
        """The stages (settings), including those added by :meth:`set_params`."""
        return [dict(s) for s in self._stages]

    @property
    def dynamics_params(self) -> Dict[str, float]:
        """True values of all parameters now in effect."""
        return dict(self._applied)

    @property
    def nominal_params(self) -> Dict[str, float]:
        """Values of the unchanged robot."""
        return dict(self.editor.nominal_params)

    @property
    def supported_params(self) -> Tuple[str, ...]:
        """Parameters this robot supports."""
        return self.editor.supported

    def stage_at(self, timestep: int) -> int:
        """
        Index of the stage due at a global timestep (ignores :meth:`set_stage`).

        :param timestep: global timestep
        :return: stage index
        """
        stage = 0
        for t in self.switch_at:
            if timestep >= t:
                stage += 1
        return stage

    # ------------------------------------------------------------------ manual control
    def set_stage(self, stage: int, immediate: bool = False) -> None:
        """
        Pin a stage by hand; timestep-based switches stop until :meth:`resume_schedule`.

        :param stage: stage index
        :param immediate: apply now, even mid-episode (otherwise at the next episode start, or the next step with
            ``mid_episode=True``)
        """
        if isinstance(stage, bool) or not isinstance(stage, (int, np.integer)) or not 0 <= stage < len(self._stages):
            raise ValueError(f"stage must be an index in [0, {len(self._stages) - 1}], got {stage!r}")
        self._pinned = int(stage)
        if immediate:
            self._apply(self._target(self.timestep), force=True)

    def set_params(self, params: Optional[Mapping[str, float]] = None, immediate: bool = False, **kwargs: float) -> int:
        """
        Pin a setting by hand. It becomes a stage (a new index, or the index of an equal existing stage).

        :param params: parameter values (missing ones nominal); may be a named stage
        :param immediate: apply now, even mid-episode
        :param kwargs: more parameter values
        :return: the stage index of this setting
        """
        setting = self._resolve_stage(params if params is not None else {}, "set_params")
        setting.update(self.editor.validate(kwargs, "set_params"))
        full = {**self.editor.nominal_params, **setting}
        for i, s in enumerate(self._stages):
            if {**self.editor.nominal_params, **s} == full:
                self.set_stage(i, immediate)
                return i
        self._stages.append(setting)
        self.set_stage(len(self._stages) - 1, immediate)
        return len(self._stages) - 1

    def resume_schedule(self) -> None:
        """Undo :meth:`set_stage` / :meth:`set_params`: stages follow ``switch_at`` again."""
        self._pinned = None

    # ------------------------------------------------------------------ core
    def _target(self, timestep: int) -> Tuple[int, Dict[str, float]]:
        stage = self._pinned if self._pinned is not None else self.stage_at(timestep)
        params = dict(self._stages[stage])
        for name, scheduler in self.schedules.items():
            params[name] = self._episode_values[name] if scheduler.per_episode else scheduler.value(timestep)
        return stage, params

    def _apply(self, target: Tuple[int, Dict[str, float]], force: bool = False) -> None:
        stage, params = target
        full = {**self.editor.nominal_params, **params}
        if force or full != self._applied:
            self._applied = self.editor.apply(params)
            if self.append_params:
                values = np.array([self._applied[k] for k in self.observed_params])
                self._obs_extra = ((values - self._obs_nominal) / self._obs_scale).astype(self.observation_space.dtype)
        self._stage = stage

    def _augment(self, obs: Any) -> Any:
        if not self.append_params:
            return obs
        return np.concatenate([obs, self._obs_extra]).astype(self.observation_space.dtype, copy=False)

    def _info(self, info: Dict[str, Any]) -> Dict[str, Any]:
        info[STAGE_KEY] = self._stage
        info[DYNAMICS_PARAMS_KEY] = dict(self._applied)
        return info

    def reset(self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None) -> Tuple[Any, Dict[str, Any]]:
        if seed is not None:
            self._episode_rng = np.random.default_rng([stable_seed(self.schedule_seed, "episode"), int(seed)])
        for name, scheduler in self.schedules.items():
            if scheduler.per_episode:
                self._episode_values[name] = scheduler.sample_episode(self._episode_rng)
        self._apply(self._target(self.timestep))
        self.episodes += 1
        obs, info = self.env.reset(seed=seed, **reset_options(options))
        return self._augment(obs), self._info(info)

    def step(self, action: Any) -> Tuple[Any, SupportsFloat, bool, bool, Dict[str, Any]]:
        if self.mid_episode:
            self._apply(self._target(self.timestep))
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._local_steps += 1
        return self._augment(obs), reward, terminated, truncated, self._info(info)


def stage_envs(
    env_id: str,
    stages: Sequence[StageLike],
    names: Optional[Sequence[str]] = None,
    env_kwargs: Optional[Mapping[str, Any]] = None,
    **schedule_kwargs: Any,
) -> Dict[str, DynamicsSchedule]:
    """
    The environments a lifelong run lives in, for evaluation: one copy of the robot per stage, each pinned to its
    stage (``set_stage(i, immediate=True)``) and named, ready for
    :class:`~sb3_lifelong.evaluation.callbacks.MultiEnvEvalCallback` or ``distill(..., eval_env=...)``.

    :param env_id: the robot's gym id (the training env's)
    :param stages: the training env's stages (settings or named stages)
    :param names: the name of each stage in the logs (default ``Env-A``, ``Env-B``, ...: the names the
        ``LifelongReplayBuffer`` gives the stages' data)
    :param env_kwargs: keyword arguments of ``gym.make``
    :param schedule_kwargs: the training env's other :class:`DynamicsSchedule` arguments that shape the observation
        (``append_params``, ``observed_params``); ``switch_at`` and ``schedules`` are refused: a copy stays in its stage
    :return: name -> pinned env, in the order of the stages (each a :class:`DynamicsSchedule` around SB3's
        ``Monitor``, so that ``evaluate_policy`` uses whole episodes and does not warn)
    """
    moving = sorted({"switch_at", "schedules"} & set(schedule_kwargs))
    if moving:
        raise ValueError(f"stage_envs: {moving} would move the copies out of their stage; give only the stages")
    names = list(names) if names is not None else [stage_name(i) for i in range(len(stages))]
    if len(names) != len(stages) or len(set(names)) != len(names):
        raise ValueError(f"stage_envs needs one distinct name per stage: {len(stages)} stages, names {names}")
    # SB3's Monitor inside (it records the robot's own episode returns): evaluate_policy(model, env) counts whole
    # episodes and does not warn that the env is not monitored, and the copy is still the DynamicsSchedule
    from stable_baselines3.common.monitor import Monitor

    envs: Dict[str, DynamicsSchedule] = {}
    for index, name in enumerate(names):
        env = DynamicsSchedule(Monitor(gym.make(env_id, **dict(env_kwargs or {}))), stages=stages, **schedule_kwargs)
        env.set_stage(index, immediate=True)
        envs[name] = env
    return envs
