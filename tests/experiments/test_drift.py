"""A preset's drift: a parameter that changes without boundaries over the whole life. Refused with the parameter named
when it is not one, its range is not one, or a stage sets it; the collector's robot has the ramp's value at every
timestep (computed here by hand) through its stages; the evaluation environments observe what it observes."""

import dataclasses
import json
import pathlib

import numpy as np
import pytest

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.experiments import PRESETS, run_seed
from sb3_lifelong.experiments.costs import fingerprint
from sb3_lifelong.experiments.jobs import eval_envs, make_env
from sb3_lifelong.experiments.presets import (
    collection_differences,
    evaluation_stages,
    preset_name,
    same_settings,
    switch_points,
)

STUDIES = pathlib.Path(__file__).resolve().parents[2] / "benchmarks" / "studies"

#: the tiny preset (Hopper, 200 + 400 steps, episodes of at most 50), its floor slippery in Env-B, the right hip
#: deforming from 0 to 0.3 rad over the 600 steps of its life
DRIFTING = dataclasses.replace(PRESETS["tiny"], stages=({}, {"friction": 0.5}), drift={"hip_deformation": (0.0, 0.3)})
#: Hopper's floor friction (its MuJoCo model's)
NOMINAL_FRICTION = 2.0
#: the observation's last entry is the hip's deformation over its observation scale
HIP_OBS_SCALE = 0.5


def test_a_drift_of_a_parameter_the_robot_does_not_know_is_refused():
    with pytest.raises(ValueError, match="drift: unknown dynamics parameter 'hip_wear'"):
        dataclasses.replace(PRESETS["tiny"], drift={"hip_wear": (0.0, 0.3)})


@pytest.mark.parametrize(
    "values", [(1.0, 1.0), (1.0,), (1.0, 1.5, 2.0), (1.0, "2"), (1.0, float("nan")), (1.0, 6.0), (True, 2.0), 2.0, "ab"]
)
def test_a_drift_that_is_no_range_is_refused_with_its_parameter_named(values):
    # the feet's scale: from 0.1 to 5 times nominal
    with pytest.raises(
        ValueError, match=r"drift\['foot_scale'\] must be \(start, end\): two different finite numbers in \[0.1, 5\]"
    ):
        dataclasses.replace(DRIFTING, drift={"foot_scale": values})


def test_a_drift_is_kept_as_floats():
    drift = dataclasses.replace(DRIFTING, drift={"foot_scale": [1, 2]}).drift
    assert drift == {"foot_scale": (1.0, 2.0)} and [type(value) for value in drift["foot_scale"]] == [float, float]


def test_a_drift_of_a_parameter_a_stage_sets_or_of_nothing_is_refused():
    with pytest.raises(ValueError, match=r"drift: stage\(s\) \[1\] set 'hip_deformation'"):
        dataclasses.replace(PRESETS["tiny"], drift={"hip_deformation": (0.0, 0.3)})  # Env-B: hip 0.3
    with pytest.raises(ValueError, match=r"drift: stage\(s\) \[1\] set 'hip_deformation'"):
        dataclasses.replace(DRIFTING, stages=("default", "hip_0.3"))  # a named stage
    with pytest.raises(ValueError, match="drift must be a non-empty dict"):
        dataclasses.replace(DRIFTING, drift={})


def test_a_drift_outside_the_robots_own_range_is_refused_where_the_robot_is_built():
    # Hopper's floor contact cannot be stiffer than two of its time steps (0.008 s): MuJoCo would clamp it
    preset = dataclasses.replace(DRIFTING, drift={"ground_softness": (0.001, 0.1)})
    with pytest.raises(ValueError, match="LinearRamp for ground_softness"):
        make_env(preset)


