"""
Golden values of the evaluation callbacks (``sb3_lifelong.evaluation.callbacks``): the names given to evaluation
environments, the documented defaults, each check at its boundary, the folders made, what is logged per evaluation
(its exact values), when a new best is declared (a tie is not one), how two children's answers combine, each
source's average Q-value under a critic whose value is known by hand, and when a log's first row falls after a
resume. Each test here was written against a survivor of the module's mutation run (``benchmarks/mutation``).
"""

import csv
import warnings
from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import KVWriter, Logger, configure
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_lifelong import MPO, LifelongReplayBuffer
from sb3_lifelong.evaluation.callbacks import (
    Q_CSV_FIELDS,
    MultiEnvEvalCallback,
    SourceQCallback,
    TrainLogCallback,
    make_eval_envs,
)

SMALL = dict(policy_kwargs=dict(net_arch=[16]), batch_size=16, learning_starts=10_000, num_samples=4)


class NoSpecEnv(gym.Env):
    """An environment made without ``gym.make``: it has no spec (or the one a test gives it)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, dtype=np.float32), {}

    def step(self, action):
        return np.zeros(2, dtype=np.float32), 1.0, True, False, {}


# ------------------------------------------------------------------------------------------------------ names
def test_a_vec_env_is_named_after_its_first_env_and_its_own_spec_comes_first() -> None:
    assert list(make_eval_envs([DummyVecEnv([lambda: gym.make("Pendulum-v1")])])) == ["Pendulum-v1"]
    own = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
    own.spec = SimpleNamespace(id="Mine")  # type: ignore[attr-defined]
    assert list(make_eval_envs([own])) == ["Mine"]
    # a VecEnv whose first env has no spec, one env without a spec, one whose spec has no id: env<position>
    assert list(make_eval_envs([gym.make("Pendulum-v1"), DummyVecEnv([NoSpecEnv])])) == ["Pendulum-v1", "env1"]
    assert list(make_eval_envs(NoSpecEnv())) == ["env0"]
    unnamed = NoSpecEnv()
    unnamed.spec = SimpleNamespace(id=None)  # type: ignore[assignment]
    assert list(make_eval_envs([gym.make("Pendulum-v1"), unnamed])) == ["Pendulum-v1", "env1"]


def test_envs_of_one_id_are_numbered_in_order() -> None:
    names = list(make_eval_envs(["Pendulum-v1"] * 4))
    assert names == ["Pendulum-v1", "Pendulum-v1_1", "Pendulum-v1_2", "Pendulum-v1_3"]


# ---------------------------------------------------------------------------------------- defaults and checks
def test_the_documented_defaults(tmp_path) -> None:
    evaluation = MultiEnvEvalCallback(gym.make("Pendulum-v1"))
    assert (evaluation.eval_freq, evaluation.n_eval_episodes, evaluation.verbose) == (10_000, 5, 0)
    assert evaluation.deterministic is True and evaluation.eval_at_start is False and evaluation.same_episodes is False
    assert evaluation.best_mean_reward == -np.inf and evaluation.last_mean_reward == -np.inf
    source_q = SourceQCallback()
    assert (source_q.log_freq, source_q.batch_size, source_q.monte_carlo) == (10_000, 4096, True)
    assert TrainLogCallback(tmp_path / "train.csv").log_freq == 10_000


def test_each_frequency_is_accepted_from_one_and_refused_at_zero() -> None:
    env = gym.make("Pendulum-v1")
    one = MultiEnvEvalCallback(env, eval_freq=1, n_eval_episodes=1)
    assert (one.eval_freq, one.n_eval_episodes) == (1, 1)
    with pytest.raises(ValueError, match=r"must be >= 1, got 0 and 1"):
        MultiEnvEvalCallback(env, eval_freq=0, n_eval_episodes=1)
    with pytest.raises(ValueError, match=r"must be >= 1, got 1 and 0"):
        MultiEnvEvalCallback(env, eval_freq=1, n_eval_episodes=0)
    least = SourceQCallback(log_freq=1, batch_size=1)
    assert (least.log_freq, least.batch_size) == (1, 1)
    with pytest.raises(ValueError, match=r"got 0 and 1"):
        SourceQCallback(log_freq=0, batch_size=1)
    with pytest.raises(ValueError, match=r"got 1 and 0"):
        SourceQCallback(log_freq=1, batch_size=0)


def untrained() -> MPO:
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL)
    model.set_logger(configure(None, []))
    return model


def test_every_folder_is_made_with_its_parents_and_may_exist_already(tmp_path) -> None:
    model = untrained()
    for _ in range(2):  # the second time every folder exists
        callback = MultiEnvEvalCallback(
            gym.make("Pendulum-v1"),
            n_eval_episodes=1,
            log_path=tmp_path / "a" / "b" / "eval.csv",
            best_model_save_path=tmp_path / "c" / "d",
            evaluations_dir=tmp_path / "e" / "f",
        )
        callback.init_callback(model)
    assert (tmp_path / "a" / "b" / "eval.csv").is_file()
    assert (tmp_path / "c" / "d").is_dir() and (tmp_path / "e" / "f").is_dir()
    train_log = TrainLogCallback(tmp_path / "g" / "h" / "train.csv", log_freq=1)
    train_log.init_callback(model)
    model.logger.record("train/loss", 1.5)
    model.num_timesteps = 1
    train_log.on_step()
    with open(tmp_path / "g" / "h" / "train.csv", newline="") as handle:
        assert list(csv.reader(handle)) == [["timesteps", "loss"], ["1", "1.5"]]


# ------------------------------------------------------------------------------------------ what is logged
class Capture(KVWriter):
    """A logger output that keeps every dump's values."""

    def __init__(self) -> None:
        self.dumps: list[dict[str, Any]] = []

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, Any], step: int = 0) -> None:
        self.dumps.append(dict(key_values))


