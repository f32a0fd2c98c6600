"""benchmarks/studies/paper_op3/paper_op3.py: Stage 1 to Amendment 3's switch and the gate, the four Env-B runs
continued from the Stage-1 agent, their resumes and their files, at seconds' scale (Hopper-v5, which has falls and
``x_position`` and a hip to deform; OP3 itself once, when its model loads)."""

import csv
import json
import math
import os
import pickle
import re

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
    line, support = paper.main(["status", "--results", str(root / "res")])
    assert support == "support: not swept"
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


# ------------------------------------------------------------------------------------------------ the claims' rules
#: scipy.stats.t.ppf(0.975, 2): the 95 % t quantile with two degrees of freedom (three seeds)
T_975_2 = 4.302652729911275


def test_the_t_interval_and_the_readings_against_hand_computed_numbers(paper):
    # 1, 2, 3: mean 2, sd 1, half-width t(0.975, 2) * 1 / sqrt(3) = 2.4841
    out = paper.read_interval([1.0, 2.0, 3.0], "above", 0.0)
    half = T_975_2 / math.sqrt(3)
    assert out["n"] == 3 and out["mean"] == pytest.approx(2.0) and out["sd"] == pytest.approx(1.0)
    assert out["low"] == pytest.approx(2 - half) and out["high"] == pytest.approx(2 + half)
    assert out["reading"] == "inconclusive"  # [-0.48, 4.48] crosses 0
    assert paper.read_interval([5.0, 6.0, 7.0], "above", 0.0)["reading"] == "holds"  # [3.52, 8.48]
    assert paper.read_interval([-5.0, -6.0, -7.0], "above", 0.0)["reading"] == "fails"
    assert paper.read_interval([5.0, 6.0, 7.0], "below", 0.0)["reading"] == "fails"
    assert paper.read_interval([-5.0, -6.0, -7.0], "below", 0.0)["reading"] == "holds"
    # four seeds 0.5, 0.6, 0.7, 0.6: mean 0.6, sd 0.0816, t(0.975, 3) = 3.1824: [0.470, 0.730], below 0.8 and 0.73
    four = paper.read_interval([0.5, 0.6, 0.7, 0.6], "below", 0.8)
    assert four["high"] == pytest.approx(0.6 + 3.182446305284263 * math.sqrt(0.02 / 3) / 2) and four["reading"] == "holds"
    assert paper.read_interval([0.5, 0.6, 0.7, 0.6], "below", 0.72)["reading"] == "inconclusive"
    # the edges (no spread: the interval is the mean; 0.5 and 0.75 are exact in binary): a bound on the threshold is
    # not on the claimed side (strict), and is on the other
    assert paper.read_interval([0.5] * 3, "below", 0.5)["reading"] == "fails"
    assert paper.read_interval([0.5] * 3, "above", 0.5)["reading"] == "fails"
    assert paper.read_interval([0.5] * 3, "below", 0.75)["reading"] == "holds"
    assert paper.read_interval([0.75] * 3, "above", 0.5)["reading"] == "holds"
    assert paper.read_interval([0.25, 0.5, 0.75], "below", 0.5)["reading"] == "inconclusive"
    # fewer than three testable seeds: not testable, whatever the values
    two = paper.read_interval([5.0, 6.0], "above", 0.0)
    assert two["reading"] == "not testable" and "2 testable seeds" in two["why"]
    with pytest.raises(ValueError, match="'below' or 'above'"):
        paper.read_interval([1.0, 2.0, 3.0], "under", 0.0)


def end(a, b):
    return {"end": {"Env-A": {"mean_return": a}, "Env-B": {"mean_return": b}}, "finished": True}


def seed_jobs(frozen=1000.0, mpo=(600.0, 900.0), mpo_a=(1000.0, 0.0), crr=(800.0, 700.0), exp=(950.0, 850.0),
              ind=(500.0, 800.0), a_only=(1000.0, 100.0), q=(120.0, 100.0)):  # fmt: skip
    """One testable seed's finished jobs, with the end returns (Env-A, Env-B) and C4b's Q given."""
    return {
        "stage1": {"learnt": True, "switch_step": 350_000, **end(frozen, 50.0)},
        "env_b_mpo": {**end(*mpo), "switch_step": 350_000, "timesteps": 1_350_000},
        "env_b_mpo_a": end(*mpo_a),
        "env_b_online_crr_exp": end(*crr),
        "student_exp_combined": {**end(*exp), "q_env_a_rows": 0.0},
        "student_indicator_combined": {**end(*ind), "q_env_a_rows": q[0]},
        "student_indicator_a_only": {**end(*a_only), "q_env_a_rows": q[1]},
    }


