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
from sb3_lifelong.buffers import BufferFormatError

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


def chunk_names(chunks) -> list[str]:
    return [f"chunk.{chunk['start']:012d}.bin" for chunk in chunks]


@pytest.mark.parametrize("version", [1, 2])
def test_a_writer_migrates_a_single_file_directory_to_chunk_files(tmp_path, version):
    """Opening for writing copies the rows into layout "chunked": the same chunks, checksums, sources and identity;
    the field files are gone once the new manifest is in place."""
    path = fixture_copy(tmp_path, version)
    old = json.load(open(os.path.join(path, "manifest.json")))
    with LifelongReplayBuffer.open(path, device="cpu") as buffer:
        assert buffer.store.layout == "chunked" and buffer.store.capacity is None
    new = json.load(open(os.path.join(path, "manifest.json")))
    assert (new["version"], new["layout"], new["capacity"], new["first_row"]) == (3, "chunked", None, 0)
    for key in ("buffer_id", "chunks", "fields", "sources", "num_transitions", "next_stream_id", "spaces"):
        assert new[key] == old[key], key
    assert sorted(os.listdir(path)) == sorted([*chunk_names(old["chunks"]), "manifest.json", "writer.lock"])
    with LifelongReplayBuffer.open(path, read_only=True, device="cpu", verify="all") as reopened:
        check_rows(reopened, version)


def test_a_damaged_single_file_directory_is_not_migrated(tmp_path):
    """A flipped bit found while copying: the writer refuses (naming the file and salvage), the directory unchanged."""
    path = fixture_copy(tmp_path, 1)
    rewards = bytearray(open(os.path.join(path, "rewards.bin"), "rb").read())
    rewards[4 * 13] ^= 0x08  # row 13: the second chunk, which verify="last" (the default) does not read
    open(os.path.join(path, "rewards.bin"), "wb").write(bytes(rewards))
    before = directory_bytes(path)
    with pytest.raises(BufferFormatError, match=r"rewards\.bin: checksum mismatch in chunk starting at row 10.*salvage"):
        LifelongReplayBuffer.open(path, device="cpu")
    assert directory_bytes(path) == before  # no chunk file left, no field file changed
    report = LifelongReplayBuffer.check_directory(path)
    assert [chunk.start for chunk in report.damaged] == [10] and report.layout == "single"


def test_a_field_file_that_is_a_link_is_refused(tmp_path):
    outside = tmp_path / "someone_elses_file.bin"
    outside.write_bytes(b"precious")
    path = fixture_copy(tmp_path, 1)
    os.remove(os.path.join(path, "rewards.bin"))
    os.symlink(outside, os.path.join(path, "rewards.bin"))
    before = directory_bytes(path)
    for read_only in (True, False):
        with pytest.raises(BufferFormatError, match=r"field file rewards\.bin is missing or not a regular file"):
            LifelongReplayBuffer.open(path, device="cpu", read_only=read_only)
    assert outside.read_bytes() == b"precious" and directory_bytes(path) == before
    os.remove(os.path.join(path, "rewards.bin"))
    shutil.copy(os.path.join(DATA, "single_file_v1", "rewards.bin"), os.path.join(path, "rewards.bin"))
    os.remove(os.path.join(path, "flags.bin"))
    with pytest.raises(BufferFormatError, match=r"field file flags\.bin is missing") as error:
        LifelongReplayBuffer.open(path, device="cpu", read_only=True)
    assert "chunk" not in str(error.value)


def test_a_truncated_field_file_keeps_the_chunks_before(tmp_path):
    path = fixture_copy(tmp_path, 1)
    with open(os.path.join(path, "rewards.bin"), "r+b") as file:
        file.truncate(15 * 4)  # rows 15.. lost: chunks 10-19 and 20-23
    with pytest.raises(BufferFormatError, match=r"rewards\.bin.*truncated"):
        LifelongReplayBuffer.open(path, device="cpu", verify="none")
    report = LifelongReplayBuffer.check_directory(path)
    assert [chunk.start for chunk in report.damaged] == [10, 20]
    copy, report = LifelongReplayBuffer.salvage(path, tmp_path / "copy", read_only=True, device="cpu")
    assert report.copied == 10 and copy.store.layout == "chunked"
    np.testing.assert_array_equal(copy.read_range("rewards", 0, 10), expected(1)["rewards"][:10])


