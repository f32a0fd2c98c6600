"""Callbacks for lifelong learning: evaluate the current policy on every environment the robot has seen."""

import csv
import inspect
import os
import pathlib
from collections.abc import Mapping, Sequence
from copy import deepcopy
from typing import Any, Optional, Union

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecNormalize, unwrap_vec_normalize

from sb3_lifelong.core.atomic import atomic_write
from sb3_lifelong.evaluation.overestimation import MonteCarloProbe

CSV_FIELDS = ["timesteps", "env", "mean_reward", "std_reward", "n_episodes"]
#: the columns of :class:`SourceQCallback`'s CSV: ``q_mean`` over ``n`` uniform samples; with ``monte_carlo``, on the
#: fixed sample of ``n_mc`` transitions with a Monte-Carlo return, the mean Q-value ``q_probe``, the mean return
#: ``mc_return`` and ``overestimation = q_probe - mc_return`` (empty for a source with no such transition yet)
Q_CSV_FIELDS = ["timesteps", "source", "name", "q_mean", "n", "q_probe", "mc_return", "overestimation", "n_mc"]

#: the experiments seed the evaluation environments of a run with seed ``s`` from ``EVAL_SEED_OFFSET + s`` (apart
#: from the training environment's ``s``), so that a run's evaluations are reproducible. With ``same_episodes`` the
#: k-th environment gets ``EVAL_SEED_OFFSET + s + k``, so environment k + 1 of seed ``s`` starts its episodes from the
#: same draws as environment k of seed ``s + 1`` (another robot, another policy; the protocol's seeds keep it so that
#: their committed evaluations stay reproducible)
EVAL_SEED_OFFSET = 10_000


EvalEnvs = Union[GymEnv, str, Sequence[Union[GymEnv, str]], Mapping[str, Union[GymEnv, str]]]


def _csv_header(path: pathlib.Path) -> list[str]:
    """:return: the first row of the CSV file at ``path`` (empty when there is none)"""
    if not path.is_file():
        return []
    with open(path, newline="") as handle:
        return next(csv.reader(handle), [])


def _env_name(env: Any, index: int) -> str:
    if isinstance(env, str):
        return env
    spec = getattr(env, "spec", None)
    if spec is None and isinstance(env, VecEnv):
        try:
            spec = env.get_attr("spec", indices=[0])[0]
        except Exception:
            spec = None
    return spec.id if spec is not None and getattr(spec, "id", None) else f"env{index}"


def make_eval_envs(eval_env: EvalEnvs) -> dict[str, VecEnv]:
    """
    Normalise one or several evaluation environments to named ``VecEnv`` objects (gym ids are made, gym envs
    are wrapped in ``Monitor`` and ``DummyVecEnv``).

    :param eval_env: an env, a gym id, a list of them (named after their gym id) or a dict name -> env
    :return: dict name -> VecEnv
    """
    if isinstance(eval_env, dict):
        named = list(eval_env.items())
    elif isinstance(eval_env, (list, tuple)):
        named = [(_env_name(env, index), env) for index, env in enumerate(eval_env)]
    else:
        named = [(_env_name(eval_env, 0), eval_env)]
    result: dict[str, VecEnv] = {}
    for name, env in named:
        unique, suffix = name, 1
        while unique in result:
            unique, suffix = f"{name}_{suffix}", suffix + 1
        if isinstance(env, str):
            env = gym.make(env)
        if not isinstance(env, VecEnv):
            env = DummyVecEnv([lambda env=env: env if is_wrapped(env, Monitor) else Monitor(env)])  # type: ignore[misc]
        result[unique] = env
    return result


