"""benchmarks/studies/mpo_1m/mpo_1m.py: one resumable run with seeded deterministic evaluations, and its report read
by the registered rules."""

import csv
import json

import numpy as np
import pytest
from testkit import benchmark_module


@pytest.fixture
def bench():
    return benchmark_module("mpo_1m")


def rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_run_resumes_from_its_checkpoint_and_drops_later_rows(bench, tmp_path):
    common = ["--algo", "mpo", "--env", "Pendulum-v1", "--seed", "3", "--eval-every", "400", "--checkpoint-every", "400"]
    common += [
        "--net-arch",
        "16",
        "16",
        "--eval-episodes",
        "2",
        "--runs",
        str(tmp_path / "runs"),
        "--results",
        str(tmp_path / "res"),
    ]
    bench.main(["run", *common, "--steps", "1200"])
    name = bench.run_name("mpo", "Pendulum-v1", 3, None)
    csv_path = tmp_path / "res" / f"{name}.csv"
    first = rows(csv_path)
    assert [int(row["timesteps"]) for row in first] == [0, 400, 800, 1200]
    assert [int(row["updates"]) for row in first] == [0, 0, 0, 50]  # (1200 - 1000 warm-up) / 4: Acme's ratio
    assert all(int(row["episodes"]) == 2 and float(row["mean_length"]) == 200 for row in first)
    # an evaluation written after the last checkpoint (a run killed before its next one) is evaluated again
    with open(csv_path, "a", newline="") as handle:
        csv.writer(handle).writerow([1400, 100, 0.0, 0.0, 200, 0, "nan", 2, 99.0])
    bench.main(["run", *common, "--steps", "1600"])
    resumed = rows(csv_path)
    assert [int(row["timesteps"]) for row in resumed] == [0, 400, 800, 1200, 1600]
    assert [int(row["updates"]) for row in resumed][-1] == 150
    assert resumed[:4] == first
    meta = json.loads((tmp_path / "res" / f"{name}.json").read_text())
    assert [machine["from_timesteps"] for machine in meta["machines"]] == [0, 1200]
    assert meta["settings"] == {
        "train_freq": 4,
        "gradient_steps": 1,
        "updates_per_step": 0.25,
        "n_steps": 4,
        "batch_size": 256,
        "learning_rate": 3e-4,
        "net_arch": [16, 16],
    }
    with pytest.raises(SystemExit, match="multiple of --eval-every"):
        bad = list(common)
        bad[bad.index("--checkpoint-every") + 1] = "700"
        bench.main(["run", *bad, "--steps", "1600"])


def test_evaluation_episodes_are_seeded_and_deterministic(bench):
    from sb3_lifelong import MPO
    from sb3_lifelong.mpo.presets import acme_mujoco

    env = bench.make_env("Pendulum-v1", None)
    model = MPO("MlpPolicy", env, seed=0, **acme_mujoco(policy_kwargs={"net_arch": [16]}))
    first, second = bench.evaluate(model, env, 3), bench.evaluate(model, env, 3)
    assert first == {**second, "mean_distance": first["mean_distance"]} and np.isnan(first["mean_distance"])
    assert first["falls"] == 0 and first["mean_length"] == 200


