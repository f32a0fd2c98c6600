"""
Safety v4: what the buffer accepts it can always commit and read back, exactly; what it cannot, it refuses at once.

- source metadata (``info["dynamics_params"]``, ``set_source``): numpy scalars converted exactly, values beyond the
  manifest reader's own limits refused at the add, naming the source and the key; a refused add leaves every earlier
  row committable;
- integer (and bool) fields store only what their dtype holds exactly (no wrap-around, no truncation), ``done`` is 0/1;
- a truncated ``.npz`` is a ``ValueError`` naming the file, and a member cut short is not "stored with pickle";
- ``salvage`` never writes inside its source, and ``--chunk-size`` must be positive;
- a buffer path that is a file, or a folder of someone else's files, is refused before anything is written.
"""

import io
import json
import os
import zipfile

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers import BufferFormatError
from sb3_lifelong.buffers.__main__ import main
from sb3_lifelong.buffers.manifest import MAX_METADATA_DEPTH, MAX_NUMBER_CHARS

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)


def add(buffer, row, info=None, **given):
    """One transition of one env: observation ``[row, -row, 0.5 row]``, reward ``row``."""
    obs = np.array([[row, -row, row * 0.5]], np.float32)
    args = dict(obs=obs, next_obs=obs + 1, action=np.zeros((1, 2), np.float32), reward=np.array([row], np.float32))
    args.update(done=np.zeros(1), infos=[dict(info or {})])
    args.update(given)
    buffer.add(**args)


def nested(depth):
    """A dict whose innermost value (1) lies ``depth`` levels below the metadata object (``{"x": 1}``: depth 1)."""
    value = 1
    for _ in range(depth - 1):
        value = {"a": value}
    return {"x": value}


def snapshot(directory):
    return {entry: (directory / entry).read_bytes() for entry in sorted(os.listdir(directory))}


# ------------------------------------------------------------------------------------------------- source metadata
def test_numpy_metadata_is_converted_exactly_and_reopens_equal(tmp_path):
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=tmp_path / "b", chunk_size=4)
    params = {
        "big": np.int64(2**62 + 1),  # not a float64: float() would round it
        "mass": np.float32(0.1),
        "half": np.float16(0.3),
        "on": np.bool_(True),
        "gains": np.array([1, 2, 3], np.uint8),
        "pair": (np.int32(-4), 2.5),
    }
    add(buffer, 0, {"stage": 1, "dynamics_params": params})
    expected = {
        "big": 2**62 + 1,
        "mass": float(np.float32(0.1)),
        "half": float(np.float16(0.3)),
        "on": True,
        "gains": [1, 2, 3],
        "pair": [-4, 2.5],
    }
    types = {"big": int, "mass": float, "half": float, "on": bool, "gains": list, "pair": list}
    assert buffer.sources[1] == {"name": "Env-B", "metadata": expected}
    assert {key: type(value) for key, value in buffer.sources[1]["metadata"].items()} == types
    buffer.close()
    again = LifelongReplayBuffer.open(tmp_path / "b", read_only=True)
    assert again.sources[1] == {"name": "Env-B", "metadata": expected}
    assert {key: type(value) for key, value in again.sources[1]["metadata"].items()} == types
    assert type(again.sources[1]["metadata"]["gains"][0]) is int and again.size() == 1


BEYOND_LIMITS = {
    "nan": ({"x": np.nan}, r"\['x'\]: nan is not finite"),
    "inf float32": ({"x": np.float32(np.inf)}, r"\['x'\]: .*inf.* is not finite"),
    "nan in a list": ({"x": [1.0, float("nan")]}, r"\['x'\]\[1\]: nan is not finite"),
    "int of 101 digits": ({"x": 10**100}, r"\['x'\]: an int of 101 characters, more than the 100 .*MAX_NUMBER_CHARS"),
    "int of 120 digits": ({"x": -(10**119)}, r"\['x'\]: an int of 121 characters"),
    "nested 9 deep": (nested(MAX_METADATA_DEPTH + 1), r"\['x'\](\['a'\]){8}: nested 9 levels deep.*MAX_METADATA_DEPTH"),
    "int key": ({"x": {1: 2.0}}, r"\['x'\]: the key 1 is a int: keys of JSON objects are strings"),
    "object": ({"x": object()}, r"\['x'\]: a value of type object"),
    "string array": ({"x": np.array(["a"])}, r"\['x'\]: an array of dtype <U1"),
}