def test_a_migration_interrupted_before_its_commit_is_done_again(tmp_path, monkeypatch):
    """Killed after the chunk files were written, before the manifest: still layout "single" (readers ignore the chunk
    files); the next writer copies again and commits."""
    from sb3_lifelong.buffers.rowstore import RowStore

    path = fixture_copy(tmp_path, 2)
    manifest = open(os.path.join(path, "manifest.json"), "rb").read()

    def interrupted(self, chunks, num_committed):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(RowStore, "_commit", interrupted)
        with pytest.raises(KeyboardInterrupt):
            LifelongReplayBuffer.open(path, device="cpu")
    assert open(os.path.join(path, "manifest.json"), "rb").read() == manifest
    assert {"chunk.000000000000.bin", "rewards.bin"} <= set(os.listdir(path))
    with LifelongReplayBuffer.open(path, read_only=True, device="cpu", verify="all") as reader:
        assert reader.store.layout == "single"
        check_rows(reader, 2)
    with LifelongReplayBuffer.open(path, device="cpu") as writer:  # the lock was released: a writer opens
        assert writer.store.layout == "chunked"
        check_rows(writer, 2)
    assert not [name for name in os.listdir(path) if name.endswith(".bin") and not name.startswith("chunk.")]


def test_field_files_left_after_a_migration_are_removed_by_the_next_writer(tmp_path):
    """Killed after the migration's commit, before the field files were deleted: readers read the chunk files; the
    next writer deletes the field files; ``mode="overwrite"`` deletes them too."""
    path = fixture_copy(tmp_path, 1)
    LifelongReplayBuffer.open(path, device="cpu").close()
    for name in os.listdir(os.path.join(DATA, "single_file_v1")):
        if name.endswith(".bin"):
            shutil.copy(os.path.join(DATA, "single_file_v1", name), os.path.join(path, name))
    with LifelongReplayBuffer.open(path, read_only=True, device="cpu", verify="all") as reader:
        check_rows(reader, 1)
    assert "rewards.bin" in os.listdir(path)
    with LifelongReplayBuffer.open(path, device="cpu") as writer:
        check_rows(writer, 1)
    assert not [name for name in os.listdir(path) if name.endswith(".bin") and not name.startswith("chunk.")]
    for name in os.listdir(os.path.join(DATA, "single_file_v1")):
        if name.endswith(".bin"):
            shutil.copy(os.path.join(DATA, "single_file_v1", name), os.path.join(path, name))
    from sb3_lifelong.buffers.ownership import owned_buffer_files

    owned = owned_buffer_files(path)
    assert "rewards.bin" in owned and "chunk.000000000020.bin" in owned and owned[-1] == "manifest.json"


@pytest.mark.parametrize("read_mode", ["mmap", "pread"])
def test_a_reader_follows_a_migration(tmp_path, read_mode):
    """A reader of the single-file directory keeps its rows while a writer migrates it and appends, and refresh()
    then serves the new layout's rows, old and new."""
    path = fixture_copy(tmp_path, 1)
    held = 24
    reader = LifelongReplayBuffer.open(path, read_only=True, device="cpu", read_mode=read_mode)
    assert reader.store.layout == "single"
    with LifelongReplayBuffer.open(path, device="cpu") as writer:
        writer.append_rows({name: writer.read_range(name, 0, held) for name in writer.store.fields})
        writer.flush()
        check_rows(reader, 1)  # the field files are deleted, the reader's open files and maps still read them
        assert reader.refresh() == 2 * held and reader.store.layout == "chunked"
        check_rows(reader, 1)
        check_rows(reader, 1, first=held)
    reader.close()


