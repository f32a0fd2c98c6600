"""
The offline entry points' values, pinned: ``learn_offline``'s defaults, what zero updates do, which space the data
gets, and which statistics a new offline run starts from. Each a behaviour a mutant of ``common/offline.py`` changed
while the rest of the suite passed (the mutation benchmark, issue 66).
"""

import inspect

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from testkit import flat_params, pendulum_data, signature_defaults

from sb3_lifelong import BC, CRR

SMALL = dict(policy_kwargs=dict(net_arch=[16, 16]), batch_size=16, seed=0)


def test_every_default_of_learn_offline():
    """Written out as the docs' parameter list says them: a change of one is a change of behaviour (a CHANGELOG
    line and a change here)."""
    assert signature_defaults(CRR.learn_offline) == dict(
        callback=None,
        eval_env=None,
        eval_freq=10_000,
        n_eval_episodes=5,
        log_interval=1_000,
        tb_log_name=None,
        reset_num_timesteps=True,
        progress_bar=False,
        eval_sources=None,
    )
    assert inspect.signature(BC.learn_offline) == inspect.signature(CRR.learn_offline)


def test_zero_updates_train_nothing_and_fewer_are_refused():
    model = CRR.from_offline_data(pendulum_data(60), env=gym.make("Pendulum-v1"), **SMALL)
    before = flat_params(model).clone()
    assert model.learn_offline(0, log_interval=0) is model
    assert model.num_timesteps == 0 and model._n_updates == 0 and th.equal(flat_params(model), before)
    model.learn_offline(3, log_interval=0)
    assert model.num_timesteps == 3 and model._n_updates == 3 and not th.equal(flat_params(model), before)
    with pytest.raises(ValueError, match="total_updates must be >= 0, got -1"):
        model.learn_offline(-1)


def test_a_given_observation_space_is_the_datas_beside_an_env():
    """``observation_space`` and ``action_space`` given with an env describe the data; the model acts in the env's."""
    env = gym.make("Pendulum-v1")
    observed = spaces.Box(-5.0, 5.0, (3,), np.float32)
    acted = spaces.Box(-3.0, 3.0, (1,), np.float32)
    model = CRR.from_offline_data(pendulum_data(60), env=env, observation_space=observed, action_space=acted, **SMALL)
    assert model.replay_buffer.observation_space == observed and model.replay_buffer.action_space == acted
    assert model.observation_space == env.observation_space and model.action_space == env.action_space
    assert model.n_envs == 1
    # without an env: the data's spaces are the model's, and it counts one env, as SB3's models of one env
    alone = CRR.from_offline_data(pendulum_data(60), observation_space=observed, action_space=acted, **SMALL)
    assert alone.observation_space == observed and alone.action_space == acted and alone.n_envs == 1


def test_a_new_offline_run_starts_its_episode_statistics_anew_and_a_continued_one_keeps_them():
    model = CRR("MlpPolicy", "Pendulum-v1", learning_starts=50, **SMALL)
    model.learn(400)  # two 200-step episodes online
    assert len(model.ep_info_buffer) == 2
    model.learn_offline(2, log_interval=0, reset_num_timesteps=False)
    assert len(model.ep_info_buffer) == 2 and model.num_timesteps == 402
    model.learn_offline(2, log_interval=0)
    assert len(model.ep_info_buffer) == 0 and len(model.ep_success_buffer) == 0 and model.num_timesteps == 2


def test_a_new_offline_run_counts_its_episodes_from_zero():
    model = CRR("MlpPolicy", "Pendulum-v1", learning_starts=50, **SMALL)
    model.learn(400)
    assert model._episode_num == 2
    model.learn_offline(1, log_interval=0, reset_num_timesteps=False)
    assert model._episode_num == 2
    model.learn_offline(1, log_interval=0)
    assert model._episode_num == 0