def test_an_evaluation_logs_each_envs_mean_std_and_mean_episode_length(tmp_path) -> None:
    model = untrained()
    capture = Capture()
    model.set_logger(Logger(folder=None, output_formats=[capture]))
    envs = {"long": gym.make("Pendulum-v1"), "short": gym.make("Pendulum-v1", max_episode_steps=50)}
    callback = MultiEnvEvalCallback(envs, n_eval_episodes=2, seed=0, evaluations_dir=tmp_path)
    callback.init_callback(model)
    means = callback.evaluate()
    logged = capture.dumps[-1]
    assert logged["eval/long/mean_ep_length"] == 200.0 and logged["eval/short/mean_ep_length"] == 50.0
    saved = np.load(tmp_path / "evaluations.npz")
    assert saved["ep_lengths"].tolist() == [[[200, 200], [50, 50]]]
    for index, name in enumerate(envs):
        rewards = saved["results"][0, index]
        assert logged[f"eval/{name}/mean_reward"] == pytest.approx(np.mean(rewards), abs=1e-9) == means[name]
        assert logged[f"eval/{name}/std_reward"] == pytest.approx(np.std(rewards), abs=1e-9)
    assert logged["eval/mean_over_envs"] == pytest.approx((means["long"] + means["short"]) / 2, abs=1e-9)


def test_an_unmonitored_vec_env_is_evaluated_without_a_warning() -> None:
    """The user's own VecEnv is evaluated as given: SB3's warning about a missing ``Monitor`` is not raised."""
    callback = MultiEnvEvalCallback(DummyVecEnv([lambda: gym.make("Pendulum-v1")]), n_eval_episodes=1)
    callback.init_callback(untrained())
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        callback.evaluate()


class Answer(BaseCallback):
    """A child callback that counts its calls and answers ``answer``."""

    def __init__(self, answer: bool) -> None:
        super().__init__()
        self.answer, self.calls = answer, 0

    def _on_step(self) -> bool:
        self.calls += 1
        return self.answer


