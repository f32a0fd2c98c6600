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
