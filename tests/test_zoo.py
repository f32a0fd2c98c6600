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
    buffer = LifelongReplayBuffer.open(tmp_path / "logs" / "mpo" / "Hopper-v5_1" / "lifetime", read_only=True)  # the run's
    counts = buffer.source_counts()
    assert sum(counts.values()) == 400 and set(counts) == {0, 1}  # every transition, tagged with its stage
    assert buffer.sources[1]["metadata"]["hip_deformation"] == pytest.approx(0.3)
    buffer.close()
    with open(tmp_path / "stages.csv") as handle:
        rows = [line.split(",")[:2] for line in handle.read().splitlines()[1:]]
    assert rows == [["200", "Env-A"], ["200", "Env-B"], ["400", "Env-A"], ["400", "Env-B"]]
    zoo("enjoy", "--algo", "mpo", "--env", "Hopper-v5", "-f", "logs", "-n", "50", "--no-render", cwd=tmp_path)


SEEDED_YML = """
Pendulum-v1:
  n_timesteps: 30
  policy: 'MlpPolicy'
  learning_starts: 1000
  batch_size: 8
  num_samples: 2
  policy_kwargs: "dict(net_arch=[8])"
  replay_buffer_class: sb3_lifelong.LifelongReplayBuffer
  replay_buffer_kwargs: "dict(path='lifetime', chunk_size=16)"
"""


def test_each_run_of_a_hyperparameter_file_gets_its_own_buffer(tmp_path, monkeypatch):
    """Before: the yaml's path was the same directory for every run, and a second run (--seed 1) refused to add to the
    first run's buffer. Now a relative path is a folder of the run's, and -i continues the saved model's buffer."""
    import argparse

    from rl_zoo3.exp_manager import ExperimentManager

    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.zoo import register

    register()
    register()  # again: patched once
    monkeypatch.chdir(tmp_path)
    (tmp_path / "lifelong.yml").write_text(SEEDED_YML)

    def train(seed: int, **kwargs) -> str:
        manager = ExperimentManager(
            argparse.Namespace(),
            "mpo",
            "Pendulum-v1",
            "logs",
            config="lifelong.yml",
            seed=seed,
            eval_freq=-1,
            verbose=0,
            **kwargs,
        )
        model, _ = manager.setup_experiment()
        manager.learn(model)
        manager.save_trained_model(model)
        model.replay_buffer.close()
        return manager.save_path

    runs = [train(0), train(1)]
    assert [os.path.basename(run) for run in runs] == ["Pendulum-v1_1", "Pendulum-v1_2"]
    buffers = [LifelongReplayBuffer.open(os.path.join(run, "lifetime"), read_only=True) for run in runs]
    assert [buffer.size() for buffer in buffers] == [30, 30] and buffers[0].buffer_id != buffers[1].buffer_id
    assert not (tmp_path / "lifetime").exists()
    continued = train(0, trained_agent=os.path.join(runs[0], "Pendulum-v1.zip"))  # -i: the saved model's buffer goes on
    assert not os.path.exists(os.path.join(continued, "lifetime"))
    assert buffers[0].refresh() == 60 and buffers[1].refresh() == 30
    for buffer in buffers:
        buffer.close()


def test_buffer_paths_of_a_hyperparameter_file():
    from sb3_lifelong.zoo import run_buffer_path

    run = os.path.join("logs", "mpo", "Hopper-v5_2")
    assert run_buffer_path("lifetime", run, 3, "mpo", "Hopper-v5") == os.path.join(run, "lifetime")
    assert run_buffer_path("/data/{algo}/{env}_{seed}", run, 3, "mpo", "Hopper-v5") == "/data/mpo/Hopper-v5_3"
    assert run_buffer_path("/data/{run}", run, 3, "mpo", "Hopper-v5") == "/data/Hopper-v5_2"
    with pytest.raises(ValueError, match=r"names \{user\}: a buffer path may use \{seed\}, \{run\}, \{env\}, \{algo\}"):
        run_buffer_path("/data/{user}", run, 3, "mpo", "Hopper-v5")


def test_each_optimization_trial_gets_its_own_buffer():
    from types import SimpleNamespace

    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.zoo import _objective

    kwargs = dict(path=os.path.join("logs", "run", "lifetime"), chunk_size=16)
    manager = SimpleNamespace(_hyperparams=dict(replay_buffer_class=LifelongReplayBuffer, replay_buffer_kwargs=kwargs))
    seen = []

    def objective(manager, trial):
        seen.append(manager._hyperparams["replay_buffer_kwargs"])
        return 0.0

    for number in (0, 1):
        _objective(objective, manager, SimpleNamespace(number=number))
    assert [entry["path"] for entry in seen] == [os.path.join(kwargs["path"], f"trial_{n}") for n in (0, 1)]
    assert all(entry["chunk_size"] == 16 for entry in seen)
    assert manager._hyperparams["replay_buffer_kwargs"] is kwargs and kwargs["path"] == os.path.join("logs", "run", "lifetime")


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
