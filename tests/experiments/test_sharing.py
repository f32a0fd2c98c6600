"""A sharing study's settings and jobs: two collections, their merge, the students after it, and what is refused."""

import dataclasses
import pathlib

import pytest

from sb3_lifelong.experiments.presets import (
    PRESETS,
    Job,
    left_environments,
    sharing_text,
    study_ends,
)
from sb3_lifelong.experiments.runner import job_graph

THREE = dict(stages=({}, {"hip_deformation": 0.3}, {"friction": 0.1}), env_names=("Env-A", "Env-B", "Env-C"))


def sharing_preset(sharing: str, **changes):
    base = dict(THREE, stage_steps=(200, 300, 400), online=False, students=("CRR_exp_beta1", "BC"), sharing=sharing)
    return dataclasses.replace(PRESETS["tiny"], **{**base, **changes})


def test_a_sharing_seed_runs_both_collections_then_the_merge_then_the_students():
    preset = sharing_preset("independent")
    assert preset.jobs() == ["collect", "collect_agent2", "share", "distill_CRR_exp_beta1", "distill_BC"]
    assert preset.requires("distill_BC") == ("share",)
    assert preset.requires("share") == ("collect", "collect_agent2")
    assert preset.requires("collect_agent2") == () and preset.requires("collect") == ()
    assert preset.with_requirements(["distill_BC"]) == ["collect", "collect_agent2", "share", "distill_BC"]
    assert preset.collector_steps == (200, 300) and preset.data_buffer == "buffer_shared"
    # without sharing: every job after collect, the students on the lifetime buffer
    plain = PRESETS["tiny"]
    assert plain.requires("distill_BC") == ("collect",) and plain.with_requirements(["distill_BC"]) == [
        "collect",
        "distill_BC",
    ]
    assert plain.collector_steps == plain.stage_steps and plain.data_buffer == "buffer"


def test_the_copy_set_up_waits_for_the_switch_and_the_independent_one_for_nothing():
    graph = {task.key: task for task in job_graph(sharing_preset("copy"), [3])}
    assert list(graph) == [
        "seed_3/collect@200",
        "seed_3/collect",
        "seed_3/collect_agent2",
        "seed_3/share",
        "seed_3/distill_CRR_exp_beta1",
        "seed_3/distill_BC",
    ]
    assert graph["seed_3/collect@200"].after == () and graph["seed_3/collect@200"].until == 200
    assert graph["seed_3/collect"].after == graph["seed_3/collect_agent2"].after == ("seed_3/collect@200",)
    assert graph["seed_3/share"].after == ("seed_3/collect", "seed_3/collect_agent2")
    assert graph["seed_3/distill_BC"].after == ("seed_3/share",)
    independent = {task.key: task for task in job_graph(sharing_preset("independent"), [0], jobs=["distill_BC"])}
    assert list(independent) == ["seed_0/collect", "seed_0/collect_agent2", "seed_0/share", "seed_0/distill_BC"]
    assert independent["seed_0/collect"].after == independent["seed_0/collect_agent2"].after == ()


def test_a_study_without_sharing_keeps_its_graph():
    graph = job_graph(PRESETS["tiny"], [0, 1], jobs=["distill_BC"])
    assert [(task.key, task.after) for task in graph] == [
        ("seed_0/collect", ()),
        ("seed_0/distill_BC", ("seed_0/collect",)),
        ("seed_1/collect", ()),
        ("seed_1/distill_BC", ("seed_1/collect",)),
    ]


def test_the_sharing_jobs_are_named_like_the_others():
    for name in ("collect_agent2", "share"):
        assert Job.parse(name).kind == name and str(Job.parse(name)) == name
    with pytest.raises(ValueError, match="not a job"):
        Job("share", "BC")


def test_a_sharing_study_reads_its_first_robot_only_where_it_left_an_environment():
    described = sharing_preset("copy").describe()
    assert described["sharing"] == "copy" and "sharing" not in PRESETS["tiny"].describe()
    assert study_ends(described) == [200, 500, 500]  # Env-C's stage ends with Env-B's: side by side
    assert study_ends(dataclasses.replace(PRESETS["tiny"], **THREE, stage_steps=(1, 2, 3)).describe()) == [1, 3, 6]
    assert left_environments(described) == ["Env-A"]
    assert left_environments(PRESETS["tiny"].describe()) == ["Env-A"]
    assert "its copy at the switch learns Env-C" in sharing_text(described)
    assert "from scratch" in sharing_text(sharing_preset("independent").describe()) and sharing_text({}) == ""


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(sharing="parallel"), "sharing must be one of"),  # (replaces the copy set-up)
        (dict(stages=({}, {"friction": 0.1}), env_names=("A", "B"), stage_steps=(1, 1)), "three stages"),
        (dict(drift={"hip_deformation": (0.0, 0.3)}, stages=({}, {}, {})), "no drift"),
        (dict(online=True), "no online baselines"),
    ],
)
def test_a_sharing_preset_that_cannot_run_is_refused(changes, message):
    with pytest.raises(ValueError, match=message):
        sharing_preset(changes.pop("sharing", "copy"), **changes)


