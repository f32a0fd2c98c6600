"""benchmarks/studies/paper_op3/paper_op3.py: Stage 1 to Amendment 3's switch and the gate, the four Env-B runs
continued from the Stage-1 agent, their resumes and their files, at seconds' scale (Hopper-v5, which has falls and
``x_position`` and a hip to deform; OP3 itself once, when its model loads)."""

import csv
import json
import math
import os
import pickle

import numpy as np
import pytest
from testkit import benchmark_module

#: a seed's jobs at seconds' scale: Hopper, 16 units, evaluations every 200 steps of 2 episodes
SMALL = ["--env", "Hopper-v5", "--net-arch", "16", "--eval-every", "200", "--checkpoint-every", "400"]
SMALL += ["--eval-episodes", "2", "--end-episodes", "2"]
#: the appended hip deformation of Env-B in the observation: (0.3 - 0) / its obs_scale 0.5
ENV_B_OBS = 0.6


def rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def header(path):
    with open(path, newline="") as handle:
        return next(csv.reader(handle))


def buffer_of(folder):
    """:return: the job's whole buffer as saved in its checkpoint: sources and the observations' last column"""
    with open(folder / "replay.pkl", "rb") as handle:
        buffer = pickle.load(handle)
    n = buffer.size()
    return buffer, buffer.read_range("sources", 0, n), buffer.read_range("observations", 0, n)[:, -1]


@pytest.fixture
def paper():
    return benchmark_module("paper_op3")


def test_the_switch_rule_on_evaluations_written_by_hand(paper):
    def evals(falls, distances, every=10):
        return [
            {"timesteps": k * every, "falls": f, "episodes": 10, "mean_distance": d}
            for k, (f, d) in enumerate(zip(falls, distances))
        ]

    # walking from 20 on; before min_steps (40) the criterion is not read, at 40 the window 20, 30, 40 meets it
    walking = evals([9, 9, 0, 0, 0, 0, 0], [0.1, 0.1, 3, 3, 3, 3, 3])
    assert paper.switch_step(walking, min_steps=40, max_steps=60) == 40
    assert paper.switch_step(walking, min_steps=10, max_steps=60) == 40  # the first window of three that meets it
    # the window's mean, not each evaluation: falls 3, 0, 0 is 1.0 of 10 (at most 1: met); distance 0, 3, 3 is 2.0 m
    assert paper.switch_met(evals([3, 0, 0], [0.0, 3.0, 3.0]))
    assert not paper.switch_met(evals([3, 1, 0], [3.0, 3.0, 3.0]))  # 1.33 falls
    assert not paper.switch_met(evals([0, 0, 0], [1.9, 2.0, 2.0]))  # 1.97 m
    assert not paper.switch_met(evals([0, 0], [3.0, 3.0]))  # fewer than three evaluations
    # never met: Stage 1 goes on until an evaluation reaches max_steps, and ends there
    falling = evals([5] * 7, [3.0] * 7)
    assert paper.switch_step(falling[:6], min_steps=20, max_steps=60) is None
    assert paper.switch_step(falling, min_steps=20, max_steps=60) == 60
    # met only after max_steps: too late
    late = evals([9] * 7 + [0] * 3, [0.0] * 7 + [3.0] * 3)
    assert paper.switch_step(late, min_steps=20, max_steps=60) == 60


def test_the_gate_reads_the_registered_thresholds(paper):
    score = {"falls": 2, "episodes": 20, "mean_distance": 2.0}
    assert paper.gate_passed(score)
    assert not paper.gate_passed({**score, "falls": 3})
    assert not paper.gate_passed({**score, "mean_distance": 1.99})
    assert not paper.gate_passed({**score, "mean_distance": float("nan")})  # no distance: not walking


@pytest.fixture(scope="module")
def learnt(tmp_path_factory):
    """Stage 1 of seed 0 whose criterion and gate anything meets (thresholds opened): it switches at its min-steps."""
    paper = benchmark_module("paper_op3")
    paper.MIN_DISTANCE, paper.FALL_SHARE, paper.GATE_FALL_SHARE = -math.inf, 1.0, 1.0
    root = tmp_path_factory.mktemp("learnt")
    common = [*SMALL, "--seed", "0", "--runs", str(root / "runs"), "--results", str(root / "res")]
    record = paper.main(["stage1", *common, "--min-steps", "1200", "--max-steps", "1600"])
    return paper, common, root, record


