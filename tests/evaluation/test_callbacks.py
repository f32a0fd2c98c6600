import csv

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env

from sb3_lifelong import MPO
from sb3_lifelong.evaluation.callbacks import MultiEnvEvalCallback

SMALL = dict(policy_kwargs=dict(net_arch=[32, 32]), batch_size=32, learning_starts=50, num_samples=8)


def test_evaluates_every_env_on_schedule(tmp_path):
    envs = {"env_a": gym.make("Pendulum-v1", g=10.0), "env_b": gym.make("Pendulum-v1", g=5.0)}
    log_path = tmp_path / "eval.csv"
    callback = MultiEnvEvalCallback(envs, eval_freq=100, n_eval_episodes=2, log_path=log_path)
    model = MPO("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=0), seed=0, **SMALL)
    model.learn(300, callback=callback)
    # timesteps 100, 200, 300 (n_envs=2 steps by 2: the schedule follows num_timesteps, not calls)
    assert [row["timesteps"] for row in callback.results] == [100, 100, 200, 200, 300, 300]
    assert {row["env"] for row in callback.results} == {"env_a", "env_b"}
    with open(log_path) as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 6 and rows[0]["env"] == "env_a"
    assert all(float(row["mean_reward"]) < 0 for row in rows)
    # learning again appends to the same CSV and continues the schedule
    model.learn(100, callback=callback, reset_num_timesteps=False)
    with open(log_path) as handle:
        assert [int(row["timesteps"]) for row in csv.DictReader(handle)] == [100, 100, 200, 200, 300, 300, 400, 400]


def test_seeded_evaluations_are_reproducible():
    """With ``seed``, the same policy gets the same evaluations from fresh environments; another seed, others."""

    def evaluations(seed: int) -> list[float]:
        envs = {"env_a": gym.make("Pendulum-v1"), "env_b": gym.make("Pendulum-v1", g=5.0)}
        callback = MultiEnvEvalCallback(envs, eval_freq=100, n_eval_episodes=2, seed=seed)
        model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL)
        model.learn(200, callback=callback)  # two evaluations, each on the episodes of its timestep
        return [row["mean_reward"] for row in callback.results]

    first = evaluations(3)
    assert len(first) == 4 and first == evaluations(3)
    assert first != evaluations(4)


def test_seeded_episodes_follow_the_timestep_not_the_process():
    """With a seed, an evaluation's episodes are chosen by the timestep: new environments and a new callback (a run
    resumed in a new process) evaluate a policy as the callback that ran before did; each timestep plays new episodes,
    or the same ones with ``same_episodes``."""
    from stable_baselines3.common.logger import configure

    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL)  # a fixed policy: differences are the episodes'
    model.set_logger(configure(None, []))

    def new_callback(same_episodes: bool) -> MultiEnvEvalCallback:
        envs = {"env_a": gym.make("Pendulum-v1"), "env_b": gym.make("Pendulum-v1", g=5.0)}
        callback = MultiEnvEvalCallback(envs, eval_freq=100, n_eval_episodes=2, seed=7, same_episodes=same_episodes)
        callback.init_callback(model)
        return callback

    def evaluate_at(callback: MultiEnvEvalCallback, timesteps: int) -> dict[str, float]:
        callback.num_timesteps = timesteps
        return callback.evaluate()

    running = new_callback(same_episodes=False)
    first, second = evaluate_at(running, 100), evaluate_at(running, 200)
    assert first["env_a"] != second["env_a"] and first["env_b"] != second["env_b"]  # new episodes
    assert evaluate_at(new_callback(same_episodes=False), 200) == second  # resumed: the episodes of its timestep
    assert evaluate_at(running, 100) == first  # whatever ran in between
    same = new_callback(same_episodes=True)
    assert evaluate_at(same, 100) == evaluate_at(same, 200) == evaluate_at(new_callback(same_episodes=True), 300)
    assert running.episode_seed(0) != running.episode_seed(1) and same.episode_seed(1) == 8
    for bad in (-1, True, 1.5):
        with pytest.raises(ValueError, match="non-negative int"):
            MultiEnvEvalCallback([gym.make("Pendulum-v1")], seed=bad)
    envs = {"env_a": gym.make("Pendulum-v1"), "env_b": gym.make("Pendulum-v1", g=5.0)}
    numpy_seeded = MultiEnvEvalCallback(envs, eval_freq=100, n_eval_episodes=2, seed=np.int64(7), same_episodes=True)
    numpy_seeded.init_callback(model)  # gymnasium refuses numpy integers as seeds: the callback keeps a Python int
    assert type(numpy_seeded.seed) is int and numpy_seeded.evaluate() == evaluate_at(same, 100)


