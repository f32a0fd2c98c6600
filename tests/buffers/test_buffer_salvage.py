"""
One damaged chunk no longer makes a whole buffer unreadable: ``check_directory`` / ``python -m sb3_lifelong.buffers
verify`` list the damaged chunks, ``salvage`` copies the intact ones into a new directory. The damaged original is
never written; opening it stays strict.
"""

import os
import runpy
import sys

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError
from sb3_lifelong.buffers.__main__ import main

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)
LAYOUTS = {"single": None, "chunked": 1_000}
ROW_BYTES = {"observations": 12, "next_observations": 12, "actions": 8, "rewards": 4}  # then flags, sources, ...


def make(path, layout, rows=100, n_envs=2):
    """Rows 0..rows-1 (obs[:, 0] = row), n_envs envs per add, chunks of 20 rows: 5 chunks of 10 steps each."""
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=20, capacity=LAYOUTS[layout], device="cpu")
    buffer.set_source(3, "stage_three", {"mass": 1.5})
    for k in range(0, rows, n_envs):
        index = np.arange(k, k + n_envs)
        obs = np.stack([index, -index, index * 0.5], 1).astype(np.float32)
        buffer.add(obs, obs + 1, np.zeros((n_envs, 2), np.float32), index.astype(np.float32), np.zeros(n_envs), [{}] * n_envs)
    buffer.close()


def flip(path, layout, chunk, row=3):
    """Flip a bit of the reward of row ``row`` of chunk ``chunk`` (rows 20 * chunk ...)."""
    if layout == "single":
        name, offset = path / "rewards.bin", (20 * chunk + row) * 4
    else:
        name, offset = path / f"chunk.{20 * chunk:012d}.bin", 20 * (12 + 12 + 8) + row * 4
    data = bytearray(name.read_bytes())
    data[offset] ^= 0x10
    name.write_bytes(bytes(data))


def snapshot(directory):
    return {entry: (directory / entry).read_bytes() for entry in sorted(os.listdir(directory))}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_bit_flip_is_served_by_default_found_by_verify_all_and_salvaged(tmp_path, layout):
    path = tmp_path / "b"
    make(path, layout)
    flip(path, layout, chunk=1)
    before = snapshot(path)
    # documented: verify="last" (the default) does not read earlier chunks, so the flipped reward is served
    served = LifelongReplayBuffer.open(path, read_only=True)
    assert served.read_range("rewards", 23, 24)[0] != 23.0
    with pytest.raises(BufferFormatError, match=r"checksum.*python -m sb3_lifelong\.buffers salvage"):
        LifelongReplayBuffer.open(path, read_only=True, verify="all")  # the default stays strict
    report = LifelongReplayBuffer.check_directory(path)
    assert [(c.start, c.rows) for c in report.damaged] == [(20, 20)]
    assert "checksum mismatch" in report.damaged[0].damage
    assert report.intact_transitions == 80 and report.lost_transitions == 20
    copy, report = LifelongReplayBuffer.salvage(path, tmp_path / "copy", read_only=True, verify="all")
    assert report.copied == 80 and len(report.damaged) == 1
    expected = np.r_[0:20, 40:100]
    np.testing.assert_array_equal(copy.read_range("observations", 0, 80)[:, 0], expected)
    np.testing.assert_array_equal(copy.read_range("rewards", 0, 80), expected)
    assert copy.sources[3] == {"name": "stage_three", "metadata": {"mass": 1.5}}
    assert copy.capacity == LAYOUTS[layout] and copy.observation_space == OBS and copy.action_space == ACT
    assert snapshot(path) == before  # the damaged original was only read (no lock file, no manifest written)


def test_streams_never_chain_across_a_left_out_chunk(tmp_path):
    """Rows after the gap get new stream ids: an n-step return of row 19 (the last before the gap) must not add the
    rewards of rows 41, 43 (after it: the same env, 20 rows later in the copy)."""
    path = tmp_path / "b"
    make(path, "single")
    flip(path, "single", chunk=1)
    copy, _ = LifelongReplayBuffer.salvage(path, tmp_path / "copy", read_only=True, n_steps=3, gamma=0.5, device="cpu")
    streams = copy.read_range("streams", 0, 80)
    assert set(streams[:20].tolist()).isdisjoint(streams[20:].tolist())
    assert len(set(streams[20:].tolist())) == 2  # the two envs, one new id each, the same for every row after the gap
    samples = copy._get_samples(np.array([18, 19, 20, 21]))
    np.testing.assert_allclose(samples.rewards.numpy().ravel(), [18, 19, 40 + 0.5 * 42 + 0.25 * 44, 41 + 0.5 * 43 + 0.25 * 45])
    np.testing.assert_allclose(samples.discounts.numpy().ravel(), [0.5, 0.5, 0.125, 0.125])