@pytest.mark.parametrize("log_interval, dumps", [(1, [1, 2, 3]), (2, [2, 3]), (0, [])])
def test_log_interval_one_dumps_every_update_and_zero_never(tmp_path, log_interval, dumps):
    import csv

    from stable_baselines3.common.logger import configure

    model = CRR.from_offline_data(pendulum_data(60), env=gym.make("Pendulum-v1"), **SMALL)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn_offline(3, log_interval=log_interval)
    with open(tmp_path / "progress.csv", newline="") as handle:
        assert [int(row["time/updates"]) for row in csv.DictReader(handle)] == dumps


def test_the_tensorboard_run_is_named_after_the_algorithm_unless_named(tmp_path):
    pytest.importorskip("torch.utils.tensorboard", reason="tensorboard is not installed")
    model = CRR.from_offline_data(pendulum_data(60), env=gym.make("Pendulum-v1"), tensorboard_log=str(tmp_path), **SMALL)
    model.learn_offline(2, log_interval=1)
    model.learn_offline(2, log_interval=1, tb_log_name="student")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["CRR_1", "student_1"]


def per_source_student():
    from sb3_lifelong import LifelongReplayBuffer

    rng = np.random.default_rng(0)
    obs_space, act_space = spaces.Box(-1.0, 1.0, (3,), np.float32), spaces.Box(-1.0, 1.0, (1,), np.float32)
    buffer = LifelongReplayBuffer(10, obs_space, act_space, device="cpu")
    for source, name in ((0, "Env-A"), (3, "Env-B")):
        buffer.set_source(source, name=name)
        for _ in range(20):
            obs = rng.uniform(-1, 1, (1, 3)).astype(np.float32)
            buffer.add(obs, obs, rng.uniform(-1, 1, (1, 1)).astype(np.float32), rng.normal(size=1), np.zeros(1), [{}])
    return CRR.from_offline_data(buffer, actor_per_source=True, policy_kwargs=dict(net_arch=[8]), batch_size=8, seed=0)


def test_eval_sources_that_the_data_does_not_hold_are_refused_naming_the_datas():
    model = per_source_student()
    assert model.source_ids == [0, 3]
    with pytest.raises(ValueError, match=r"environments: \{'b': 1\}. The data's sources: 0 \(Env-A\), 3 \(Env-B\)$"):
        model.learn_offline(1, eval_env={"a": gym.make("Pendulum-v1")}, eval_sources={"a": 3, "b": 1})
    assert model.num_timesteps == 0  # refused before any update
    model.learn_offline(2, log_interval=0)  # no eval_sources: nothing to check, it trains
    assert model.num_timesteps == 2
    # a model with one actor checks nothing here (MultiEnvEvalCallback refuses sources without per-source actors)
    single = CRR.from_offline_data(pendulum_data(60), env=gym.make("Pendulum-v1"), **SMALL)
    single._check_eval_sources({"a": 7})


def test_the_speed_logged_is_this_calls_updates_over_its_seconds(tmp_path, monkeypatch):
    """A continued run of 3 updates (after 4) that the clock says took 0.25 s logs 12 updates per second."""
    import csv
    import types

    from stable_baselines3.common.logger import configure

    from sb3_lifelong.common import offline

    model = CRR.from_offline_data(pendulum_data(60), env=gym.make("Pendulum-v1"), **SMALL)
    model.learn_offline(4, log_interval=0)
    clock = iter([10_000_000_000, 10_250_000_000])  # ns: the call's start, then its one dump
    monkeypatch.setattr(offline, "time", types.SimpleNamespace(time_ns=lambda: next(clock)))
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn_offline(3, log_interval=7, reset_num_timesteps=False)  # one dump, at update 7
    with open(tmp_path / "progress.csv", newline="") as handle:
        (row,) = list(csv.DictReader(handle))
    assert (row["time/updates"], row["time/updates_per_second"], row["time/time_elapsed"]) == ("7", "12", "0")
    assert row["train/n_updates"] == "7"
