"""
Directories written by earlier code keep opening: the committed fixtures ``data/single_file_v1`` and
``data/single_file_v2`` are buffers in layout "single" (one append-only file per field) written by the code that
still wrote that layout (``data/make_single_file_fixtures.py`` says how). Every row is recomputed from the values that
script added, read-only and after a writer has opened (and migrated) the directory.
"""

from __future__ import annotations

import json
import os
import shutil
import sys

import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "data"))
from make_single_file_fixtures import SPECS, V1_OBS, V2_OBS, rows

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data")


def fixture_copy(tmp_path, version: int) -> str:
    path = str(tmp_path / f"v{version}")
    shutil.copytree(os.path.join(DATA, f"single_file_v{version}"), path)
    return path


def directory_bytes(path: str) -> dict[str, bytes]:
    return {name: open(os.path.join(path, name), "rb").read() for name in sorted(os.listdir(path)) if name != "writer.lock"}


def expected(version: int) -> dict[str, np.ndarray]:
    """The stored form of every row the fixture's script added (row = step * n_envs + env)."""
    steps, n_envs, _ = SPECS[version]
    added = [rows(version, step, env) for step in range(steps) for env in range(n_envs)]
    out: dict[str, np.ndarray] = {
        "actions": np.stack([r["action"] for r in added]).astype(np.float32 if version == 1 else np.int64),
        "rewards": np.array([r["reward"] for r in added], dtype=np.float32),
        "flags": np.array([int(r["done"]) | 2 * int(r["truncated"]) for r in added], dtype=np.uint8),
        "sources": np.array([r["source"] for r in added], dtype=np.uint16),
    }
    if version == 1:
        out["observations"] = np.stack([r["obs"] for r in added])
        out["next_observations"] = np.stack([r["next_obs"] for r in added])
    else:
        for key in V2_OBS.spaces:
            out[f"observations.{key}"] = np.stack([r["obs"][key] for r in added])
            out[f"next_observations.{key}"] = np.stack([r["next_obs"][key] for r in added])
    return out


def check_rows(buffer: LifelongReplayBuffer, version: int, first: int = 0) -> None:
    want = expected(version)
    count = len(want["rewards"])
    for name, values in want.items():
        got = buffer.read_range(name, first, first + count)
        stored = got.reshape(values.shape) if version == 2 and name == "actions" else got
        np.testing.assert_array_equal(stored.astype(values.dtype), values, err_msg=name)
        assert got.dtype == buffer.store.dtypes[name]
    for name, (dtype, shape) in buffer.store.fields.items():  # every field (streams, widths too): the bytes written
        raw = np.fromfile(os.path.join(DATA, f"single_file_v{version}", f"{name}.bin"), dtype=dtype).reshape(-1, *shape)
        np.testing.assert_array_equal(buffer.read_range(name, first, first + count), raw, err_msg=name)


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("read_mode", ["mmap", "pread"])
def test_a_single_file_directory_reads_every_row_and_is_not_changed(tmp_path, version, read_mode):
    path = fixture_copy(tmp_path, version)
    before = directory_bytes(path)
    with LifelongReplayBuffer.open(path, read_only=True, device="cpu", read_mode=read_mode, verify="all") as buffer:
        steps, n_envs, _ = SPECS[version]
        assert buffer.size() == steps * n_envs
        check_rows(buffer, version)
        if version == 1:
            assert buffer.source_counts(by_name=True) == {"Env-A": 12, "Env-B": 12}
            assert buffer.observation_space == V1_OBS
        else:
            assert buffer.observation_space == V2_OBS
        assert len(buffer.sample(16).rewards) == 16
        assert buffer.refresh() == steps * n_envs
    assert directory_bytes(path) == before  # a reader writes nothing


@pytest.mark.parametrize("version", [1, 2])
def test_a_writer_continues_a_single_file_directory(tmp_path, version):
    path = fixture_copy(tmp_path, version)
    buffer_id = json.load(open(os.path.join(path, "manifest.json")))["buffer_id"]
    steps, n_envs, _ = SPECS[version]
    held = steps * n_envs
    with LifelongReplayBuffer.open(path, device="cpu", verify="all") as buffer:
        assert buffer.size() == held and buffer.buffer_id == buffer_id
        check_rows(buffer, version)
        more = buffer.read_range  # a second copy of the old rows, appended as new ones
        buffer.append_rows({name: more(name, 0, held) for name in buffer.store.fields})
        assert buffer.size() == 2 * held
    with LifelongReplayBuffer.open(path, read_only=True, device="cpu", verify="all") as reopened:
        assert reopened.size() == 2 * held and reopened.buffer_id == buffer_id
        check_rows(reopened, version)
        check_rows(reopened, version, first=held)