@pytest.mark.parametrize("damage", ["missing", "truncated"])
def test_a_missing_or_truncated_chunk_file(tmp_path, damage):
    path = tmp_path / "b"
    make(path, "chunked")
    chunk = path / "chunk.000000000040.bin"
    if damage == "missing":
        chunk.unlink()
    else:
        chunk.write_bytes(chunk.read_bytes()[:100])
    for verify in ("none", "last", "all"):
        with pytest.raises(BufferFormatError, match=r"chunk\.000000000040\.bin.*salvage"):
            LifelongReplayBuffer.open(path, read_only=True, verify=verify)
    assert main(["verify", str(path)]) == 1
    assert main(["salvage", str(path), str(tmp_path / "copy")]) == 1
    copy = LifelongReplayBuffer.open(tmp_path / "copy", read_only=True, verify="all")
    np.testing.assert_array_equal(copy.read_range("rewards", 0, 80), np.r_[0:40, 60:100])


def test_a_truncated_field_file_keeps_the_chunks_before(tmp_path):
    path = tmp_path / "b"
    make(path, "single")
    rewards = path / "rewards.bin"
    rewards.write_bytes(rewards.read_bytes()[: 50 * 4])  # rows 50.. lost: chunks 2 (40-59), 3 and 4
    report = LifelongReplayBuffer.check_directory(path)
    assert [c.start for c in report.damaged] == [40, 60, 80]
    copy, report = LifelongReplayBuffer.salvage(path, tmp_path / "copy", read_only=True)
    np.testing.assert_array_equal(copy.read_range("rewards", 0, 40), np.arange(40))
    assert report.copied == 40


def test_an_evicted_prefix_is_not_copied(tmp_path):
    """With a capacity, only the retained rows are copied (the first chunk's evicted rows are left out)."""
    path = tmp_path / "b"
    buffer = LifelongReplayBuffer(0, OBS, ACT, path=path, chunk_size=20, capacity=50)
    for k in range(100):
        obs = np.full((1, 3), k, np.float32)
        buffer.add(obs, obs, np.zeros((1, 2), np.float32), np.array([k], np.float32), np.zeros(1), [{}])
    buffer.close()
    copy, report = LifelongReplayBuffer.salvage(path, tmp_path / "copy", read_only=True, verify="all")
    assert report.damaged == [] and report.copied == 50
    np.testing.assert_array_equal(copy.read_range("rewards", 0, 50), np.arange(50, 100))


def test_salvage_refuses_to_write_over_anything(tmp_path):
    path = tmp_path / "b"
    make(path, "single")
    with pytest.raises(FileExistsError, match="not an empty directory"):
        LifelongReplayBuffer.salvage(path, path)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError):
        LifelongReplayBuffer.salvage(path, tmp_path / "full")
    assert (tmp_path / "full" / "notes.txt").read_text() == "mine"
    (path / "manifest.json").write_text("{")
    assert main(["verify", str(path)]) == 2
    assert main(["salvage", str(path), str(tmp_path / "copy")]) == 2
    assert not (tmp_path / "copy").exists()


def run_module(monkeypatch, *args):
    """``python -m sb3_lifelong.buffers ARGS``, in this process (a new one would import torch again)."""
    monkeypatch.setattr(sys, "argv", ["python -m sb3_lifelong.buffers", *args])
    monkeypatch.delitem(sys.modules, "sb3_lifelong.buffers.__main__", raising=False)  # imported above: run afresh
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_module("sb3_lifelong.buffers", run_name="__main__", alter_sys=True)
    return exit_info.value.code


def test_command_line(tmp_path, monkeypatch, capsys):
    path = tmp_path / "b"
    make(path, "chunked")
    assert run_module(monkeypatch, "verify", str(path)) == 0
    assert "0 damaged; 100 transitions intact" in capsys.readouterr().out
    flip(path, "chunked", chunk=4)
    assert run_module(monkeypatch, "verify", str(path)) == 1
    out = capsys.readouterr().out
    assert "rows 80 to 99" in out and "checksum mismatch" in out
    assert run_module(monkeypatch, "salvage", str(path), str(tmp_path / "copy"), "--chunk-size", "7") == 1
    assert "copied 80 transitions to" in capsys.readouterr().out
    assert run_module(monkeypatch, "verify", str(tmp_path / "copy")) == 0
    assert run_module(monkeypatch, "verify", str(tmp_path / "nothing")) == 2
    assert "no buffer directory" in capsys.readouterr().err