def test_the_robot_has_the_ramps_value_at_every_timestep_through_its_stages():
    switch_at = switch_points(DRIFTING)
    assert switch_at == [200]
    # the ramp by hand: 0.3 rad * t / 600, constant after the end of the life; Env-B's friction from step 200
    by_hand = {0: (0.0, NOMINAL_FRICTION), 150: (0.075, NOMINAL_FRICTION), 300: (0.15, 0.5), 600: (0.3, 0.5), 900: (0.3, 0.5)}
    for timestep, (hip, friction) in by_hand.items():
        env = make_env(DRIFTING, switch_at=switch_at, start_timestep=timestep)
        observation, info = env.reset(seed=0)
        assert info["dynamics_params"]["hip_deformation"] == pytest.approx(hip), timestep
        assert info["dynamics_params"]["friction"] == pytest.approx(friction), timestep
        assert env.observed_params == ["friction", "hip_deformation"]
        assert observation[-1] == pytest.approx(hip / HIP_OBS_SCALE, abs=1e-6)
    # stepped: every episode starts with the ramp's value at its first timestep and keeps it to its end
    env = make_env(DRIFTING, switch_at=switch_at)
    env.action_space.seed(0)
    _, info = env.reset(seed=0)
    starts, episode_hip = [(0, info["dynamics_params"]["hip_deformation"])], info["dynamics_params"]["hip_deformation"]
    for step in range(1, 400):
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        assert info["dynamics_params"]["hip_deformation"] == episode_hip
        if terminated or truncated:
            _, info = env.reset()
            episode_hip = info["dynamics_params"]["hip_deformation"]
            starts.append((step, episode_hip))
    assert len(starts) >= 8  # episodes of at most 50 steps
    for timestep, hip in starts:
        assert hip == pytest.approx(0.3 * timestep / 600), timestep


def test_the_evaluation_environments_observe_what_the_collector_observes():
    collector = make_env(DRIFTING)
    envs = eval_envs(DRIFTING)
    assert list(envs) == ["Env-A", "Env-B"]
    for name, env in envs.items():
        assert env.observation_space == collector.observation_space, name
        assert env.observed_params == ["friction", "hip_deformation"]
        observation, info = env.reset(seed=0)
        assert info["dynamics_params"]["hip_deformation"] == 0.0 and observation[-1] == 0.0  # the nominal hip
    assert envs["Env-B"].dynamics_params["friction"] == pytest.approx(0.5)


def test_drift_eval_at_pins_each_stages_evaluation_robot_where_the_ramp_was():
    # Env-A on the robot of the life's first step, Env-B on the robot at 3/4 of it: hip 0.3 * 0.75 rad, its friction
    placed = dataclasses.replace(DRIFTING, drift_eval_at=(0, 0.75))
    assert placed.drift_eval_at == (0.0, 0.75)
    collector = make_env(placed)
    by_hand = {"Env-A": (0.0, NOMINAL_FRICTION), "Env-B": (0.225, 0.5)}
    envs = eval_envs(placed)
    assert list(envs) == ["Env-A", "Env-B"]
    for name, (hip, friction) in by_hand.items():
        env = envs[name]
        assert env.observation_space == collector.observation_space and env.observed_params == ["friction", "hip_deformation"]
        for _ in range(2):  # pinned: every episode on the same robot
            observation, info = env.reset(seed=0)
            assert info["dynamics_params"]["hip_deformation"] == pytest.approx(hip), name
            assert info["dynamics_params"]["friction"] == pytest.approx(friction), name
            assert observation[-1] == pytest.approx(hip / HIP_OBS_SCALE, abs=1e-6)
    # the same robots, as plain settings: a named stage's values and the drift's
    named = dataclasses.replace(PRESETS["tiny"], stages=("default", "foot_1.6"), drift={"friction": (1.0, 3.0)})
    evaluated = evaluation_stages(named.stages, named.drift, (0.5, 1.0))
    assert evaluated == [{"friction": 2.0}, {"foot_scale": 1.6, "friction": 3.0}]
    assert evaluation_stages(named.stages, named.drift, None) == ["default", "foot_1.6"]
    described = json.loads(json.dumps(placed.describe()))
    assert described["drift_eval_at"] == [0.0, 0.75] and "drift_eval_at" not in DRIFTING.describe()
    assert not same_settings(described, json.loads(json.dumps(DRIFTING.describe())))