def test_the_second_collection_of_a_copy_needs_the_first_robot_at_the_switch(tmp_path: pathlib.Path):
    from sb3_lifelong.experiments.sharing import collect_agent2, share

    with pytest.raises(FileNotFoundError, match="runs to the switch first"):
        collect_agent2(sharing_preset("copy"), 0, tmp_path)
    assert not (tmp_path / "collect_agent2").exists()  # refused before it claimed anything
    with pytest.raises(ValueError, match="no sharing set-up"):
        share(PRESETS["tiny"], tmp_path)


def test_a_sharing_study_does_not_reuse_another_studys_collection(tmp_path: pathlib.Path):
    from sb3_lifelong.experiments.protocol import adopt_collection

    with pytest.raises(ValueError, match="not reused"):
        adopt_collection(sharing_preset("copy"), 0, tmp_path / "other", tmp_path / "this")
    assert not (tmp_path / "this").exists()


def filled(rows, reward_at=None):
    import gymnasium as gym
    import numpy as np

    from sb3_lifelong import LifelongReplayBuffer

    buffer = LifelongReplayBuffer(0, gym.spaces.Box(-1, 1, (2,)), gym.spaces.Box(-1, 1, (1,)), device="cpu")
    for i in range(rows):
        reward = 9.0 if i == reward_at else float(i)
        obs = np.full((1, 2), i, dtype=np.float32)
        buffer.add(obs, obs + 1, np.zeros((1, 1)), np.array([reward]), np.array([False]), [{}])
    return buffer


def test_the_merge_refuses_a_copy_of_another_stage_1(tmp_path: pathlib.Path):
    from sb3_lifelong.experiments.sharing import check_copy

    stage1 = filled(5)
    check_copy(stage1, filled(8), tmp_path)  # the copy's first five rows are Stage 1's: merged
    for other in (filled(8, reward_at=4), filled(4)):  # one reward differs; fewer rows than Stage 1
        with pytest.raises(RuntimeError, match="copied from another Stage 1"):
            check_copy(stage1, other, tmp_path)


def test_a_job_does_not_claim_a_buffer_it_did_not_write(tmp_path: pathlib.Path):
    from sb3_lifelong.experiments.jobs import NotOwnedError
    from sb3_lifelong.experiments.sharing import AGENT2_BUFFER, collect_agent2

    left = tmp_path / AGENT2_BUFFER
    left.mkdir()
    (left / "rows.npy").write_bytes(b"kept")  # e.g. left behind when collect_agent2/ was moved away
    with pytest.raises(NotOwnedError, match="is there already"):
        collect_agent2(sharing_preset("independent"), 0, tmp_path)
    assert (left / "rows.npy").read_bytes() == b"kept" and not (tmp_path / "collect_agent2").exists()


def test_a_sharing_seed_has_no_online_jobs(tmp_path: pathlib.Path):
    from sb3_lifelong.experiments.protocol import run_seed

    with pytest.raises(ValueError, match="unknown jobs"):
        run_seed(sharing_preset("copy"), 0, tmp_path, jobs=["online_CRR_indicator"])


def test_a_job_after_a_blocked_one_is_blocked_and_named_on_ray():
    """Ray passes each result on: a job after a failed one is blocked, and so are the jobs after that one."""
    from sb3_lifelong.experiments.runner import _after

    def never(*args):
        raise AssertionError("a job after a failed one ran")

    job = _after(never)
    first = job(PRESETS["tiny"], "out", 0, "collect_agent2", None, dict(key="seed_0/collect@200", error="Traceback"))
    assert first == dict(key="seed_0/collect_agent2", blocked="seed_0/collect@200 failed")
    second = job(PRESETS["tiny"], "out", 0, "collect", 200, first)
    assert second == dict(key="seed_0/collect@200", blocked="seed_0/collect_agent2 failed")


def test_list_says_what_each_job_of_a_sharing_seed_does(tmp_path: pathlib.Path, capsys):
    from sb3_lifelong.experiments.__main__ import main

    presets = tmp_path / "presets.py"
    presets.write_text(
        "import dataclasses\n"
        "from sb3_lifelong.experiments.presets import PRESETS as PACKAGE\n"
        "STAGES = ({}, {'hip_deformation': 0.3}, {'friction': 0.1})\n"
        "PRESETS = {'shared': dataclasses.replace(PACKAGE['tiny'], stages=STAGES, stage_steps=(1, 1, 1), online=False,\n"
        "    env_names=('Env-A', 'Env-B', 'Env-C'), students=('BC',), sharing='copy')}\n"
    )
    assert main(["list", "--presets", str(presets), "--preset", "shared"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines() if line.startswith("  ")}
    assert list(lines) == ["collect", "collect_agent2", "share", "distill_BC"]
    assert "the first robot" in lines["collect"] and "the second robot" in lines["collect_agent2"]
    assert "merged" in lines["share"]