def claims(paper, seeds, unfinished=None):
    return {c["claim"]: c for c in paper.claims_from(seeds, unfinished or {})["claims"]}


def test_every_claims_series_is_the_readmes_and_read_by_its_rule(paper):
    seeds = {0: seed_jobs(), 1: seed_jobs(mpo=(500.0, 1000.0)), 2: seed_jobs(mpo=(700.0, 800.0), a_only=(900.0, 0.0))}
    read = claims(paper, seeds)
    # C1: 0.6, 0.5, 0.7, mean 0.6, sd 0.1: [0.352, 0.848] crosses 0.8
    assert read["C1"]["series"] == {0: 0.6, 1: 0.5, 2: 0.7} and read["C1"]["reading"] == "inconclusive"
    assert read["C1"]["high"] == pytest.approx(0.6 + T_975_2 * 0.1 / math.sqrt(3))
    assert read["C1 registered"]["series"] == {0: 0.6, 1: 0.5, 2: 0.7}  # frozen 1000 on every seed
    assert read["C1 registered"]["reading"] == "reported, not read" and read["C1 drift"]["series"] == {0: 1, 1: 1, 2: 1}
    assert read["C2a"]["series"] == {0: 200.0, 1: 300.0, 2: 100.0}  # online CRR exp - MPO, Env-A
    assert read["C2b"]["series"] == {0: 200.0, 1: 300.0, 2: 100.0}  # MPO - online CRR exp, Env-B
    assert read["C3a"]["series"] == {0: 0.95, 1: 0.95, 2: 0.95}  # exp / max(MPO end, frozen) = 950 / 1000
    assert read["C3b"]["series"] == pytest.approx({0: 850 / 900, 1: 0.85, 2: 850 / 800})
    assert read["C4a"]["series"] == pytest.approx({0: 0.5, 1: 0.5, 2: 500 / 900})
    assert read["C4b"]["series"] == {0: 20.0, 1: 20.0, 2: 20.0} and read["C4b"]["reading"] == "holds"
    assert read["C5"]["series"] == pytest.approx({0: 0.95, 1: 0.95, 2: 950 / 900})
    # C3a's denominator is the larger of MPO end and the frozen agent
    seeds[2]["env_b_mpo"] = {**end(1200.0, 800.0), "switch_step": 350_000, "timesteps": 1_350_000}
    assert claims(paper, seeds)["C3a"]["series"][2] == pytest.approx(950 / 1200)


def test_a_ratio_whose_denominator_is_at_most_100_on_any_seed_is_not_testable(paper):
    seeds = {k: seed_jobs() for k in range(3)}
    seeds[1]["env_b_mpo_a"] = end(100.0, 0.0)  # C1's denominator: 100 is not above 100
    read = claims(paper, seeds)
    assert read["C1"]["reading"] == "not testable" and "seeds {1: 100.0}" in read["C1"]["why"]
    assert read["C1"]["series"][1] == 6.0  # reported all the same
    seeds[1]["env_b_mpo_a"] = end(100.5, 0.0)
    assert claims(paper, seeds)["C1"]["reading"] != "not testable"
    # a difference has no denominator: C2a reads negative returns
    seeds = {k: seed_jobs(mpo=(-50.0, 900.0), crr=(-10.0 + k, 700.0)) for k in range(3)}
    assert claims(paper, seeds)["C2a"]["reading"] == "holds"
    seeds = {k: seed_jobs(a_only=(90.0 + k, 0.0)) for k in range(3)}  # C4a's and C5's denominator
    read = claims(paper, seeds)
    assert read["C4a"]["reading"] == read["C5"]["reading"] == "not testable"