@pytest.mark.parametrize(
    "eval_at, message",
    [
        ((0.0,), "one fraction of the life in"),
        ((0.0, 0.5, 1.0), "one fraction of the life in"),
        ((0.0, 1.5), "one fraction of the life in"),
        ((0.0, float("nan")), "one fraction of the life in"),
        ((0.0, True), "one fraction of the life in"),
        ("01", "one fraction of the life in"),
    ],
)
def test_a_drift_eval_at_that_is_no_fraction_per_stage_is_refused(eval_at, message):
    with pytest.raises(ValueError, match=rf"drift_eval_at must be {message} \[0, 1\] per stage \(2 stages\)"):
        dataclasses.replace(DRIFTING, drift_eval_at=eval_at)
    with pytest.raises(ValueError, match="drift_eval_at places the drifting parameters, and the preset has no drift"):
        dataclasses.replace(PRESETS["tiny"], drift_eval_at=(0.0, 1.0))


def test_a_preset_without_a_drift_builds_the_robot_it_did():
    preset = PRESETS["tiny"]
    assert preset.drift is None and preset.observed_params is None
    env = make_env(preset, switch_at=switch_points(preset))
    assert env.schedules == {} and env.observed_params == ["hip_deformation"]
    assert [env.observed_params for env in eval_envs(preset).values()] == [["hip_deformation"]] * 2


def test_a_drift_is_recorded_and_makes_another_study():
    described = json.loads(json.dumps(DRIFTING.describe()))
    assert described["drift"] == {"hip_deformation": [0.0, 0.3]}
    assert same_settings(described, json.loads(json.dumps(dataclasses.replace(DRIFTING).describe())))
    slower = dataclasses.replace(DRIFTING, drift={"hip_deformation": (0.0, 0.2)})
    assert not same_settings(described, json.loads(json.dumps(slower.describe())))
    assert "drift" not in PRESETS["tiny"].describe()  # as before the field: a paused student's record, the costs' key


def test_the_presets_without_a_drift_are_the_studies_they_were():
    # their cost log's keys (the fingerprint of their settings, computed before the field existed)
    fingerprints = {
        "cpu": "58b33013c0e15cd0",
        "paper": "dae6d8f6a18277a5",
        "tiny": "4e11612d76bbf64c",
        "demo": "4cca6c3e9c64b84a",
    }
    assert {name: fingerprint(preset.describe()) for name, preset in PRESETS.items()} == fingerprints
    # the committed studies recorded before the field are their presets
    for study in ("paper_cpu", "paper_cpu_three", "paper_cpu_three_c51", "paper_cpu_foot"):
        folder = STUDIES / study
        assert preset_name(json.loads((folder / "preset.json").read_text()), folder), study
    # a drift makes another collection
    recorded = json.loads(json.dumps(dataclasses.replace(PRESETS["tiny"], stages=({}, {})).describe()))
    drifting = dataclasses.replace(PRESETS["tiny"], stages=({}, {}), drift={"foot_scale": (1, 2)})
    assert collection_differences(recorded, json.loads(json.dumps(drifting.describe()))) == ["drift"]


def test_the_collection_of_a_drifting_preset_holds_the_ramp(tmp_path):
    run_seed(DRIFTING, 0, tmp_path, jobs=["collect"], log=lambda line: None)
    with LifelongReplayBuffer.open(tmp_path / "seed_0" / "buffer", read_only=True) as buffer:
        counts = buffer.source_counts()  # Env-B from the first episode that starts at step 200 or later
        assert buffer.size() == 600 and sorted(counts) == [0, 1] and 200 <= counts[0] < 250
        assert [source["name"] for source in buffer.sources.values()] == ["Env-A", "Env-B"]
        hip = buffer.read_range("observations", 0, 600)[:, -1] * HIP_OBS_SCALE
    # row t's episode started at most 49 steps earlier, with the ramp's value there: 0.3 rad * start / 600
    timesteps = np.arange(600)
    assert np.all(hip <= 0.3 * timesteps / 600 + 1e-6) and np.all(hip >= 0.3 * (timesteps - 49) / 600 - 1e-6)
    assert np.all(np.diff(hip) >= -1e-6) and hip[0] == 0.0 and hip[-1] > 0.25


def test_a_preset_of_one_stage_is_refused_before_anything_runs():
    """The report reads the switches between stages: a one-stage study is refused when its preset is made, not after
    its jobs have run."""
    with pytest.raises(ValueError, match=r"at least two stages .* got 1"):
        dataclasses.replace(PRESETS["tiny"], stages=({},), stage_steps=(200,), env_names=("Env-A",))