def test_stage1_ends_at_the_switch_and_writes_what_its_docstring_says(learnt):
    paper, common, root, record = learnt
    res, runs = root / "res" / "seed_0", root / "runs" / "seed_0" / "stage1"
    # evaluations every 200 steps: the window 800-1200 is the first at or after min-steps; the rule ends it there
    assert [int(row["timesteps"]) for row in rows(res / "stage1.csv")] == list(range(0, 1400, 200))
    assert header(res / "stage1.csv") == paper.STAGE1_FIELDS
    assert record["switch_step"] == 1200 and record["criterion_met"] and record["learnt"]
    assert set(record) >= {"switch_step", "criterion_met", "gate", "learnt", "end", "env", "param", "seed"}
    assert set(record["gate"]) == {"falls", "episodes", "mean_distance", "mean_return", "passed"}
    assert record["gate"]["episodes"] == 2 and record["gate"]["passed"]
    assert set(record["end"]) == {"Env-A", "Env-B"} and record["end"]["Env-A"]["falls"] == record["gate"]["falls"]
    assert record == json.loads((res / "stage1.json").read_text())
    assert (runs / "agent.zip").exists() and (runs / "replay.pkl").exists() and not (runs / "model.zip").exists()
    buffer, sources, appended = buffer_of(runs)
    assert buffer.size() == 1200 and set(sources) == {0} and np.all(appended == 0)  # Env-A, nominal value appended
    assert buffer.sources[0]["name"] == "Env-A"
    # a finished Stage 1 is not run again
    assert paper.main(["stage1", *common, "--min-steps", "1200", "--max-steps", "1600"]) == record
    with pytest.raises(SystemExit, match="--env Hopper-v5, not Walker2d-v5"):
        paper.main(["stage1", *[a if a != "Hopper-v5" else "Walker2d-v5" for a in common]])


@pytest.mark.parametrize("method", ["mpo", "mpo_a"])
def test_mpo_continues_the_same_agent_in_env_b_and_mpo_a_in_env_a(learnt, method):
    paper, common, root, _ = learnt
    meta = paper.main(["env_b", *common, "--method", method, "--steps", "400"])
    res = root / "res" / "seed_0"
    stage1 = rows(res / "stage1.csv")
    mine = rows(res / f"env_b_{method}.csv")
    assert header(res / f"env_b_{method}.csv") == paper.ENV_B_FIELDS
    assert [(int(r["timesteps"]), int(r["stage2_steps"]), r["env"]) for r in mine] == [
        (t, t - 1200, env) for t in (1200, 1400, 1600) for env in ("Env-A", "Env-B")
    ]
    # the same agent: its updates go on from Stage 1's (warm-up 1000 steps, then one per 4 steps), and at L its Env-A
    # evaluation (the same episodes) is Stage 1's last one
    assert int(mine[0]["updates"]) == int(stage1[-1]["updates"]) == 50 and int(mine[-1]["updates"]) == 150
    assert float(mine[0]["mean_return"]) == float(stage1[-1]["mean_return"])
    buffer, sources, appended = buffer_of(root / "runs" / "seed_0" / f"env_b_{method}")
    assert buffer.size() == 1600  # 1200 of Stage 1, then 400
    if method == "mpo":
        assert meta["train_env"] == "Env-B" and list(np.bincount(sources)) == [1200, 400]
        assert np.all(appended[:1200] == 0) and np.allclose(appended[1200:], ENV_B_OBS)
    else:
        assert meta["train_env"] == "Env-A" and set(sources) == {0} and np.all(appended == 0)
    assert meta["finished"] and meta["timesteps"] == 1600 and meta["switch_step"] == 1200 and not meta["forced"]
    assert set(meta["end"]) == {"Env-A", "Env-B"} and meta["end"]["Env-B"]["episodes"] == 2
    assert meta["settings"]["algorithm"] == "MPO" and meta["settings"]["train_freq"] == 4