def test_c5_is_read_only_where_c4a_holds_and_c2s_trade_off_needs_both(paper):
    # C4a holds (0.5, 0.5, 0.5 below 0.8) and exp recovers (0.95 each, above 0.9): C5 holds
    seeds = {k: seed_jobs() for k in range(3)}
    read = paper.claims_from(seeds, {})
    by = {c["claim"]: c for c in read["claims"]}
    assert by["C4a"]["reading"] == "holds" and by["C5"]["reading"] == "holds"
    assert by["C2a"]["reading"] == by["C2b"]["reading"] == "holds" and read["c2_trade_off"] == "reproduced"
    # no drop (the combined indicator student at 0.9 of the A-only one): C4a fails, C5 is not read
    seeds = {k: seed_jobs(ind=(900.0 + k, 800.0)) for k in range(3)}
    by = claims(paper, seeds)
    assert by["C4a"]["reading"] == "fails" and by["C5"]["reading"] == "not testable" and "C4a holds" in by["C5"]["why"]
    assert by["C5"]["series"] == pytest.approx({0: 0.95, 1: 0.95, 2: 0.95})  # reported, not read
    # an inconclusive C4a is not a drop either
    seeds = {0: seed_jobs(ind=(500.0, 0.0)), 1: seed_jobs(ind=(900.0, 0.0)), 2: seed_jobs(ind=(600.0, 0.0))}
    by = claims(paper, seeds)
    assert by["C4a"]["reading"] == "inconclusive" and by["C5"]["reading"] == "not testable"
    # C2b fails (online CRR learns Env-B faster): no trade-off
    seeds = {k: seed_jobs(crr=(800.0, 1000.0 + k)) for k in range(3)}
    read = paper.claims_from(seeds, {})
    assert read["c2_trade_off"] == "not reproduced"


def test_excluded_seeds_and_missing_jobs_are_named(paper):
    seeds = {k: seed_jobs() for k in range(4)}
    seeds[1]["stage1"] = {"learnt": False, "criterion_met": False, "switch_step": 500_000, **end(10.0, 5.0)}
    seeds[1]["stage1"]["gate"] = {"falls": 20, "episodes": 20, "mean_distance": 0.1}
    del seeds[3]["student_indicator_a_only"]
    read = paper.claims_from(seeds, {3: ["student_indicator_a_only"]})
    assert read["testable"] == [0, 2, 3] and read["excluded"][1].startswith("Env-A not learnt")
    by = {c["claim"]: c for c in read["claims"]}
    assert set(by["C1"]["series"]) == {0, 2, 3} and by["C1"]["n"] == 3
    assert set(by["C4a"]["series"]) == {0, 2} and by["C4a"]["reading"] == "not testable"  # two seeds left
    assert by["C4a"]["missing"] == {3: ["student_indicator_a_only"]}
    assert read["missing"] == {3: {"student_indicator_a_only": "running"}}
    assert read["seeds"][0] == {"seed": 0, "L": 350_000, "env_a_rows": 350_000, "env_b_rows": 1_000_000,
                                "rows_from": "MPO's steps", "ratio": "1:2.86"}  # fmt: skip


# ------------------------------------------------------------------------------------------------ the students
#: a student at seconds' scale: 200 updates, evaluated every 100 (2 episodes), a checkpoint every 100
STUDENT = ["--updates", "200", "--eval-every", "100", "--checkpoint-every", "100"]


@pytest.fixture(scope="module")
def lifetime(learnt):
    """The learnt seed's MPO collection (1200 Env-A rows, then 400 Env-B rows): the students' lifetime buffer."""
    paper, common, _, _ = learnt
    paper.main(["env_b", *common, "--method", "mpo", "--steps", "400"])  # done already or now: the same files
    return learnt


def copy_seed(root, seed, to, new_seed=None):
    """Copy a seed's Stage 1 record and its MPO collection (record and buffer) to another study folder."""
    new_seed = seed if new_seed is None else new_seed
    res, runs = to / "res" / f"seed_{new_seed}", to / "runs" / f"seed_{new_seed}" / "env_b_mpo"
    res.mkdir(parents=True, exist_ok=True)
    runs.mkdir(parents=True, exist_ok=True)
    for name in ("stage1.json", "env_b_mpo.json"):
        (res / name).write_text((root / "res" / f"seed_{seed}" / name).read_text())
    (runs / "replay.pkl").write_bytes((root / "runs" / f"seed_{seed}" / "env_b_mpo" / "replay.pkl").read_bytes())