@pytest.mark.parametrize("case", sorted(BEYOND_LIMITS))
def test_metadata_beyond_the_readers_limits_is_refused_at_the_add(tmp_path, case):
    bad, message = BEYOND_LIMITS[case]
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=tmp_path / "b", chunk_size=4)
    for row in range(6):  # a chunk committed, two rows pending
        add(buffer, row, {"stage": 1, "dynamics_params": {"mass": 1.0}})
    with pytest.raises(ValueError, match=r"add\(\): info\['dynamics_params'\] of env 0: source 2 \('Env-C'\).*" + message):
        add(buffer, 99, {"stage": 2, "dynamics_params": bad})
    assert buffer.size() == 6 and 2 not in buffer.sources
    for row in range(6, 9):  # the writer goes on: later adds commit (a chunk at row 8), flush and close too
        add(buffer, row, {"stage": 1})
    add(buffer, 9, {"stage": 2, "dynamics_params": {"mass": 3.0}})  # the same stage, with metadata that can be stored
    buffer.flush()
    buffer.close()
    again = LifelongReplayBuffer.open(tmp_path / "b", read_only=True)
    assert again.size() == 10
    np.testing.assert_array_equal(again.read_range("rewards", 0, 10), np.arange(10, dtype=np.float32))
    np.testing.assert_array_equal(again.read_range("sources", 0, 10), [1] * 9 + [2])
    assert again.sources[2] == {"name": "Env-C", "metadata": {"mass": 3.0}}


def test_metadata_at_the_limits_is_accepted_and_reopens_equal(tmp_path):
    at_limits = {
        "long": -(10 ** (MAX_NUMBER_CHARS - 2)),  # "-1" and 98 zeros: 100 characters
        **nested(MAX_METADATA_DEPTH),
        "float": -1.7976931348623157e308,
        "text": "\ud800 \x00 é",  # a lone surrogate, a NUL: JSON escapes them
    }
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=tmp_path / "b")
    buffer.set_source(4, "edge", at_limits)
    add(buffer, 0)
    buffer.close()
    assert LifelongReplayBuffer.open(tmp_path / "b", read_only=True).sources[4] == {"name": "edge", "metadata": at_limits}


def test_the_reader_refuses_what_the_writer_refuses(tmp_path):
    """One set of limits: a manifest edited to hold metadata one level deeper than the writer accepts is refused."""
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=tmp_path / "b")
    buffer.set_source(4, "edge", nested(MAX_METADATA_DEPTH))
    add(buffer, 0)
    buffer.close()
    manifest_file = tmp_path / "b" / "manifest.json"
    manifest = json.loads(manifest_file.read_text())
    manifest["sources"]["4"]["metadata"] = nested(MAX_METADATA_DEPTH + 1)
    manifest_file.write_text(json.dumps(manifest))
    with pytest.raises(BufferFormatError, match=r"manifest source 4: \['x'\].*nested 9 levels deep.*MAX_METADATA_DEPTH"):
        LifelongReplayBuffer.open(tmp_path / "b", read_only=True)


@pytest.mark.parametrize("path", [None, "b"])
def test_a_refused_set_source_changes_nothing(tmp_path, path):
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=None if path is None else tmp_path / path)
    buffer.set_source(3, "three", {"k": 1})
    with pytest.raises(ValueError, match=r"source 5 \('five'\).*\['k'\]: nan is not finite.*nothing was changed"):
        buffer.set_source(5, "five", {"k": float("nan")})
    with pytest.raises(ValueError, match=r"source 3 \('three'\).*\['k'\]: inf is not finite"):
        buffer.name_source(3, metadata={"k": float("inf")})
    add(buffer, 0)
    assert buffer.read_range("sources", 0, 1).tolist() == [3]  # still the source of the next transitions
    assert buffer.sources == {3: {"name": "three", "metadata": {"k": 1}}}
    buffer.flush()


def test_the_metadata_returned_is_a_copy(tmp_path):
    """Changing what ``sources`` returns (a nested list included) cannot put a NaN into the next commit."""
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=tmp_path / "b")
    buffer.set_source(1, "one", {"gains": [1.0, 2.0]})
    buffer.sources[1]["metadata"]["gains"].append(float("nan"))
    buffer.store.source(1)["metadata"]["gains"].append(float("nan"))
    add(buffer, 0)
    buffer.close()
    assert LifelongReplayBuffer.open(tmp_path / "b", read_only=True).sources[1]["metadata"] == {"gains": [1.0, 2.0]}


# ------------------------------------------------------------------------------------------ casts into integer fields
IMAGE = gym.spaces.Box(0, 255, (2,), np.uint8)