class MultiEnvEvalCallback(BaseCallback):
    """
    Every ``eval_freq`` timesteps, evaluate the model's policy on each of several environments (Env-A, Env-B, ...)
    and log ``eval/<name>/mean_reward`` and ``eval/<name>/std_reward`` (plus ``eval/mean_over_envs``) to the
    model's logger (tensorboard, CSV, stdout), and append one row per environment to a CSV file.

    Works the same during online learning (timesteps = environment steps) and offline training, where the
    algorithms of this package count gradient updates as timesteps.

    As SB3's ``EvalCallback``: ``best_model_save_path``, ``evaluations.npz`` (``evaluations_dir``),
    ``callback_on_new_best`` and ``callback_after_eval`` (e.g. ``StopTrainingOnRewardThreshold``,
    ``StopTrainingOnNoModelImprovement``), where the score of an evaluation is ``eval/mean_over_envs``, the mean
    of the environments' mean returns (``best_mean_reward`` and ``last_mean_reward`` hold it). When the model
    trains on a ``VecNormalize`` environment, each evaluation environment is wrapped in a ``VecNormalize`` that is
    not updated (``training=False``, raw rewards) and receives the training statistics before every evaluation.

    :param eval_envs: the environments: a mapping name -> env or gym id (names appear in the logs), a sequence
        of envs or gym ids (named after their gym id), or one env (see :func:`make_eval_envs`)
    :param eval_freq: evaluate every ``eval_freq`` timesteps (counted with ``model.num_timesteps``, so that the
        number of parallel environments does not change the schedule)
    :param n_eval_episodes: episodes per environment and evaluation
    :param deterministic: evaluate the deterministic policy (the Gaussian's mean)
    :param log_path: CSV file to append the results to (columns: timesteps, env, mean_reward, std_reward,
        n_episodes), or None
    :param eval_at_start: also evaluate before the first step
    :param sources: for models with one actor per source (CRR's ``actor_per_source=True`` diagnostic): the source
        id whose actor acts in each environment, by environment name (``{"Env-A": 0, "Env-B": 1}``); the model's
        ``select_source`` is called before each of these environments and the model's own selection is restored after
    :param seed: seed of the evaluation environments (a non-negative int; None: not seeded): before every
        evaluation each environment is seeded from ``seed``, its position and the timestep, so that an evaluation's
        episodes depend on neither the process's history nor the evaluations before it: a run's evaluations are
        reproducible, and a run resumed exactly in a new process (new environments) evaluates as an uninterrupted one
        (with ``deterministic=True``: a stochastic policy's draws come from torch's generator, which is not seeded
        here)
    :param same_episodes: with ``seed``, every evaluation plays the same episodes (the k-th environment is seeded with
        ``seed + k`` before each): differences between evaluations are then the policy's alone. Without it each
        evaluation plays new episodes (the mean over several evaluations then covers more starts)
    :param verbose: 1 prints one line per evaluation (every environment's mean reward and the mean over them)
    :param best_model_save_path: folder where the model is saved as ``best_model.zip`` whenever
        ``eval/mean_over_envs`` beats every earlier evaluation of this callback (None: not saved)
    :param evaluations_dir: folder where ``evaluations.npz`` is rewritten after every evaluation (SB3's
        ``EvalCallback(log_path=...)``): ``timesteps`` ``[n_evals]``, ``env_names`` ``[n_envs]``, ``results`` and
        ``ep_lengths`` ``[n_evals, n_envs, n_eval_episodes]`` (None: not written)
    :param callback_on_new_best: callback called after an evaluation that set a new best score; it may stop
        training by returning False (its ``parent`` is this callback)
    :param callback_after_eval: callback called after every evaluation; it may stop training by returning False
        (its ``parent`` is this callback)
    """

    def __init__(
        self,
        eval_envs: EvalEnvs,
        eval_freq: int = 10_000,
        n_eval_episodes: int = 5,
        deterministic: bool = True,
        log_path: Optional[Union[str, os.PathLike]] = None,
        eval_at_start: bool = False,
        sources: Optional[Mapping[str, int]] = None,
        seed: Optional[int] = None,
        same_episodes: bool = False,
        verbose: int = 0,
        best_model_save_path: Optional[Union[str, os.PathLike]] = None,
        evaluations_dir: Optional[Union[str, os.PathLike]] = None,
        callback_on_new_best: Optional[BaseCallback] = None,
        callback_after_eval: Optional[BaseCallback] = None,
    ):
        super().__init__(verbose)
        if isinstance(eval_envs, (Mapping, list, tuple)) and len(eval_envs) == 0:
            raise ValueError("MultiEnvEvalCallback needs at least one evaluation environment")
        if eval_freq < 1 or n_eval_episodes < 1:
            raise ValueError(f"eval_freq and n_eval_episodes must be >= 1, got {eval_freq} and {n_eval_episodes}")
        if isinstance(eval_envs, Mapping):
            bad = [name for name in eval_envs if not name or "/" in name]
            if bad:
                raise ValueError(f"Evaluation environment names must be non-empty and contain no '/': {bad}")
        self.eval_envs = make_eval_envs(eval_envs)
        self.eval_freq = eval_freq
        self.n_eval_episodes = n_eval_episodes
        self.deterministic = deterministic
        self.log_path = pathlib.Path(log_path) if log_path is not None else None
        self.eval_at_start = eval_at_start
        self.sources = dict(sources) if sources is not None else None
        if self.sources is not None:
            unknown = sorted(set(self.sources) - set(self.eval_envs))
            if unknown:
                raise ValueError(f"sources names environments {unknown} that are not evaluated ({list(self.eval_envs)})")
        self.results: list[dict[str, Any]] = []
        self._next_eval = 0
        if same_episodes and seed is None:
            raise ValueError("same_episodes=True needs a seed: the evaluation environments are seeded before every evaluation")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
            raise ValueError(f"seed must be a non-negative int or None, got {seed!r}")
        self.seed = int(seed) if seed is not None else None  # a Python int: gymnasium refuses numpy integers
        self.same_episodes = same_episodes
        self.best_model_save_path = pathlib.Path(best_model_save_path) if best_model_save_path is not None else None
        self.evaluations_dir = pathlib.Path(evaluations_dir) if evaluations_dir is not None else None
        self.callback_on_new_best = callback_on_new_best
        self.callback_after_eval = callback_after_eval
        for child in (callback_on_new_best, callback_after_eval):
            if child is not None:
                child.parent = self
        #: ``eval/mean_over_envs`` of the best and of the last evaluation (-inf before the first), as SB3's EvalCallback
        self.best_mean_reward = -np.inf
        self.last_mean_reward = -np.inf
        self.evaluations_timesteps: list[int] = []
        self.evaluations_results: list[list[list[float]]] = []
        self.evaluations_length: list[list[list[int]]] = []
        self._normalized_envs: dict[str, VecNormalize] = {}
        self._continue_training = True

    def _init_callback(self) -> None:
        for child in (self.callback_on_new_best, self.callback_after_eval):
            if child is not None:
                child.init_callback(self.model)
        if self.best_model_save_path is not None:
            self.best_model_save_path.mkdir(parents=True, exist_ok=True)
        if self.evaluations_dir is not None:
            self.evaluations_dir.mkdir(parents=True, exist_ok=True)
        if self.sources is not None and not hasattr(self.model, "active_source"):
            raise TypeError(
                f"MultiEnvEvalCallback(sources=...) needs a model with one actor per source, got {type(self.model).__name__}"
            )
        # first evaluation at the next multiple of eval_freq (learn may resume at any timestep); an evaluate() called
        # before training logs, and draws its episodes, at the model's timestep
        self.num_timesteps = self.model.num_timesteps
        self._next_eval = (self.model.num_timesteps // self.eval_freq + 1) * self.eval_freq
        if self.log_path is not None:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            if not self.log_path.exists():
                with open(self.log_path, "w", newline="") as handle:
                    csv.writer(handle).writerow(CSV_FIELDS)

    def _on_training_start(self) -> None:
        if self.eval_at_start:
            self.evaluate()

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next_eval:
            self.evaluate()
            while self._next_eval <= self.num_timesteps:
                self._next_eval += self.eval_freq
        continue_training, self._continue_training = self._continue_training, True
        return continue_training

    def _normalized(self, name: str, env: VecEnv, training: VecNormalize) -> VecEnv:
        """``env`` seeing observations normalised with the training env's current statistics (never updated here)."""
        if isinstance(env, VecNormalize):  # the user's own wrapper: only its statistics are synchronised
            evaluated = env
        else:
            if name not in self._normalized_envs:
                self._normalized_envs[name] = VecNormalize(
                    env,
                    training=False,
                    norm_obs=training.norm_obs,
                    norm_reward=False,
                    clip_obs=training.clip_obs,
                    epsilon=training.epsilon,
                    norm_obs_keys=training.norm_obs_keys,
                )
            evaluated = self._normalized_envs[name]
        if training.norm_obs:
            evaluated.obs_rms = deepcopy(training.obs_rms)
        return evaluated

    def _record_best(self, score: float) -> None:
        """SB3's EvalCallback after an evaluation: the best model, ``callback_on_new_best``, ``callback_after_eval``."""
        continue_training = True
        self.last_mean_reward = score
        if score > self.best_mean_reward:
            self.best_mean_reward = score
            if self.best_model_save_path is not None:
                self.model.save(self.best_model_save_path / "best_model")
            if self.callback_on_new_best is not None:
                continue_training = self.callback_on_new_best.on_step()
        if self.callback_after_eval is not None:
            continue_training = self.callback_after_eval.on_step() and continue_training
        self._continue_training = self._continue_training and continue_training

    def episode_seed(self, index: int) -> int:
        """
        :param index: an evaluation environment's position
        :return: the seed it gets before the evaluation at the current timestep: ``seed + index`` with
            ``same_episodes``, else one drawn from ``(seed, index, num_timesteps)`` (a new one at every timestep, and
            the same one for any run at that timestep)
        """
        assert self.seed is not None
        if self.same_episodes:
            return self.seed + index
        return int(np.random.SeedSequence([self.seed, index, self.num_timesteps]).generate_state(1)[0])

    def evaluate(self) -> dict[str, float]:
        """
        Evaluate now on every environment, log and record the results.

        :return: mean reward per environment name
        """
        means: dict[str, float] = {}
        rows = []
        model: Any = self.model
        selected = model.active_source if self.sources is not None else None
        training_env = self.model.get_env()
        training_normalization = unwrap_vec_normalize(training_env) if training_env is not None else None
        all_rewards: list[list[float]] = []
        all_lengths: list[list[int]] = []
        for index, (name, env) in enumerate(self.eval_envs.items()):
            if self.seed is not None:
                env.seed(self.episode_seed(index))  # applied at the reset that starts this evaluation
            if self.sources is not None and name in self.sources:
                model.select_source(self.sources[name])
            if training_normalization is not None:
                env = self._normalized(name, env, training_normalization)
            episode_rewards, episode_lengths = evaluate_policy(
                self.model,
                env,
                n_eval_episodes=self.n_eval_episodes,
                deterministic=self.deterministic,
                return_episode_rewards=True,
                warn=False,
            )
            mean, std = float(np.mean(episode_rewards)), float(np.std(episode_rewards))
            means[name] = mean
            all_rewards.append(np.asarray(episode_rewards, dtype=np.float64).tolist())  # per episode (return_episode_rewards)
            all_lengths.append(np.asarray(episode_lengths, dtype=np.int64).tolist())
            self.logger.record(f"eval/{name}/mean_reward", mean)
            self.logger.record(f"eval/{name}/std_reward", std)
            self.logger.record(f"eval/{name}/mean_ep_length", float(np.mean(episode_lengths)))
            row = dict(
                timesteps=self.num_timesteps, env=name, mean_reward=mean, std_reward=std, n_episodes=self.n_eval_episodes
            )
            rows.append(row)
        if selected is not None:
            model.select_source(selected)
        score = float(np.mean(list(means.values())))
        self.logger.record("eval/mean_over_envs", score)
        self.results.extend(rows)
        if self.log_path is not None:
            with open(self.log_path, "a", newline="") as handle:
                writer = csv.DictWriter(handle, fieldnames=CSV_FIELDS)
                writer.writerows(rows)
        self.evaluations_timesteps.append(self.num_timesteps)
        self.evaluations_results.append(all_rewards)
        self.evaluations_length.append(all_lengths)
        if self.evaluations_dir is not None:
            np.savez(
                self.evaluations_dir / "evaluations.npz",
                timesteps=np.array(self.evaluations_timesteps, dtype=np.int64),
                env_names=np.array(list(self.eval_envs), dtype=str),
                results=np.array(self.evaluations_results, dtype=np.float64),
                ep_lengths=np.array(self.evaluations_length, dtype=np.int64),
            )
        if self.verbose >= 1:  # one line per evaluation
            shown = ", ".join(f"{row['env']} {row['mean_reward']:.2f} +/- {row['std_reward']:.2f}" for row in rows)
            best = " (new best)" if score > self.best_mean_reward else ""
            print(f"Eval at {self.num_timesteps}: mean reward {shown}; mean over environments {score:.2f}{best}")
        self.logger.dump(self.num_timesteps)
        self._record_best(score)
        return means


def _widen_csv(path: pathlib.Path, fields: list[str]) -> None:
    """Rewrite the CSV file ``path`` with the header ``fields`` (which extends its own), its rows padded with empty
    values; the file is replaced atomically."""
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))[1:]
    with atomic_write(path, "w", newline="") as widened:  # a failed write leaves the log as it was
        writer = csv.writer(widened)
        writer.writerow(fields)
        writer.writerows(row + [""] * (len(fields) - len(row)) for row in rows)