def test_the_a_only_student_draws_env_a_rows_only_and_c4b_reads_the_same_rows(lifetime):
    paper, common, root, _ = lifetime
    made = {}
    for student in ("indicator_a_only", "indicator_combined"):
        made[student] = paper.main(["student", *common, *STUDENT, "--student", student, "--support-scale", "1"])
    a_only, combined = made["indicator_a_only"], made["indicator_combined"]
    # every row the A-only student drew is an Env-A row: 200 updates of 256, counted from its batches
    assert a_only["rows_per_source"] == {"Env-A": 1200, "Env-B": 0}
    assert a_only["drawn_per_source"] == {"Env-A": 200 * 256, "Env-B": 0} and a_only["a_only"]
    assert combined["rows_per_source"] == {"Env-A": 1200, "Env-B": 400} and not combined["a_only"]
    drawn = combined["drawn_per_source"]
    assert sum(drawn.values()) == 200 * 256 and 0.15 < drawn["Env-B"] / (200 * 256) < 0.35  # 400 of 1600 rows
    assert a_only["buffer_rows"] == combined["buffer_rows"] == {"Env-A": 1200, "Env-B": 400}
    # C4b's rows: the same 1,024 Env-A rows for both, those of the fixed generator
    _, sources, _ = buffer_of(root / "runs" / "seed_0" / "env_b_mpo")
    chosen = paper.q_rows(sources, 0)
    assert len(chosen) == 1024 and len(set(chosen)) == 1024 and np.all(sources[chosen] == 0)
    assert a_only["q_rows"] == combined["q_rows"] == {
        "count": 1024, "seed": paper.Q_ROWS_SEED, "digest": paper.rows_digest(chosen), "first": chosen[:8].tolist()
    }  # fmt: skip
    assert not np.array_equal(paper.q_rows(sources, 1), chosen)  # another seed's buffer: other rows
    assert a_only["q_env_a_rows"] != combined["q_env_a_rows"] and np.isfinite(a_only["q_env_a_rows"])
    # the support: the buffer's reward bounds over 1 - gamma, the same for both, 51 atoms, and the files
    assert a_only["support"] == combined["support"] and a_only["support"]["n_atoms"] == 51
    assert a_only["support"]["from"] == "--support-scale" and a_only["support"]["v_min"] == a_only["support"]["base_v_min"]
    res = root / "res" / "seed_0"
    csv_rows = rows(res / "student_indicator_a_only.csv")
    assert header(res / "student_indicator_a_only.csv") == paper.STUDENT_FIELDS
    assert [(int(r["updates"]), r["env"]) for r in csv_rows] == [(u, e) for u in (100, 200) for e in ("Env-A", "Env-B")]
    assert set(a_only["end"]) == {"Env-A", "Env-B"} and a_only["end"]["Env-A"]["episodes"] == 2
    assert a_only["settings"]["advantage_transform"] == "indicator" and a_only["settings"]["batch_size"] == 256
    assert a_only["finished"] and a_only["switch_step"] == 1200 and a_only["machines"][0]["device"] == "cpu"


def test_a_3x_support_is_three_times_as_wide(paper):
    one, three = paper.scaled_support((-2.0, 5.0), 1), paper.scaled_support((-2.0, 5.0), 3)
    assert one["v_min"] == pytest.approx(-200.0) and one["v_max"] == pytest.approx(500.0)
    assert three["v_min"] == pytest.approx(-600.0) and three["v_max"] == pytest.approx(1500.0)
    assert three["base_v_min"] == one["v_min"]
    assert paper.scaled_support((1.0, 5.0), 3)["v_min"] == 0.0  # the support holds 0 (value_support)