def test_protocol_evaluations_play_the_same_episodes(tmp_path):
    """The protocol's jobs evaluate every time on the same seeded episodes (their returns are compared over time)."""
    from sb3_lifelong.evaluation.callbacks import EVAL_SEED_OFFSET
    from sb3_lifelong.experiments import PRESETS
    from sb3_lifelong.experiments.jobs import job_callbacks

    evaluation = job_callbacks(PRESETS["tiny"], tmp_path, eval_freq=100, seed=3)[1]
    assert isinstance(evaluation, MultiEnvEvalCallback)
    # 10_000 + s: the reset seeds every committed study was evaluated on (their READMEs: 10000..10009 for seed 0)
    assert evaluation.same_episodes and evaluation.seed == EVAL_SEED_OFFSET + 3 == 10_003


def test_logged_to_tensorboard(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    envs = [gym.make("Pendulum-v1"), gym.make("Pendulum-v1", g=3.0)]
    callback = MultiEnvEvalCallback(envs, eval_freq=60, n_eval_episodes=1)
    model = MPO("MlpPolicy", "Pendulum-v1", tensorboard_log=str(tmp_path), seed=0, **SMALL)
    model.learn(120, callback=callback, tb_log_name="run")
    accumulator = EventAccumulator(str(tmp_path / "run_1"))
    accumulator.Reload()
    tags = accumulator.Tags()["scalars"]
    assert "eval/Pendulum-v1/mean_reward" in tags and "eval/Pendulum-v1_1/mean_reward" in tags
    assert [event.step for event in accumulator.Scalars("eval/Pendulum-v1/mean_reward")] == [60, 120]


def test_bad_arguments():
    with pytest.raises(ValueError, match="at least one"):
        MultiEnvEvalCallback({})
    with pytest.raises(ValueError, match="eval_freq"):
        MultiEnvEvalCallback([gym.make("Pendulum-v1")], eval_freq=0)
    with pytest.raises(ValueError, match="no '/'"):
        MultiEnvEvalCallback({"a/b": gym.make("Pendulum-v1")})


def test_source_q_callback_groups_by_source(tmp_path):
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.evaluation.callbacks import SourceQCallback

    model = MPO("MlpPolicy", "Pendulum-v1", replay_buffer_class=LifelongReplayBuffer, seed=0, **SMALL)
    model.replay_buffer.set_source(0, name="env_a")
    model.learn(100)
    model.replay_buffer.set_source(1, name="env_b")
    callback = SourceQCallback(log_freq=50, batch_size=512, log_path=tmp_path / "q.csv")
    model.learn(100, callback=callback, reset_num_timesteps=False)
    names = {row["name"] for row in callback.results}
    assert names == {"env_a", "env_b"}
    assert [row["timesteps"] for row in callback.results if row["name"] == "env_a"] == [150, 200]
    # each source gets a finite average under its own name (its exact value: test_overestimation.py)
    means = callback.measure()
    assert set(means) == {"env_a", "env_b"} and all(np.isfinite(v) for v in means.values())
    assert "diagnostics/q_mean/env_a" in model.logger.name_to_value
    with open(tmp_path / "q.csv") as handle:
        assert len(list(csv.DictReader(handle))) == 6  # two measurements during learn, one by hand


def test_source_q_callback_needs_source_tags():
    from sb3_lifelong.evaluation.callbacks import SourceQCallback

    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL)
    with pytest.raises(TypeError, match="source tags"):
        model.learn(60, callback=SourceQCallback(log_freq=10))


def test_an_older_q_log_is_widened_and_keeps_its_rows(tmp_path):
    """A q.csv of an earlier version (without the Monte-Carlo columns) gains them, its rows kept and padded empty."""
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.evaluation.callbacks import Q_CSV_FIELDS, SourceQCallback

    log = tmp_path / "q.csv"
    old = [["100", "0", "env_a", "-1.25", "64"], ["100", "1", "env_b", "-2.5", "64"]]
    with open(log, "w", newline="") as handle:
        csv.writer(handle).writerows([Q_CSV_FIELDS[:5], *old])
    model = MPO("MlpPolicy", "Pendulum-v1", replay_buffer_class=LifelongReplayBuffer, seed=0, **SMALL)
    model.replay_buffer.set_source(0, name="env_a")
    model.learn(60, callback=SourceQCallback(log_freq=50, batch_size=64, log_path=log))
    with open(log, newline="") as handle:
        rows = list(csv.reader(handle))
    assert rows[0] == Q_CSV_FIELDS
    assert rows[1:3] == [row + [""] * (len(Q_CSV_FIELDS) - 5) for row in old]
    assert len(rows) == 4 and len(rows[3]) == len(Q_CSV_FIELDS)  # the new measurement, every column