class SourceQCallback(BaseCallback):
    """
    Diagnostic (needs source tags): every ``log_freq`` timesteps, the average Q-value the model's critic gives to
    each source's data (``diagnostics/q_mean/<source name>``): the overestimation curves of the paper, where the
    Q-values of an environment that is no longer visited drift away. Also written to ``log_path`` as CSV.

    The model must have ``critic`` (MPO, CRR, SAC, TD3) and a replay buffer that returns source ids
    (:class:`~sb3_lifelong.LifelongReplayBuffer` or a view of several). Uniform samples of ``batch_size``
    transitions are grouped by source, so each source's average is over its own data.

    :param log_freq: period, in timesteps (updates when training offline)
    :param batch_size: transitions sampled for each measurement
    :param log_path: optional CSV file (columns: timesteps, source, name, q_mean, n)
    :param data: the transitions to measure on (a ``LifelongReplayBuffer`` or view); default: the model's replay
        buffer. Give the whole lifetime here when the model samples its own buffer with per-source weights (a
        student trained on one source's data still gets its Q-values on the others)
    :param monte_carlo: also measure each source's overestimation against the truth
        (``diagnostics/overestimation/<name>``: mean Q(s, a) minus the discounted return that followed in the stored
        episode, on a fixed sample of ``batch_size`` transitions per source, :class:`MonteCarloProbe`; and
        ``diagnostics/mc_return/<name>``); a source whose overestimation grows is being forgotten
    :param reward_scale: per-source reward scale the model trains with (source id -> factor), for the returns
    """

    def __init__(
        self,
        log_freq: int = 10_000,
        batch_size: int = 4096,
        log_path: Optional[Union[str, os.PathLike]] = None,
        data: Optional[Any] = None,
        monte_carlo: bool = True,
        reward_scale: Optional[dict[int, float]] = None,
    ):
        super().__init__()
        if log_freq < 1 or batch_size < 1:
            raise ValueError(f"log_freq and batch_size must be >= 1, got {log_freq} and {batch_size}")
        self.log_freq = log_freq
        self.batch_size = batch_size
        self.log_path = pathlib.Path(log_path) if log_path is not None else None
        self.data = data
        self.monte_carlo = monte_carlo
        self.reward_scale = reward_scale
        self.results: list[dict[str, Any]] = []
        self._next = 0
        self._probe: Optional[MonteCarloProbe] = None
        self._fields = list(Q_CSV_FIELDS)

    def _buffer(self) -> Any:
        return self.data if self.data is not None else getattr(self.model, "replay_buffer", None)

    def _init_callback(self) -> None:
        buffer = self._buffer()
        if buffer is None or "return_sources" not in inspect.signature(buffer.sample).parameters:
            raise TypeError(
                "SourceQCallback is a diagnostic that needs source tags: use a LifelongReplayBuffer "
                f"(got {type(buffer).__name__})"
            )
        if not hasattr(self.model, "critic"):
            raise TypeError(f"SourceQCallback needs a model with a critic, got {type(self.model).__name__}")
        self._next = (self.model.num_timesteps // self.log_freq + 1) * self.log_freq
        if self.monte_carlo and self._probe is None:
            if not hasattr(self.model, "gamma"):
                raise TypeError(
                    "SourceQCallback(monte_carlo=True) needs the model's discount factor gamma for the returns, "
                    f"got {type(self.model).__name__} without one (monte_carlo=False measures the Q-values only)"
                )
            gamma = float(self.model.gamma)  # type: ignore[attr-defined]
            self._probe = MonteCarloProbe(buffer, gamma, self.batch_size, reward_scale=self.reward_scale)
        if self.log_path is not None:
            if not self.log_path.exists() or self.log_path.stat().st_size == 0:
                self.log_path.parent.mkdir(parents=True, exist_ok=True)
                with open(self.log_path, "w", newline="") as handle:
                    csv.writer(handle).writerow(Q_CSV_FIELDS)
            with open(self.log_path, newline="") as handle:
                header = next(csv.reader(handle), [])
            if not header:
                raise ValueError(
                    f"{str(self.log_path)!r} starts with an empty line: it has no header to append Q-values under "
                    "(give a new file, or remove the empty line)"
                )
            if header != Q_CSV_FIELDS and header == Q_CSV_FIELDS[: len(header)]:
                # an older run's file, without the Monte-Carlo columns: widened (its rows keep their values, the new
                # columns empty), so that a resumed run does not drop what it measures
                _widen_csv(self.log_path, Q_CSV_FIELDS)
                header = list(Q_CSV_FIELDS)
            self._fields = header  # a file of other columns keeps them

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self.measure()
            while self._next <= self.num_timesteps:
                self._next += self.log_freq
        return True

    def measure(self) -> dict[str, float]:
        """:return: the average Q-value per source name, now"""
        import torch as th

        buffer: Any = self._buffer()
        if buffer.size() == 0:
            return {}
        # a model trained on a VecNormalize env sees normalised observations: so must its critic here
        normalizer = getattr(self.model, "_vec_normalize_env", None)
        samples, sources = buffer.sample(self.batch_size, env=normalizer, return_sources=True)
        # ``data`` may sample onto another device than the model's (it is not the model's own buffer)
        device = self.model.device
        observations = samples.observations
        if isinstance(observations, dict):
            observations = {key: value.to(device) for key, value in observations.items()}
        else:
            observations = observations.to(device)
        critic: Any = self.model.critic  # type: ignore[attr-defined]
        with th.no_grad():
            q_values = critic(observations, samples.actions.to(device))[0].flatten().cpu()
        sources = sources.cpu()
        names = buffer.sources
        truth = self._probe.measure(critic, self.model.device, normalizer) if self._probe is not None else {}
        means: dict[str, float] = {}
        rows = []
        for source in th.unique(sources).tolist():
            mask = sources == source
            name = names.get(source, {}).get("name", f"source_{source}")
            means[name] = float(q_values[mask].mean())
            self.logger.record(f"diagnostics/q_mean/{name}", means[name])
            row = dict(timesteps=self.num_timesteps, source=source, name=name, q_mean=means[name], n=int(mask.sum()))
            if source in truth:
                measured = truth[source]
                self.logger.record(f"diagnostics/overestimation/{name}", measured.overestimation)
                self.logger.record(f"diagnostics/mc_return/{name}", measured.mc_return)
                row.update(q_probe=measured.q_mean, mc_return=measured.mc_return, n_mc=measured.n)
                row.update(overestimation=measured.overestimation)
            rows.append(row)
        self.results.extend(rows)
        if self.log_path is not None:
            with open(self.log_path, "a", newline="") as handle:
                csv.DictWriter(handle, fieldnames=self._fields, extrasaction="ignore").writerows(rows)
        return means


class TrainLogCallback(BaseCallback):
    """
    Every ``log_freq`` timesteps (updates when training offline), the model's ``train/*`` values (the means since
    the logger's last dump: ``train/weight_ess``, ``train/beta``, losses, ...) as a row of a CSV file, so that a run
    without tensorboard keeps them beside its ``eval.csv``.

    :param log_path: the CSV file (columns: ``timesteps`` and one per ``train/`` key of the first row)
    :param log_freq: period, in timesteps
    """

    def __init__(self, log_path: Union[str, os.PathLike], log_freq: int = 10_000):
        super().__init__()
        if log_freq < 1:
            raise ValueError(f"log_freq must be >= 1, got {log_freq}")
        self.log_path = pathlib.Path(log_path)
        self.log_freq = log_freq
        self._fields: Optional[list[str]] = None
        self._next = 0

    def _init_callback(self) -> None:
        self._next = (self.model.num_timesteps // self.log_freq + 1) * self.log_freq

    def _on_step(self) -> bool:
        if self.num_timesteps < self._next:
            return True
        while self._next <= self.num_timesteps:
            self._next += self.log_freq
        values = {key[len("train/") :]: value for key, value in self.logger.name_to_value.items() if key.startswith("train/")}
        if not values:
            return True
        if self._fields is None:
            header = _csv_header(self.log_path)
            if header and header[0] == "timesteps":  # a resumed run goes on in the same file, with its columns
                self._fields = header
            else:
                self._fields = ["timesteps", *sorted(values)]
                self.log_path.parent.mkdir(parents=True, exist_ok=True)
                with open(self.log_path, "w", newline="") as handle:
                    csv.writer(handle).writerow(self._fields)
        with open(self.log_path, "a", newline="") as handle:
            row = {"timesteps": self.num_timesteps, **values}
            csv.DictWriter(handle, fieldnames=self._fields, extrasaction="ignore").writerow(row)
        return True