def test_a_registered_student_refuses_without_support_json(lifetime, tmp_path, monkeypatch):
    paper, _, root, _ = lifetime
    copy_seed(root, 0, tmp_path)
    common = [*SMALL, "--seed", "0", "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    support = tmp_path / "res" / "support.json"
    real = paper.load_lifetime_buffer

    def started(args):
        raise AssertionError("a 500k-update student started without a registered support.json")

    monkeypatch.setattr(paper, "load_lifetime_buffer", started)  # a refusal that fails ends here, not in 500k updates
    with pytest.raises(SystemExit, match=re.escape(f"support sweep has not fixed the support ({support} does not exist)")):
        paper.main(["student", *common, "--student", "exp_combined"])  # 500k updates by default
    with pytest.raises(SystemExit, match=r"support\.json does not exist"):
        paper.main(["student", *common, *STUDENT, "--student", "exp_combined"])  # a small one too, without a scale
    assert not (tmp_path / "res" / "seed_0" / "student_exp_combined.csv").exists()
    support.write_text(json.dumps({"choice": 3, "registered": False, "why_not_registered": "100 updates, not 100000"}))
    with pytest.raises(SystemExit, match="is not the registered sweep \\(100 updates, not 100000\\)"):
        paper.main(["student", *common, "--student", "exp_combined"])
    monkeypatch.setattr(paper, "load_lifetime_buffer", real)
    record = paper.main(["student", *common, *STUDENT, "--student", "exp_combined"])  # a small check reads it
    assert record["support"]["scale"] == 3 and record["support"]["from"] == str(support)


def test_a_student_needs_a_finished_mpo_collection(paper, tmp_path):
    common = [*SMALL, "--seed", "3", "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    with pytest.raises(SystemExit, match=r"env_b --method mpo has not finished \(.*env_b_mpo.json does not exist\)"):
        paper.main(["student", *common, *STUDENT, "--student", "exp_combined", "--support-scale", "1"])


def test_a_killed_student_resumes_to_the_same_rows_as_an_uninterrupted_one(lifetime, tmp_path, monkeypatch):
    paper, _, root, _ = lifetime
    runs = {}
    for name in ("whole", "killed"):
        copy_seed(root, 0, tmp_path / name)
        runs[name] = [*SMALL, "--seed", "0", "--runs", str(tmp_path / name / "runs")]
        runs[name] += ["--results", str(tmp_path / name / "res"), "--student", "exp_combined", "--support-scale", "1"]
        runs[name] += ["--updates", "400", "--eval-every", "100", "--checkpoint-every", "200"]
    whole = paper.main(["student", *runs["whole"]])
    real = kill_at(paper, monkeypatch, 7)  # evaluations at 100 (A, B), 200 (A, B; checkpoint), 300; killed at 400's A
    with pytest.raises(KeyboardInterrupt):
        paper.main(["student", *runs["killed"]])
    csv_path = tmp_path / "killed" / "res" / "seed_0" / "student_exp_combined.csv"
    assert [int(r["updates"]) for r in rows(csv_path)] == [100, 100, 200, 200, 300, 300]
    monkeypatch.setattr(paper, "evaluate", real)
    with pytest.raises(SystemExit, match="checkpoint ran with total_updates 400, not 600"):
        paper.main(["student", *runs["killed"][:-5], "600", *runs["killed"][-4:]])
    resumed = paper.main(["student", *runs["killed"]])
    drop = ("wall_s",)
    same = [{k: v for k, v in r.items() if k not in drop} for r in rows(csv_path)]
    assert same == [
        {k: v for k, v in r.items() if k not in drop}
        for r in rows(tmp_path / "whole" / "res" / "seed_0" / "student_exp_combined.csv")
    ]
    assert resumed["drawn_per_source"] == whole["drawn_per_source"] and resumed["end"] == whole["end"]
    assert resumed["q_env_a_rows"] == whole["q_env_a_rows"]
    assert [m["from_updates"] for m in resumed["machines"]] == [0, 200]


def test_the_sweep_reads_the_first_three_testable_seeds_and_fixes_the_wider_mean(lifetime, tmp_path):
    paper, _, root, _ = lifetime
    for seed in (0, 2, 3):  # seed 1 failed the gate: the first three testable seeds are 0, 2 and 3
        copy_seed(root, 0, tmp_path, new_seed=seed)
    failed = tmp_path / "res" / "seed_1"
    failed.mkdir()
    (failed / "stage1.json").write_text(json.dumps({"learnt": False}))
    common = [*SMALL, "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    common += ["--updates", "100", "--eval-every", "100", "--checkpoint-every", "100"]
    assert paper.sweep_seeds(tmp_path / "res") == [0, 2, 3]
    assert paper.main(["sweep", *common, "--seed", "2", "--support-scale", "3"]) is None  # one part: no choice yet
    assert not (tmp_path / "res" / "support.json").exists()
    assert json.loads((tmp_path / "res" / "seed_2" / "sweep_exp_combined_3x.json").read_text())["finished"]
    record = paper.main(["sweep", *common])
    assert record == json.loads((tmp_path / "res" / "support.json").read_text())
    assert record["seeds"] == [0, 2, 3] and set(record["per_seed"]["2"]) == {"1x", "3x"}
    for seed in ("0", "2", "3"):
        for width in ("1x", "3x"):
            done = json.loads((tmp_path / "res" / f"seed_{seed}" / f"sweep_exp_combined_{width}.json").read_text())
            part = record["per_seed"][seed][width]
            assert part["Env-A"] == done["end"]["Env-A"]["mean_return"] and done["updates"] == 100
            assert part["mean"] == pytest.approx((part["Env-A"] + part["Env-B"]) / 2)
            assert done["support"]["scale"] == int(width[0]) and done["settings"]["advantage_transform"] == "exp"
    means = {w: np.mean([record["per_seed"][s][w]["mean"] for s in ("0", "2", "3")]) for w in ("1x", "3x")}
    assert record["mean_over_seeds"] == pytest.approx(means)
    assert record["choice"] == (3 if means["3x"] > means["1x"] else 1)
    assert not record["registered"] and "100 updates, not 100000" in record["why_not_registered"]
    # the rule: fewer than three known testable seeds, or a stage 1 not finished before the third
    (tmp_path / "res" / "seed_3" / "stage1.json").unlink()
    with pytest.raises(SystemExit, match=r"2 are known so far \(\[0, 2\]\); stage 1 of seed 3 has not finished"):
        paper.sweep_seeds(tmp_path / "res")


def test_support_record_breaks_a_tie_to_the_datas_own_width(paper, tmp_path):
    for seed in range(3):
        for scale in (1, 3):
            folder = tmp_path / f"seed_{seed}"
            folder.mkdir(exist_ok=True)
            done = {"finished": True, **end(100.0 * scale if seed == 0 else 100.0, 300.0), "updates": 100_000}
            done.update(support={"v_min": 0.0, "v_max": 1.0}, env=paper.OP3, param=paper.PARAM, net_arch=None)
            done.update(end_episodes=20, stage1_learnt=True)
            (folder / f"sweep_exp_combined_{scale}x.json").write_text(json.dumps(done))
    record = paper.support_record(tmp_path, [0, 1, 2])
    assert record["choice"] == 3 and record["registered"] and record["why_not_registered"] is None
    assert record["mean_over_seeds"] == pytest.approx({"1x": 200.0, "3x": 200.0 + 200.0 / 2 / 3})
    done["end"]["Env-A"]["mean_return"] = 100.0
    (tmp_path / "seed_0" / "sweep_exp_combined_3x.json").write_text(json.dumps(done))
    assert paper.support_record(tmp_path, [0, 1, 2])["choice"] == 1  # a tie: 1x
    (tmp_path / "seed_2" / "sweep_exp_combined_1x.json").unlink()
    assert paper.support_record(tmp_path, [0, 1, 2]) is None


def test_the_report_names_missing_jobs_and_never_crashes(lifetime, tmp_path):
    paper, _, root, _ = lifetime
    copy_seed(root, 0, tmp_path)
    res = tmp_path / "res"
    (res / "seed_0" / "env_b_mpo_a.json").write_text(json.dumps({"finished": False}))  # running
    (res / "seed_1").mkdir()
    (res / "seed_1" / "stage1.csv").write_text("timesteps\n0\n")  # stage 1 running
    report = paper.main(["report", "--results", str(res)])
    text = (res / "claims.md").read_text()
    assert json.loads((res / "claims.json").read_text())["testable"] == [0] == report["testable"]
    assert report["excluded"] == {1: "stage 1 has not finished"} and "- seed 1: stage 1 has not finished" in text
    assert report["missing"][0]["env_b_mpo_a"] == "running" and report["missing"][0]["student_exp_combined"] == "missing"
    assert "- seed 0: env_b_mpo_a (running), env_b_online_crr_exp (missing)" in text
    assert all(c["reading"] in ("not testable", "reported, not read") for c in report["claims"])
    assert "| 0 | 1200 | 1200 | 400 | 1:0.33 | testable |" in text and "Support: not fixed yet" in text
    # a small student is read, and named as not the registered one
    paper.main(["student", *SMALL, "--seed", "0", "--runs", str(tmp_path / "runs"), "--results", str(res), *STUDENT,
                "--student", "indicator_a_only", "--support-scale", "1"])  # fmt: skip
    report = paper.main(["report", "--results", str(res)])
    assert report["unregistered"] == {"seed 0: student_indicator_a_only": "200 updates, support from --support-scale"}
    assert "- seed 0: student_indicator_a_only: 200 updates" in (res / "claims.md").read_text()
    assert "student_indicator_a_only" not in report["missing"][0]
    empty = paper.main(["report", "--results", str(tmp_path / "none")])  # no seed at all: every claim not testable
    assert empty["testable"] == [] and {c["reading"] for c in empty["claims"]} == {"not testable", "reported, not read"}
    lines = paper.main(["status", "--results", str(res)])
    assert lines[-1] == "support: not swept"