def test_left_field_files_wait_for_a_synced_commit(tmp_path, monkeypatch):
    """A migration whose commit was not synced (the directory's fsync failed) may be undone by a power loss: the next
    writer deletes the field files only after its own commit is synced."""
    import errno
    import stat

    from sb3_lifelong.buffers.files import CommitNotDurableError

    path = fixture_copy(tmp_path, 1)
    real_fsync = os.fsync

    def failing_fsync(fd):
        if (
            stat.S_ISDIR(os.fstat(fd).st_mode)
            and "manifest.json" in os.listdir(path)
            and json.load(open(os.path.join(path, "manifest.json"))).get("layout") == "chunked"
        ):
            raise OSError(errno.EIO, "Input/output error (injected)")
        return real_fsync(fd)

    for attempt in range(2):  # the migrating writer, then one that finds its field files
        with monkeypatch.context() as patch:
            patch.setattr(os, "fsync", failing_fsync)
            with pytest.raises(CommitNotDurableError, match="opening it again"):
                LifelongReplayBuffer.open(path, device="cpu")
        assert "rewards.bin" in os.listdir(path), attempt  # kept: the synced manifest may still be the single one
    with LifelongReplayBuffer.open(path, device="cpu") as writer:
        check_rows(writer, 1)
    assert not [name for name in os.listdir(path) if name.endswith(".bin") and not name.startswith("chunk.")]


def test_the_versions_written(tmp_path):
    """Without a capacity a manifest is version 3 (version 2 cannot say so: earlier code refuses it as unknown); with
    one, version 2. A version 2 manifest of layout "chunked" without a capacity is refused."""
    from gymnasium import spaces as gym_spaces

    obs, act = gym_spaces.Box(-1, 1, (2,), np.float32), gym_spaces.Box(-1, 1, (1,), np.float32)
    for capacity, version in ((None, 3), (100, 2)):
        path = tmp_path / f"c{capacity}"
        buffer = LifelongReplayBuffer(0, obs, act, path=path, capacity=capacity, device="cpu")
        buffer.add(np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 1)), np.zeros(1), np.zeros(1), [{}])
        buffer.close()
        manifest = json.load(open(path / "manifest.json"))
        assert (manifest["version"], manifest["layout"], manifest["capacity"]) == (version, "chunked", capacity)
    manifest = json.load(open(tmp_path / "cNone" / "manifest.json"))
    (tmp_path / "cNone" / "manifest.json").write_text(json.dumps(dict(manifest, version=2)))
    with pytest.raises(BufferFormatError, match="without a capacity needs format version 3"):
        LifelongReplayBuffer.open(tmp_path / "cNone", read_only=True, device="cpu")


def test_a_refreshed_reader_keeps_no_map_of_the_field_files(tmp_path):
    """One chunk: the chunk file's segment has the rows of the single segment; the reader maps it, not the deleted
    field files (which would keep their disk space)."""
    path = fixture_copy(tmp_path, 1)
    manifest = json.load(open(os.path.join(path, "manifest.json")))
    manifest.update(num_transitions=10, chunks=manifest["chunks"][:1])  # the rows after the first chunk: an unflushed tail
    with open(os.path.join(path, "manifest.json"), "w") as file:
        json.dump(manifest, file)
    reader = LifelongReplayBuffer.open(path, read_only=True, device="cpu", read_mode="mmap")
    reader.sample(4)
    LifelongReplayBuffer.open(path, device="cpu").close()  # migrated: one chunk file
    assert reader.refresh() == 10 and reader.store.layout == "chunked"
    reader.sample(4)
    with open("/proc/self/maps") as maps:
        mapped = [line for line in maps if path in line]
    assert mapped and all("chunk.000000000000.bin" in line for line in mapped), mapped
    np.testing.assert_array_equal(reader.read_range("rewards", 0, 10), expected(1)["rewards"][:10])
    reader.close()


def test_no_space_for_the_copy_is_explained_and_changes_nothing(tmp_path, monkeypatch):
    import errno

    path = fixture_copy(tmp_path, 2)
    before = directory_bytes(path)
    real_write = os.write

    def full(fd, data):
        if os.path.basename(os.readlink(f"/proc/self/fd/{fd}")).startswith("chunk."):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(OSError, match=r"copying this directory of an earlier version .* needs free space") as error:
        LifelongReplayBuffer.open(path, device="cpu")
    assert error.value.errno == errno.ENOSPC
    monkeypatch.setattr(os, "write", real_write)
    assert directory_bytes(path) == before