@pytest.mark.parametrize("method, transform", [("online_crr_exp", "exp"), ("online_crr_indicator", "indicator")])
def test_online_crr_starts_from_the_stage1_policy_and_a_copy_of_its_buffer(learnt, method, transform):
    paper, common, root, _ = learnt
    meta = paper.main(["env_b", *common, "--method", method, "--steps", "400"])
    res = root / "res" / "seed_0"
    mine = rows(res / f"env_b_{method}.csv")
    # the Stage-1 policy's weights: at L, in Env-A, it plays Stage 1's last evaluation (the same episodes)
    stage1 = rows(res / "stage1.csv")
    assert float(mine[0]["mean_return"]) == float(stage1[-1]["mean_return"]) and mine[0]["env"] == "Env-A"
    assert [int(r["updates"]) for r in mine[::2]] == [0, 50, 100]  # its own updates, one per 4 steps from the first
    settings = meta["settings"]
    assert settings["algorithm"] == "CRR" and settings["advantage_transform"] == transform
    assert (settings["train_freq"], settings["gradient_steps"], settings["batch_size"]) == (4, 1, 256)
    assert settings["beta"] == 1.0 and settings["n_steps"] == 1
    buffer, sources, appended = buffer_of(root / "runs" / "seed_0" / f"env_b_{method}")
    assert list(np.bincount(sources)) == [1200, 400] and np.allclose(appended[1200:], ENV_B_OBS)
    assert {k: v["name"] for k, v in buffer.sources.items()} == {0: "Env-A", 1: "Env-B"} and buffer.n_steps == 1
    _, stage1_sources, _ = buffer_of(root / "runs" / "seed_0" / "stage1")
    assert len(stage1_sources) == 1200  # a copy: the Stage-1 buffer is unchanged


def test_status_names_the_switch_the_gate_and_the_jobs(learnt):
    paper, common, root, _ = learnt
    paper.main(["env_b", *common, "--method", "mpo", "--steps", "400"])  # done already or now: the same files
    (line,) = paper.main(["status", "--results", str(root / "res")])
    assert line.startswith("seed_0: L = 1200 (criterion met: True), gate ") and ": learnt; env_b: mpo done" in line