@pytest.mark.parametrize(
    "value, message",
    [
        (np.array([[300, 1]]), r"observations of env 0: the value 300 is out of range: the field is stored as uint8"),
        (np.array([[1, -1]]), r"observations of env 0: the value -1 is out of range.*integers from 0 to 255"),
        (np.array([[0.7, 1.0]]), r"observations of env 0: the value 0.7 is not an integer"),
        (np.array([[np.nan, 1.0]]), r"observations of env 0: the value nan is not finite"),
        (np.array([[255.5, 256.0]]), r"observations of env 0: the value 255.5 \(and 1 more\) is not an integer"),
    ],
)
@pytest.mark.parametrize("path", [None, "b"])
def test_lossy_casts_into_an_integer_observation_are_refused(tmp_path, value, message, path):
    buffer = LifelongReplayBuffer(0, IMAGE, ACT, device="cpu", path=None if path is None else tmp_path / path, chunk_size=2)
    good = dict(obs=np.array([[255.0, 0.0]]), next_obs=np.array([[7, 8]], np.int64), action=np.zeros((1, 2)), reward=[0.0])
    buffer.add(**good, done=[False], infos=[{}])  # exact values of other dtypes are converted
    with pytest.raises(ValueError, match=message):
        buffer.add(**dict(good, obs=value), done=[False], infos=[{}])
    with pytest.raises(ValueError, match=message.replace("observations", "next_observations")):
        buffer.add(**dict(good, next_obs=value), done=[False], infos=[{}])
    assert buffer.size() == 1
    buffer.add(**good, done=[False], infos=[{}])
    np.testing.assert_array_equal(buffer.read_range("observations", 0, 2), [[255, 0], [255, 0]])
    np.testing.assert_array_equal(buffer.read_range("next_observations", 0, 2), [[7, 8], [7, 8]])
    assert buffer.store.dtypes["observations"] == np.uint8


@pytest.mark.parametrize(
    "action, message",
    [
        (np.array([0.7]), r"actions of env 0: the value 0.7 is not an integer: the field is stored as int64"),
        (np.array([2**63], np.uint64), r"actions of env 0: the value 9223372036854775808 is out of range"),
        (np.array([9.3e18]), r"actions of env 0: the value 9.3e\+18 is out of range"),
    ],
)
def test_lossy_casts_into_integer_actions_are_refused(action, message):
    buffer = LifelongReplayBuffer(0, OBS, gym.spaces.Discrete(4), device="cpu")
    obs = np.zeros((1, 3), np.float32)
    buffer.add(obs, obs, np.array([3.0]), [0.0], [False], [{}])
    with pytest.raises(ValueError, match=message):
        buffer.add(obs, obs, action, [0.0], [False], [{}])
    assert buffer.size() == 1 and buffer.read_range("actions", 0, 1).tolist() == [[3]]


def test_lossy_casts_into_a_dict_observation_key_are_refused():
    space = gym.spaces.Dict({"image": IMAGE, "pos": OBS})
    buffer = LifelongReplayBuffer(0, space, ACT, device="cpu")
    obs = {"image": np.array([[1, 2]]), "pos": np.zeros((1, 3), np.float32)}
    with pytest.raises(ValueError, match=r"observations\['image'\] of env 0: the value 300 is out of range.*uint8"):
        buffer.add(dict(obs, image=np.array([[300, 2]])), obs, np.zeros((1, 2)), [0.0], [False], [{}])
    buffer.add(obs, obs, np.zeros((1, 2)), [0.0], [False], [{}])
    assert buffer.size() == 1 and buffer.read_range("observations.image", 0, 1).tolist() == [[1, 2]]


@pytest.mark.parametrize("done, message", [([2], r"dones of env 0: the value 2 is out of range"), ([0.5], r"0.5 is not")])
def test_a_done_that_is_not_0_or_1_is_refused(tmp_path, done, message):
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=tmp_path / "b")
    add(buffer, 0, done=np.array([1]))
    add(buffer, 1, done=np.array([1.0]))
    with pytest.raises(ValueError, match=message + r".*stored as bool \(only 0 and 1\)"):
        add(buffer, 2, done=np.array(done))
    assert buffer.size() == 2 and buffer.read_range("flags", 0, 2).tolist() == [1, 1]


# ---------------------------------------------------------------------------------------------- truncated exports
@pytest.fixture
def exported(tmp_path):
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu")
    for row in range(50):
        add(buffer, row, done=np.array([row % 10 == 9]))
    file = tmp_path / "data.npz"
    buffer.save_npz(file)
    return file


@pytest.mark.parametrize("keep", [0.0, 0.1, 0.5, 0.999])
def test_a_truncated_npz_is_a_value_error_naming_the_file(exported, keep):
    raw = exported.read_bytes()
    exported.write_bytes(raw[: int(len(raw) * keep)])
    with pytest.raises(ValueError, match=f"{exported}: not a readable .npz archive: it is truncated or damaged") as error:
        LifelongReplayBuffer.from_d4rl(exported)
    assert "pickle" not in str(error.value)