def test_a_tie_is_not_a_new_best(tmp_path, capsys) -> None:
    """The same episodes of the same policy score the same: the first evaluation is a new best, the second is not."""
    new_best = Answer(True)
    callback = MultiEnvEvalCallback(
        gym.make("Pendulum-v1"),
        n_eval_episodes=1,
        seed=0,
        same_episodes=True,
        verbose=1,
        best_model_save_path=tmp_path,
        callback_on_new_best=new_best,
    )
    callback.init_callback(untrained())
    first = callback.evaluate()["Pendulum-v1"]
    assert callback.best_mean_reward == first and new_best.calls == 1
    assert (tmp_path / "best_model.zip").is_file()
    (tmp_path / "best_model.zip").unlink()
    second = callback.evaluate()["Pendulum-v1"]
    assert second == first and new_best.calls == 1 and not (tmp_path / "best_model.zip").exists()
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and lines[0].endswith("(new best)") and not lines[1].endswith("(new best)")
    quiet = MultiEnvEvalCallback(gym.make("Pendulum-v1"), n_eval_episodes=1, seed=0, verbose=0)
    quiet.init_callback(untrained())
    quiet.evaluate()
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize("on_new_best, after_eval, go_on", [(False, True, False), (True, False, False), (True, True, True)])
def test_training_stops_when_either_child_says_so(on_new_best: bool, after_eval: bool, go_on: bool) -> None:
    first, second = Answer(on_new_best), Answer(after_eval)
    callback = MultiEnvEvalCallback(
        gym.make("Pendulum-v1"), eval_freq=5, n_eval_episodes=1, callback_on_new_best=first, callback_after_eval=second
    )
    model = untrained()
    callback.init_callback(model)
    answers = []
    for step in range(1, 6):
        model.num_timesteps = step
        answers.append(callback.on_step())
    assert answers == [True] * 4 + [go_on] and first.calls == second.calls == 1


# ------------------------------------------------------------------------------------ each source's Q-value
class KnownCritic(th.nn.Module):
    """``Q(s, a) = 2 s_0 + a_0`` (a second critic's value is ignored by the callback)."""

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        q = 2.0 * obs[:, :1] + actions[:, :1]
        return q, q + 100.0


def stub_model(buffer: LifelongReplayBuffer, gamma: Any = 0.5) -> Any:
    model = SimpleNamespace(
        critic=KnownCritic(), replay_buffer=buffer, num_timesteps=0, device=th.device("cpu"), logger=configure(None, [])
    )
    model.get_env = lambda: None
    if gamma is not None:
        model.gamma = gamma
    return model


def constant_sources(rows: int = 40) -> LifelongReplayBuffer:
    """Source 0's rows are all s_0 = 1, a = 0.5 (Q = 2.5), source 1's s_0 = 3, a = -0.5 (Q = 5.5); every episode
    is 4 steps of reward 1 that terminate."""
    buffer = LifelongReplayBuffer(0, gym.spaces.Box(-10, 10, (2,), np.float32), gym.spaces.Box(-1, 1, (1,), np.float32))
    for source, (s0, action) in enumerate([(1.0, 0.5), (3.0, -0.5)]):
        buffer.set_source(source, name=f"env_{'ab'[source]}")
        for t in range(rows):
            obs = np.array([[s0, 0.0]], dtype=np.float32)
            buffer.add(obs, obs, np.array([[action]], np.float32), np.array([1.0]), np.array([t % 4 == 3]), [{}])
    return buffer


