"""Atomic writes (sb3_lifelong.core.atomic): a failed write leaves the previous file as it was, and no temporary file."""

import errno
import json
import os

import pytest

from sb3_lifelong.core import atomic
from sb3_lifelong.core.atomic import AtomicWriteError, atomic_write, write_json_atomic, write_text_atomic


def test_a_write_replaces_the_file_whole(tmp_path):
    path = tmp_path / "scores.csv"
    path.write_text("old\n")
    with atomic_write(path, "w", newline="") as handle:
        handle.write("new,1\n")
        assert path.read_text() == "old\n"  # nothing of the new version shows before it is complete
    assert path.read_text() == "new,1\n"
    assert os.listdir(tmp_path) == ["scores.csv"]
    write_json_atomic(tmp_path / "done.json", {"b": 1, "a": [2]})
    assert json.loads((tmp_path / "done.json").read_text()) == {"a": [2], "b": 1}


def test_a_disk_full_midway_leaves_the_previous_file(tmp_path):
    path = tmp_path / "done.json"
    write_json_atomic(path, {"seconds": 12.5})
    before = path.read_bytes()
    with pytest.raises(AtomicWriteError) as caught:
        with atomic_write(path, "w") as handle:
            handle.write('{"seconds": ')
            handle.flush()
            raise OSError(errno.ENOSPC, "No space left on device")
    assert caught.value.errno == errno.ENOSPC
    assert str(path) in str(caught.value) and caught.value.filename == str(path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["done.json"]  # no temporary file left


def test_a_failed_sync_or_rename_leaves_the_previous_file(tmp_path, monkeypatch):
    path = tmp_path / "report.md"
    path.write_text("the old report\n")

    def fsync_fails(fd: int) -> None:
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(atomic.os, "fsync", fsync_fails)
    with pytest.raises(AtomicWriteError, match=f"could not write {path}.*Input/output error"):
        write_text_atomic(path, "a new report\n")
    monkeypatch.undo()

    def replace_fails(source: str, target: str) -> None:
        raise OSError(errno.EXDEV, "Invalid cross-device link")

    monkeypatch.setattr(atomic.os, "replace", replace_fails)
    with pytest.raises(AtomicWriteError, match=r"report\.md"):
        write_text_atomic(path, "a new report\n")
    assert path.read_text() == "the old report\n"
    assert os.listdir(tmp_path) == ["report.md"]


def test_other_exceptions_go_through_and_leave_the_previous_file(tmp_path):
    path = tmp_path / "model.zip"
    path.write_bytes(b"PK old")
    with pytest.raises(KeyError, match="not serialisable"):
        with atomic_write(path) as handle:
            handle.write(b"PK half")
            raise KeyError("not serialisable")
    with pytest.raises(ValueError, match="Out of range float"):
        write_json_atomic(path, {"x": float("nan")})
    assert path.read_bytes() == b"PK old"
    assert os.listdir(tmp_path) == ["model.zip"]


def test_refuses_a_directory_and_other_modes(tmp_path):
    with pytest.raises(IsADirectoryError, match="is a directory"):
        write_text_atomic(tmp_path, "x")
    with pytest.raises(ValueError, match="mode must be"):
        with atomic_write(tmp_path / "log.csv", "a"):
            pass
    with pytest.raises(AtomicWriteError, match=r"could not write .*missing") as caught:
        write_text_atomic(tmp_path / "missing" / "done.json", "{}")
    assert caught.value.errno == errno.ENOENT


def test_a_failed_directory_sync_after_the_rename_says_the_file_is_replaced(tmp_path, monkeypatch):
    """The new version is in place: the error says it may not be durable, not that the previous version is kept."""
    import stat

    path = tmp_path / "done.json"
    write_json_atomic(path, {"seconds": 1})
    real_fsync = os.fsync

    def directory_fsync_fails(fd: int) -> None:
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            raise OSError(errno.EIO, "Input/output error")
        real_fsync(fd)

    monkeypatch.setattr(atomic.os, "fsync", directory_fsync_fails)
    with pytest.raises(atomic.CommitNotDurableError, match="was replaced, but the fsync of its directory failed") as caught:
        write_json_atomic(path, {"seconds": 2})
    assert caught.value.errno == errno.EIO and not isinstance(caught.value, AtomicWriteError)
    assert json.loads(path.read_text()) == {"seconds": 2}
    assert os.listdir(tmp_path) == ["done.json"]


def test_the_one_writer_of_a_file_may_use_a_fixed_temporary_name(tmp_path, monkeypatch):
    """``fixed_temporary``: ``<name>.tmp``, written with os.write (every byte); a link planted there is unlinked."""
    outside = tmp_path / "outside"
    outside.write_text("not ours")
    path = tmp_path / "manifest.json"
    os.symlink(outside, tmp_path / "manifest.json.tmp")
    names, real_write = [], os.write

    def short_write(fd: int, data) -> int:  # a write may write fewer bytes than asked
        names.append(os.path.basename(os.readlink(f"/proc/self/fd/{fd}")))
        return real_write(fd, memoryview(data)[:5])

    if os.path.isdir("/proc/self/fd"):
        monkeypatch.setattr(atomic.os, "write", short_write)
    write_json_atomic(str(path), {"num_transitions": 3, "layout": "chunked"}, fixed_temporary=True)
    monkeypatch.undo()
    assert path.read_bytes() == json.dumps({"num_transitions": 3, "layout": "chunked"}, indent=1, sort_keys=True).encode()
    assert set(names) <= {"manifest.json.tmp"} and (len(names) > 1 or not os.path.isdir("/proc/self/fd"))
    assert outside.read_text() == "not ours" and sorted(os.listdir(tmp_path)) == ["manifest.json", "outside"]