def test_the_best_model_folder_may_be_nested(tmp_path):
    """``best_model_save_path`` is created with its parents, as SB3's ``EvalCallback`` does."""
    folder = tmp_path / "runs" / "seed_0" / "best"
    callback = MultiEnvEvalCallback(
        {"env": gym.make("Pendulum-v1")}, eval_freq=50, n_eval_episodes=1, best_model_save_path=folder
    )
    MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL).learn(60, callback=callback)
    assert (folder / "best_model.zip").is_file()


def test_a_train_log_of_no_frequency_is_refused(tmp_path):
    from sb3_lifelong.evaluation.callbacks import TrainLogCallback

    with pytest.raises(ValueError, match="log_freq must be >= 1, got 0"):
        TrainLogCallback(tmp_path / "train.csv", log_freq=0)


# ------------------------------------------------------------------------------------- each check at its boundary
def test_the_callbacks_checks_name_the_problem() -> None:
    from sb3_lifelong.evaluation.callbacks import SourceQCallback, TrainLogCallback

    envs = {"Env-A": gym.make("Pendulum-v1")}
    with pytest.raises(ValueError, match=r"sources names environments \['Env-B'\] that are not evaluated \(\['Env-A'\]\)"):
        MultiEnvEvalCallback(envs, sources={"Env-A": 0, "Env-B": 1})
    with pytest.raises(ValueError, match="same_episodes=True needs a seed"):
        MultiEnvEvalCallback(envs, same_episodes=True)
    assert MultiEnvEvalCallback(envs, same_episodes=True, seed=0).seed == 0  # the smallest seed
    for kwargs in (dict(log_freq=0), dict(batch_size=0)):
        with pytest.raises(ValueError, match=r"log_freq and batch_size must be >= 1"):
            SourceQCallback(**kwargs)
    with pytest.raises(ValueError, match=r"log_freq must be >= 1, got 0"):
        TrainLogCallback("train.csv", log_freq=0)
    assert TrainLogCallback("train.csv", log_freq=1).log_freq == 1


def test_sources_need_a_model_with_one_actor_per_source() -> None:
    envs = {"Env-A": gym.make("Pendulum-v1")}
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL)
    with pytest.raises(
        TypeError, match=r"MultiEnvEvalCallback\(sources=...\) needs a model with one actor per source, got MPO"
    ):
        model.learn(60, callback=MultiEnvEvalCallback(envs, eval_freq=50, n_eval_episodes=1, sources={"Env-A": 0}))


def test_source_q_needs_a_critic_and_logs_nothing_from_an_empty_buffer() -> None:
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.evaluation.callbacks import SourceQCallback

    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, replay_buffer_class=LifelongReplayBuffer, **SMALL)
    callback = SourceQCallback(log_freq=20, batch_size=16, monte_carlo=False)
    callback.init_callback(model)
    assert model.replay_buffer.size() == 0 and callback.measure() == {}
    del model.critic
    with pytest.raises(TypeError, match="SourceQCallback needs a model with a critic, got MPO"):
        SourceQCallback(log_freq=20).init_callback(model)


def test_eval_at_start_evaluates_the_untrained_policy_at_step_0(tmp_path) -> None:
    envs = {"Env-A": gym.make("Pendulum-v1")}
    callback = MultiEnvEvalCallback(envs, eval_freq=100, n_eval_episodes=1, eval_at_start=True, seed=0)
    MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL).learn(100, callback=callback)
    assert [row["timesteps"] for row in callback.results] == [0, 100]
    late = MultiEnvEvalCallback(envs, eval_freq=100, n_eval_episodes=1, seed=0)
    MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL).learn(100, callback=late)
    assert [row["timesteps"] for row in late.results] == [100]


def test_train_log_writes_the_train_values_every_log_freq_and_a_resume_keeps_its_columns(tmp_path) -> None:
    from sb3_lifelong.evaluation.callbacks import TrainLogCallback

    path = tmp_path / "logs" / "train.csv"
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL)
    model.learn(200, callback=TrainLogCallback(path, log_freq=50))
    with open(path, newline="") as handle:
        first = list(csv.reader(handle))
    header = first[0]
    assert header[0] == "timesteps" and "critic_loss" in header and header[1:] == sorted(header[1:])
    # no train/ values before the first update (learning_starts=50): rows from then on, one per 50 steps
    assert [int(row[0]) for row in first[1:]] == [100, 150, 200]
    model.learn(100, callback=TrainLogCallback(path, log_freq=50), reset_num_timesteps=False)
    with open(path, newline="") as handle:
        again = list(csv.reader(handle))
    assert again[0] == header and [int(row[0]) for row in again[1:]] == [100, 150, 200, 250, 300]
