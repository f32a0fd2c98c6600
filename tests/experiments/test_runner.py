"""A study as a graph of jobs: order, parallel workers, skip-finished, a failed job re-run alone, Ray and a pool."""

import os
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch as th
from testkit import flat_params

from sb3_lifelong import BC, CRR, LifelongReplayBuffer
from sb3_lifelong.experiments import PRESETS
from sb3_lifelong.experiments.runner import job_graph, run_study

TINY = PRESETS["tiny"]
JOBS = ["collect", "distill_CRR_exp_beta1", "distill_BC"]


def test_job_graph_puts_collection_first():
    graph = job_graph(TINY, [0, 1], JOBS)
    assert [job.key for job in graph] == [f"seed_{s}/{j}" for s in (0, 1) for j in JOBS]
    for job in graph:
        assert job.after == (() if job.name == "collect" else (f"seed_{job.seed}/collect",))
    assert len(job_graph(TINY, [3])) == len(TINY.jobs())


def test_process_pool_skip_finished_and_rerun_failed(tmp_path):
    out = str(tmp_path)
    lines: list[str] = []
    results = run_study(TINY, [0, 1], out, workers=2, backend="process", jobs=JOBS, log=lines.append)
    assert all(r["ran"] and r["error"] is None for r in results.values()) and len(results) == 6
    assert any("process pool of 2" in line for line in lines)
    # everything done: a second run runs nothing
    again = run_study(TINY, [0, 1], out, workers=2, backend="process", jobs=JOBS, log=lines.append)
    assert not any(r["ran"] for r in again.values())
    # one student lost (crashed) and one seed's buffer unreadable: the lost one re-runs, the broken one fails alone
    (tmp_path / "seed_1" / "distill_BC" / "done.json").unlink(missing_ok=True)
    manifest = tmp_path / "seed_0" / "buffer" / "manifest.json"
    saved = manifest.read_bytes()
    manifest.write_text("{broken")
    (tmp_path / "seed_0" / "distill_CRR_exp_beta1" / "done.json").unlink()
    lines.clear()
    third = run_study(TINY, [0, 1], out, workers=2, backend="process", jobs=JOBS, log=lines.append)
    assert third["seed_1/distill_BC"]["ran"] and third["seed_1/distill_BC"]["error"] is None
    assert "Traceback" in third["seed_0/distill_CRR_exp_beta1"]["error"]
    assert any(line.startswith("[FAILED] seed_0/distill_CRR_exp_beta1") for line in lines)
    assert sum(r["ran"] for r in third.values()) == 1
    manifest.write_bytes(saved)
    fourth = run_study(TINY, [0, 1], out, workers=2, backend="process", jobs=JOBS, log=lines.append)
    assert [key for key, r in fourth.items() if r["ran"]] == ["seed_0/distill_CRR_exp_beta1"]


def test_a_failed_collection_blocks_its_seed_only(tmp_path):
    (tmp_path / "seed_0").mkdir()
    (tmp_path / "seed_0" / "collect").write_text("not a directory")  # collect cannot create its directory
    lines: list[str] = []
    results = run_study(TINY, [0, 1], str(tmp_path), workers=2, backend="process", jobs=JOBS[:2], log=lines.append)
    assert results["seed_0/collect"]["error"]
    assert results["seed_0/distill_CRR_exp_beta1"]["error"].startswith("not run")
    assert results["seed_1/distill_CRR_exp_beta1"]["ran"]
    assert any(line.startswith("[not run] seed_0/distill_CRR_exp_beta1") for line in lines)


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="backend"):
        run_study(TINY, [0], str(tmp_path), backend="slurm")
    with pytest.raises(ValueError, match="workers"):
        run_study(TINY, [0], str(tmp_path), workers=0)