def write_run(folder, algo, env, seed, finals):
    name = bench_name = f"{algo}_{env}_s{seed}"
    meta = {"algo": algo, "env": env, "seed": seed, "steps": 1_000_000, "eval_episodes": 10, "appended": None}
    meta["machines"] = [{"from_timesteps": 0, "cpu": "test CPU", "cpu_flags": []}]
    (folder / f"{name}.json").write_text(json.dumps(meta))
    with open(folder / f"{bench_name}.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(benchmark_module("mpo_1m").FIELDS)
        for k in range(101):
            value = finals if k >= 91 else 0.0  # the last 10 evaluations hold the final return
            writer.writerow([k * 10_000, k * 2500, value, 0, 1000, 0, "nan", 10, k * 10.0])


@pytest.mark.parametrize(
    "mpo, sac, reading",
    [
        ((9000, 9100, 9200), (9000, 9000, 9000), "holds"),
        ((5000, 5100, 5200), (9000, 9000, 9000), "fails"),
        ((9000, 4000, 9400), (9000, 9000, 9000), "inconclusive"),
    ],
)
def test_report_reads_m1_and_m2_by_the_registered_rules(bench, tmp_path, mpo, sac, reading):
    for seed, (mine, theirs) in enumerate(zip(mpo, sac)):
        write_run(tmp_path, "mpo", "HalfCheetah-v5", seed, mine)
        write_run(tmp_path, "sac", "HalfCheetah-v5", seed, theirs)
    readings = {r["claim"]: r for r in bench.read_claims(bench.load_runs(tmp_path))}
    assert readings["M1"]["reading"] == reading and readings["M1"]["n"] == 3
    assert readings["M1"]["bound"] == pytest.approx(-900.0)  # 10 % of SAC's mean final return
    assert readings["M1"]["mean"] == pytest.approx(np.mean(np.subtract(mpo, sac)))
    # M2: 0.9 x the zoo's 9,535 = 8,581.5; SAC's 9,000 on every seed is above it (sd 0: a zero-width interval)
    assert readings["M2 sac"]["reading"] == "holds" and readings["M2 sac"]["bound"] == pytest.approx(8581.5)
    bench.main(["report", "--results", str(tmp_path), "--out", str(tmp_path)])
    text = (tmp_path / "results.md").read_text()
    assert "| HalfCheetah-v5 | M1 | 3 |" in text and reading in text and (tmp_path / "curves.png").stat().st_size > 0


def test_a_run_that_has_not_finished_has_no_final_return(bench, tmp_path):
    write_run(tmp_path, "mpo", "Hopper-v5", 0, 1000.0)
    meta = json.loads((tmp_path / "mpo_Hopper-v5_s0.json").read_text())
    (tmp_path / "mpo_Hopper-v5_s0.json").write_text(json.dumps({**meta, "steps": 2_000_000}))
    (run,) = bench.load_runs(tmp_path)
    assert not run["finished"] and np.isnan(bench.final_return(run))


def test_the_op3_stage1_rule_picks_the_shortest_length_every_seed_meets(bench, tmp_path):
    fields = bench.FIELDS
    for seed, walks_from in ((0, 250_000), (1, 290_000)):
        name = f"mpo_OP3Walk-v0_hip_deformation_s{seed}"
        meta = {"algo": "mpo", "env": "sb3_lifelong/OP3Walk-v0", "seed": seed, "steps": 500_000, "eval_episodes": 10}
        meta["machines"] = [{"from_timesteps": 0, "cpu": "test CPU", "cpu_flags": []}]
        (tmp_path / f"{name}.json").write_text(json.dumps(meta))
        with open(tmp_path / f"{name}.csv", "w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(fields)
            for k in range(51):
                walking = k * 10_000 >= walks_from
                writer.writerow([k * 10_000, k * 2500, 1000, 0, 1000, 0 if walking else 4, 3.0 if walking else 0.1, 10, k])
    lines = bench.stage1_rule(bench.load_runs(tmp_path))
    # at 300k seed 1 has walked for two of the three evaluations ending there: mean distance 2.03, falls 1.33 > 1
    assert "| 300k | s0: 0.0 / 3.00; s1: 1.3 / 2.03 | no |" in lines
    assert "| 400k | s0: 0.0 / 3.00; s1: 0.0 / 3.00 | yes |" in lines
    assert lines[-1] == "Stage-1 length by the rule: 400k"


def test_the_queue_runs_what_is_pending_in_order_and_a_held_run_is_refused(bench, tmp_path, monkeypatch, capsys):
    """Pending: the registered runs that reached --steps neither in --results nor in the committed results; a run is
    one command at a time (its lock)."""
    committed, results = tmp_path / "committed", tmp_path / "res"
    committed.mkdir()
    results.mkdir()
    monkeypatch.setattr(bench, "RESULTS", committed)
    monkeypatch.setattr(bench, "REGISTERED", [("mpo", "Pendulum-v1", 0), ("sac", "Pendulum-v1", 0), ("mpo", "Pendulum-v1", 1)])
    bench._write_rows(committed / "mpo_Pendulum-v1_s0.csv", [{"timesteps": 400}])  # done, committed
    bench._write_rows(results / "sac_Pendulum-v1_s0.csv", [{"timesteps": 200}])  # stopped half-way
    assert bench.pending(results, 400) == [("sac", "Pendulum-v1", 0), ("mpo", "Pendulum-v1", 1)]
    bench.main(["queue", "--runs", str(tmp_path / "runs"), "--results", str(results), "--steps", "400", "--dry-run"])
    assert "2 runs pending: sac_Pendulum-v1_s0, mpo_Pendulum-v1_s1" in capsys.readouterr().out
    # --limit: the first pending runs only (those a session's time allows)
    bench.main(
        ["queue", "--runs", str(tmp_path / "runs"), "--results", str(results), "--steps", "400", "--dry-run", "--limit", "1"]
    )
    assert "starting the first 1: sac_Pendulum-v1_s0\n" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        bench.main(["queue", "--runs", str(tmp_path / "runs"), "--limit", "0"])
    # one run to 400 steps through the queue (a command of its own); then nothing is pending
    monkeypatch.setattr(bench, "REGISTERED", [("mpo", "Pendulum-v1", 1)])
    bench.main(["queue", "--runs", str(tmp_path / "runs"), "--results", str(results), "--steps", "400", "--poll", "0.5"])
    assert "mpo_Pendulum-v1_s1 ended (exit status 0)" in capsys.readouterr().out
    assert [int(row["timesteps"]) for row in rows(results / "mpo_Pendulum-v1_s1.csv")] == [0, 400]
    assert bench.pending(results, 400) == []
    # a run held by another command is refused, and nothing of it is written
    import fcntl

    folder = tmp_path / "runs" / "mpo_Pendulum-v1_s2"
    folder.mkdir(parents=True)
    with open(folder / "run.lock", "a") as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(SystemExit, match="mpo_Pendulum-v1_s2 is being run by another command"):
            held_run = ["run", "--algo", "mpo", "--env", "Pendulum-v1", "--seed", "2", "--steps", "400"]
            bench.main([*held_run, "--runs", str(tmp_path / "runs"), "--results", str(results)])
    assert not (results / "mpo_Pendulum-v1_s2.csv").exists()
