"""verbose=1 says what happens in a few lines (about one per evaluation); SB3's tables of every logged value are verbose=2."""

import gymnasium as gym
import pytest
from stable_baselines3.common.logger import configure

from sb3_lifelong import CRR, MPO
from sb3_lifelong.evaluation.callbacks import MultiEnvEvalCallback

SMALL = dict(policy_kwargs=dict(net_arch=[16]), batch_size=16, learning_starts=20, num_samples=4, seed=0)


def short(**kwargs) -> gym.Env:
    return gym.make("Pendulum-v1", max_episode_steps=20, **kwargs)


def table_lines(out: str) -> list[str]:
    return [line for line in out.splitlines() if line.startswith("|")]


@pytest.mark.parametrize("verbose", [1, 2])
def test_verbose_one_prints_evaluations_not_tables(verbose, capsys):
    model = MPO("MlpPolicy", short(), verbose=verbose, **SMALL)
    envs = {"Env-A": short(), "Env-B": short(g=5.0)}
    callback = MultiEnvEvalCallback(envs, eval_freq=20, n_eval_episodes=1, verbose=1)
    model.learn(80, log_interval=1, callback=callback)  # four 20-step episodes: four dumps of the training values
    student = model.distill(CRR, total_updates=20, eval_env=envs, eval_freq=10, n_eval_episodes=1, log_interval=5)
    out = capsys.readouterr().out
    evaluations = [line for line in out.splitlines() if line.startswith("Eval at ")]
    assert len(evaluations) == 4 + 2  # one line per evaluation: 4 online, 2 of the student
    assert "Env-A" in evaluations[0] and "Env-B" in evaluations[0] and "mean over environments" in evaluations[0]
    if verbose == 1:
        assert table_lines(out) == [] and len(out.splitlines()) < 15, out
    else:
        assert any("train/" in line for line in table_lines(out))
    assert student.num_timesteps == 20


def test_a_logger_given_by_the_user_keeps_its_stdout(capsys):
    model = MPO("MlpPolicy", short(), verbose=1, **SMALL)
    model.set_logger(configure(None, ["stdout"]))
    model.learn(40, log_interval=1)
    assert table_lines(capsys.readouterr().out)


def test_a_teacher_that_prints_only_has_a_student_that_prints(capsys):
    """A teacher whose logger has no folder (stdout only): the student prints its tables too, and writes no files."""
    import sys

    from stable_baselines3.common.logger import HumanOutputFormat, Logger

    model = MPO("MlpPolicy", short(), **SMALL)
    model.set_logger(Logger(None, [HumanOutputFormat(sys.stdout)]))
    model.learn(40, log_interval=1)
    capsys.readouterr()
    student = model.distill(CRR, total_updates=10, log_interval=5, verbose=2)
    assert student.logger.get_dir() is None
    assert [type(f) for f in student.logger.output_formats] == [HumanOutputFormat]
    assert any("train/" in line for line in table_lines(capsys.readouterr().out))


def test_verbose_two_prints_the_students_tables_beside_its_files(tmp_path, capsys):
    """A teacher logging to ``tensorboard_log``: the student writes beside it, and prints SB3's tables at verbose=2
    only; a second student of the same name writes into the same folder."""
    model = MPO("MlpPolicy", short(), tensorboard_log=str(tmp_path), **SMALL)
    model.learn(40, log_interval=1)
    capsys.readouterr()
    for verbose, tables in ((1, False), (2, True)):
        student = model.distill(CRR, total_updates=10, log_interval=5, verbose=verbose, tb_log_name="student")
        assert student.logger.get_dir() == str(tmp_path / "MPO_1" / "student")
        assert any("train/" in line for line in table_lines(capsys.readouterr().out)) is tables, verbose


def test_a_teacher_that_never_learnt_leaves_the_student_its_own_logs(tmp_path):
    """A teacher with a ``tensorboard_log`` but no logger yet (it never called learn) has no folder to follow: the
    student logs into the tensorboard folder on its own, as a model given that folder does."""
    model = MPO("MlpPolicy", short(), tensorboard_log=str(tmp_path), **SMALL)
    env = short()
    obs, _ = env.reset(seed=0)
    for _ in range(40):
        action = env.action_space.sample()
        next_obs, reward, terminated, truncated, _ = env.step(action)
        model.replay_buffer.add(obs[None], next_obs[None], action[None], [reward], [terminated], [{}])
        obs = next_obs if not (terminated or truncated) else env.reset()[0]
    assert getattr(model, "_logger", None) is None
    student = model.distill(CRR, total_updates=10, log_interval=5, tb_log_name="student")
    assert student.logger.get_dir() == str(tmp_path / "student_1")
