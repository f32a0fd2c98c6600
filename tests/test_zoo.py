"""MPO and CRR from rl-zoo3: train and enjoy through the zoo's own commands, with this package's hyperparameters."""

import os
import subprocess
import sys

import pytest
import yaml

from sb3_lifelong.zoo import ALGORITHMS, hyperparams_file

pytest.importorskip("rl_zoo3", reason="rl-zoo3 is not installed (pip install sb3_lifelong[extra])")


def zoo(*args: str, cwd) -> str:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [sys.executable, "-m", "sb3_lifelong.zoo", *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=600
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    return result.stdout


@pytest.mark.parametrize("algo", sorted(ALGORITHMS))
def test_train_and_enjoy(tmp_path, algo):
    out = zoo("train", "--algo", algo, "--env", "Pendulum-v1", "-n", "300", "-f", "logs", "--eval-freq", "-1", cwd=tmp_path)
    assert str(hyperparams_file(algo)) in out  # the package's hyperparameter file was used
    run = tmp_path / "logs" / algo / "Pendulum-v1_1"
    assert (run / "Pendulum-v1.zip").exists()
    assert "learning_starts" in (run / "Pendulum-v1" / "config.yml").read_text()
    zoo("enjoy", "--algo", algo, "--env", "Pendulum-v1", "-f", "logs", "-n", "50", "--no-render", cwd=tmp_path)


def test_hyperparameter_files_cover_the_benchmarked_tasks():
    for algo in ALGORITHMS:
        params = yaml.safe_load(hyperparams_file(algo).read_text())
        for env_id in ("Hopper-v5", "Walker2d-v5", "HalfCheetah-v5", "Pendulum-v1"):
            assert params[env_id]["policy"] == "MlpPolicy" and params[env_id]["n_timesteps"] > 0
    with pytest.raises(ValueError, match="no hyperparameters"):
        hyperparams_file("ppo")


def test_usage_without_a_command(capsys):
    from sb3_lifelong.zoo.__main__ import main

    with pytest.raises(SystemExit, match="usage"):
        main([])


def test_help_exits_zero(tmp_path):
    help_text = zoo("--help", cwd=tmp_path)
    assert "record-video" in help_text
    assert "``" not in help_text and ":class:" not in help_text  # plain text, not the docstring's reStructuredText
    assert "--algo" in zoo("record-video", "--help", cwd=tmp_path)  # the zoo's own arguments
    with pytest.raises(SystemExit, match="unknown command 'trian'"):
        from sb3_lifelong.zoo.__main__ import main

        main(["trian"])


LIFELONG_YML = """
Hopper-v5:
  n_timesteps: 400
  policy: 'MlpPolicy'
  learning_starts: 100
  batch_size: 32
  num_samples: 8
  policy_kwargs: "dict(net_arch=[32, 32])"
  normalize: "dict(norm_obs=True, norm_reward=False)"
  replay_buffer_class: sb3_lifelong.LifelongReplayBuffer
  replay_buffer_kwargs: "dict(path='lifetime')"
  env_wrapper:
    - sb3_lifelong.envs.DynamicsSchedule:
        stages: [{}, {hip_deformation: 0.3}]
        switch_at: [200]
        append_params: true
  callback:
    - sb3_lifelong.zoo.StageEvalCallback:
        env_id: Hopper-v5
        stages: [{}, {hip_deformation: 0.3}]
        append_params: true
        eval_freq: 200
        n_eval_episodes: 1
        log_path: stages.csv
"""


def test_two_stage_run_into_the_lifetime_buffer_from_a_hyperparameter_file(tmp_path):
    """The docs' recipe at a tiny budget: the lifetime buffer, DynamicsSchedule and the stage evaluations from yaml."""
    from sb3_lifelong import LifelongReplayBuffer

    (tmp_path / "lifelong.yml").write_text(LIFELONG_YML)
    zoo(
        "train",
        "--algo",
        "mpo",
        "--env",
        "Hopper-v5",
        "-conf",
        "lifelong.yml",
        "-f",
        "logs",
        "--eval-freq",
        "-1",
        cwd=tmp_path,
    )
    buffer = LifelongReplayBuffer.open(tmp_path / "lifetime", read_only=True)
    counts = buffer.source_counts()
    assert sum(counts.values()) == 400 and set(counts) == {0, 1}  # every transition, tagged with its stage
    assert buffer.sources[1]["metadata"]["hip_deformation"] == pytest.approx(0.3)
    buffer.close()
    with open(tmp_path / "stages.csv") as handle:
        rows = [line.split(",")[:2] for line in handle.read().splitlines()[1:]]
    assert rows == [["200", "Env-A"], ["200", "Env-B"], ["400", "Env-A"], ["400", "Env-B"]]
    zoo("enjoy", "--algo", "mpo", "--env", "Hopper-v5", "-f", "logs", "-n", "50", "--no-render", cwd=tmp_path)


def test_optimize_searches_mpo(tmp_path):
    (tmp_path / "tiny.yml").write_text("Pendulum-v1:\n  n_timesteps: 200\n  policy: 'MlpPolicy'\n  learning_starts: 100\n")
    out = zoo(
        "train", "--algo", "mpo", "--env", "Pendulum-v1", "-conf", "tiny.yml", "-f", "logs", "-optimize",
        "--n-trials", "1", "--n-jobs", "1", "--sampler", "random", "--pruner", "none", "--n-evaluations", "1",
        "--eval-episodes", "1", cwd=tmp_path,
    )  # fmt: skip
    assert "num_samples" in out and "epsilon_mean" in out and "Number of finished trials:  1" in out


@pytest.mark.parametrize("algo", sorted(ALGORITHMS))
def test_samplers_give_the_algorithms_arguments(algo):
    """Each sampled trial builds a model; the converter gives the same arguments from the trial's recorded params."""
    import gymnasium as gym
    import optuna

    from sb3_lifelong.zoo.optimize import CONVERTERS, SAMPLERS

    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(3):
        trial = study.ask()
        kwargs = SAMPLERS[algo](trial, 1, 1, {})
        assert CONVERTERS[algo](trial.params) == kwargs
        assert kwargs["gamma"] == pytest.approx(trial.user_attrs["gamma"])
        model = ALGORITHMS[algo]("MlpPolicy", gym.make("Pendulum-v1"), **kwargs)
        assert model.batch_size == kwargs["batch_size"] and model.policy.layer_norm == kwargs["policy_kwargs"]["layer_norm"]
        study.tell(trial, 0.0)
