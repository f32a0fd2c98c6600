"""
Forgetting and transfer in the continual-learning field's terms (Continual World, CORA, GEM), from the evaluations of
every environment that :class:`~sb3_lifelong.evaluation.callbacks.MultiEnvEvalCallback` makes.

The record is the matrix ``R[i][j]``: the return in environment ``j`` at the end of stage ``i`` (stage ``i`` trains in
environment ``i``). Returns have no common scale across robots, so every entry is normalised per environment as

    s[i][j] = (R[i][j] - b[j]) / (r[j] - b[j])

with ``b[j]`` a uniformly random policy's return in environment ``j`` and ``r[j]`` a reference return there (given, or
by default the best end-of-stage return seen in ``j``): 0 is random, 1 the reference. From ``s``, after the last stage
``N - 1`` that has ended:

- **average performance** ``A = mean_j s[N-1][j]`` over every environment (Continual World's "average performance");
- **forgetting** of environment ``j < N - 1``: ``F_j = s[j][j] - s[N-1][j]`` (its score at the end of its own stage
  minus at the end; Continual World's and CORA's forgetting), and ``F`` their mean;
- **backward transfer** ``BWT = mean_{j < N-1} (s[N-1][j] - s[j][j]) = -F`` (GEM, Lopez-Paz and Ranzato 2017);
- **forward transfer** ``FWT = mean_{j >= 1} s[j-1][j]``: the score in environment ``j`` before training in it, above
  a random policy's (GEM's forward transfer with the random policy as the baseline; Continual World's compares
  learning curves with a single-task reference instead, which needs separate runs).
"""

import json
import math
import os
import pathlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Optional, Union

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from sb3_lifelong.core.atomic import write_text_atomic

#: how the scores are normalised, written beside the metrics
NORMALISATION = "s[i][j] = (R[i][j] - random[j]) / (reference[j] - random[j]); 0: a uniformly random policy, 1: the reference"


def continual_metrics(
    returns: Sequence[Sequence[float]], random: Sequence[float], reference: Optional[Sequence[float]] = None
) -> dict[str, Any]:
    """
    The field's metrics of a return matrix (see the module's docstring).

    :param returns: ``R[i][j]``, one row per ended stage (at least one), one column per environment; stage ``i``
        trained in environment ``i``. An environment not evaluated before its stage (``j > i``) may be NaN: forward
        transfer is then NaN
    :param random: a uniformly random policy's return in each environment
    :param reference: the reference return of each environment (None: the largest ``R[i][j]`` over the rows)
    :return: ``scores`` (the normalised matrix), ``average_performance``, ``forgetting`` (per environment that a later
        stage followed, and ``forgetting_mean``), ``backward_transfer``, ``forward_transfer`` (NaN where not defined
        yet: forgetting and backward transfer need two stages, forward transfer a row before an environment's stage)
    """
    matrix = np.asarray(returns, dtype=np.float64)
    if matrix.ndim != 2 or matrix.shape[0] < 1:
        raise ValueError(f"returns must be a matrix with one row per ended stage, got shape {matrix.shape}")
    stages, envs = matrix.shape
    if stages > envs:
        raise ValueError(f"{stages} stages but {envs} environments: stage i trains in environment i")
    seen = np.tril(np.ones_like(matrix, dtype=bool))  # environment j at the end of stage i >= j: measured
    if not np.all(np.isfinite(matrix[seen])):
        raise ValueError(
            f"returns must be finite in every environment at the end of its own stage and later, got {matrix.tolist()}"
        )
    low = np.asarray(random, dtype=np.float64)
    high = np.nanmax(matrix, axis=0) if reference is None else np.asarray(reference, dtype=np.float64)
    if low.shape != (envs,) or high.shape != (envs,):
        raise ValueError(f"random and reference need one value per environment ({envs}), got {low.shape} and {high.shape}")
    if not np.all(high > low):
        bad = [j for j in range(envs) if not high[j] > low[j]]
        raise ValueError(
            f"the reference must exceed the random policy's return in every environment; it does not in {bad} "
            f"(reference {high.tolist()}, random {low.tolist()}): nothing was learnt there to normalise by"
        )
    scores = (matrix - low) / (high - low)
    last = stages - 1
    forgetting = {j: float(scores[j, j] - scores[last, j]) for j in range(last)}
    forward = [float(scores[j - 1, j]) for j in range(1, min(stages + 1, envs))]  # the rows before each stage
    return dict(
        scores=scores.tolist(),
        average_performance=float(scores[last].mean()),
        forgetting=forgetting,
        forgetting_mean=float(np.mean(list(forgetting.values()))) if forgetting else math.nan,
        backward_transfer=-float(np.mean(list(forgetting.values()))) if forgetting else math.nan,
        forward_transfer=float(np.mean(forward)) if forward else math.nan,
    )


