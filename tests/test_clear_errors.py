"""Mistakes of a new user get a clear message naming the problem (and the path), not a traceback from deep inside."""

import json

import numpy as np
import pytest
from gymnasium import spaces

from sb3_lifelong import CRR, LifelongReplayBuffer
from sb3_lifelong.distill import distill
from sb3_lifelong.experiments.__main__ import main

OBS = spaces.Box(-1.0, 1.0, (3,), np.float32)
ACT = spaces.Box(-1.0, 1.0, (2,), np.float32)


# ---------------------------------------------------------------------------------------------- experiments CLI
def test_run_with_a_negative_seed_is_refused_before_anything_is_created(tmp_path, capsys):
    """Before: seed_-1/ was created, then numpy's 'Seed must be between 0 and 2**32 - 1' came as a traceback."""
    with pytest.raises(SystemExit) as exited:
        main(["run", "--preset", "tiny", "--seed", "-1", "--output", str(tmp_path / "study")])
    assert exited.value.code == 2
    assert "seeds are ints in [0, 2**32 - 1] (numpy's range), got -1" in capsys.readouterr().err
    assert not (tmp_path / "study").exists()
    with pytest.raises(SystemExit):
        main(["study", "--preset", "tiny", "--seeds", "0", str(2**32), "--output", str(tmp_path / "study")])
    assert "got 4294967296" in capsys.readouterr().err


def test_an_output_that_is_a_file_is_refused(tmp_path, capsys):
    """Before: FileExistsError from mkdir, as a traceback."""
    output = tmp_path / "results.txt"
    output.write_text("my results")
    for command in (["run", "--seed", "0"], ["study", "--seeds", "0"]):
        with pytest.raises(SystemExit) as exited:
            main([*command, "--preset", "tiny", "--output", str(output)])
        assert exited.value.code == 2
        assert f"--output {output} exists and is not a directory" in capsys.readouterr().err
    assert output.read_text() == "my results"


def test_report_on_a_missing_or_empty_directory(tmp_path, capsys):
    """Before: FileNotFoundError of preset.json, as a traceback."""
    with pytest.raises(SystemExit) as exited:
        main(["report", str(tmp_path / "missing")])
    assert exited.value.code == 2 and f"{tmp_path / 'missing'}: no such directory" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as exited:
        main(["report", str(tmp_path / "empty")])
    assert exited.value.code == 2 and "holds no study (no preset.json)" in capsys.readouterr().err
    (tmp_path / "started").mkdir()
    (tmp_path / "started" / "preset.json").write_text(json.dumps({"env_names": ["A", "B"], "stage_steps": [10, 10]}))
    with pytest.raises(SystemExit) as exited:  # a study whose first seed has not finished collecting
        main(["report", str(tmp_path / "started")])
    assert exited.value.code == 1 and "no finished seed in" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------- distill
def two_source_buffer(n: int = 100) -> LifelongReplayBuffer:
    rng = np.random.default_rng(0)
    buffer = LifelongReplayBuffer(10, OBS, ACT, device="cpu")
    for source in (0, 2):
        buffer.set_source(source, name=f"env_{source}")
        for _ in range(n):
            obs = rng.uniform(-1, 1, (1, 3)).astype(np.float32)
            buffer.add(obs, obs, np.full((1, 2), 0.5, np.float32), np.zeros(1), np.zeros(1), [{"stage": source}])
    return buffer


def test_distill_eval_sources_are_checked_before_training():
    """Before: the unknown source failed only at the first evaluation, after eval_freq updates."""
    buffer = two_source_buffer()
    with pytest.raises(ValueError, match=r"does not hold.*\{'Env-B': 7\}\. The data's sources: 0 \(env_0\), 2 \(env_2\)"):
        distill(
            buffer,
            student_class=CRR,
            total_updates=50,
            eval_env={"Env-A": "Pendulum-v1", "Env-B": "Pendulum-v1"},
            eval_freq=40,
            eval_sources={"Env-A": 0, "Env-B": 7},
            actor_per_source=True,
            policy_kwargs=dict(net_arch=[8]),
            batch_size=16,
            seed=0,
        )


def test_learn_offline_eval_sources_are_checked_before_any_update():
    model = CRR.from_offline_data(two_source_buffer(), actor_per_source=True, policy_kwargs=dict(net_arch=[8]), batch_size=16)
    with pytest.raises(ValueError, match=r"\{'Env-B': 1\}"):
        model.learn_offline(
            50, eval_env={"Env-A": "Pendulum-v1", "Env-B": "Pendulum-v1"}, eval_freq=40, eval_sources={"Env-A": 2, "Env-B": 1}
        )
    assert model._n_updates == 0


# ---------------------------------------------------------------------------------------------- d4rl import
def test_from_d4rl_refuses_terminals_that_are_not_0_or_1(tmp_path):
    """Before: terminals=2 was read as True, silently."""
    n = 5
    data = dict(
        observations=np.zeros((n, 3), np.float32),
        actions=np.zeros((n, 2), np.float32),
        rewards=np.zeros(n, np.float32),
        next_observations=np.ones((n, 3), np.float32),
        terminals=np.array([0, 0, 2, 0, 1]),
    )
    with pytest.raises(ValueError, match=r"'terminals' must hold only 0/1"):
        LifelongReplayBuffer.from_d4rl(data, path=tmp_path / "buffer")
    assert not (tmp_path / "buffer").exists()  # nothing created
    with pytest.raises(ValueError, match=r"'timeouts' must hold only 0/1"):
        LifelongReplayBuffer.from_d4rl({**data, "terminals": np.zeros(n, bool), "timeouts": np.full(n, -1)})