@pytest.mark.parametrize("monte_carlo", [False, True])
def test_each_source_gets_the_mean_q_of_its_own_rows(tmp_path, monte_carlo: bool) -> None:
    buffer = constant_sources()
    callback = SourceQCallback(log_freq=1, batch_size=64, monte_carlo=monte_carlo, log_path=tmp_path / "q.csv")
    callback.init_callback(stub_model(buffer))
    means = callback.measure()
    assert means == {"env_a": pytest.approx(2.5, abs=1e-6), "env_b": pytest.approx(5.5, abs=1e-6)}
    rows = {row["name"]: row for row in callback.results}
    assert rows["env_a"]["n"] + rows["env_b"]["n"] == 64 and min(rows["env_a"]["n"], rows["env_b"]["n"]) > 0
    if not monte_carlo:
        assert all("mc_return" not in row for row in callback.results)
        return
    # every row's discounted return (gamma 0.5) over the 4-step episodes: 1.875, 1.75, 1.5, 1 -> mean 1.53125
    for name, q in (("env_a", 2.5), ("env_b", 5.5)):
        assert rows[name]["mc_return"] == pytest.approx(1.53125, abs=1e-6)
        assert rows[name]["q_probe"] == pytest.approx(q, abs=1e-6)
        assert rows[name]["overestimation"] == pytest.approx(q - 1.53125, abs=1e-6)
    with open(tmp_path / "q.csv", newline="") as handle:
        assert [row["overestimation"] != "" for row in csv.DictReader(handle)] == [True, True]


def test_the_probe_needs_the_models_discount() -> None:
    buffer = constant_sources()
    with pytest.raises(TypeError, match=r"monte_carlo=True\) needs the model's discount factor gamma"):
        SourceQCallback(log_freq=1).init_callback(stub_model(buffer, gamma=None))
    SourceQCallback(log_freq=1, monte_carlo=False).init_callback(stub_model(buffer, gamma=None))


def test_a_q_log_keeps_its_own_columns_gets_a_header_when_empty_and_refuses_a_blank_first_line(tmp_path) -> None:
    buffer = constant_sources()
    other = tmp_path / "other.csv"
    other.write_text("timesteps,name,q_mean\n")
    callback = SourceQCallback(log_freq=1, batch_size=16, monte_carlo=False, log_path=other)
    callback.init_callback(stub_model(buffer))
    callback.measure()
    with open(other, newline="") as handle:
        rows = list(csv.reader(handle))
    assert rows[0] == ["timesteps", "name", "q_mean"] and [len(row) for row in rows[1:]] == [3, 3]
    nested = tmp_path / "runs" / "seed_0" / "q.csv"  # its folders are made, with their parents
    SourceQCallback(log_path=nested, monte_carlo=False).init_callback(stub_model(buffer))
    with open(nested, newline="") as handle:
        assert list(csv.reader(handle)) == [Q_CSV_FIELDS]
    empty = tmp_path / "logs" / "q.csv"
    empty.parent.mkdir()
    empty.touch()
    SourceQCallback(log_path=empty, monte_carlo=False).init_callback(stub_model(buffer))
    with open(empty, newline="") as handle:
        assert list(csv.reader(handle)) == [Q_CSV_FIELDS]
    blank = tmp_path / "blank.csv"
    blank.write_text("\n1,0,env_a,2.5,16\n")
    with pytest.raises(ValueError, match=r"blank.csv' starts with an empty line"):
        SourceQCallback(log_path=blank, monte_carlo=False).init_callback(stub_model(buffer))
    assert blank.read_text() == "\n1,0,env_a,2.5,16\n"


# --------------------------------------------------------------------------------------- after a resume
def test_a_train_logs_first_row_after_a_resume_is_at_the_next_multiple(tmp_path) -> None:
    model = untrained()
    model.num_timesteps = 25
    train_log = TrainLogCallback(tmp_path / "train.csv", log_freq=10)
    train_log.init_callback(model)
    written = []
    for step in range(26, 42):
        model.num_timesteps = step
        model.logger.record("train/loss", float(step))
        train_log.on_step()
        if (tmp_path / "train.csv").exists():
            with open(tmp_path / "train.csv", newline="") as handle:
                written = [int(row[0]) for row in list(csv.reader(handle))[1:]]
    assert written == [30, 40]