def test_a_member_cut_short_is_not_reported_as_pickle(exported, tmp_path):
    with zipfile.ZipFile(exported) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    members["rewards.npy"] = members["rewards.npy"][:-8]  # the archive is valid, one member is short
    short = tmp_path / "short.npz"
    with zipfile.ZipFile(short, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    with pytest.raises(ValueError, match=f"{short}: array 'rewards' cannot be read: the archive is truncated") as error:
        LifelongReplayBuffer.from_d4rl(short)
    assert "pickle" not in str(error.value)
    # an object array is still named as such
    buffer = io.BytesIO()
    np.savez(buffer, observations=np.array([1, None], dtype=object))
    (tmp_path / "objects.npz").write_bytes(buffer.getvalue())
    with pytest.raises(ValueError, match=r"objects.npz: array 'observations' is stored with pickle"):
        LifelongReplayBuffer.from_d4rl(tmp_path / "objects.npz")


# ------------------------------------------------------------------------------------------------------- salvage
@pytest.fixture
def source(tmp_path):
    path = tmp_path / "src"
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=path, chunk_size=5)
    for row in range(12):
        add(buffer, row)
    buffer.close()
    return path


@pytest.mark.parametrize("inside", ["inner", "inner/deeper"])
@pytest.mark.parametrize("through_link", [False, True])
def test_salvage_never_writes_inside_its_source(source, tmp_path, capsys, inside, through_link):
    before = snapshot(source)
    base = source
    if through_link:
        (tmp_path / "link").symlink_to(source, target_is_directory=True)
        base = tmp_path / "link"
    destination = base / inside
    assert main(["salvage", str(source), str(destination)]) == 2
    assert "never writes into the directory it copies from" in capsys.readouterr().err
    assert snapshot(source) == before  # nothing created, nothing changed
    with pytest.raises(FileExistsError, match="never writes into the directory it copies from"):
        LifelongReplayBuffer.salvage(source, destination)
    assert snapshot(source) == before


@pytest.mark.parametrize("value", ["0", "-3", "ten"])
def test_salvage_chunk_size_must_be_positive(source, tmp_path, capsys, value):
    with pytest.raises(SystemExit) as exit_status:
        main(["salvage", str(source), str(tmp_path / "copy"), "--chunk-size", value])
    assert exit_status.value.code == 2
    assert "--chunk-size: " in capsys.readouterr().err and not (tmp_path / "copy").exists()
    with pytest.raises(ValueError, match="chunk_size must be a positive int"):
        LifelongReplayBuffer.salvage(source, tmp_path / "copy", chunk_size=0)
    assert not (tmp_path / "copy").exists()
    assert main(["salvage", str(source), str(tmp_path / "copy"), "--chunk-size", "4"]) == 0
    assert LifelongReplayBuffer.open(tmp_path / "copy", read_only=True).size() == 12


# ---------------------------------------------------------------------------------------------------- buffer paths
@pytest.mark.parametrize("read_only", [False, True])
def test_a_path_that_is_a_file_is_refused_naming_it(tmp_path, read_only):
    file = tmp_path / "results.csv"
    file.write_text("a,b\n")
    with pytest.raises(NotADirectoryError, match=f"buffer path '{file}' is an existing file, not a directory"):
        LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=file, read_only=read_only)
    assert file.read_text() == "a,b\n"


@pytest.mark.parametrize("mode", ["new", "append", "overwrite"])
def test_a_folder_of_other_files_is_refused_unless_allowed(tmp_path, mode):
    folder = tmp_path / "results"
    folder.mkdir()
    for name in ["notes.txt", "model.zip", "a.png", "b.png", "c.png", "d.png"]:
        (folder / name).write_text(name)
    before = snapshot(folder)
    message = (
        r"holds no buffer \(no manifest.json\) but 6 other entries: 'a.png', 'b.png', 'c.png', 'd.png', 'model.zip' and 1 more"
    )
    with pytest.raises(FileExistsError, match=message + ".*allow_foreign_files=True"):
        LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=folder, mode=mode)
    assert snapshot(folder) == before  # not even a lock file
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=folder, mode=mode, allow_foreign_files=True, chunk_size=2)
    for row in range(3):
        add(buffer, row)
    buffer.close()
    assert {name: (folder / name).read_bytes() for name in before} == before
    again = LifelongReplayBuffer.open(folder)  # a buffer now: it opens without the option
    assert again.size() == 3 and again.read_range("rewards", 0, 3).tolist() == [0, 1, 2]


def test_what_a_killed_creator_leaves_is_not_foreign(tmp_path):
    folder = tmp_path / "b"
    folder.mkdir()
    for name in ["writer.lock", "manifest.json.tmp", "rewards.bin"]:  # an empty field file: no rows to lose
        (folder / name).write_bytes(b"")
    buffer = LifelongReplayBuffer(0, OBS, ACT, device="cpu", path=folder)
    add(buffer, 0)
    buffer.close()
    assert LifelongReplayBuffer.open(folder, read_only=True).size() == 1