def test_ray_local_two_workers(tmp_path, monkeypatch, study):
    # about 30 s beside two training runs on 2 cores (412 s while Ray's workers ran at niceness 15)
    pytest.importorskip("ray", reason='Ray is not installed (pip install "sb3_lifelong[cluster]")')
    monkeypatch.delenv("RAY_worker_niceness", raising=False)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    lines: list[str] = []
    results = run_study(TINY, [0], str(tmp_path), workers=2, backend="ray", jobs=JOBS, log=lines.append)
    assert all(r["ran"] and r["error"] is None for r in results.values()) and len(results) == 3
    assert any("Ray on this machine, 2 worker(s)" in line for line in lines)
    assert os.environ["RAY_worker_niceness"] == "0"  # the jobs ran at normal priority
    # what Ray's workers computed is what one process computes for the same seed (the session's sequential study):
    # the same transitions, and students with the same weights
    sequential = study[0] / "seed_0"
    with LifelongReplayBuffer.open(tmp_path / "seed_0" / "buffer", read_only=True) as ours:
        with LifelongReplayBuffer.open(sequential / "buffer", read_only=True) as theirs:
            assert ours.size() == theirs.size() == sum(TINY.stage_steps)
            for name in ("observations", "actions", "rewards", "sources"):
                np.testing.assert_array_equal(ours.read_range(name, 0, ours.size()), theirs.read_range(name, 0, theirs.size()))
    for job, algorithm in (("distill_CRR_exp_beta1", CRR), ("distill_BC", BC)):
        mine, theirs = (algorithm.load(root / job / "student.zip") for root in (tmp_path / "seed_0", sequential))
        th.testing.assert_close(flat_params(mine), flat_params(theirs), rtol=0, atol=0, msg=job)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_ray_cluster_by_address(tmp_path, monkeypatch):
    """A study submitted to a Ray head started here (``ray start --head``), as on a cluster (about 60 s)."""
    pytest.importorskip("ray", reason='Ray is not installed (pip install "sb3_lifelong[cluster]")')
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")  # the head and this driver agree: no token on loopback
    monkeypatch.setenv("RAY_worker_niceness", "0")
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    port = _free_port()
    head = subprocess.Popen(
        [sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--block", f"--port={port}",
         "--node-ip-address=127.0.0.1", "--num-cpus=2", "--include-dashboard=false"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:
        lines: list[str] = []
        results = run_study(TINY, [0], str(tmp_path), address=f"127.0.0.1:{port}", jobs=JOBS[::2], log=lines.append)
        assert all(r["ran"] and r["error"] is None for r in results.values()) and len(results) == 2
        assert lines[0] == f"study: 2 jobs on the Ray cluster at 127.0.0.1:{port}"
        assert (tmp_path / "seed_0" / "distill_BC" / "done.json").exists()
    finally:
        os.killpg(head.pid, signal.SIGTERM)  # this head's processes only, not other Ray instances on the machine
        head.wait(120)


def _square(x: int) -> int:
    return x * x


@pytest.mark.parametrize("workers, backend", [(1, "auto"), (2, "process")])
def test_map_parallel_keeps_the_order(workers, backend):
    from sb3_lifelong.experiments.runner import map_parallel

    assert map_parallel(_square, [dict(x=x) for x in range(5)], workers=workers, backend=backend) == [0, 1, 4, 9, 16]
    with pytest.raises(ValueError, match="backend"):
        map_parallel(_square, [], backend="slurm")


def test_a_shared_buffer_that_lost_transitions_is_refused():
    from sb3_lifelong.experiments.sharing import check_shared

    class Counts:
        def __init__(self, counts):
            self.counts = counts

        def source_counts(self):
            return self.counts

    check_shared(Counts({0: 10, 1: 20, 2: 20}), {0: 10, 1: 20, 2: 20})
    with pytest.raises(RuntimeError, match="collectors collected"):
        check_shared(Counts({0: 20, 1: 20, 2: 20}), {0: 10, 1: 20, 2: 20})


def test_study_reusing_another_study_collection(tmp_path):
    """``study --collection-from``: every seed's buffers come from the other study; only the students run."""
    import dataclasses

    from sb3_lifelong.experiments.__main__ import main

    source = tmp_path / "source"
    run_study(TINY, [0, 1], str(source), workers=2, backend="process", jobs=JOBS[:1], log=lambda line: None)
    argv = ["study", "--preset", "tiny", "--seeds", "0", "1", "--output", str(tmp_path / "c51"), "--workers", "2"]
    argv += ["--backend", "process", "--jobs", "distill_BC", "--collection-from", str(source), "--no-report"]
    assert main(argv) == 0
    for seed in (0, 1):
        run_dir = tmp_path / "c51" / f"seed_{seed}"
        assert (run_dir / "buffer").is_symlink() and (run_dir / "distill_BC" / "done.json").exists()
        assert os.path.getmtime(run_dir / "collect" / "stage1.zip") == os.path.getmtime(
            source / f"seed_{seed}" / "collect" / "stage1.zip"
        )  # copied, not collected again
    with pytest.raises(ValueError, match="other settings"):
        run_study(dataclasses.replace(TINY, learning_rate=0.5), [0], str(tmp_path / "lr"), collection_from=str(source))