def _returning(env: gym.Env) -> Callable[[], gym.Env]:
    """:return: a factory of ``env`` itself, for a VecEnv around an existing environment"""
    return lambda: env


def random_policy_returns(
    envs: Mapping[str, Union[gym.Env, VecEnv]],
    episodes: int,
    env_seeds: Optional[Sequence[int]] = None,
    action_seeds: Optional[Sequence[int]] = None,
) -> dict[str, float]:
    """
    A uniformly random policy's mean return in each environment: the zero of the scores of :func:`continual_metrics`.
    With seeds, the measurement is the same every time.

    :param envs: environment name -> environment (a gymnasium env or a VecEnv, whose sub-environments all play)
    :param episodes: episodes per environment, the first ones to end
    :param env_seeds: the seed each environment gets before its first reset, in the order of ``envs`` (None: unseeded)
    :param action_seeds: the seed of each environment's action space, which draws the actions (None: unseeded)
    :return: environment name -> mean return over ``episodes`` episodes
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    for what, seeds in (("env_seeds", env_seeds), ("action_seeds", action_seeds)):
        if seeds is not None and len(seeds) != len(envs):
            raise ValueError(f"{what} has {len(seeds)} seeds for {len(envs)} environments ({list(envs)})")
    out = {}
    for index, (name, env) in enumerate(envs.items()):
        vec_env = env if isinstance(env, VecEnv) else DummyVecEnv([_returning(env)])
        if env_seeds is not None:
            vec_env.seed(int(env_seeds[index]))
        space = vec_env.action_space
        if action_seeds is not None:
            space.seed(int(action_seeds[index]))
        returns: list[float] = []
        vec_env.reset()
        total = np.zeros(vec_env.num_envs)
        while len(returns) < episodes:
            actions = np.stack([space.sample() for _ in range(vec_env.num_envs)])
            _, rewards, dones, _ = vec_env.step(actions)
            total += rewards
            for k in np.flatnonzero(dones):
                returns.append(float(total[k]))
                total[k] = 0.0
        out[name] = float(np.mean(returns[:episodes]))
    return out


class ContinualMetricsCallback(BaseCallback):
    """
    Keeps ``R[i][j]`` (the return in environment ``j`` at the end of stage ``i``) from a
    :class:`~sb3_lifelong.evaluation.callbacks.MultiEnvEvalCallback` and logs the field's forgetting and transfer
    metrics after each of its evaluations: pass it as that callback's ``callback_after_eval``.

    The evaluated environments are the stages' environments, in stage order (``stage_envs`` gives them). An evaluation
    at timestep ``t`` belongs to the first stage whose end is at or after ``t`` (the last stage after every end): the
    row of a stage is its last evaluation, so choose ``eval_freq`` to divide the stage ends and the row is the agent
    at the end of the stage. A stage's row is provisional while the stage runs.

    Logged (tensorboard, CSV, stdout, as the model's logger is set up): ``continual/average_performance``,
    ``continual/forgetting`` and ``continual/forgetting/<env>``, ``continual/backward_transfer``,
    ``continual/forward_transfer``, and the raw ``continual/R/after_<env i>/<env j>`` (``R[i][j]``, e.g.
    ``continual/R/after_Env-B/Env-A``: Env-A's return at the end of the stage in Env-B). With ``log_path``, the matrix, the
    scores, the metrics and the normalisation are written there as JSON after every evaluation.

    :param stage_ends: the timestep at which each stage ends, one per environment but the last may be omitted (the last
        stage runs to the end of training)
    :param random_returns: a uniformly random policy's return per environment name (None: measured when training
        starts, on ``random_episodes`` episodes of each evaluation environment, seeded like the evaluations)
    :param reference_returns: the reference return per environment name (None: the best end-of-stage return seen)
    :param random_episodes: episodes per environment for the random policy's return
    :param log_path: JSON file for the record, or None
    :param verbose: 1 prints the metrics after each evaluation
    """

    def __init__(
        self,
        stage_ends: Sequence[int],
        random_returns: Optional[Mapping[str, float]] = None,
        reference_returns: Optional[Mapping[str, float]] = None,
        random_episodes: int = 10,
        log_path: Optional[Union[str, os.PathLike]] = None,
        verbose: int = 0,
    ):
        super().__init__(verbose)
        ends = [int(end) for end in stage_ends]
        if (
            any(isinstance(end, bool) for end in stage_ends)
            or any(b <= a for a, b in zip(ends, ends[1:]))
            or (ends and ends[0] <= 0)
        ):
            raise ValueError(f"stage_ends must be strictly increasing positive timesteps, got {list(stage_ends)}")
        if random_episodes < 1:
            raise ValueError(f"random_episodes must be >= 1, got {random_episodes}")
        self.stage_ends = ends
        self.random_returns = dict(random_returns) if random_returns is not None else None
        self.reference_returns = dict(reference_returns) if reference_returns is not None else None
        self.random_episodes = random_episodes
        self.log_path = pathlib.Path(log_path) if log_path is not None else None
        self.rows: dict[int, dict[str, float]] = {}
        self.row_timesteps: dict[int, int] = {}
        self.metrics: dict[str, Any] = {}

    def _env_names(self) -> list[str]:
        names = list(getattr(self.parent, "eval_envs", {}))
        if not names:
            raise TypeError("ContinualMetricsCallback must be the callback_after_eval of a MultiEnvEvalCallback")
        if len(self.stage_ends) not in (len(names), len(names) - 1):
            raise ValueError(
                f"{len(self.stage_ends)} stage ends for {len(names)} evaluated environments ({names}): give one end per "
                "stage, in the order of the environments (the last may be omitted)"
            )
        for what, given in (("random_returns", self.random_returns), ("reference_returns", self.reference_returns)):
            if given is not None and set(given) != set(names):
                raise ValueError(f"{what} names {sorted(given)}, the evaluated environments are {names}")
        return names

    def _init_callback(self) -> None:
        self._env_names()

    def measure_random(self) -> dict[str, float]:
        """
        :return: a uniformly random policy's mean return in each evaluation environment (:func:`random_policy_returns`),
            seeded like the evaluations when the parent has a seed
        """
        parent: Any = self.parent
        count = len(parent.eval_envs)
        seeded = parent.seed is not None
        return random_policy_returns(
            parent.eval_envs,
            self.random_episodes,
            env_seeds=[parent.episode_seed(index) for index in range(count)] if seeded else None,
            action_seeds=[parent.seed + index for index in range(count)] if seeded else [0] * count,
        )

    def stage_of(self, timesteps: int) -> int:
        """:return: the stage an evaluation at ``timesteps`` belongs to"""
        for stage, end in enumerate(self.stage_ends):
            if timesteps <= end:
                return stage
        return len(self.stage_ends)

    def _on_step(self) -> bool:
        names = self._env_names()
        parent: Any = self.parent
        if self.random_returns is None:
            self.random_returns = self.measure_random()
        stage = min(self.stage_of(parent.num_timesteps), len(names) - 1)
        latest = {row["env"]: float(row["mean_reward"]) for row in parent.results if row["timesteps"] == parent.num_timesteps}
        self.rows[stage] = {name: latest[name] for name in names}
        self.row_timesteps[stage] = int(parent.num_timesteps)
        if sorted(self.rows) != list(range(len(self.rows))):  # training started inside a later stage: no matrix
            return True
        matrix = [[self.rows[i][name] for name in names] for i in range(len(self.rows))]
        reference = None if self.reference_returns is None else [self.reference_returns[n] for n in names]
        try:
            self.metrics = continual_metrics(matrix, [self.random_returns[n] for n in names], reference)
        except ValueError as error:  # nothing learnt yet above a random policy somewhere: nothing to normalise by
            self.metrics = dict(error=str(error))
            self._write(names, matrix, reference)
            return True
        self.logger.record("continual/average_performance", self.metrics["average_performance"])
        for j, value in self.metrics["forgetting"].items():
            self.logger.record(f"continual/forgetting/{names[j]}", value)
        for key in ("forgetting_mean", "backward_transfer", "forward_transfer"):
            if not math.isnan(self.metrics[key]):
                self.logger.record(f"continual/{key.replace('_mean', '')}", self.metrics[key])
        for i, row in enumerate(matrix):  # row i: the end of the stage in environment i, named as that environment
            for name, value in zip(names, row):
                self.logger.record(f"continual/R/after_{names[i]}/{name}", value)
        self.logger.dump(parent.num_timesteps)  # the evaluation dumped its own values before this callback ran
        if self.verbose >= 1:
            shown = {k: self.metrics[k] for k in ("average_performance", "forgetting_mean", "forward_transfer")}
            print(f"Continual metrics at {parent.num_timesteps}: {shown}")
        self._write(names, matrix, reference)
        return True

    def _write(self, names: list[str], matrix: list[list[float]], reference: Optional[list[float]]) -> None:
        """The record as JSON at ``log_path`` (replaced atomically), when there is one."""
        assert self.random_returns is not None
        if self.log_path is not None:
            record = dict(
                envs=names, stage_ends=self.stage_ends, row_timesteps=[self.row_timesteps[i] for i in range(len(matrix))],
                returns=matrix, random=[self.random_returns[n] for n in names],
                reference=reference if reference is not None else "the best end-of-stage return per environment",
                normalisation=NORMALISATION, **{k: v for k, v in self.metrics.items()},
            )  # fmt: skip
            if "forgetting" in self.metrics:
                record["forgetting"] = {names[j]: v for j, v in self.metrics["forgetting"].items()}
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            write_text_atomic(self.log_path, json.dumps(record, indent=1, allow_nan=True))