def test_env_b_refuses_without_stage1_or_a_learnt_gate_and_names_why(paper, tmp_path):
    common = [*SMALL, "--seed", "4", "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    with pytest.raises(SystemExit, match="stage 1 of seed 4 has not finished"):
        paper.main(["env_b", *common, "--method", "mpo", "--force"])
    record = paper.main(["stage1", *common, "--min-steps", "200", "--max-steps", "400"])
    # an untrained hopper falls and walks nowhere: Stage 1 runs to max-steps, and the gate fails
    assert record["switch_step"] == 400 and not record["criterion_met"] and not record["gate"]["passed"]
    assert not record["learnt"]
    with pytest.raises(SystemExit, match=r"Env-A not learnt on seed 4 \(switch at 400, criterion met: False; gate: 2 falls"):
        paper.main(["env_b", *common, "--method", "online_crr_exp"])
    assert not (tmp_path / "res" / "seed_4" / "env_b_online_crr_exp.csv").exists()
    meta = paper.main(["env_b", *common, "--method", "mpo_a", "--steps", "200", "--force"])
    assert meta["forced"] and not meta["stage1_learnt"] and meta["finished"]


def kill_at(paper, monkeypatch, calls):
    """Make the ``calls``-th evaluation raise, as a job killed there."""
    real, count = paper.evaluate, [0]

    def evaluate(*args, **kwargs):
        count[0] += 1
        if count[0] == calls:
            raise KeyboardInterrupt("killed")
        return real(*args, **kwargs)

    monkeypatch.setattr(paper, "evaluate", evaluate)
    return real


def test_a_killed_stage1_resumes_from_its_checkpoint_and_drops_later_rows(paper, tmp_path, monkeypatch):
    common = [*SMALL, "--seed", "1", "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    common += ["--min-steps", "1000", "--max-steps", "1200"]
    real = kill_at(paper, monkeypatch, 5)  # evaluations at 0, 200, 400 (checkpoint), 600; killed at 800
    with pytest.raises(KeyboardInterrupt):
        paper.main(["stage1", *common])
    csv_path = tmp_path / "res" / "seed_1" / "stage1.csv"
    before = rows(csv_path)
    assert [int(r["timesteps"]) for r in before] == [0, 200, 400, 600]
    monkeypatch.setattr(paper, "evaluate", real)
    with pytest.raises(SystemExit, match="checkpoint ran with --max-steps 1200, not 1400"):  # the rule stays
        paper.main(["stage1", *common[:-1], "1400"])
    paper.main(["stage1", *common])
    after = rows(csv_path)
    assert [int(r["timesteps"]) for r in after] == [0, 200, 400, 600, 800, 1000, 1200]  # 600 evaluated again
    assert after[:3] == before[:3] and after[3]["wall_s"] != before[3]["wall_s"]
    runs = json.loads((tmp_path / "res" / "seed_1" / "stage1_runs.json").read_text())
    assert [m["from_timesteps"] for m in runs["machines"]] == [0, 400]
    assert int(after[-1]["updates"]) == 50  # (1200 - 1000) / 4: the resumed agent kept its count


@pytest.mark.parametrize("method", ["mpo", "online_crr_exp"])
def test_a_killed_env_b_job_resumes_from_its_checkpoint(paper, tmp_path, monkeypatch, method):
    common = [*SMALL, "--seed", "2", "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    paper.main(["stage1", *common, "--min-steps", "200", "--max-steps", "400"])
    # two evaluations (Env-A, Env-B) per point: at L, 200, 400 (checkpoint), 600; killed at 800's Env-A
    real = kill_at(paper, monkeypatch, 9)
    with pytest.raises(KeyboardInterrupt):
        paper.main(["env_b", *common, "--method", method, "--steps", "800", "--force"])
    csv_path, json_path = (tmp_path / "res" / "seed_2" / f"env_b_{method}.{ext}" for ext in ("csv", "json"))
    assert [int(r["stage2_steps"]) for r in rows(csv_path)] == [0, 0, 200, 200, 400, 400, 600, 600]
    assert not json.loads(json_path.read_text())["finished"]
    monkeypatch.setattr(paper, "evaluate", real)
    meta = paper.main(["env_b", *common, "--method", method, "--steps", "800", "--force"])
    assert [int(r["stage2_steps"]) for r in rows(csv_path)] == [s for s in (0, 200, 400, 600, 800) for _ in "AB"]
    assert meta["finished"] and meta["timesteps"] == 1200 and [m["from_timesteps"] for m in meta["machines"]] == [400, 800]
    buffer, sources, _ = buffer_of(tmp_path / "runs" / "seed_2" / f"env_b_{method}")
    assert list(np.bincount(sources)) == [400, 800] and type(buffer).__name__ == "LifelongReplayBuffer"
    assert meta["settings"]["algorithm"] == ("MPO" if method == "mpo" else "CRR")
    # MPO warms up for its first 1000 steps of life (Stage 1 counts), a CRR updates from its first step; one per 4
    assert int(rows(csv_path)[-1]["updates"]) == (50 if method == "mpo" else 200)


def test_op3_stage1_and_env_b_append_the_hip(paper, tmp_path):
    if not os.environ.get("MENAGERIE_ROOT"):
        pytest.skip("OP3 needs MENAGERIE_ROOT (mujoco-menagerie's robotis_op3)")
    try:
        paper.make_env(paper.OP3, paper.PARAM).reset(seed=0)
    except Exception as error:  # any reason the model does not load
        pytest.skip(f"the OP3 model cannot be loaded: {error}")
    common = ["--seed", "0", "--net-arch", "16", "--eval-every", "200", "--checkpoint-every", "200"]
    common += [
        "--eval-episodes",
        "1",
        "--end-episodes",
        "1",
        "--runs",
        str(tmp_path / "runs"),
        "--results",
        str(tmp_path / "res"),
    ]
    record = paper.main(["stage1", *common, "--min-steps", "200", "--max-steps", "200"])
    assert record["env"] == paper.OP3 and record["switch_step"] == 200
    paper.main(["env_b", *common, "--method", "mpo", "--steps", "200", "--force"])
    _, sources, appended = buffer_of(tmp_path / "runs" / "seed_0" / "env_b_mpo")
    assert list(np.bincount(sources)) == [200, 200]
    assert np.all(appended[:200] == 0) and np.allclose(appended[200:], ENV_B_OBS)
